"""A known payload stored or deleted for samples the twin worker has already processed: the
windows it changes are processed again, once (redo requests, ``cranetwin.storage.redo``), and
the result equals a processing that had the payload (or not) from the start: progress counters,
derived summaries, analytics parts and events."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from conftest import assert_same_progress
from cranetwin.model import load_machine
from cranetwin.samples import SampleArrays
from cranetwin.service.backend import Backend, Progress
from cranetwin.service.history import stored_duty
from cranetwin.service.worker import TwinWorker
from cranetwin.settings import Settings
from cranetwin.storage import analytics_windows as aw
from cranetwin.storage import redo
from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

T0 = 1795420800.0  # a whole day
MID = "crane-p"
MACHINE = load_machine("patu655")
HEAVY_KG = 2500.0
"""The known payload in the second half of minutes 1 and 2 (the samples' own: 400 kg), beyond
the PATU 655's rated load: overload events where the estimate found none."""


@pytest.fixture(scope="module")
def base() -> SampleArrays:
    return kinematic_samples(MACHINE, 120.0)


def _backend(url: str, base: SampleArrays) -> Backend:
    b = Backend.open(url)
    b.store.add_machine(MID, wire_id=9, secret=b"k" * 32)
    b.store.write_blocks(list(tiled_blocks(MID, MACHINE, T0, 250.0, 1.0, base=base,
                                           origin_s=T0)))
    return b


def _write_known(b: Backend) -> None:
    """The known payload over [T0 + 60, T0 + 180) at the sample times: 0 kg in the first half
    of each minute, :data:`HEAVY_KG` in the second."""
    t_ns = round(T0 * 1e9) + 60 * 10**9 + np.arange(12000, dtype=np.int64) * 10**7
    kg = np.where(np.mod(t_ns / 1e9, 60.0) >= 30.0, HEAVY_KG, 0.0)
    got = b.store.write_payload(MID, kg, t_ns=t_ns)
    assert got.stored >= 1


def _worker(b: Backend) -> TwinWorker:
    return TwinWorker(b, Settings(database_url="unused", worker_in_process=False),
                      clock=lambda: 0.0)  # never quiet: the last, partial minute waits


def _state(b: Backend) -> dict[str, object]:
    """What the worker stored: progress, minute parts, lift seconds, events, summaries."""
    p = b.progress(MID)
    assert p is not None
    eng = b.store.engine
    summ = b.summaries(MID, ["payload", "torque:theta1", "force:lift"], T0, T0 + 300, 1000)
    return {
        "progress": p,
        "duty": stored_duty(eng, MID),  # (work cycles, Σ ratio³, until): damage to date
        "parts": {a: d for a, _, _, d in aw.windows(eng, MID, 60, T0 - 600, T0 + 3600)},
        "seconds": {a: d for a, _, _, d in aw.windows(eng, MID, -3, T0 - 600, T0 + 3600)},
        "times": {a: aw.window_times(eng, MID, 60, a) for a, *_ in
                  aw.windows(eng, MID, 60, T0 - 600, T0 + 3600)},
        "events": sorted((round(e.t_s, 6), e.kind) for e in b.store.events(MID, T0 - 600,
                                                                          T0 + 3600)),
        "summaries": {k: tuple(np.asarray(x) for x in v) for k, v in summ.items()},
    }


def _same(a: dict[str, object], b: dict[str, object]) -> None:
    assert_same_progress(a["progress"], b["progress"])
    da, db = a["duty"], b["duty"]
    assert da is not None and db == pytest.approx(da, rel=1e-12), "duty"
    for k in ("parts", "seconds", "times", "events"):
        assert a[k] == b[k], k
    sa, sb = a["summaries"], b["summaries"]
    assert isinstance(sa, dict) and isinstance(sb, dict) and sa.keys() == sb.keys()
    for k in sa:
        for x, y in zip(sa[k], sb[k], strict=True):
            np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-9, err_msg=k)


