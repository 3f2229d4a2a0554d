"""The twin worker's idle machines on PostgreSQL: a machine whose next window is not ready has
no turn and no reads beyond its data range, yet a late block behind its watermark and a redo
request (a known payload stored for processed samples) are still processed by the next pass,
and its next window when it is ready."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from cranetwin.model import load_machine
from cranetwin.samples import SampleArrays, SampleBlock
from cranetwin.service.backend import Backend
from cranetwin.service.worker import TwinWorker
from cranetwin.settings import Settings
from cranetwin.storage import analytics_windows as aw
from cranetwin.storage import redo
from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

T0 = 1795420800.0  # a whole day
MID = "crane-i"
MACHINE = load_machine("patu655")


def _blocks(base: SampleArrays, start: float, seconds: float, seq0: int) -> list[SampleBlock]:
    return list(tiled_blocks(MID, MACHINE, start, seconds, 1.0, base=base, seq0=seq0,
                             origin_s=T0))


def _counted(worker: TwinWorker) -> list[str]:
    """The machines whose turn the worker runs, recorded as they come."""
    turns: list[str] = []
    real = worker.catch_up

    def spy(rec: Any, *args: Any, **kwargs: Any) -> int:
        turns.append(rec.machine_id)
        return real(rec, *args, **kwargs)

    worker.catch_up = spy  # type: ignore[method-assign]
    return turns


def _minute_n(b: Backend, w0: float) -> int:
    got = {a: n for a, _, n, _ in aw.windows(b.store.engine, MID, 60, T0 - 600, T0 + 3600)}
    return got[w0]


@pytest.mark.postgres
@pytest.mark.timeout(300)
def test_idle_machine_skipped_yet_late_block_and_redo_request_processed(pg_url: str) -> None:
    base = kinematic_samples(MACHINE, 120.0)
    b = Backend.open(pg_url)
    b.store.add_machine(MID, wire_id=9, secret=b"k" * 32)
    worker = TwinWorker(b, Settings(database_url="unused", worker_in_process=False),
                        clock=lambda: 0.0)  # never quiet: the partial minute waits
    turns = _counted(worker)
    b.store.write_blocks(_blocks(base, T0, 30.0, 0))  # a 10-s hole in minute 0
    b.store.write_blocks(_blocks(base, T0 + 40.0, 85.0, 1000))
    assert worker.run_once() == 2
    assert worker.run_once() == 0  # read fully: the mark stored, the machine known
    assert _minute_n(b, T0) == pytest.approx(5000, abs=5)
    turns.clear()
    assert worker.run_once() == 0
    assert turns == []  # idle: no turn
    b.store.write_blocks(_blocks(base, T0 + 125.0, 1.0, 2000))  # new data, no window ready
    assert worker.run_once() == 0
    assert turns == []

    b.store.write_blocks(_blocks(base, T0 + 30.0, 10.0, 3000))  # the hole, late
    worker.run_once()
    assert turns == [MID]
    assert _minute_n(b, T0) == pytest.approx(6000, abs=5)  # minute 0 redone with it
    turns.clear()
    assert worker.run_once() == 0
    assert turns == []  # nothing redone twice: idle again

    t_ns = round(T0 * 1e9) + 60 * 10**9 + np.arange(3000, dtype=np.int64) * 10**7
    assert b.store.write_payload(MID, np.full(t_ns.size, 900.0), t_ns=t_ns).stored >= 1
    assert redo.pending(b.store.engine, [MID])  # minute 1 was processed: a request
    worker.run_once()
    assert turns == [MID]
    assert redo.pending(b.store.engine, [MID]) == {}  # done
    turns.clear()

    b.store.write_blocks(_blocks(base, T0 + 126.0, 60.0, 4000))  # minute 2 ready
    assert worker.run_once() == 1
    assert turns == [MID]
    p = b.progress(MID)
    assert p is not None and p.watermark_s == T0 + 180
    b.close()
