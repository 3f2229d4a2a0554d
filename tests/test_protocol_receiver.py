"""Server-side protocol state: forgeries never answered, replays only of what is durable, jumps
and restarts never make new data look old, validation at the edge, acks, bounds, clock offset."""

from __future__ import annotations

import numpy as np
import pytest

import cranetwin.protocol.receiver as receiver_mod
from cranetwin.protocol import (
    BadHmacError,
    ChannelSpec,
    DatagramError,
    GarbageError,
    Layout,
    Limits,
    MachineKey,
    Receiver,
    RefusedError,
    ReplayedError,
    StatusReport,
    UnknownMachineError,
    decode_ack,
    decode_refusal,
    encode_ack,
    encode_data,
    encode_status,
)
from cranetwin.protocol.wire import HEADER, MAGIC, TAG_BYTES, TYPE_DATA, tag

LAYOUT = Layout((ChannelSpec("p", 0.0, 25e6, 5000.0), ChannelSpec("s", 0.0, 1.0, 1e-4)))
KEY = MachineKey(7, "m7", b"k" * 32, LAYOUT)
PERIOD = 10_000_000
NOW = 1_800_000_000 * 10**9  # server clock of these tests [ns]
EPOCH = 1234


def _dg(seq: int, low: int | None = None, t0: int = NOW, key: MachineKey = KEY,
        epoch: int = EPOCH, values: np.ndarray | None = None) -> bytes:
    v = np.array([[1e6, 0.1], [1.005e6, 0.1001]]) if values is None else values
    return encode_data(key, seq, t0, PERIOD, v, oldest_unacked=low, epoch=epoch)


def _rx(**limits: float) -> Receiver:
    return Receiver({7: KEY}, Limits(**limits))  # type: ignore[arg-type]


def test_duplicate_before_durable_is_accepted_after_durable_is_replayed() -> None:
    r = _rx()
    assert r.receive(_dg(0), NOW).seq == 0
    assert r.receive(_dg(0), NOW).seq == 0  # not durable yet: idempotent write, let it through
    r.mark_durable("m7", EPOCH, 0)
    with pytest.raises(ReplayedError) as info:
        r.receive(_dg(0), NOW)
    err = info.value
    assert (err.reason, err.machine_id, err.epoch, err.seq) == ("replayed", "m7", EPOCH, 0)
    ack = decode_ack(r.ack("m7", EPOCH, NOW), KEY)
    assert ack.covers(0) and ack.epoch == EPOCH


def test_selective_durable_then_gap_fill_advances_cumulative() -> None:
    r = _rx()
    for s in (0, 2, 3, 5):
        r.receive(_dg(s, low=0), NOW)
        r.mark_durable("m7", EPOCH, s)
    ack = decode_ack(r.ack("m7", EPOCH, 123), KEY)
    assert ack.cumulative == 1 and ack.selective == (2, 3, 5) and ack.server_time_ns == 123
    for s in (2, 3, 5):
        with pytest.raises(ReplayedError):
            r.receive(_dg(s, low=0), NOW)
    assert r.receive(_dg(4, low=0), NOW).seq == 4  # accepted but not durable: not acked
    r.receive(_dg(1, low=0), NOW)
    r.mark_durable("m7", EPOCH, 1)
    ack = decode_ack(r.ack("m7", EPOCH, 0), KEY)
    assert ack.cumulative == 4 and ack.selective == (5,)


def test_released_seqs_start_the_cumulative_ack_but_never_drop_data() -> None:
    r = _rx()
    r.receive(_dg(20, low=12), NOW)  # the sender no longer holds anything below 12
    assert decode_ack(r.ack("m7", EPOCH, NOW), KEY).cumulative == 12
    # an authentic datagram below that is not known durable here: written again (idempotent),
    # never acked unseen
    assert r.receive(_dg(5), NOW).seq == 5
    assert r.receive(_dg(13, low=12), NOW).seq == 13


