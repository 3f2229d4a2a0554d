"""An operator's redo request (``cranetwin worker redo``, :func:`cranetwin.storage.redo.
request_whole`): the twin worker processes again every window of the range behind its watermark
that holds samples — processed, failed, or never processed — once, with the machine's current
description; windows outside the range are left as they are; a request recorded while the redo
runs stays for the next pass."""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from sqlalchemy import update
from sqlalchemy.orm import Session
from typer.testing import CliRunner

from conftest import assert_same_progress
from cranetwin.cli import app
from cranetwin.model import load_machine
from cranetwin.samples import SampleArrays
from cranetwin.service.backend import Backend
from cranetwin.service.history import stored_duty
from cranetwin.service.worker import TwinWorker
from cranetwin.settings import Settings
from cranetwin.storage import analytics_windows as aw
from cranetwin.storage import redo
from cranetwin.storage.failed_windows import FAILED_LEVEL, failed_spans
from cranetwin.storage.machines import MachineRow
from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

T0 = 1795420800.0  # a whole day
TS = T0 + 3600.0 - 120.0
"""First sample: minutes 58 and 59 of one hour, 0 and 1 of the next (the worker rolls the first
hour up when its progress mark passes it)."""
MID = "crane-r"
MACHINE = load_machine("patu655")
PATU = resources.files("cranetwin.machines").joinpath("patu655.toml").read_text()
HEAVY = PATU.replace("mass_kg = 143.66", "mass_kg = 190.0", 1)
assert HEAVY != PATU
"""The PATU 655 with its lift boom 46 kg heavier: an operator's calibration changed it."""
LEVELS = {"parts": 60, "seconds": -3, "hours": 3600, "days": 86400}


@pytest.fixture(scope="module")
def base() -> SampleArrays:
    return kinematic_samples(MACHINE, 120.0)


def _backend(url: str, base: SampleArrays, model: str = "patu655") -> Backend:
    b = Backend.open(url)
    b.store.add_machine(MID, wire_id=9, secret=b"k" * 32, model=model)
    b.store.write_blocks(list(tiled_blocks(MID, MACHINE, TS, 250.0, 1.0, base=base,
                                           origin_s=TS)))
    return b


def _set_model(b: Backend, model: str) -> None:
    with Session(b.store.engine) as s, s.begin():
        s.execute(update(MachineRow).where(MachineRow.machine_id == MID).values(model=model))


def _worker(b: Backend) -> TwinWorker:
    return TwinWorker(b, Settings(database_url="unused", worker_in_process=False),
                      clock=lambda: 0.0)  # never quiet: the last, partial minute waits


def _rows(b: Backend, level: int) -> dict[float, bytes]:
    return {a: d for a, _, _, d in aw.windows(b.store.engine, MID, level, T0, T0 + 86400)}


def _state(b: Backend) -> dict[str, Any]:
    """What the worker stored: progress, duty, minute parts and lift seconds, hour and day
    parts, events, summaries."""
    eng = b.store.engine
    out: dict[str, Any] = {k: _rows(b, lvl) for k, lvl in LEVELS.items()}
    out["progress"] = b.progress(MID)
    out["duty"] = stored_duty(eng, MID)
    out["times"] = {a: aw.window_times(eng, MID, 60, a) for a in out["parts"]}
    out["events"] = sorted((round(e.t_s, 6), e.kind) for e in b.store.events(MID, T0, T0 + 86400))
    summ = b.summaries(MID, ["payload", "torque:theta1", "force:lift"], TS, TS + 300, 1000)
    out["summaries"] = {k: tuple(np.asarray(x) for x in v) for k, v in summ.items()}
    return out


def _same(a: dict[str, Any], b: dict[str, Any]) -> None:
    assert_same_progress(a["progress"], b["progress"])
    assert a["duty"] is not None and b["duty"] == pytest.approx(a["duty"], rel=1e-12), "duty"
    for k in (*LEVELS, "times", "events"):
        assert a[k] == b[k], k
    assert a["summaries"].keys() == b["summaries"].keys()
    for k in a["summaries"]:
        for x, y in zip(a["summaries"][k], b["summaries"][k], strict=True):
            np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-9, err_msg=k)


