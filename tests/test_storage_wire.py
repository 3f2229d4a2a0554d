"""What the wire carried is what storage returns: integer steps, values bit for bit, exact sample
times and the carried period, on SQLite and PostgreSQL; rows written before the shared codec still
read back."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cranetwin import codec as intcodec
from cranetwin.protocol import ChannelSpec, Layout, MachineKey, decode_data, encode_data
from cranetwin.samples import SampleBlock
from cranetwin.storage import Store, codec
from cranetwin.storage.blocks import MAX_SPAN_NS, read_range

SECRET = b"0123456789abcdef0123456789abcdef"
STEP_LIMIT = 2**52  # storage keeps |steps| below this
_ids = itertools.count(1)

pytestmark = pytest.mark.timeout(300)


@pytest.fixture
def store(db_url: str) -> Store:
    return Store.open(db_url)


@st.composite
def datagrams(draw: st.DrawFn) -> tuple[MachineKey, bytes]:
    """A data datagram of any layout: any resolution, steps up to the storage limit, gaps."""
    c = draw(st.integers(1, 12))
    res = draw(st.lists(st.one_of(st.sampled_from([1e-4, 3e-7, 0.1, 5.0, 5000.0]),
                                  st.floats(1e-6, 1e4, allow_nan=False)),
                        min_size=c, max_size=c))
    wid = next(_ids)
    key = MachineKey(wid, f"m{wid}", SECRET,
                     Layout(tuple(ChannelSpec(f"ch{i}", -1.0, 1.0, r) for i, r in enumerate(res))))
    n = draw(st.integers(1, 60))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    bits = draw(st.sampled_from([0, 3, 12, 30, 50, 51]))
    k = rng.integers(-(2**bits), 2**bits + 1, (n, c))
    if draw(st.booleans()):  # extremes
        k[rng.random((n, c)) < 0.3] = STEP_LIMIT - 1
        k[rng.random((n, c)) < 0.3] = -(STEP_LIMIT - 1)
    v = k.astype(np.float64) * np.asarray(res)
    v[rng.random((n, c)) < draw(st.sampled_from([0.0, 0.1, 0.6, 1.0]))] = np.nan
    period = draw(st.integers(1, 2**32 - 1))
    while (n - 1) * period > MAX_SPAN_NS:
        n -= 1
    t0 = draw(st.integers(0, 2**62))
    return key, encode_data(key, draw(st.integers(0, 2**40)), t0, period, v[:n], epoch=7)


def _register(store: Store, key: MachineKey) -> None:
    store.add_machine(key.machine_id, key.wire_id, key.secret)


@settings(max_examples=40, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(dg=datagrams())
def test_wire_to_storage_to_read_returns_what_the_wire_carried(
        store: Store, dg: tuple[MachineKey, bytes]) -> None:
    key, datagram = dg
    carried = decode_data(datagram, key)
    assert carried.steps is not None
    _register(store, key)
    res = store.write_batch([carried])
    if np.abs(carried.steps).max() >= STEP_LIMIT:  # beyond what storage keeps: refused, said so
        assert res.refused
        return
    assert len(res.new) == 1 and res.new[0] is carried
    got = store.read_samples(key.machine_id, carried.t0_ns / 1e9 - 1.0,
                             carried.t_end_ns / 1e9 + 1.0)
    assert got.t_ns is not None
    assert np.array_equal(got.t_ns, carried.times_ns())
    assert got.period_ns == carried.period_ns
    assert got.channels == carried.channels
    assert np.array_equal(got.values, carried.values, equal_nan=True)  # bit for bit
    with store._session() as s:  # the stored run itself: the same integer steps
        (blk,) = read_range(s, store._pk[key.machine_id], carried.t0_ns, carried.t_end_ns)
    assert (blk.t0_ns, blk.period_ns, blk.resolution) == (carried.t0_ns, carried.period_ns,
                                                          carried.resolution)
    assert np.array_equal(blk.steps, carried.steps)
    assert np.array_equal(blk.missing, np.isnan(carried.values))


def test_decoded_steps_are_the_quantised_values(store: Store) -> None:
    layout = Layout((ChannelSpec("a", -1.0, 1.0, 0.1), ChannelSpec("b", -1.0, 1.0, 5000.0),
                     ChannelSpec("c", -1.0, 1.0, 1.0)))
    key = MachineKey(900, "m900", SECRET, layout)
    v = np.array([[0.1, 5000.0, np.nan], [np.nan, -10000.0, np.nan], [0.7, 0.0, np.nan]])
    blk = decode_data(encode_data(key, 1, 10**18, 10_000_000, v), key)
    assert blk.steps is not None
    assert blk.steps.tolist() == [[1, 1, 0], [0, -2, 0], [7, 0, 0]]
    assert np.array_equal(blk.values, intcodec.on_grid(v, layout.resolutions), equal_nan=True)


def test_read_reports_no_period_when_it_changes_inside_the_range(store: Store) -> None:
    store.add_machine("m", 1, SECRET)
    chans, res = ("a",), (0.5,)
    t0 = 1_700_000_000 * 10**9
    b1 = SampleBlock("m", 1, t0, 10_000_000, chans, res, np.arange(10.0)[:, None] * 0.5)
    b2 = SampleBlock("m", 2, t0 + 10**9, 20_000_000, chans, res, np.arange(5.0)[:, None] * 0.5)
    store.write_blocks([b1, b2])
    each = store.read_samples("m", t0 / 1e9, (t0 + 9 * 10_000_000) / 1e9 + 1e-3)
    assert each.period_ns == 10_000_000 and each.t_ns is not None and each.t_ns.size == 10
    both = store.read_samples("m", t0 / 1e9, t0 / 1e9 + 10.0)
    assert both.period_ns is None
    assert both.t_ns is not None
    assert np.array_equal(both.t_ns, np.concatenate([b1.times_ns(), b2.times_ns()]))
    assert np.array_equal(both.t_s, both.t_ns / 1e9)


def test_blocks_without_steps_are_quantised_once_as_before(store: Store) -> None:
    store.add_machine("m", 1, SECRET)
    v = np.array([[0.1 + 1e-12, np.nan], [0.2, 3.0]])
    b = SampleBlock("m", 1, 10**18, 10_000_000, ("a", "b"), (0.1, 1.0), v)
    store.write_blocks([b])
    got = store.read_samples("m", 0, 2e9)
    assert np.array_equal(got.values, intcodec.on_grid(v, (0.1, 1.0)), equal_nan=True)
    assert got.period_ns == 10_000_000


def test_blocks_with_malformed_steps_are_refused(store: Store) -> None:
    store.add_machine("m", 1, SECRET)
    v = np.array([[1.0], [2.0]])
    bad = [SampleBlock("m", 1, 10**18, 10, ("a",), (1.0,), v, steps=np.array([[1], [2], [3]])),
           SampleBlock("m", 2, 2 * 10**18, 10, ("a",), (1.0,), v, steps=v.copy())]
    res = store.write_batch(bad)
    assert [o.reason for o in res.outcomes] == ["unstorable", "unstorable"]


# Blobs written by the storage codec before it was built on cranetwin.codec (same format, v1).
_OLD_BLOB = bytes.fromhex(
    "0108010004000000040000007801636062e45c20dcddc4c0cb17c1c0c6fa9f0108f819f8f98114131083f920"
    "31282089cfc4c084ae9e1d66108c565a0400f11f0943")
_OLD_SMALL = bytes.fromhex("010100000400000002000000789c6360628c6208f077030003b20143")


def test_blobs_written_before_the_shared_codec_still_decode_and_are_rewritten_identically() -> None:
    k = np.array([[0, 2000, -7, 2**40], [1, 1990, -7, 2**40 + 3], [0, 0, 0, 0],
                  [-5, 1985, 300, -(2**50)]], dtype=np.int64)
    m = np.zeros(k.shape, dtype=bool)
    m[2, :] = True
    m[0, 2] = True
    k[m] = 0
    got, mask = codec.decode_ints(_OLD_BLOB)
    assert np.array_equal(got, k) and np.array_equal(mask, m)
    assert codec.encode_many(k[None], m[None])[0] == _OLD_BLOB
    small, none = codec.decode_ints(_OLD_SMALL)
    assert np.array_equal(small, k[:, :2] % 50) and not none.any()
    assert codec.encode_ints(k[:, :2] % 50) == _OLD_SMALL