def test_sequence_jumps_clock_resets_and_new_epochs_never_look_replayed() -> None:
    r = _rx()
    # a sender whose clock was far ahead at one start (seq = Unix ms), then sane again
    r.receive(_dg(2_000_000_000_000, epoch=1), NOW)
    r.mark_durable("m7", 1, 2_000_000_000_000)
    assert decode_ack(r.ack("m7", 1, NOW), KEY).cumulative == 2_000_000_000_001
    assert r.receive(_dg(5, epoch=1), NOW).seq == 5  # backward within the epoch: still stored
    assert not decode_ack(r.ack("m7", 1, NOW), KEY).covers(5)  # and not acked before it is
    r.mark_durable("m7", 1, 5)
    assert decode_ack(r.ack("m7", 1, NOW), KEY).covers(5)
    # a sender that lost its journal starts a new epoch at 0: none of it is a replay
    for s in range(3):
        item = r.receive(_dg(s, epoch=2), NOW)
        assert (item.epoch, item.seq) == (2, s)
        r.mark_durable("m7", 2, s)
    assert decode_ack(r.ack("m7", 2, NOW), KEY).cumulative == 3  # epochs are separate


@pytest.mark.parametrize("seq", [2**63, 2**63 + 5, 2**64 - 1])
def test_sequence_numbers_beyond_2_63_are_refused_and_answered(seq: int) -> None:
    r = _rx()
    body = bytearray(HEADER.pack(MAGIC, 2, TYPE_DATA, 7, EPOCH))
    good = _dg(0)
    body += seq.to_bytes(8, "big") + good[len(body) + 8:-TAG_BYTES]
    dg = bytes(body) + tag(KEY.secret, body)
    with pytest.raises(RefusedError) as info:
        r.receive(dg, NOW)
    assert info.value.reason == "bad_seq" and info.value.seq == seq
    ref = decode_refusal(r.refusal(info.value, NOW), KEY)
    assert (ref.epoch, ref.seq, ref.reason) == (EPOCH, seq, "bad_seq")


def test_forgeries_are_rejected_before_anything_else_and_never_answered() -> None:
    r = _rx()
    r.receive(_dg(3), NOW)
    r.mark_durable("m7", EPOCH, 3)
    before = decode_ack(r.ack("m7", EPOCH, NOW), KEY).cumulative
    dg = bytearray(_dg(3))
    dg[50] ^= 0x10  # a value changed in flight
    with pytest.raises(BadHmacError) as info:
        r.receive(bytes(dg), NOW)
    assert not info.value.authenticated
    thief = MachineKey(7, "m7", b"x" * 32, LAYOUT)  # right id, wrong secret, a durable seq
    with pytest.raises(BadHmacError) as info:
        r.receive(_dg(3, key=thief), NOW)
    assert info.value.machine_id is None and info.value.seq is None
    forged = bytearray(_dg(1000, low=999))
    forged[-TAG_BYTES:] = bytes(TAG_BYTES)
    with pytest.raises(BadHmacError):
        r.receive(bytes(forged), NOW)
    assert decode_ack(r.ack("m7", EPOCH, NOW), KEY).cumulative == before == 4  # nothing moved
    assert r.receive(_dg(4), NOW).seq == 4


def test_unknown_machine_and_server_datagrams_sent_to_the_server() -> None:
    r = Receiver(lambda wid: KEY if wid == 7 else None)
    other = MachineKey(8, "m8", b"k" * 32, LAYOUT)
    with pytest.raises(UnknownMachineError) as info:
        r.receive(_dg(0, key=other), NOW)
    assert info.value.reason == "unknown_machine" and info.value.wire_id == 8
    with pytest.raises(GarbageError):
        r.receive(encode_ack(KEY, 3), NOW)


