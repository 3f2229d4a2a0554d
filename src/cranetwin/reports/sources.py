"""Where report data come from: simulator recordings, twin results, storage, or a demo.

Each source yields consecutive :class:`~cranetwin.analytics.LoadHistory` chunks (bounded memory)
and knows its total size for a progress bar. The reach and height of the load point need the
kinematics, which is why these adapters live here and not in :mod:`cranetwin.analytics`.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import numpy.typing as npt

from cranetwin.analytics import AnalyticsConfig, AnalyticsState, LoadHistory
from cranetwin.errors import CraneTwinError, ReportError
from cranetwin.importer.payload import LiftError, on_grid
from cranetwin.model import Machine, load_machine
from cranetwin.testing.histories import Misuse, SyntheticCrane

if TYPE_CHECKING:
    from cranetwin.importer.replay import PayloadColumn
    from cranetwin.sim import Recording
    from cranetwin.storage import StoreSpec
    from cranetwin.twin import TwinResult

F64 = npt.NDArray[np.float64]
DAY_S = 86400.0
WINDOW_S = 4 * 3600.0  # storage is read and replayed four hours at a time


def _reach_height(machine: Machine, q: F64) -> tuple[F64, F64]:
    from cranetwin.physics import load_point_position

    tip = load_point_position(machine, q)
    base = np.asarray(machine.joints[0].origin_m, dtype=float)
    d = tip - base
    return np.hypot(d[:, 0], d[:, 1]), d[:, 2]


def history_from_recording(machine: Machine, rec: Recording) -> LoadHistory:
    """The simulator's ground truth of a recording as a load history.

    Args:
        machine: The machine simulated.
        rec: A :class:`cranetwin.sim.Recording` (its ``truth`` is used: exact forces, wrenches,
            pressures and payload on the fine grid).

    Raises:
        ReportError: The recording has no joint wrenches (not computed by the simulator).
    """
    tr = rec.truth
    if not np.all(np.isfinite(tr.joint_wrench)):
        raise ReportError("the recording's truth has no joint wrenches; simulate with them on")
    reach, height = _reach_height(machine, tr.q)
    return LoadHistory.from_arrays(
        machine, t_s=tr.t_s, cyl_force=tr.cyl_force, q=tr.q, qd=tr.qd, payload_kg=tr.payload_kg,
        reach_m=reach, height_m=height, joint_wrench=tr.joint_wrench, rod_s=tr.rod_s,
        rod_v=tr.rod_v, p_a=tr.p_a, p_b=tr.p_b)


def history_from_twin(machine: Machine, res: TwinResult) -> LoadHistory:
    """A twin replay result as a load history (NaN-free instants only, and none bridged across
    a dropout: the rule of the twin worker's windows, :func:`cranetwin.service.history.window_rows`,
    so a report from a file, from stored samples and from the worker's stored parts count the
    same instants), with where its payload is steady and the payload net of each lift's empty
    reading (:func:`cranetwin.service.analytics.lift_payload`).

    Args:
        machine: The machine replayed.
        res: A :class:`cranetwin.twin.TwinResult`.
    """
    from cranetwin.service.analytics import cylinder_loads, lift_payload

    reach, height = _reach_height(machine, res.q)
    ok = np.isfinite(res.cyl_force).all(axis=1) & np.isfinite(res.joint_wrench).all(axis=(1, 2))
    ok &= np.isfinite(res.payload_kg) & np.isfinite(res.q).all(axis=1)
    ok &= ~np.asarray(res.gap, dtype=bool)
    steady, net = lift_payload(res)

    def k(a: F64) -> F64:
        return a if ok.all() else a[ok]
    return LoadHistory.from_arrays(
        machine, t_s=k(res.t_s), cyl_force=k(res.cyl_force), q=k(res.q), qd=k(res.qd),
        payload_kg=np.maximum(k(net), 0.0), reach_m=k(reach), height_m=k(height),
        joint_wrench=k(res.joint_wrench), rod_s=k(res.rod_s), rod_v=k(res.rod_v),
        p_a=k(res.p_a), p_b=k(res.p_b), payload_steady=k(steady),
        cyl_load=cylinder_loads(machine, k(res.q), k(res.id_torque), k(res.cyl_force)))


class Source(Protocol):
    """A stream of load-history chunks of one machine."""

    machine: Machine
    label: str

    def total(self) -> int:
        """Units of progress (samples or chunks) that :meth:`chunks` will report."""
        ...

    def chunks(self) -> Iterator[tuple[LoadHistory | None, int]]:
        """Consecutive chunks (None: progress without data), each with its units of progress."""
        ...


@dataclass
class DemoSource:
    """Synthetic shifts (see :class:`cranetwin.testing.histories.SyntheticCrane`) with a few
    injected misuse events, for a report that works without any data."""

    machine: Machine
    days: int = 30
    rate_hz: float = 100.0
    seed: int = 0
    start_epoch_s: float | None = None
    label: str = "demo: synthetic 8-hour shifts"

    def __post_init__(self) -> None:
        per_day = int(8 * 3600 // 45) + 1
        last = max(self.days - 1, 0)
        mis = Misuse(overload=(17,), end_stop=(min(1, last) * per_day + 33,),
                     overspeed=(min(4, last) * per_day + 101,))
        kw = {} if self.start_epoch_s is None else {"start_epoch_s": self.start_epoch_s}
        self.crane = SyntheticCrane(self.machine, seed=self.seed, days=self.days, misuse=mis,
                                    **kw)

    def total(self) -> int:
        return int(self.days * 8 * 3600 * self.rate_hz)

    def chunks(self) -> Iterator[tuple[LoadHistory | None, int]]:
        for h in self.crane.chunks(self.rate_hz, 3600.0):
            yield h, h.n


@dataclass
class RecordingSource:
    """A simulator recording file (``.npz`` or ``.csv``), analysed on its ground truth."""

    machine: Machine
    path: Path
    label: str = ""

    def __post_init__(self) -> None:
        from cranetwin.sim import Recording

        try:
            self.rec = Recording.load(self.path)
        except CraneTwinError:
            raise
        except (OSError, ValueError, KeyError) as exc:
            raise ReportError(f"cannot read recording {self.path}: {exc}") from exc
        self.label = self.label or f"recording {self.path.name} (scenario {self.rec.scenario})"

    def total(self) -> int:
        return self.rec.truth.n

    def chunks(self) -> Iterator[tuple[LoadHistory | None, int]]:
        h = history_from_recording(self.machine, self.rec)
        step = 360_000
        for a in range(0, h.n, step):
            part = h.slice(a, min(a + step, h.n))
            yield part, part.n


@dataclass
class StoreSource:
    """A registered machine's range from storage: merged from the twin worker's stored analytics
    parts (:meth:`range_state`, what :func:`cranetwin.reports.build_report` uses), or replayed
    four hours at a time by :meth:`chunks` (the direct path)."""

    url: str | StoreSpec
    """A database URL, or where the settings store (shards included)."""
    machine_id: str
    t0_s: float
    t1_s: float
    grid_hz: float = 100.0
    label: str = ""
    margin_s: float = 2.0
    """Samples read either side of a replayed minute [s] (the worker's ``twin_margin_s``)."""

    def __post_init__(self) -> None:
        try:
            from cranetwin.storage import open_store
            from cranetwin.storage.engine import display_url
        except ImportError as exc:  # pragma: no cover - storage is part of the package
            raise ReportError(f"storage is not available: {exc}") from exc
        self.store = open_store(self.url)
        info = {m.machine_id: m for m in self.store.machines()}
        if self.machine_id not in info:
            raise ReportError(f"unknown machine {self.machine_id!r}; registered: "
                              f"{sorted(info)}")
        model = info[self.machine_id].model
        if "\n" in model or "[" in model:
            import tomllib

            from cranetwin.model import machine_from_dict

            self.machine = machine_from_dict(tomllib.loads(model), f"machine {self.machine_id}")
        else:
            self.machine = load_machine(model)
        if not self.t1_s > self.t0_s:
            raise ReportError(f"--to ({self.t1_s}) must be after --from ({self.t0_s})")
        self.label = self.label or f"machine {self.machine_id} from " + (
            display_url(self.url) if isinstance(self.url, str) else self.url.display())

    def total(self) -> int:
        return int(np.ceil((self.t1_s - self.t0_s) / WINDOW_S))

    def range_state(self, config: AnalyticsConfig | None = None) -> AnalyticsState:
        """The analysis of [t0_s, t1_s) merged from the analytics parts the twin worker stored
        (:func:`cranetwin.service.history.range_state`); minutes without a part (the edges, not
        processed yet) are replayed the way the worker replays them."""
        from cranetwin.service.backend import Backend
        from cranetwin.service.history import range_state, window_history
        from cranetwin.service.replayer import Replayer

        backend = Backend(self.store)
        replayer = Replayer(self.store.read_payload)  # the stored known payload, as the worker
        prog = backend.progress(self.machine_id)

        def edge(a: float, b: float) -> LoadHistory | None:
            return window_history(backend, replayer, self.machine, self.machine_id, a, b,
                                  self.margin_s)
        engine = self.store.engine_for(self.machine_id)
        return range_state(engine, self.machine, self.machine_id, self.t0_s,
                           self.t1_s, edge, prog.watermark_s if prog is not None else None,
                           config=config,
                           next_sample=lambda t: backend.next_sample_time(self.machine_id, t))

    def schedule(self) -> list[Any]:
        """The machine's service schedule now: what is due when
        (:func:`cranetwin.service.schedules.statuses`), for the report's section."""
        from cranetwin.service.backend import Backend
        from cranetwin.service.schedules import statuses

        return statuses(Backend(self.store), self.machine_id)

    def history_usage(self) -> tuple[float, float] | None:
        """(operating s, calendar s) of the machine's whole recorded history: the twin worker's
        operating time from the first stored sample to its progress mark; None before the
        worker processed anything."""
        from sqlalchemy.orm import Session

        from cranetwin.storage.apikeys import get_progress

        dr = self.store.data_range(self.machine_id)
        with Session(self.store.engine_for(self.machine_id)) as s:
            row = get_progress(s, self.machine_id)
            if row is None or dr is None or not row.operating_s > 0:
                return None
            return float(row.operating_s), float(row.watermark_s - dr[0])

    def chunks(self) -> Iterator[tuple[LoadHistory | None, int]]:
        from cranetwin.service.replayer import read_range
        from cranetwin.twin import iter_replay

        t = self.t0_s
        last = -np.inf
        while t < self.t1_s:
            t_next = min(t + WINDOW_S, self.t1_s)
            samples, known = read_range(self.store, self.machine_id, t, t_next)
            if samples.t_s.shape[0] >= 16:
                for res in iter_replay(samples, self.machine, grid_hz=self.grid_hz,
                                       payload=known):
                    h = history_from_twin(self.machine, res) if res.n else None
                    if h is not None and h.n:
                        h = h.slice(int(np.searchsorted(h.t_s, last, side="right")), h.n)
                        if h.n:
                            last = float(h.t_s[-1])
                            yield h, 0
            yield None, 1
            t = t_next


def is_simulator_recording(path: Path) -> bool:
    """True for the simulator's own recording files (``.npz``, or a CSV whose first line is the
    ``# cranetwin-recording:`` header); anything else is a user's file for the importer."""
    if path.suffix.lower() == ".npz":
        return True
    if path.suffix.lower() != ".csv":
        return False
    try:
        with path.open(encoding="utf-8", errors="replace") as fh:
            return fh.readline().startswith("# cranetwin-recording:")
    except OSError:
        return False


@dataclass
class ImportedFileSource:
    """A user's recording (CSV, Parquet, MDF4; docs/IMPORT.md), read through the importer with
    its mapping and analysed on the twin's replay of its samples (not on any truth file).

    A known payload series (the mapping's ``[payload]`` column) is the analysis's payload
    where it is known (the twin's estimate elsewhere). With ``payload_column="use"`` (the
    default) the twin's inverse dynamics use it too (joint loads, wrenches; not with a
    constant ``payload_kg``, which wins); with ``"compare"`` the twin's joint loads come from
    its estimate (or ``payload_kg``) and the estimate is compared with the series per lift
    (``lifts``, after :meth:`chunks`).

    Attributes:
        machine: The machine recorded.
        path: The file.
        mapping: Its mapping TOML (None: the default mapping).
        payload_kg: Known constant payload [kg], or None to estimate it.
        grid_hz: Replay grid [Hz], a multiple of the sample rate.
        payload_column: A known payload series: ``"use"`` or ``"compare"``
            (:data:`cranetwin.importer.replay.PayloadColumn`).
    """

    machine: Machine
    path: Path
    mapping: Path | None = None
    payload_kg: float | None = None
    grid_hz: float = 100.0
    label: str = ""
    payload_column: PayloadColumn = "use"

    def __post_init__(self) -> None:
        from cranetwin.importer import read_file

        got = read_file(self.path, self.machine, self.mapping)
        self.samples = got.samples
        self.known_payload_kg = got.payload_kg
        self.lifts: list[LiftError] | None = None
        self.import_report = got.report
        self.warnings: list[str] = []  # unresolved or inconsistent forces (after chunks())
        self.label = self.label or (f"recording {self.path.name} ({got.report.rows_accepted} "
                                    f"samples, {got.report.rows_refused} rows refused), "
                                    "replayed by the twin")

    def total(self) -> int:
        return int(self.samples.t_s.shape[0])

    def known_used_share(self) -> float | None:
        """Share of the samples whose known payload the twin's dynamics use (0 … 1), or None
        when no known payload series is used (none, ``"compare"``, or a constant given)."""
        from cranetwin.importer.replay import uses_known

        if not uses_known(self.known_payload_kg, self.payload_kg, self.payload_column):
            return None
        assert self.known_payload_kg is not None
        return float(np.isfinite(self.known_payload_kg).mean())

    def chunks(self) -> Iterator[tuple[LoadHistory | None, int]]:
        from cranetwin.importer.replay import ReplayNotes, check_samples, uses_known
        from cranetwin.signal import nominal_period
        from cranetwin.twin import iter_replay
        from cranetwin.twin.consistency import inconsistent
        from cranetwin.twin.observability import unobservable

        check_samples(self.samples, self.machine)
        done = 0
        notes = ReplayNotes.empty()  # forces, residuals, smoothing, the compared payload
        use = uses_known(self.known_payload_kg, self.payload_kg, self.payload_column)
        period = nominal_period(self.samples.t_s, self.samples.period_ns)
        gap_s = 5.0 * period  # the replay's limit
        for res in iter_replay(self.samples, self.machine, grid_hz=self.grid_hz,
                               payload=self.known_payload_kg if use else self.payload_kg):
            if not res.n:
                continue
            n = int(np.searchsorted(self.samples.t_s, res.t_s[-1], side="right")) - done
            done += n
            known = (None if self.known_payload_kg is None
                     else on_grid(res.t_s, self.samples.t_s, self.known_payload_kg, gap_s))
            notes.add(res, None if use else known, self.machine, period)
            if known is not None:
                res = replace(res, payload_kg=np.where(np.isfinite(known), known,
                                                       res.payload_kg))
            h = history_from_twin(self.machine, res)
            yield (h if h.n else None), n
        self.lifts = notes.lifts()
        self.warnings = unobservable(notes.force_observability(self.machine))
        self.warnings += inconsistent(notes.model_consistency(self.machine))
        if self.warnings:
            self.label += "; " + "; ".join(self.warnings)