def _spy(monkeypatch: pytest.MonkeyPatch, worker: TwinWorker,
         during: Any = None) -> list[float]:
    """Record the start of every span the worker redoes (``during(w0)`` called before)."""
    real = worker.process_window
    redone: list[float] = []

    def process_window(*a: Any, **k: Any) -> Any:
        if k.get("redo_w0") is not None:
            redone.append(float(k["redo_w0"]))
            if during is not None:
                during(k["redo_w0"])
        return real(*a, **k)

    monkeypatch.setattr(worker, "process_window", process_window)
    return redone


@pytest.fixture(scope="module")
def fresh(base: SampleArrays, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The oracle: the samples processed with the heavier description from the start
    (SQLite)."""
    fb = _backend(f"sqlite:///{tmp_path_factory.mktemp('fresh')}/fresh.db", base, HEAVY)
    assert _worker(fb).catch_up(fb.machine(MID)) == 4
    state = _state(fb)
    fb.close()
    return state


@pytest.mark.timeout(600)
def test_a_range_is_redone_once_with_the_new_description_never_processed_windows_too(
        db_url: str, base: SampleArrays, fresh: dict[str, Any],
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Minute 59 is passed without anything stored for it (its replay failed before failed
    spans were recorded: the failure and its record removed); the description then changes.
    A request for minutes 59 and 0 redoes exactly those two, once: both equal the processing
    with the new description from the start, minute 59 counted once in the windows and its
    operating time added; minutes 58 and 1 keep what they had. A request for the whole range
    then gives the state of processing with the new description from the start: progress
    (lift counters too), parts, hours, duty, events, summaries."""
    from cranetwin.errors import TwinError

    b = _backend(db_url, base, PATU)
    worker = _worker(b)
    eng = b.store.engine
    real_replay = worker.replayer.replay
    gap = TS + 60.0

    def replay(machine_id: str, machine: Any, samples: SampleArrays, *a: Any,
               **k: Any) -> Any:
        if abs(float(samples.t_s[0]) - (gap - worker.settings.twin_margin_s)) < 0.5:
            raise TwinError("injected: the replay of this minute fails")
        return real_replay(machine_id, machine, samples, *a, **k)

    with monkeypatch.context() as mp:
        mp.setattr(worker.replayer, "replay", replay)
        assert worker.catch_up(b.machine(MID)) == 4
    with Session(eng) as s, s.begin():  # as before failed spans were recorded
        aw.delete_window(s, MID, FAILED_LEVEL, gap)
    assert failed_spans(eng, MID, T0, T0 + 86400) == []
    before = _state(b)
    assert sorted(before["parts"]) == [TS, TS + 120, TS + 180]  # minute 59: nothing stored
    assert T0 in before["hours"]  # the first hour rolled up, without minute 59
    p0 = before["progress"]
    assert p0.windows == 4 and p0.watermark_s == TS + 240

    assert worker.catch_up(b.machine(MID)) == 0
    _set_model(b, HEAVY)
    assert worker.catch_up(b.machine(MID)) == 0  # a description change alone: nothing
    req = b.store.request_redo(MID, TS + 60, TS + 180)
    assert (req.t0_ns, req.t1_ns, req.version, req.whole) == (
        round((TS + 60) * 1e9), round((TS + 180) * 1e9) - 1, 1, True)
    assert redo.survey(eng, MID, req.t0_ns, req.t1_ns, 60.0, p0.watermark_s) == \
        redo.RangeSurvey(processed=1, failed=0, never=1, ahead=0)
    redone = _spy(monkeypatch, worker)
    assert worker.catch_up(b.machine(MID)) == 2
    assert redone == [TS + 60, TS + 120]  # each once, nothing outside
    assert redo.pending(eng, [MID]) == {}
    after = _state(b)
    for w0 in (TS, TS + 180):  # outside the range: as they were (the old description)
        assert after["parts"][w0] == before["parts"][w0], w0
        assert before["parts"][w0] != fresh["parts"][w0], w0
        assert after["seconds"][w0] == before["seconds"][w0]
    for w0 in (TS + 60, TS + 120):  # inside: with the new description
        assert after["parts"][w0] == fresh["parts"][w0] != before["parts"].get(w0)
        assert after["times"][w0] == fresh["times"][w0]
    assert after["hours"][T0] != before["hours"][T0]  # rolled up again, with minute 59
    p1 = after["progress"]
    assert p1.windows == 4 and p1.watermark_s == TS + 240
    assert (p1.operating_s, p1.idle_s) == pytest.approx(
        (fresh["progress"].operating_s, fresh["progress"].idle_s), abs=1e-6)
    assert p1.operating_s > p0.operating_s + 50.0  # minute 59's, added once
    assert worker.catch_up(b.machine(MID)) == 0  # nothing redone twice
    assert redone == [TS + 60, TS + 120]

    # the whole history: processing with the new description from the start
    b.store.request_redo(MID, TS - 600, TS + 600)
    assert worker.catch_up(b.machine(MID)) == 4
    assert redone[2:] == [TS, TS + 60, TS + 120, TS + 180]
    _same(_state(b), fresh)
    assert worker.catch_up(b.machine(MID)) == 0
    b.close()


@pytest.mark.timeout(600)
def test_a_request_recorded_while_its_redo_runs_stays_for_the_next_pass(
        db_url: str, base: SampleArrays, monkeypatch: pytest.MonkeyPatch) -> None:
    """Whole passes (the requests read with the pass's reads): the request recorded again
    while its redo runs (its version raised) is not deleted by that redo, and the next pass
    redoes the range once more; then nothing is left. A request ahead of the watermark (or
    for a range without samples) is deleted without a redo."""
    b = _backend(db_url, base)
    worker = _worker(b)
    eng = b.store.engine
    assert worker.run_once() == 4
    done = _state(b)
    again: list[redo.RedoRequest] = []

    def during(w0: float) -> None:
        if not again:
            again.append(b.store.request_redo(MID, TS, TS + 120))

    redone = _spy(monkeypatch, worker, during)
    b.store.request_redo(MID, TS, TS + 120)
    assert worker.run_once() == 2
    assert redone == [TS, TS + 60] and again[0].version == 2
    assert redo.pending(eng, [MID]) == {MID: [again[0]]}  # stays: recorded during the redo
    assert worker.run_once() == 2
    assert redone == [TS, TS + 60] * 2
    assert redo.pending(eng, [MID]) == {}
    assert worker.run_once() == 0
    _same(_state(b), done)  # the same description and samples: the same state

    b.store.request_redo(MID, TS + 240, TS + 3600)  # ahead of the watermark
    b.store.request_redo(MID, T0 - 7200, T0 - 3600)  # no samples
    assert worker.run_once() == 0 and redo.pending(eng, [MID]) == {}
    assert redone == [TS, TS + 60] * 2
    b.close()


def test_sampled_windows_follow_the_blocks(sqlite_url: str, base: SampleArrays) -> None:
    b = Backend.open(sqlite_url)
    b.store.add_machine(MID, wire_id=9, secret=b"k" * 32)
    b.store.write_blocks(list(tiled_blocks(MID, MACHINE, TS, 90.0, 1.0, base=base,
                                           origin_s=TS)))
    b.store.write_blocks(list(tiled_blocks(MID, MACHINE, TS + 245.0, 30.0, 1.0, base=base,
                                           seq0=1000, origin_s=TS)))
    eng = b.store.engine
    # samples in [TS, TS + 90) and [TS + 245, TS + 275): minutes 0, 1, 4 (2 and 3 empty)

    def sampled(a: float, z: float, win: float = 60.0) -> list[float]:
        return redo.sampled_windows(eng, MID, round(a * 1e9), round(z * 1e9), win)

    assert sampled(TS - 600, TS + 600) == [TS, TS + 60, TS + 240]
    assert sampled(TS + 61, TS + 250) == [TS + 60, TS + 240]
    assert sampled(TS + 90.5, TS + 244) == []
    assert redo.sampled_windows(eng, MID, round(TS * 1e9), round((TS + 240) * 1e9) - 1,
                                60.0) == [TS, TS + 60]  # the end inclusive [ns]
    assert sampled(TS, TS + 600, 30.0) == [TS, TS + 30, TS + 60, TS + 240, TS + 270]
    assert redo.sampled_windows(eng, "nobody", 0, round(TS * 1e9), 60.0) == []
    b.close()


def test_cli_records_the_request_and_says_what_it_covers(
        sqlite_url: str, base: SampleArrays, monkeypatch: pytest.MonkeyPatch) -> None:
    def cli(*args: str) -> Any:
        return CliRunner().invoke(app, ["worker", "redo", "--machine", MID, *args, "--db",
                                        sqlite_url])

    monkeypatch.delenv("CRANETWIN_WORKER_WINDOW_S", raising=False)
    b = _backend(sqlite_url, base)
    r = cli("--from", str(TS), "--to", str(TS + 3600), "--json")
    assert r.exit_code == 0, r.output
    got = json.loads(r.output)
    assert got == {"machine": MID, "from": "2026-11-23T08:58:00.000Z",
                   "to": "2026-11-23T09:58:00.000Z", "from_ns": round(TS * 1e9),
                   "to_ns": round((TS + 3600) * 1e9), "version": 1, "watermark": None,
                   "window_s": 60.0, "windows": {"processed": 0, "failed": 0,
                                                 "never_processed": 0, "ahead": 5}}
    worker = _worker(b)
    assert worker.catch_up(b.machine(MID)) == 4  # forward: the request ahead just deleted
    assert redo.pending(b.store.engine, [MID]) == {}

    eng = b.store.engine
    with Session(eng) as s, s.begin():  # minute 59 failed, minute 0 never processed
        aw.delete_window(s, MID, 60, TS + 60)
        aw.put_rows(s, [aw.window_row(MID, FAILED_LEVEL, TS + 60, TS + 120, 1, b"")])
        aw.delete_window(s, MID, 60, TS + 120)
    r = cli("--from", "2026-11-23T08:58:00", "--to", "2026-11-23T09:03:00")
    assert r.exit_code == 0, r.output
    assert r.output.strip() == (
        f"machine {MID}: redo of 2026-11-23T08:58:00.000Z – 2026-11-23T09:03:00.000Z "
        "requested (version 1); watermark 2026-11-23T09:02:00.000Z; windows of 60 s holding "
        "samples: 4 behind the watermark (2 processed, 1 failed, 1 never processed), redone "
        "at the twin worker's next pass; 1 ahead of it, processed as they come"), r.output
    (req,) = redo.pending(eng, [MID])[MID]
    assert req.whole and (req.t0_ns, req.t1_ns) == (round(TS * 1e9),
                                                     round((TS + 300) * 1e9) - 1)
    r = cli("--from", "2026-11-23T08:58:00", "--to", "2026-11-23T08:58:00")
    assert r.exit_code != 0 and "--to" in str(r.exception)  # (main(): status 2)
    r = CliRunner().invoke(app, ["worker", "redo", "--machine", "nobody", "--from", str(TS),
                                 "--to", str(TS + 60), "--db", sqlite_url])
    assert r.exit_code != 0 and "nobody" in str(r.exception)
    b.close()


def test_worker_alone_still_runs_the_worker(tmp_path: Path) -> None:
    """``cranetwin worker`` without a command is the worker (``--help`` lists ``redo``)."""
    r = CliRunner().invoke(app, ["worker", "--help"])
    assert r.exit_code == 0 and "--partitions" in r.output and "redo" in r.output
