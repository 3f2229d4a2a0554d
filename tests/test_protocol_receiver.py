"""Server-side protocol state: forgery and replay rejected, duplicates of unacked let through,
acks, window bounds, clock offset."""

from __future__ import annotations

import numpy as np
import pytest

import cranetwin.protocol.receiver as receiver_mod
from cranetwin.protocol import (
    BadHmacError,
    ChannelSpec,
    GarbageError,
    Layout,
    MachineKey,
    Receiver,
    ReplayedError,
    StatusReport,
    UnknownMachineError,
    decode_ack,
    encode_ack,
    encode_data,
    encode_status,
)
from cranetwin.protocol.wire import TAG_BYTES, tag

LAYOUT = Layout((ChannelSpec("p", 0.0, 25e6, 5000.0), ChannelSpec("s", 0.0, 1.0, 1e-4)))
KEY = MachineKey(7, "m7", b"k" * 32, LAYOUT)
PERIOD = 10_000_000


def _dg(seq: int, low: int | None = None, t0: int = 0, key: MachineKey = KEY) -> bytes:
    v = np.array([[1e6, 0.1], [1.005e6, 0.1001]])
    return encode_data(key, seq, t0, PERIOD, v, oldest_unacked=low)


def test_duplicate_before_durable_is_accepted_after_durable_is_replayed() -> None:
    r = Receiver({7: KEY})
    assert r.receive(_dg(0), 0).seq == 0
    assert r.receive(_dg(0), 1).seq == 0  # not durable yet: idempotent write, let it through
    r.mark_durable("m7", 0)
    with pytest.raises(ReplayedError) as info:
        r.receive(_dg(0), 2)
    assert info.value.reason == "replayed"


def test_selective_durable_then_gap_fill_advances_cumulative() -> None:
    r = Receiver({7: KEY})
    for s in (0, 2, 3, 5):
        r.receive(_dg(s, low=0), 0)
        r.mark_durable("m7", s)
    ack = decode_ack(r.ack("m7", 123), KEY)
    assert ack.cumulative == 1 and ack.selective == (2, 3, 5) and ack.server_time_ns == 123
    for s in (2, 3, 5):
        with pytest.raises(ReplayedError):
            r.receive(_dg(s, low=0), 0)
    assert r.receive(_dg(4, low=0), 0).seq == 4  # accepted but not durable: not acked
    r.receive(_dg(1, low=0), 0)
    r.mark_durable("m7", 1)
    ack = decode_ack(r.ack("m7", 0), KEY)
    assert ack.cumulative == 4 and ack.selective == (5,)


def test_sender_lag_moves_the_floor_so_old_authentic_datagrams_are_replays() -> None:
    r = Receiver({7: KEY})
    old = _dg(5)
    r.receive(_dg(20, low=12), 0)
    assert r.floor("m7") == 12
    with pytest.raises(ReplayedError):
        r.receive(old, 0)
    assert r.receive(_dg(13, low=12), 0).seq == 13


def test_forgeries_are_rejected_before_anything_else() -> None:
    r = Receiver({7: KEY})
    dg = bytearray(_dg(3))
    dg[50] ^= 0x10  # a value changed in flight
    with pytest.raises(BadHmacError):
        r.receive(bytes(dg), 0)
    thief = MachineKey(7, "m7", b"x" * 32, LAYOUT)  # right id, wrong secret
    with pytest.raises(BadHmacError):
        r.receive(_dg(3, key=thief), 0)
    # a forger can neither move the floor nor mark anything
    forged = bytearray(_dg(1000, low=999))
    forged[-TAG_BYTES:] = bytes(TAG_BYTES)
    with pytest.raises(BadHmacError):
        r.receive(bytes(forged), 0)
    assert r.floor("m7") == 0
    assert r.receive(_dg(3), 0).seq == 3


def test_unknown_machine_and_acks_sent_to_the_server() -> None:
    r = Receiver(lambda wid: KEY if wid == 7 else None)
    other = MachineKey(8, "m8", b"k" * 32, LAYOUT)
    with pytest.raises(UnknownMachineError) as info:
        r.receive(_dg(0, key=other), 0)
    assert info.value.reason == "unknown_machine" and info.value.wire_id == 8
    with pytest.raises(GarbageError):
        r.receive(encode_ack(KEY, 3), 0)


def test_status_shares_the_sequence_space() -> None:
    key = MachineKey(7, "m7", b"k" * 32, Layout(LAYOUT.channels + (
        ChannelSpec("slew_angle", -3.5, 3.5, 1e-4, True),)))
    r = Receiver({7: key})
    rep = r.receive(encode_status(key, StatusReport("", 4, 0, 60.0, 25.0, 10.0, 5.0,
                                                    {"slew_angle": 0.5})), 0)
    assert isinstance(rep, StatusReport) and rep.machine_id == "m7"
    r.mark_durable("m7", 4)
    with pytest.raises(ReplayedError):
        r.receive(encode_status(key, StatusReport("", 4, 0)), 0)


def test_window_is_bounded_and_forgotten_seqs_only_let_authentic_repeats_in(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(receiver_mod, "WINDOW", 8)
    r = Receiver({7: KEY})
    for s in range(1, 30):  # seq 0 never arrives: everything stays above the floor
        r.receive(_dg(s, low=0), 0)
        r.mark_durable("m7", s)
    st = r._by_id["m7"]
    assert len(st.durable) == 8 and len(st.heap) == 8
    assert r.receive(_dg(1, low=0), 0).seq == 1  # forgotten: accepted again (idempotent write)
    with pytest.raises(ReplayedError):
        r.receive(_dg(29, low=0), 0)


def test_clock_offset_is_the_minimum_delay_estimate() -> None:
    r = Receiver({7: KEY})
    rng = np.random.default_rng(0)
    theta = 3_000_000_000  # server runs 3 s ahead of the machine
    d_min = 20_000_000
    for i in range(200):
        t0 = 10**18 + i * 2 * PERIOD
        send_machine = t0 + 2 * PERIOD  # the batch is complete one period after its last sample
        recv_server = send_machine + theta + d_min + int(rng.exponential(50e6))
        r.receive(_dg(i, t0=t0), recv_server)
    est = r.clock_offset_ns("m7")
    assert est is not None
    assert theta + d_min <= est <= theta + d_min + 5_000_000
    assert r.clock_offset_ns("nobody") is None


def test_ack_is_authenticated_for_the_machine() -> None:
    r = Receiver({7: KEY})
    r.receive(_dg(0), 0)
    r.mark_durable("m7", 0)
    a = r.ack("m7", 5)
    body = a[:-TAG_BYTES]
    assert a[-TAG_BYTES:] == tag(KEY.secret, body)
    with pytest.raises(BadHmacError):
        decode_ack(a, MachineKey(7, "m7", b"y" * 32, LAYOUT))