@pytest.mark.parametrize(("case", "reason"), [
    ("pressure 5.5e15 Pa", "out_of_range"),
    ("negative pressure", "out_of_range"),
    ("infinite position", "out_of_range"),
    ("t0 = -2**63", "bad_time"),
    ("t0 = 2**63 - 11", "bad_time"),
    ("year 1677", "bad_time"),
    ("1970", "bad_time"),
    ("year 2200", "bad_time"),
    ("one hour ahead", "bad_time"),
    ("1201 bytes", "oversize"),
])
def test_validation_at_the_edge_refuses_with_a_reason(case: str, reason: str) -> None:
    r = _rx()
    v = np.array([[1e6, 0.1], [1.005e6, 0.1001]])
    t0 = NOW
    if case == "pressure 5.5e15 Pa":
        v[1, 0] = 5.5e15
    elif case == "negative pressure":
        v[0, 0] = -3e6  # the margin is 10 % of 25 MPa
    elif case == "infinite position":
        v[0, 1] = 1e9  # quantises (≤ 2**53 quanta) but far beyond the 1 m stroke
    elif case == "t0 = -2**63":
        t0 = -(2**63)
    elif case == "t0 = 2**63 - 11":
        t0 = 2**63 - 11 - PERIOD
    elif case == "year 1677":
        t0 = -(2**63) + 10**18
    elif case == "1970":
        t0 = 0
    elif case == "year 2200":
        t0 = 7_258_118_400 * 10**9
    elif case == "one hour ahead":
        t0 = NOW + 3600 * 10**9
    if case == "1201 bytes":
        rng = np.random.default_rng(0)
        v = np.column_stack([rng.integers(0, 5000, 4000) * 5000.0,
                             rng.integers(0, 10000, 4000) * 1e-4])
        dg = _dg(9, values=v)
        assert len(dg) > 1200
    else:
        dg = _dg(9, t0=t0, values=v)
    with pytest.raises(RefusedError) as info:
        r.receive(dg, NOW)
    err = info.value
    assert err.reason == reason and (err.machine_id, err.epoch, err.seq) == ("m7", EPOCH, 9)
    ref = decode_refusal(r.refusal(err, NOW), KEY)
    assert (ref.seq, ref.reason) == (9, reason)
    # a day-old batch (the machine was offline) and the margin are fine
    ok = np.array([[25e6 + 2e6, 0.1], [-2e6, 0.0]])
    assert r.receive(_dg(10, t0=NOW - 86400 * 10**9, values=ok), NOW).seq == 10


def test_limits_are_configurable() -> None:
    r = _rx(max_past_s=60.0, max_future_s=1.0, range_margin=0.0)
    with pytest.raises(RefusedError):
        r.receive(_dg(0, t0=NOW - 120 * 10**9), NOW)
    with pytest.raises(RefusedError):
        r.receive(_dg(1, values=np.array([[25.005e6, 0.1]])), NOW)


def test_status_shares_the_sequence_space_and_is_validated() -> None:
    key = MachineKey(7, "m7", b"k" * 32, Layout(LAYOUT.channels + (
        ChannelSpec("slew_angle", -3.5, 3.5, 1e-4, True),)))
    r = Receiver({7: key})
    rep = r.receive(encode_status(key, StatusReport("", 4, NOW, 60.0, 25.0, 10.0, 5.0,
                                                    {"slew_angle": 0.5}, epoch=EPOCH)), NOW)
    assert isinstance(rep, StatusReport) and rep.machine_id == "m7" and rep.epoch == EPOCH
    r.mark_durable("m7", EPOCH, 4)
    with pytest.raises(ReplayedError):
        r.receive(encode_status(key, StatusReport("", 4, NOW, epoch=EPOCH)), NOW)
    with pytest.raises(RefusedError) as info:
        r.receive(encode_status(key, StatusReport("", 5, NOW, channels={"slew_angle": 300.0},
                                                  epoch=EPOCH)), NOW)
    assert info.value.reason == "out_of_range"
    with pytest.raises(RefusedError) as info:
        r.receive(encode_status(key, StatusReport("", 6, 0, epoch=EPOCH)), NOW)
    assert info.value.reason == "bad_time"


