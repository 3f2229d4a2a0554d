"""A twin worker's pass reads the data ranges, progress and late-data marks of all its machines
at once (:mod:`cranetwin.service.workerpass`) and keeps the last analytics part it committed per
machine: late data found by the pass's one query is redone once, and ownership moving to
another worker and back neither skips nor doubles a window nor leaves a stale part behind."""

from __future__ import annotations

import time

import numpy as np
import pytest

from cranetwin.model import load_machine
from cranetwin.samples import SampleArrays, SampleBlock
from cranetwin.service.backend import Backend
from cranetwin.service.ownership import Ownership, PartitionSpec
from cranetwin.service.worker import TwinWorker
from cranetwin.settings import Settings
from cranetwin.storage import analytics_windows as aw
from cranetwin.storage.engine import make_engine
from cranetwin.storage.sharding import partition_of
from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

T0 = 1795420800.0  # a whole day
MACHINE = load_machine("patu655")
WIN = 4.0
P = 2


@pytest.fixture(scope="module")
def base() -> SampleArrays:
    return kinematic_samples(MACHINE, 120.0, rate_hz=20.0)


def _ids() -> list[str]:
    """Two machines per partition."""
    out: list[str] = []
    i = 0
    while len(out) < 2 * P:
        m = f"crane-p{i}"
        if sum(partition_of(x, P) == partition_of(m, P) for x in out) < 2:
            out.append(m)
        i += 1
    return out


def _blocks(mid: str, base: SampleArrays, start: float, seconds: float,
            seq0: int) -> list[SampleBlock]:
    return list(tiled_blocks(mid, MACHINE, start, seconds, 1.0, base=base, seq0=seq0,
                             origin_s=T0))


def _settings() -> Settings:
    return Settings(database_url="unused", worker_in_process=False, worker_window_s=WIN,
                    worker_settle_s=1.0, twin_margin_s=1.0)


def _parts(b: Backend, mid: str) -> list[tuple[float, float, int]]:
    return [(a - T0, z - T0, n) for a, z, n, _ in aw.windows(b.store.engine, mid, 60, T0 - 600,
                                                             T0 + 3600)]


def _drain(w: TwinWorker) -> int:
    n = 0
    while (got := w.run_once()):
        n += got
    return n


@pytest.mark.postgres
@pytest.mark.timeout(300)
def test_pass_finds_late_blocks_once(pg_url: str, base: SampleArrays) -> None:
    b = Backend.open(pg_url)
    ids = _ids()
    for i, mid in enumerate(ids):
        b.store.add_machine(mid, wire_id=i + 1, secret=b"k" * 32)
        b.store.write_blocks(_blocks(mid, base, T0, 10.0, 0))
        b.store.write_blocks(_blocks(mid, base, T0 + 40.0, 50.0, 1000))
    w = TwinWorker(b, _settings())
    _drain(w)
    before = {m: _parts(b, m) for m in ids}
    progress = {m: b.progress(m) for m in ids}
    late = ids[1]
    b.store.write_blocks(_blocks(late, base, T0 + 10.0, 30.0, 2000))  # the hole of minute 0
    # A pass takes late blocks up to pg_snapshot_xmin, the oldest transaction still running
    # anywhere on the server: on a shared server another session's open transaction holds it
    # back until that ends (seen once in a full run beside other PostgreSQL work). The late
    # blocks are then found by a later pass, still once.
    deadline = time.monotonic() + 120.0
    while (redone := w.run_once()) == 0 and time.monotonic() < deadline:
        time.sleep(0.5)
    assert redone >= 1
    for m in ids:
        after = _parts(b, m)
        assert [(a, z) for a, z, _ in after] == [(a, z) for a, z, _ in before[m]], m
        if m == late:
            assert after[0][2] == 1200 > before[m][0][2]  # the span holds the late samples
        else:
            assert after == before[m], m
        p = b.progress(m)
        assert p is not None and p.watermark_s == progress[m].watermark_s  # type: ignore[union-attr]
    assert w.run_once() == 0  # the marks were stored at the end of the pass: nothing redone twice
    b.close()


@pytest.mark.postgres
@pytest.mark.timeout(300)
def test_ownership_away_and_back_keeps_windows_and_parts(pg_url: str,
                                                         base: SampleArrays) -> None:
    b = Backend.open(pg_url)
    ids = _ids()
    for i, mid in enumerate(ids):
        b.store.add_machine(mid, wire_id=i + 1, secret=b"k" * 32)
    seq = dict.fromkeys(ids, 0)

    def fill(t0: float, seconds: float) -> None:
        for mid in ids:
            bl = _blocks(mid, base, T0 + t0, seconds, seq[mid])
            seq[mid] += len(bl)
            b.store.write_blocks(bl)

    ea, eb = make_engine(pg_url), make_engine(pg_url)
    own_a = Ownership(PartitionSpec(P, None), ea)
    wa = TwinWorker(b, _settings(), ownership=own_a)
    fill(0.0, 22.0)
    _drain(wa)  # A alone: every machine to 20 s, its last part of each cached
    assert own_a.owned == set(range(P))
    assert all(m in wa._last_part for m in ids)

    own_b = Ownership(PartitionSpec(P, None), eb)
    wb = TwinWorker(b, _settings(), ownership=own_b)
    own_b.refresh()
    wa.run_once()  # A gives a partition up (nothing new to process yet)
    moved = [m for m in ids if not own_a.owns(m)]
    assert moved and own_b.refresh() and all(own_b.owns(m) for m in moved)
    fill(22.0, 20.0)
    _drain(wb)  # B moves the moved machines' watermarks and writes their parts
    for m in moved:
        assert m not in wa._last_part and m not in wa._duty  # A let go of them
        p = b.progress(m)
        assert p is not None and p.watermark_s == T0 + 40.0
    own_b.close()  # B leaves: A takes its partitions back
    for m in moved:  # the look-back of A's next window is B's last part, not A's own last one
        stored = aw.windows(b.store.engine, m, 60, T0, T0 + 40.0)[-1]
        assert stored[1] == T0 + 40.0
        last = wa._previous_part(b.machine(m), T0 + 40.0)
        assert last is not None and last.data == stored[3], m
    fill(42.0, 20.0)
    _drain(wa)
    assert own_a.owned == set(range(P))
    for m in ids:
        p = b.progress(m)
        assert p is not None and p.watermark_s == T0 + 60.0, m
        assert p.windows == 15, m  # every 4-s window of [0, 60) once: none skipped or doubled
        parts = _parts(b, m)
        assert parts[0][0] == 0.0 and parts[-1][1] == 60.0, m
        assert all(z == a2 for (_, z, _), (a2, _, _) in zip(parts, parts[1:], strict=False)), m
        assert sum(n for *_, n in parts) == 60 * 20, m  # every instant once
        stored = aw.windows(b.store.engine, m, 60, T0, T0 + 60.0)[-1]
        last = wa._previous_part(b.machine(m), T0 + 60.0)
        assert last is not None and last.data == stored[3], m  # not a stale one
    s = b.summaries(ids[0], ["payload"], T0, T0 + 60, 1000)["payload"][0]
    np.testing.assert_array_equal(s, T0 + np.arange(60.0))  # every second summarised once
    own_a.close()
    ea.dispose()
    eb.dispose()
    b.close()