@pytest.mark.timeout(300)
def test_payload_stored_then_deleted_behind_the_worker_is_processed_again_once(
        db_url: str, base: SampleArrays, tmp_path: Path) -> None:
    b = _backend(db_url, base)
    worker = _worker(b)
    rec = b.machine(MID)
    assert worker.catch_up(rec) == 4  # minutes 0-3
    without = _state(b)
    _write_known(b)
    assert redo.pending(b.store.engine, [MID])  # the import asks for the redo
    assert worker.catch_up(rec) == 4  # minutes 1, 2 and, by the replay margin, 0 and 3
    assert redo.pending(b.store.engine, [MID]) == {}
    with_known = _state(b)
    assert worker.catch_up(rec) == 0  # nothing redone twice
    _same(_state(b), with_known)

    # the oracle: the samples and the payload stored before the first window was processed
    # (in a database of its own: SQLite)
    fb = _backend(f"sqlite:///{tmp_path}/fresh.db", base)
    _write_known(fb)
    assert _worker(fb).catch_up(fb.machine(MID)) == 4
    fresh = _state(fb)
    _same(with_known, fresh)

    # what the known payload changed, and what it did not
    p0, p1 = without["progress"], with_known["progress"]
    assert isinstance(p0, Progress) and isinstance(p1, Progress)
    assert (p1.operating_s, p1.idle_s, p1.windows) == pytest.approx(
        (p0.operating_s, p0.idle_s, p0.windows), abs=1e-6)
    assert p1.load_count == p0.load_count  # the same lifts, counted once
    assert p1.max_payload_kg == pytest.approx(HEAVY_KG, rel=0.01)
    assert p0.max_payload_kg == pytest.approx(400.0, rel=0.05)
    assert p1.payload_total_kg > p0.payload_total_kg + 2 * (HEAVY_KG - 500.0)
    d0, d1 = without["duty"], with_known["duty"]
    assert isinstance(d0, tuple) and isinstance(d1, tuple)
    assert d1[0] == d0[0] and d1[1] > d0[1]  # the same work cycles, heavier: more damage
    s0, s1 = without["summaries"], with_known["summaries"]
    assert isinstance(s0, dict) and isinstance(s1, dict)
    t, _, hi0, _ = s0["payload"]
    hi1 = s1["payload"][2]
    heavy = (np.mod(t, 60.0) >= 31.0) & (np.mod(t, 60.0) < 59.0) & (t >= T0 + 60) & (
        t < T0 + 180)
    assert np.all(hi1[heavy] == pytest.approx(HEAVY_KG, abs=1.0))
    assert np.all(hi0[heavy] < 450.0)
    assert np.array_equal(s1["force:lift"][3], s0["force:lift"][3])  # from the pressures
    ev0, ev1 = without["events"], with_known["events"]
    assert isinstance(ev0, list) and isinstance(ev1, list)
    assert len(ev1) > len(ev0) and all(T0 + 60 <= t < T0 + 180 for t, _ in set(ev1) - set(ev0))

    # deleted again: back to the processing without it, events found with it gone
    gone = b.store.delete_payload(MID, T0, T0 + 300)
    assert (gone.runs_deleted, gone.known_deleted) == (1, 12000)
    assert worker.run_once() == 4  # a whole pass: the requests read with the pass's reads
    _same(_state(b), without)
    assert worker.run_once() == 0
    b.close()
    fb.close()