def test_version_1_datagrams_are_served_as_epoch_0_with_version_1_acks() -> None:
    r = _rx()
    dg = encode_data(KEY, 1_700_000_000_000, NOW, PERIOD, np.array([[1e6, 0.1]]), epoch=0,
                     version=1)
    item = r.receive(dg, NOW)
    assert item.epoch == 0 and item.seq == 1_700_000_000_000
    r.mark_durable("m7", 0, item.seq)
    a = r.ack("m7", 0, NOW)
    assert a[2] == 1 and decode_ack(a, KEY).covers(1_700_000_000_000)
    # a refusal of a version-1 datagram releases it with an ack (v1 has no refusals)
    bad = encode_data(KEY, 1_700_000_000_001, 0, PERIOD, np.array([[1e6, 0.1]]), epoch=0,
                      version=1)
    with pytest.raises(RefusedError) as info:
        r.receive(bad, NOW)
    assert decode_ack(r.refusal(info.value, NOW), KEY).covers(1_700_000_000_001)


def test_memory_is_bounded_and_forgetting_only_lets_authentic_repeats_in(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(receiver_mod, "MAX_INTERVALS", 8)
    monkeypatch.setattr(receiver_mod, "MAX_EPOCHS", 2)
    r = _rx()
    for s in range(1, 60, 2):  # every other seq: one interval each
        r.receive(_dg(s, low=0), NOW)
        r.mark_durable("m7", EPOCH, s)
    ep = r._by_id["m7"].epochs[EPOCH]
    assert len(ep.starts) == 8
    assert r.receive(_dg(1, low=0), NOW).seq == 1  # forgotten: accepted again (idempotent)
    with pytest.raises(ReplayedError):
        r.receive(_dg(59, low=0), NOW)
    for e in (5, 6, 7):
        r.receive(_dg(0, epoch=e), NOW)
    assert list(r._by_id["m7"].epochs) == [6, 7]


def test_every_reply_is_to_an_authenticated_datagram() -> None:
    """Whatever the bytes, only errors of authenticated datagrams may be answered."""
    r = _rx()
    rng = np.random.default_rng(5)
    good = _dg(3)
    answered = 0
    for i in range(3000):
        g = bytearray(good)
        for _ in range(1 + i % 4):
            g[rng.integers(0, len(g))] ^= 1 << int(rng.integers(0, 8))
        try:
            r.receive(bytes(g), NOW)
        except (ReplayedError, RefusedError):
            answered += 1
        except DatagramError as exc:
            assert not exc.authenticated
    assert answered == 0  # a corrupted datagram never verifies


def test_clock_offset_is_the_minimum_delay_estimate() -> None:
    r = _rx()
    rng = np.random.default_rng(0)
    theta = 3_000_000_000  # server runs 3 s ahead of the machine
    d_min = 20_000_000
    for i in range(200):
        t0 = NOW + i * 2 * PERIOD
        send_machine = t0 + 2 * PERIOD  # the batch is complete one period after its last sample
        recv_server = send_machine + theta + d_min + int(rng.exponential(50e6))
        r.receive(_dg(i, t0=t0), recv_server)
    est = r.clock_offset_ns("m7")
    assert est is not None
    assert theta + d_min <= est <= theta + d_min + 5_000_000
    assert r.clock_offset_ns("nobody") is None


def test_ack_is_authenticated_for_the_machine() -> None:
    r = _rx()
    r.receive(_dg(0), NOW)
    r.mark_durable("m7", EPOCH, 0)
    a = r.ack("m7", EPOCH, 5)
    body = a[:-TAG_BYTES]
    assert a[-TAG_BYTES:] == tag(KEY.secret, body)
    with pytest.raises(BadHmacError):
        decode_ack(a, MachineKey(7, "m7", b"y" * 32, LAYOUT))
