"""A twin worker pass commits the spans of all its machines together
(:mod:`cranetwin.service.workercommit`): what it stores equals committing machine by machine,
an error before the commit stores nothing of the pass (the next pass does it, once), and a
machine whose watermark another worker moved is left out while the others are committed."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from sqlalchemy import text

from cranetwin.model import load_machine
from cranetwin.samples import SampleArrays
from cranetwin.service.backend import Backend
from cranetwin.service.worker import TwinWorker
from cranetwin.service.workercommit import LastPart
from cranetwin.settings import Settings
from cranetwin.storage import late_version
from cranetwin.storage import summaries as summ
from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

T0 = 1795420800.0  # a whole day
MACHINE = load_machine("patu655")
IDS = ["crane-a", "crane-b", "crane-c"]


@pytest.fixture(scope="module")
def base() -> SampleArrays:
    return kinematic_samples(MACHINE, 120.0, rate_hz=20.0)


def _setup(url: str, base: SampleArrays, seconds: float = 30.0) -> Backend:
    b = Backend.open(url)
    for i, mid in enumerate(IDS):
        b.store.add_machine(mid, wire_id=i + 1, secret=b"k" * 32)
        b.store.write_blocks(list(tiled_blocks(mid, MACHINE, T0, seconds, 1.0, base=base,
                                               origin_s=T0)))
    return b


def _worker(b: Backend) -> TwinWorker:
    return TwinWorker(b, Settings(database_url="unused", worker_in_process=False,
                                  worker_window_s=4.0, worker_settle_s=1.0, twin_margin_s=1.0,
                                  worker_rollup_s=0))


def _stored(b: Backend) -> dict[str, list[tuple[Any, ...]]]:
    """Every row the worker writes (its duty-to-date blob and late-data marks left out, and
    the storage writers' late-data versions)."""
    with b.store.engine.connect() as c:
        return {
            "summaries": sorted(tuple(r) for r in c.execute(text(
                "SELECT machine_pk, channel, level_s, bucket_s, n, vmin, vmax, vsum "
                "FROM summaries"))),
            "windows": sorted(tuple(r) for r in c.execute(text(
                "SELECT machine_id, level_s, t0_ns, t1_ns, n, data FROM analytics_windows "
                f"WHERE level_s NOT IN (-2, -1, 0, {late_version.LEVEL})"))),
            "events": sorted(tuple(r) for r in c.execute(text(
                "SELECT machine_pk, t_ns, kind, evidence_json FROM events"))),
            "progress": sorted(tuple(r) for r in c.execute(text(
                "SELECT machine_id, watermark_s, windows, operating_s, idle_s, load_count, "
                "payload_total_kg, theta0_rad FROM twin_progress"))),
        }


def _one_by_one(b: Backend, monkeypatch: pytest.MonkeyPatch) -> None:
    """Commit each machine's spans in a transaction of its own (the path of other databases)."""
    monkeypatch.setattr(b, "commit_spans", lambda commits: {
        c.prog.machine_id for c in commits if b._commit_one(c)})


@pytest.mark.postgres
@pytest.mark.timeout(300)
def test_pass_commit_stores_what_machine_by_machine_stores(
        pg_url: str, base: SampleArrays, monkeypatch: pytest.MonkeyPatch) -> None:
    b = _setup(pg_url, base)
    w = _worker(b)
    assert w.run_once() == 3 * 7  # 28 s ready: one span per machine
    together = _stored(b)
    b.close()
    # the same data in another schema, committed machine by machine
    from conftest import fresh_pg_schema

    with fresh_pg_schema() as url:
        b1 = _setup(url, base)
        _one_by_one(b1, monkeypatch)
        assert _worker(b1).run_once() == 3 * 7
        alone = _stored(b1)
        b1.close()
    assert len(together["progress"]) == 3 and len(together["windows"]) == 6  # part, lifts
    for k in together:  # to the last bit (a minute's sum adds its seconds in time order)
        assert together[k] == alone[k], k


@pytest.mark.postgres
@pytest.mark.timeout(300)
def test_an_error_before_the_pass_commit_stores_nothing_and_the_next_pass_does_it_once(
        pg_url: str, base: SampleArrays, monkeypatch: pytest.MonkeyPatch) -> None:
    b = _setup(pg_url, base)
    w = _worker(b)
    real = summ.replace_many

    def fail(*a: Any, **k: Any) -> int:
        real(*a, **k)  # the rows are written in the transaction, then it fails
        raise RuntimeError("connection lost")

    monkeypatch.setattr(summ, "replace_many", fail)
    before = _stored(b)  # the raw channels' summaries of the stored blocks
    with pytest.raises(RuntimeError):
        w.run_once()
    assert _stored(b) == before and not before["windows"] and not before["progress"]
    assert not w._last_part
    monkeypatch.setattr(summ, "replace_many", real)
    assert w.run_once() == 3 * 7
    first = _stored(b)
    progs = [b.progress(m) for m in IDS]
    assert all(p is not None and p.windows == 7 and p.watermark_s == T0 + 28 for p in progs)
    assert w.run_once() == 0  # nothing left, nothing doubled
    assert _stored(b) == first
    b.close()


@pytest.mark.postgres
@pytest.mark.timeout(300)
def test_a_machine_another_worker_committed_is_left_out_of_the_pass_commit(
        pg_url: str, base: SampleArrays) -> None:
    b = _setup(pg_url, base)
    w, other = _worker(b), _worker(b)
    real = b.commit_spans

    def racing(commits: list[Any]) -> set[str]:
        # another worker commits crane-b's window first (before this pass's commit)
        assert other.catch_up(b.machine("crane-b"), 1) == 1
        return real(commits)

    b.commit_spans = racing  # type: ignore[method-assign]
    w._last_part["crane-b"] = LastPart(T0 - 60, T0, b"stale")
    assert w.run_once() == 3 * 7
    b.commit_spans = real  # type: ignore[method-assign]
    pa, pb = b.progress("crane-a"), b.progress("crane-b")
    assert pa is not None and pa.windows == 7 and pa.watermark_s == T0 + 28
    assert pb is not None and pb.windows == 1 and pb.watermark_s == T0 + 4  # the other's only
    assert "crane-b" not in w._last_part and "crane-a" in w._last_part
    n_b = [r for r in _stored(b)["windows"] if r[0] == "crane-b"]
    assert {(r[2], r[3]) for r in n_b} == {(int(T0 * 1e9), int((T0 + 4) * 1e9))}
    assert w.run_once() == 6  # crane-b's remaining 24 s, from the other worker's watermark
    pb = b.progress("crane-b")
    assert pb is not None and pb.windows == 7 and pb.watermark_s == T0 + 28
    ops = [p.operating_s for p in (b.progress(m) for m in IDS) if p is not None]
    np.testing.assert_allclose(ops, ops[0])  # every instant counted once on each machine
    b.close()


def _settle(b: Backend) -> None:
    """Wait until every transaction up to the last one that stored blocks has ended (other
    clients of this server too). Until then a pass's commit-order mark stays below those
    blocks: a late one among them is found later (never lost), and a machine's first pass
    brings its first second back as late data (it starts within the replay margin of where
    that pass started, :class:`~cranetwin.storage.analytics_windows.Seen`)."""
    import time

    q = ("SELECT pg_snapshot_xmin(pg_current_snapshot())::text::bigint > "
         "(SELECT max(writer_xid::text::bigint) FROM sample_blocks)")
    deadline = time.monotonic() + 60
    with b.store.engine.connect() as c:
        while not c.execute(text(q)).scalar_one() and time.monotonic() < deadline:
            c.rollback()
            time.sleep(0.05)


def _step(w: TwinWorker, b: Backend, mid: str, path: str) -> Callable[[], int]:
    """One pass of the worker (``pass``: :meth:`TwinWorker.run_once`) or one turn of one
    machine alone (``machine``: :meth:`TwinWorker.catch_up` without the pass's reads, as the
    API, the benches and the tests call it); returns windows processed."""
    if path == "pass":
        return w.run_once
    return lambda: w.catch_up(b.machine(mid))


@pytest.mark.postgres
@pytest.mark.timeout(300)
@pytest.mark.parametrize("path", ["pass", "machine"])
def test_blocks_a_pass_saw_above_its_mark_are_not_late_data_but_late_blocks_are(
        pg_url: str, base: SampleArrays, caplog: pytest.LogCaptureFixture, path: str) -> None:
    """A transaction open anywhere on the server holds the pass's commit-order mark back, so
    blocks committed before the pass but above its mark come back next pass. Those the pass
    replayed are not redone; a late block among them (behind the watermark) still is. The
    same for a machine's turn alone (:meth:`TwinWorker.catch_up` without the pass's reads)."""
    import logging

    import psycopg

    from conftest import _pg_conninfo

    mid = "crane-a"
    b = Backend.open(pg_url)
    b.store.add_machine(mid, wire_id=1, secret=b"k" * 32)

    def write(a: float, z: float, seq0: int) -> None:
        b.store.write_blocks(list(tiled_blocks(mid, MACHINE, T0 + a, z - a, 1.0, base=base,
                                               seq0=seq0, origin_s=T0)))

    def redone() -> int:
        got = [r for r in caplog.records if "redone for late data" in r.getMessage()]
        caplog.clear()
        return len(got)

    def held_pass(*blocks: tuple[float, float, int]) -> None:
        """Blocks written while another transaction is open, then a pass; then it ends."""
        with psycopg.connect(_pg_conninfo()) as other:
            other.execute("SELECT pg_current_xact_id()")  # open, holding xmin back
            for blk in blocks:
                write(*blk)
            assert step() > 0
            other.rollback()

    caplog.set_level(logging.INFO, logger="cranetwin.service.worker")
    write(0.0, 10.0, 0)
    write(14.0, 30.0, 100)  # [10, 14) missing: written late below
    _settle(b)
    w = _worker(b)
    step = _step(w, b, mid, path)
    step()
    assert redone() == 0
    held_pass((30.0, 38.0, 300))
    assert step() == 0 and redone() == 0  # the pass above its mark saw [30, 38)
    summ_before = b.summaries(mid, ["payload"], T0 + 10, T0 + 14, 10)["payload"][0]
    assert summ_before.size == 0  # nothing replayed there yet
    held_pass((10.0, 14.0, 200), (38.0, 46.0, 400))  # a late block and the next seconds
    assert redone() == 0  # above the mark this pass: found by the next one
    _settle(b)
    step()
    assert redone() == 1  # the late block, not [38, 46)
    assert b.summaries(mid, ["payload"], T0 + 10, T0 + 14, 10)["payload"][0].size == 4
    assert step() == 0 and redone() == 0
    b.close()


@pytest.mark.postgres
@pytest.mark.timeout(300)
@pytest.mark.parametrize("path", ["pass", "machine"])
def test_a_block_whose_transaction_was_open_during_the_pass_is_late_data_of_the_next(
        pg_url: str, base: SampleArrays, caplog: pytest.LogCaptureFixture, path: str) -> None:
    """A block whose writer's transaction is still open while a pass replays the seconds it
    holds (the pass's samples lack them), committed after the pass, is not among the blocks
    the pass saw: the next pass redoes the span holding it (on a machine's turn alone too)."""
    import logging
    import time

    from sqlalchemy.orm import Session

    from cranetwin.storage import writes

    mid = "crane-a"
    b = Backend.open(pg_url)
    b.store.add_machine(mid, wire_id=1, secret=b"k" * 32)

    def blocks(a: float, z: float, seq0: int) -> list[Any]:
        return list(tiled_blocks(mid, MACHINE, T0 + a, z - a, 1.0, base=base, seq0=seq0,
                                 origin_s=T0))

    def redone() -> int:
        got = [r for r in caplog.records if "redone for late data" in r.getMessage()]
        caplog.clear()
        return len(got)

    def xmin() -> int:
        with b.store.engine.connect() as c:
            return int(c.execute(text(
                "SELECT pg_snapshot_xmin(pg_current_snapshot())::text::bigint")).scalar_one())

    caplog.set_level(logging.INFO, logger="cranetwin.service.worker")
    b.store.write_blocks(blocks(0.0, 10.0, 0))
    _settle(b)
    w = _worker(b)
    step = _step(w, b, mid, path)
    assert step() == 2  # [0, 8)
    b.store.write_blocks(blocks(10.0, 12.0, 100) + blocks(16.0, 30.0, 300))
    with b.store.engine.connect() as held:  # a writer's transaction, open across the pass
        tx = held.begin()
        pk = int(held.execute(text("SELECT id FROM machines WHERE machine_id = :m"),
                              {"m": mid}).scalar_one())

        def joined() -> Session:
            return Session(bind=held, join_transaction_mode="create_savepoint")
        res = writes.write(joined, blocks(12.0, 16.0, 200), {mid: pk})
        assert all(o.status == "stored" for o in res.outcomes)
        xid = int(held.execute(text("SELECT pg_current_xact_id()::text::bigint")).scalar_one())
        assert step() == 5  # [8, 28), without the open writer's [12, 16)
        assert redone() == 0
        tx.commit()
    assert b.summaries(mid, ["payload"], T0 + 12, T0 + 16, 10)["payload"][0].size == 0
    # every transaction below the writer's has to end (other clients of this server too)
    deadline = time.monotonic() + 60
    while xmin() <= xid and time.monotonic() < deadline:
        time.sleep(0.05)
    assert xmin() > xid
    step()
    assert redone() == 1  # the span holding [12, 16), replayed now with its samples
    assert b.summaries(mid, ["payload"], T0 + 12, T0 + 16, 10)["payload"][0].size == 4
    assert step() == 0 and redone() == 0
    b.close()
