"""Codec laws of the wire format: round trips, losslessness, and malformed input → ProtocolError."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cranetwin.errors import ProtocolError
from cranetwin.model import load_machine
from cranetwin.protocol import (
    REASONS,
    TAG_BYTES,
    Ack,
    BadHmacError,
    ChannelSpec,
    DatagramError,
    GarbageError,
    Layout,
    LayoutError,
    MachineKey,
    StatusReport,
    TruncatedError,
    WrongVersionError,
    decode_ack,
    decode_data,
    decode_status,
    encode_ack,
    encode_data,
    encode_status,
    measure_bytes_per_sample,
    on_grid,
    peek_header,
)
from cranetwin.protocol.status import ALT_SCALE, DEG_SCALE
from cranetwin.protocol.wire import get_varint, put_varint, tag, unzigzag, zigzag

PATU = load_machine("patu655")
KEY = MachineKey(42, "crane-042", b"s" * 32, Layout.from_channels(PATU.channels))
PERIOD = 10_000_000


def _grid_values(draw: st.DrawFn, layout: Layout, n: int) -> np.ndarray:
    """Values k·resolution: random walks or iid integers of a drawn magnitude, with NaNs."""
    c = len(layout.channels)
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    bits = draw(st.sampled_from([0, 1, 3, 8, 20, 40]))
    k = rng.integers(-(2**bits), 2**bits + 1, (n, c))
    if draw(st.booleans()):
        k = np.cumsum(k, axis=0) + rng.integers(-(2**40), 2**40, c)
    v = k.astype(np.float64) * np.asarray(layout.resolutions)
    v[rng.random((n, c)) < draw(st.sampled_from([0.0, 0.05, 0.5, 1.0]))] = np.nan
    return v


@st.composite
def layouts(draw: st.DrawFn) -> Layout:
    c = draw(st.integers(1, 32))
    res = draw(st.lists(st.sampled_from([1e-4, 5000.0, 5.0, 0.1, 1.0, 3e-7, 0.25]),
                        min_size=c, max_size=c))
    return Layout(tuple(ChannelSpec(f"ch{i}", -1.0, 1.0, r) for i, r in enumerate(res)))


@st.composite
def batches(draw: st.DrawFn) -> tuple[MachineKey, int, int, int, int, np.ndarray]:
    layout = draw(layouts())
    secret = draw(st.binary(min_size=16, max_size=64))
    key = MachineKey(draw(st.integers(0, 2**32 - 1)), "m", secret, layout)
    n = draw(st.integers(1, 70))
    seq = draw(st.integers(0, 2**63 - 1))
    low = draw(st.integers(0, seq))
    t0 = draw(st.integers(-(2**63), 2**63 - 1))
    period = draw(st.integers(1, 2**32 - 1))
    return key, seq, low, t0, period, _grid_values(draw, layout, n)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(batches(), st.integers(0, 2**63 - 1))
def test_data_round_trip_is_exact_on_the_resolution_grid(
        case: tuple[MachineKey, int, int, int, int, np.ndarray], epoch: int) -> None:
    key, seq, low, t0, period, v = case
    version = 1 if epoch == 0 else 2  # version 1 (no epoch) still decodes, as epoch 0
    dg = encode_data(key, seq, t0, period, v, oldest_unacked=low, epoch=epoch, version=version)
    block = decode_data(dg, key)
    assert block.seq == seq and block.t0_ns == t0 and block.period_ns == period
    assert block.epoch == epoch
    assert block.machine_id == key.machine_id and block.channels == key.layout.names
    assert block.values.shape == v.shape
    assert np.array_equal(block.values, v, equal_nan=True)  # bit-exact, NaN where NaN


@settings(max_examples=100, deadline=None)
@given(st.integers(1, 60), st.integers(0, 2**31))
def test_off_grid_values_decode_to_the_nearest_grid_point(n: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    span = np.array([c.max - c.min for c in KEY.layout.channels])
    v = np.array([c.min for c in KEY.layout.channels]) + rng.random((n, 11)) * span
    back = decode_data(encode_data(KEY, 1, 0, PERIOD, v), KEY).values
    res = np.asarray(KEY.layout.resolutions)
    assert np.all(np.abs(back - v) <= res / 2 * (1 + 1e-9))
    assert np.array_equal(back, on_grid(v, KEY.layout.resolutions))


def test_all_missing_column_is_left_out_and_costs_nothing() -> None:
    v = np.zeros((20, 11))
    v[:, 10] = np.nan
    short = encode_data(KEY, 1, 0, PERIOD, v)
    full = encode_data(KEY, 1, 0, PERIOD, np.zeros((20, 11)))
    assert len(short) < len(full)
    assert np.isnan(decode_data(short, KEY).values[:, 10]).all()


def test_varint_and_zigzag_laws() -> None:
    for v in [0, 1, -1, 63, -64, 2**62, -(2**63), 2**63 - 1]:
        assert unzigzag(zigzag(v)) == v
    assert [zigzag(v) for v in (0, -1, 1, -2, 2)] == [0, 1, 2, 3, 4]
    for u in [0, 1, 127, 128, 300, 2**63, 2**64 - 1]:
        out = bytearray()
        put_varint(out, u)
        assert get_varint(bytes(out), 0, len(out)) == (u, len(out))
    buf = bytearray()
    put_varint(buf, 300)
    assert bytes(buf) == b"\xac\x02"
    with pytest.raises(GarbageError):
        get_varint(b"\xff" * 10 + b"\x01", 0, 11)
    with pytest.raises(TruncatedError):
        get_varint(b"\x80", 0, 1)


@settings(max_examples=150, deadline=None)
@given(st.integers(0, 2**64 - 1026), st.data())
def test_ack_round_trip(cum: int, data: st.DataObject) -> None:
    sel = data.draw(st.sets(st.integers(cum + 1, min(cum + 1024, 2**64 - 1)), max_size=40))
    t = data.draw(st.integers(-(2**63), 2**63 - 1))
    epoch = data.draw(st.integers(0, 2**63 - 1))
    ack = decode_ack(encode_ack(KEY, cum, sel, server_time_ns=t, epoch=epoch,
                                version=1 if epoch == 0 else 2), KEY)
    assert ack == Ack(cum, tuple(sorted(sel)), t, epoch)
    assert all(ack.covers(s) for s in sel)
    assert cum == 0 or ack.covers(cum - 1)
    assert not ack.covers(cum)


@settings(max_examples=150, deadline=None)
@given(st.integers(0, 2**63 - 1), st.integers(-(2**63), 2**63 - 1),
       st.floats(-90, 90), st.floats(-180, 180), st.floats(-1e5, 1e5),
       st.floats(0, 1e6), st.booleans(), st.integers(-35000, 35000))
def test_status_round_trip(seq: int, t: int, lat: float, lon: float, alt: float, hours: float,
                           gps: bool, angle_k: int) -> None:
    rep = StatusReport("crane-042", seq, t, lat if gps else math.nan, lon if gps else math.nan,
                       alt, hours, {"slew_angle": angle_k * 1e-4})
    back = decode_status(encode_status(KEY, rep), KEY)
    assert back.seq == seq and back.t_ns == t and back.machine_id == "crane-042"
    # Each field is the nearest point of its wire lattice; that point's float may lie one ulp
    # beyond half a step from the input (0.3125 m → 312 mm → 0.312 is 0.5e-3 + 4e-19 away).
    slack = 1 + 1e-12
    if gps:
        assert back.latitude_deg == round(lat * DEG_SCALE) / DEG_SCALE
        assert back.longitude_deg == round(lon * DEG_SCALE) / DEG_SCALE
        assert back.altitude_m == round(alt * ALT_SCALE) / ALT_SCALE
        assert abs(back.latitude_deg - lat) <= 0.5e-7 * slack
        assert abs(back.longitude_deg - lon) <= 0.5e-7 * slack
        assert abs(back.altitude_m - alt) <= 0.5e-3 * slack
    else:
        assert math.isnan(back.latitude_deg) and math.isnan(back.altitude_m)
    assert back.operating_hours == round(hours * 3600.0) / 3600.0
    assert abs(back.operating_hours - hours) <= 0.5 / 3600 * slack
    assert back.channels == {"slew_angle": angle_k * 1e-4}


def _sample() -> bytes:
    rng = np.random.default_rng(1)
    k = np.cumsum(rng.integers(-3, 4, (50, 11)), axis=0) + 1000
    v = k * np.asarray(KEY.layout.resolutions)
    v[rng.random(v.shape) < 0.05] = np.nan
    return encode_data(KEY, 7, 10**18, PERIOD, v, oldest_unacked=3)


def _resign(body: bytes, key: MachineKey = KEY) -> bytes:
    return body + tag(key.secret, body)


def _decode_any(dg: bytes) -> object:
    head = peek_header(dg)
    if head.type == 1:
        return decode_data(dg, KEY)
    if head.type == 2:
        return decode_status(dg, KEY)
    return decode_ack(dg, KEY)


def test_every_truncation_raises_protocol_error_only() -> None:
    for dg in (_sample(), encode_status(KEY, StatusReport("x", 3, 0, 1.0, 2.0, 3.0, 4.0)),
               encode_ack(KEY, 5, [7, 9])):
        for cut in range(len(dg)):
            for cand in (dg[:cut], _resign(dg[:cut][:-TAG_BYTES]) if cut > TAG_BYTES else b""):
                with pytest.raises(DatagramError) as info:
                    _decode_any(cand)
                assert info.value.reason in REASONS


def test_specific_reasons() -> None:
    dg = _sample()
    with pytest.raises(GarbageError):
        decode_data(b"GET / HTTP/1.1\r\n\r\n" + bytes(40), KEY)
    with pytest.raises(WrongVersionError):
        decode_data(dg[:2] + b"\x03" + dg[3:], KEY)
    with pytest.raises(BadHmacError):
        decode_data(dg[:-1] + bytes([dg[-1] ^ 1]), KEY)
    other = MachineKey(42, "crane-042", b"t" * 32, KEY.layout)
    with pytest.raises(BadHmacError):
        decode_data(dg, other)
    small = MachineKey(42, "crane-042", KEY.secret, Layout(KEY.layout.channels[:10]))
    with pytest.raises(LayoutError):
        decode_data(dg, small)
    with pytest.raises(GarbageError):  # trailing byte, correctly signed
        decode_data(_resign(dg[:-TAG_BYTES] + b"\x00"), KEY)
    with pytest.raises(GarbageError):  # a data datagram is not an ack
        decode_ack(dg, KEY)
    assert issubclass(DatagramError, ProtocolError)


@settings(max_examples=500, deadline=None)
@given(st.binary(max_size=1300))
def test_random_bytes_raise_protocol_error_only(raw: bytes) -> None:
    for cand in (raw, b"CT\x01" + raw, b"CT\x01\x01" + raw, b"CT\x01\x01\x00\x00\x00\x2a" + raw):
        for c in (cand, _resign(cand)):
            try:
                _decode_any(c)
            except DatagramError as err:
                assert err.reason in REASONS


def test_100k_mutations_raise_protocol_error_only() -> None:
    """Bit flips, byte writes, cuts, insertions and splices, half of them re-signed so that the
    body parser sees them; any exception other than DatagramError fails the test."""
    rng = np.random.default_rng(2026)
    seeds = [_sample(), encode_status(KEY, StatusReport("x", 9, 5, 60.0, 25.0, 1.0, 2.0,
                                                        {"slew_angle": 0.1})),
             encode_ack(KEY, 100, [102, 110])]
    reasons: dict[str, int] = {}
    ok = 0
    n = 100_000
    ops = rng.integers(0, 5, n)
    for i in range(n):
        dg = bytearray(seeds[i % 3])
        op = ops[i]
        p = int(rng.integers(0, len(dg)))
        if op == 0:
            dg[p] ^= 1 << int(rng.integers(0, 8))
        elif op == 1:
            dg[p] = int(rng.integers(0, 256))
        elif op == 2:
            del dg[p:]
        elif op == 3:
            dg[p:p] = rng.bytes(int(rng.integers(1, 9)))
        else:
            q = int(rng.integers(0, len(dg)))
            dg[p:] = seeds[(i + 1) % 3][q:]
        cand = bytes(dg)
        if i % 2 and len(cand) > TAG_BYTES:
            cand = _resign(cand[:-TAG_BYTES])
        try:
            _decode_any(cand)
            ok += 1
        except DatagramError as err:
            reasons[err.reason] = reasons.get(err.reason, 0) + 1
    assert set(reasons) <= set(REASONS)
    assert {"garbage", "truncated", "bad_hmac", "wrong_version"} <= set(reasons)
    assert ok > 0  # some re-signed mutations of sample values are valid datagrams


def test_key_repr_hides_the_secret() -> None:
    assert "sss" not in repr(KEY) and "32 bytes" in repr(KEY)


def test_patu655_bandwidth_target_on_noisy_smooth_motion() -> None:
    """≤ 20 bytes/sample (payload incl. headers and tag) for 11 channels at 100 Hz, lossless."""
    rng = np.random.default_rng(5)
    t = np.arange(3000) * 0.01
    cols = []
    for ch in PATU.channels:
        mid, amp = (ch.min + ch.max) / 2, (ch.max - ch.min) * 0.3
        x = mid + amp * np.sin(2 * np.pi * t / 8 + rng.uniform(0, 6))
        x = x + rng.normal(0, 2 * ch.resolution, t.size)
        cols.append(np.round(x / ch.resolution) * ch.resolution)
    v = np.stack(cols, axis=1)
    v[rng.random(v.shape) < 0.01] = np.nan
    stats = measure_bytes_per_sample(KEY, v, PERIOD, batch_samples=50)
    assert stats.lossless
    assert stats.bytes_per_sample <= 20.0
    assert stats.max_datagram_bytes <= 1200
    assert stats.samples == 3000 and stats.datagrams == 60


def test_oversize_batches_are_split_below_the_mtu_limit() -> None:
    rng = np.random.default_rng(3)
    v = rng.integers(-(2**30), 2**30, (400, 11)) * np.asarray(KEY.layout.resolutions)
    stats = measure_bytes_per_sample(KEY, v, PERIOD, batch_samples=400)
    assert stats.max_datagram_bytes <= 1200 and stats.lossless and stats.datagrams > 1


def test_protocol_imports_no_io_modules() -> None:
    code = ("import sys, cranetwin.protocol; bad = {'socket', 'asyncio', 'sqlalchemy', "
            "'fastapi', 'selectors'} & set(sys.modules); print(sorted(bad))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_length_limits() -> None:
    rng = np.random.default_rng(9)
    k = np.cumsum(rng.integers(-2, 3, (4096, 11)), axis=0)
    v = k * np.asarray(KEY.layout.resolutions)
    assert np.array_equal(decode_data(encode_data(KEY, 0, 0, PERIOD, v), KEY).values, v)
    one = decode_data(encode_data(KEY, 0, 5, PERIOD, v[:1]), KEY)
    assert one.n == 1 and np.array_equal(one.values, v[:1])
    for bad in (v[:0], np.vstack([v, v[:1]])):
        with pytest.raises(ValueError):
            encode_data(KEY, 0, 0, PERIOD, bad)
    with pytest.raises(ValueError):
        encode_data(KEY, 5, 0, PERIOD, v[:3], oldest_unacked=6)
