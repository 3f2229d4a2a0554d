"""Storage laws, on SQLite and PostgreSQL: idempotent block writes, exact read-back, summaries that
agree with the raw samples, idempotent derived summaries and events, secrets never listed."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from sqlalchemy import inspect

from cranetwin.errors import StorageError
from cranetwin.samples import SampleBlock
from cranetwin.storage import Event, Store, UnknownMachineError, codec

CHANNELS = ("lift_pA", "lift_pB", "lift_s", "slew_torque")
RES = (5000.0, 5000.0, 1e-4, 5.0)
T0_NS = 1_700_000_000 * 10**9 + 250_000_000  # not on a second boundary
PERIOD = 10_000_000  # 100 Hz
SECRET = b"0123456789abcdef0123456789abcdef"

pytestmark = pytest.mark.timeout(60)


def make_block(machine: str, seq: int, n: int = 100, rng: np.random.Generator | None = None,
               t0_ns: int | None = None) -> SampleBlock:
    """A block of ``n`` samples starting right after block ``seq - 1`` (random-walk values)."""
    rng = rng or np.random.default_rng(seq)
    k = np.cumsum(rng.integers(-30, 31, size=(n, len(CHANNELS))), axis=0) + 2000
    t0 = T0_NS + seq * n * PERIOD if t0_ns is None else t0_ns
    return SampleBlock(machine, seq, t0, PERIOD, CHANNELS, RES, k * np.asarray(RES))


@pytest.fixture
def store(db_url: str) -> Store:
    s = Store.open(db_url)
    s.add_machine("crane-1", 1, SECRET)
    s.add_machine("crane-2", 2, SECRET[::-1], metadata={"site": "Lappeenranta"})
    return s


def test_open_migrates_and_is_repeatable(db_url: str) -> None:
    Store.open(db_url).close()
    s = Store.open(db_url)
    tables = set(inspect(s.engine).get_table_names())
    assert {"machines", "sample_blocks", "summaries", "events", "alembic_version"} <= tables


def test_open_rejects_unknown_database() -> None:
    with pytest.raises(StorageError, match="unsupported database"):
        Store.open("mysql://nobody@127.0.0.1/x")


def test_machines_listed_without_secret(store: Store) -> None:
    ms = store.machines()
    assert [m.machine_id for m in ms] == ["crane-1", "crane-2"]
    assert ms[1].metadata == {"site": "Lappeenranta"}
    for m in ms:
        assert not hasattr(m, "secret")
        assert SECRET.hex() not in repr(m) and "0123456789abcdef" not in repr(m)
    assert store.machine_keys()[1] == ("crane-1", SECRET)


@pytest.mark.parametrize("kwargs", [{"machine_id": "crane-1", "wire_id": 9},
                                    {"machine_id": "crane-9", "wire_id": 1}])
def test_add_machine_rejects_duplicates(store: Store, kwargs: dict[str, object]) -> None:
    with pytest.raises(StorageError, match="already registered"):
        store.add_machine(secret=SECRET, **kwargs)  # type: ignore[arg-type]


@pytest.mark.parametrize(("wire_id", "secret"), [(-1, SECRET), (2**32, SECRET), (5, b"short")])
def test_add_machine_rejects_bad_values(store: Store, wire_id: int, secret: bytes) -> None:
    with pytest.raises(StorageError):
        store.add_machine("crane-x", wire_id, secret)


def test_unknown_machine_raises(store: Store) -> None:
    with pytest.raises(UnknownMachineError, match="nope"):
        store.get_machine("nope")
    with pytest.raises(UnknownMachineError):
        store.write_blocks([make_block("nope", 0)])


def test_write_blocks_is_idempotent_and_reads_back_exactly(store: Store) -> None:
    blocks = [make_block("crane-1", s) for s in range(10)]
    assert store.write_blocks(blocks[:6]) == 6
    # overlap with what is stored plus a duplicate inside the same batch
    assert store.write_blocks(blocks[4:] + [blocks[7]]) == 4
    assert store.write_blocks(blocks) == 0
    got = store.read_samples("crane-1", 0.0, 2e9)
    expected = np.concatenate([b.values for b in blocks])
    t_exp = np.concatenate([b.times_ns() for b in blocks])
    assert got.channels == CHANNELS
    assert np.array_equal(got.values, expected)  # bit-exact, not approximately
    assert np.max(np.abs(got.t_s - t_exp / 1e9)) < 1e-6  # float64 seconds: sub-µs at 2023
    st_ = store.stats("crane-1")
    assert (st_.blocks, st_.samples) == (10, 1000)
    assert store.stats("crane-2").samples == 0


def test_read_samples_half_open_range_and_order(store: Store) -> None:
    blocks = [make_block("crane-1", s) for s in (3, 0, 2, 1)]  # stored out of order
    store.write_blocks(blocks)
    t0 = (T0_NS + 150 * PERIOD) / 1e9
    t1 = (T0_NS + 250 * PERIOD) / 1e9
    got = store.read_samples("crane-1", t0, t1)
    assert got.t_s.size == 100
    assert np.all(np.diff(got.t_s) > 0)
    ordered = np.concatenate([make_block("crane-1", s).values for s in range(4)])
    assert np.array_equal(got.values, ordered[150:250])


def test_read_samples_merges_channel_layouts_and_nan(store: Store) -> None:
    a = make_block("crane-1", 0, n=10)
    vals = a.values.copy()
    vals[2, 1] = np.nan
    a = SampleBlock("crane-1", 0, a.t0_ns, PERIOD, CHANNELS, RES, vals)
    b = SampleBlock("crane-1", 1, a.t0_ns + 10 * PERIOD, PERIOD, ("slew_angle",), (1e-4,),
                    np.arange(5.0)[:, None] * 1e-4)
    store.write_blocks([a, b])
    got = store.read_samples("crane-1", 0, 2e9)
    assert got.channels == (*CHANNELS, "slew_angle")
    assert np.isnan(got.values[2, 1]) and np.isnan(got.values[:10, 4]).all()
    assert np.isnan(got.values[10:, :4]).all()
    assert np.array_equal(got.values[10:, 4], b.values[:, 0])


def _raw_buckets(values: np.ndarray, t_ns: np.ndarray, width_s: int,
                 origin: float, m: int) -> tuple[np.ndarray, ...]:
    idx = ((t_ns // 10**9 - origin) // width_s).astype(int)
    c = values.shape[1]
    lo, hi, mean = (np.full((m, c), np.nan) for _ in range(3))
    cnt = np.zeros((m, c), dtype=int)
    for i in range(m):
        sel = values[idx == i]
        for j in range(c):
            col = sel[:, j][~np.isnan(sel[:, j])]
            if col.size:
                lo[i, j], hi[i, j] = col.min(), col.max()
                mean[i, j], cnt[i, j] = col.mean(), col.size
    return lo, hi, mean, cnt


@pytest.mark.parametrize("final_rollup", [False, True])
@pytest.mark.parametrize("max_points", [1000, 7, 3])
def test_summaries_agree_with_raw_samples_and_never_double_count(
        store: Store, max_points: int, final_rollup: bool) -> None:
    blocks = [make_block("crane-1", s, n=250) for s in range(60)]  # 150 s, crosses minutes
    store.write_blocks(blocks[:40])
    assert store.rollup() >= 2  # minutes rolled up, then touched again by late blocks below
    store.write_blocks(blocks[20:])  # half of it again: must not be counted twice
    store.write_blocks(blocks[::7])
    if final_rollup:
        assert store.rollup() >= 1
        assert store.rollup() == 0
    raw = store.read_samples("crane-1", 0, 2e9)
    t0, t1 = raw.t_s[0] - 0.5, raw.t_s[-1] + 1
    summ = store.summaries("crane-1", ["lift_s", "slew_torque"], t0, t1, max_points=max_points)
    assert summ.t_s.size <= max_points
    assert summ.bucket_s in ((1,) if max_points == 1000 else (60, 120, 180))
    t_ns = np.rint(raw.t_s * 1e9).astype(np.int64)
    sel = raw.values[:, [2, 3]]
    lo, hi, mean, cnt = _raw_buckets(sel, t_ns, summ.bucket_s, summ.t_s[0], summ.t_s.size)
    assert np.array_equal(summ.count, cnt)
    assert int(summ.count.sum()) == 2 * 60 * 250
    assert np.array_equal(summ.min, lo, equal_nan=True)
    assert np.array_equal(summ.max, hi, equal_nan=True)
    np.testing.assert_allclose(summ.mean, mean, rtol=1e-12)


def test_data_range_and_next_block_start_follow_the_stored_blocks(store: Store) -> None:
    assert store.data_range("crane-1") is None
    assert store.next_block_start("crane-1", 0.0) is None
    blocks = [make_block("crane-1", s, n=100) for s in (3, 0, 7)]  # 1 s each, gaps between
    store.write_blocks(blocks)
    store.write_blocks([make_block("crane-2", 20)])  # another machine's data is not counted
    lo, hi = store.data_range("crane-1") or (0.0, 0.0)
    assert lo == pytest.approx(min(b.t0_ns for b in blocks) / 1e9, abs=1e-6)
    assert hi == pytest.approx(max(b.t_end_ns for b in blocks) / 1e9, abs=1e-6)
    b3 = blocks[0]
    after = (b3.t_end_ns + 1_000_000) / 1e9  # just past block 3: block 7 is next
    assert store.next_block_start("crane-1", after) == pytest.approx(blocks[2].t0_ns / 1e9,
                                                                     abs=1e-6)
    assert store.next_block_start("crane-1", hi + 1.0) is None
    with pytest.raises(UnknownMachineError):
        store.data_range("nope")


def test_summaries_repeated_channel_counted_once(store: Store) -> None:
    store.write_blocks([make_block("crane-1", s, n=250) for s in range(30)])
    store.rollup()
    raw = store.read_samples("crane-1", 0, 2e9)
    t0, t1 = raw.t_s[0], raw.t_s[-1] + 1
    once = store.summaries("crane-1", ["lift_s"], t0, t1, max_points=3)
    twice = store.summaries("crane-1", ["lift_s", "lift_s"], t0, t1, max_points=3)
    assert np.array_equal(twice.count[:, 1], once.count[:, 0])
    assert int(once.count.sum()) == raw.t_s.size


def test_summaries_reject_bad_range(store: Store) -> None:
    with pytest.raises(StorageError):
        store.summaries("crane-1", ["lift_s"], 10.0, 10.0, 100)
    with pytest.raises(StorageError):
        store.summaries("crane-1", ["lift_s"], 0.0, 10.0, 0)


def test_write_summaries_windows_add_up_and_reruns_change_nothing(store: Store) -> None:
    t = 1_700_000_040.0 + np.arange(0, 120, 0.01)  # two whole minutes
    v = np.column_stack([np.sin(t), 1e5 * np.cos(t)])
    chans = ["force:lift", "force:jib"]
    for _ in range(2):  # a replay re-run must not double anything
        for a in range(0, 12000, 700):  # 7-s windows, not minute-aligned
            store.write_summaries("crane-1", t[a:a + 700], chans, v[a:a + 700])
    fine = store.summaries("crane-1", chans, t[0], t[-1] + 0.01, max_points=120)
    assert fine.bucket_s == 1 and np.all(fine.count == 100)
    np.testing.assert_allclose(fine.min[:, 0], v[:, 0].reshape(120, 100).min(axis=1))
    s = store.summaries("crane-1", chans, t[0], t[-1] + 0.01, max_points=2)
    assert s.bucket_s == 60 and s.count.tolist() == [[6000, 6000], [6000, 6000]]
    np.testing.assert_allclose(s.max[0], v[:6000].max(axis=0))
    np.testing.assert_allclose(s.mean[1], v[6000:].mean(axis=0), rtol=1e-9, atol=1e-9)
    with pytest.raises(StorageError, match="shape"):
        store.write_summaries("crane-1", t, chans, v[:, :1])


def test_events_idempotent_and_filtered(store: Store) -> None:
    evs = [Event("crane-1", 1_700_000_000.5, "overload", "critical", {"moment_knm": 21.3}),
           Event("crane-1", 1_700_000_001.0, "end_stop_impact", "warning", {"cyl": "lift"}),
           Event("crane-2", 1_700_000_000.5, "overload")]
    assert store.add_events(evs) == 3
    assert store.add_events(evs) == 0
    got = store.events("crane-1", 1_700_000_000, 1_700_000_002)
    assert [e.kind for e in got] == ["overload", "end_stop_impact"]
    assert got[0].evidence == {"moment_knm": 21.3} and got[0].severity == "critical"
    assert [e.kind for e in store.events("crane-1", 0, 2e9, kinds=["end_stop_impact"])] == [
        "end_stop_impact"]
    with pytest.raises(StorageError, match="severity"):
        store.add_events([Event("crane-1", 0.0, "x", "fatal")])


def test_last_seen_and_status(store: Store) -> None:
    assert store.get_machine("crane-1").last_seen_s is None
    b = make_block("crane-1", 5)
    store.write_blocks([b, make_block("crane-1", 2)])
    assert store.get_machine("crane-1").last_seen_s == pytest.approx(b.t_end_ns / 1e9)
    store.update_status("crane-2", 1_700_000_100.0, latitude_deg=61.05, longitude_deg=28.19,
                        operating_hours=1234.5)
    store.update_status("crane-2", 1_700_000_050.0, latitude_deg=0.0)  # older: ignored
    m = store.get_machine("crane-2")
    assert (m.latitude_deg, m.longitude_deg, m.operating_hours) == (61.05, 28.19, 1234.5)


@settings(max_examples=60, deadline=None)
@given(k=hnp.arrays(np.int64, hnp.array_shapes(min_dims=2, max_dims=2, max_side=40),
                    elements=st.integers(-(2**50), 2**50)),
       nan_frac=st.floats(0, 1))
def test_codec_round_trip_is_exact(k: np.ndarray, nan_frac: float) -> None:
    res = np.linspace(1e-4, 5000, k.shape[1])
    v = k * res
    rng = np.random.default_rng(k.size)
    v[rng.random(v.shape) < nan_frac] = np.nan
    out = codec.decode(codec.encode(v, tuple(res)), tuple(res))
    assert np.array_equal(out, v, equal_nan=True)


def test_codec_rejects_corrupt_blobs() -> None:
    v = make_block("m", 0).values
    blob = codec.encode(v, RES)
    for bad in (blob[:5], blob[:-3], blob[:12] + b"\x00" * 20, b"\x07" + blob[1:]):
        with pytest.raises(codec.CodecError):
            codec.decode(bad, RES)
    with pytest.raises(codec.CodecError):
        codec.encode(np.array([[np.inf]]), (1.0,))


def test_codec_compresses_sensor_like_data() -> None:
    b = make_block("m", 0, n=1000)
    assert len(codec.encode(b.values, RES)) < 0.25 * b.values.nbytes


@settings(max_examples=40, deadline=None)
@given(b=st.integers(1, 6), n=st.integers(1, 30), c=st.integers(1, 5),
       scale=st.sampled_from([1, 100, 40_000, 2**31, 2**50]), seed=st.integers(0, 2**16))
def test_vectorised_encoding_equals_per_block_encoding(b: int, n: int, c: int, scale: int,
                                                       seed: int) -> None:
    rng = np.random.default_rng(seed)
    k = rng.integers(-scale, scale, size=(b, n, c))
    mask = rng.random(k.shape) < 0.1
    k[mask] = 0
    blobs = codec.encode_many(k, mask)
    for i in range(b):
        assert blobs[i] == codec.encode_ints(k[i], mask[i], level=1)
        kk, mm = codec.decode_ints(blobs[i])
        assert np.array_equal(kk, k[i]) and np.array_equal(mm, mask[i])


def test_per_second_summary_of_a_block_matches_numpy() -> None:
    from cranetwin.storage.blocks import per_second

    b = make_block("m", 0, n=250)  # starts 0.25 s into a second: 3 partial/whole seconds
    k, mask = codec.quantise(b.values, RES)
    mask[5, 1] = True
    (agg,) = per_second(k[None], mask[None], np.array([b.t0_ns]), np.array([PERIOD]))
    m = agg.shape[0] // 4
    sec = b.times_ns() // 10**9
    assert m == sec[-1] - sec[0] + 1 == 3
    for i, s in enumerate(range(sec[0], sec[-1] + 1)):
        for j in range(len(CHANNELS)):
            sel = (sec == s) & ~mask[:, j]
            assert agg[i, j] == sel.sum()
            assert agg[m + i, j] == k[sel, j].min() and agg[2 * m + i, j] == k[sel, j].max()
            assert agg[3 * m + i, j] == k[sel, j].sum()