@pytest.fixture(scope="module")
def fresh(base: SampleArrays, tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    """The oracle: the samples and the payload stored before the first window was processed
    (SQLite)."""
    fb = _backend(f"sqlite:///{tmp_path_factory.mktemp('fresh')}/fresh.db", base)
    _write_known(fb)
    assert _worker(fb).catch_up(fb.machine(MID)) == 4
    state = _state(fb)
    fb.close()
    return state


FAILING_W0 = T0 + 60.0
"""The minute whose processing fails (the first with the known payload)."""


def _fail_minute(monkeypatch: pytest.MonkeyPatch, worker: TwinWorker, kind: str) -> list[float]:
    """Make the replay (``kind`` "replay") or the analytics part ("analytics") of the span
    starting at :data:`FAILING_W0` raise, as the twin or the analytics do for data they cannot
    use; returns the list the failed attempts' starts are appended to."""
    from cranetwin.errors import AnalyticsError, TwinError
    from cranetwin.service import history

    failed: list[float] = []
    if kind == "analytics":
        real_part = history.part_row

        def part_row(machine: object, machine_id: str, w0: float, *a: object) -> object:
            if w0 == FAILING_W0:
                failed.append(w0)
                raise AnalyticsError("injected: the analytics of this minute fail")
            return real_part(machine, machine_id, w0, *a)  # type: ignore[arg-type]

        monkeypatch.setattr(history, "part_row", part_row)
    else:
        real_replay = worker.replayer.replay
        margin = worker.settings.twin_margin_s

        def replay(machine_id: str, machine: object, samples: SampleArrays, *a: object,
                   **k: object) -> object:
            if abs(float(samples.t_s[0]) - (FAILING_W0 - margin)) < 0.5:
                failed.append(FAILING_W0)
                raise TwinError("injected: the replay of this minute fails")
            return real_replay(machine_id, machine, samples, *a, **k)  # type: ignore[arg-type]

        monkeypatch.setattr(worker.replayer, "replay", replay)
    return failed


@pytest.mark.timeout(300)
@pytest.mark.parametrize("kind", ["analytics", "replay"])
def test_a_failed_minute_is_processed_with_a_payload_stored_later(
        db_url: str, base: SampleArrays, fresh: dict[str, object], kind: str,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A minute whose replay or analytics failed is processed (the progress mark moves on), so
    it has no part; a known payload stored for it later has it processed again with the
    payload — and, the failure gone, the result is that of processing with the payload from
    the start: its windows and operating time counted once."""
    from cranetwin.storage.failed_windows import FAILED_LEVEL, failed_spans

    b = _backend(db_url, base)
    worker = _worker(b)
    rec = b.machine(MID)
    eng = b.store.engine
    failed = _fail_minute(monkeypatch, worker, kind)
    assert worker.catch_up(rec) == 4  # minutes 0-3: the failing one too (processed)
    assert failed == [FAILING_W0]
    p = b.progress(MID)
    assert p is not None and p.watermark_s == T0 + 240 and p.windows == 4
    assert FAILING_W0 not in {a for a, *_ in aw.windows(eng, MID, 60, T0, T0 + 300)}
    assert failed_spans(eng, MID, T0, T0 + 300) == [(FAILING_W0, FAILING_W0 + 60)]
    times = aw.window_times(eng, MID, FAILED_LEVEL, FAILING_W0)
    assert times is not None and (times[0] > 50.0) == (kind == "analytics")  # what was counted

    monkeypatch.undo()  # the cause is gone; the payload stored over the failed minute
    _write_known(b)
    assert worker.catch_up(rec) == 4  # minutes 1 (the failed one), 2 and, by the margin, 0, 3
    assert failed_spans(eng, MID, T0, T0 + 300) == []
    assert redo.pending(eng, [MID]) == {}
    _same(_state(b), fresh)
    assert worker.catch_up(rec) == 0
    b.close()


@pytest.mark.timeout(300)
def test_a_minute_failing_again_in_its_redo_is_retried_at_the_next_payload_change(
        db_url: str, base: SampleArrays, monkeypatch: pytest.MonkeyPatch) -> None:
    """A minute whose redo for a payload fails (the replay with the payload) is recorded as
    failed, counted as before; the payload deleted later, the minute is retried and the state
    is that of processing without a payload at all."""
    from cranetwin.storage.failed_windows import failed_spans

    b = _backend(db_url, base)
    worker = _worker(b)
    rec = b.machine(MID)
    eng = b.store.engine
    assert worker.catch_up(rec) == 4
    without = _state(b)
    failed = _fail_minute(monkeypatch, worker, "replay")
    _write_known(b)
    assert worker.catch_up(rec) == 4  # minutes 0, 2, 3 redone; 1 tried, failed (what it
    assert failed == [FAILING_W0]     # stored before stays, as counted, until retried)
    assert failed_spans(eng, MID, T0, T0 + 300) == [(FAILING_W0, FAILING_W0 + 60)]
    p0, p1 = without["progress"], b.progress(MID)
    assert isinstance(p0, Progress) and p1 is not None
    assert (p1.windows, p1.operating_s) == (p0.windows, pytest.approx(p0.operating_s))

    monkeypatch.undo()
    b.store.delete_payload(MID, T0, T0 + 300)
    assert worker.catch_up(rec) == 4
    assert failed_spans(eng, MID, T0, T0 + 300) == []
    _same(_state(b), without)
    b.close()
