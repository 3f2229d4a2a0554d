"""``cranetwin bench redo``: what an operator's redo of a range costs the twin worker
(``cranetwin worker redo``, :mod:`cranetwin.storage.redo`).

Input: one PATU 655 of ``minutes`` minutes of 100-Hz kinematic samples
(:func:`cranetwin.testing.blocks.kinematic_samples`, 1-s blocks) in a fresh database (a
temporary SQLite file, or ``--db``: give PostgreSQL an empty schema). One
:class:`~cranetwin.service.worker.TwinWorker` at the settings' defaults (60-s windows) processes
them forward (timed: ``forward_ms_per_window``); then a request for the whole range is recorded
and surveyed as the command does (``request_ms``, after a full garbage collection: the
command runs in a process of its own), and the worker's next turn redoes it
(``redo_ms_per_window``: replays, commits, roll-up, lift recount, duty). ``baseline``: the
forward processing of the same windows. ``loadavg``: the 1-min load average at the start and
the end (the host is shared).
"""

from __future__ import annotations

import gc
import os
import tempfile
import time
from typing import Any

import typer

from cranetwin.bench import emit


def run(minutes: int = 60, db: str | None = None) -> dict[str, Any]:
    """The figures of the module docstring."""
    from cranetwin.model import load_machine
    from cranetwin.service.backend import Backend
    from cranetwin.service.worker import TwinWorker
    from cranetwin.settings import Settings
    from cranetwin.storage import redo
    from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

    t0 = 1795420800.0  # a whole day
    machine = load_machine("patu655")
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        b = Backend.open(db or f"sqlite:///{tmp}/redo.db")
        try:
            b.store.add_machine("bench-redo", wire_id=9, secret=b"k" * 32)
            b.store.write_blocks(list(tiled_blocks(
                "bench-redo", machine, t0, minutes * 60.0 + 10.0, 1.0,
                base=kinematic_samples(machine, 120.0), origin_s=t0)))
            w = TwinWorker(b, Settings(database_url="unused", worker_in_process=False),
                           clock=lambda: 0.0)  # never quiet: the partial last minute waits
            t = time.perf_counter()
            forward = w.catch_up(b.machine("bench-redo"))
            forward_s = time.perf_counter() - t
            gc.collect()  # the replays' garbage: a full collection (~0.2 s) would fall
            t = time.perf_counter()  # into the request (the command's own process has none)
            req = b.store.request_redo("bench-redo", t0, t0 + minutes * 60.0)
            prog = b.progress("bench-redo")
            got = redo.survey(b.store.engine_for("bench-redo"), "bench-redo", req.t0_ns,
                              req.t1_ns, w.settings.worker_window_s,
                              None if prog is None else prog.watermark_s)
            request_s = time.perf_counter() - t
            t = time.perf_counter()
            redone = w.catch_up(b.machine("bench-redo"))
            redo_s = time.perf_counter() - t
            left = redo.pending(b.store.engine_for("bench-redo"), ["bench-redo"])
        finally:
            b.close()
    return {"db": (db or "sqlite").split(":")[0], "minutes": minutes,
            "forward_windows": forward, "redone_windows": redone,
            "survey_processed": got.processed, "requests_left": len(left),
            "request_ms": request_s * 1e3,
            "redo_ms_per_window": redo_s * 1e3 / max(redone, 1),
            "baseline": "forward processing of the same windows",
            "forward_ms_per_window": forward_s * 1e3 / max(forward, 1),
            "loadavg": f"{load0:.2f} → {os.getloadavg()[0]:.2f}"}


def register(bench_app: typer.Typer) -> None:
    @bench_app.command("redo")
    def redo_cmd(
        minutes: int = typer.Option(60, min=1, help="Minutes of samples processed, then "
                                                    "redone."),
        db: str | None = typer.Option(None, help="Database (default: a temporary SQLite "
                                                 "file; PostgreSQL: an empty schema)."),
        as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
    ) -> None:
        """Cost of an operator's redo of a range (cranetwin worker redo) per window."""
        emit(run(minutes, db), as_json)
