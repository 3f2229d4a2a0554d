"""The twin's replay of a file or of arrays as a table of named columns (docs/IMPORT.md).

:func:`replay_table` (whole result in memory) and :func:`iter_replay_table` (chunk by chunk,
bounded memory; what ``cranetwin replay --out`` writes) run
:func:`cranetwin.twin.iter_replay` and name its outputs. Columns, in order (``<joint>`` and
``<cyl>`` are the machine's joint and cylinder names; joint units are rad for revolute and m
for prismatic joints, "load" units N·m or N accordingly):

=================================  =================  ==========================================
column                             unit               what
=================================  =================  ==========================================
``t_s``                            s (Unix epoch)     grid time
``q.<joint>``                      rad or m           joint position
``qd.<joint>``                     rad/s or m/s       joint velocity
``qdd.<joint>``                    rad/s² or m/s²     joint acceleration (kinematic)
``rod_s.<cyl>``                    m                  rod position (stroke), smoothed
``rod_v.<cyl>``                    m/s                rod velocity
``p_a.<cyl>``, ``p_b.<cyl>``       Pa                 piston- and rod-side pressure, smoothed
``force.<cyl>``                    N                  cylinder force, paper Eq. 1–2
``torque_act.<joint>``             N·m or N           actuator load on the joint
``torque_id.<joint>``              N·m or N           inverse-dynamics load (with the payload)
``residual.<joint>``               N·m or N           torque_act − torque_id
``wrench.<joint>.fx|fy|fz``        N                  joint reaction force, child body frame
``wrench.<joint>.mx|my|mz``        N·m                joint reaction moment, child body frame
``tip.x``, ``tip.y``, ``tip.z``    m                  load point in the world frame
``payload_kg``                     kg                 payload used (given, known, or estimated)
``payload_std_kg``                 kg                 one-sigma uncertainty of the estimate (0
                                                      where given or known)
``payload_known_kg``               kg                 only with a known payload series (the
                                                      mapping's ``[payload]`` column): it
``payload_error_kg``               kg                 only when the series is compared, not
                                                      used: ``payload_kg − payload_known_kg``
``gap``                            0/1                1 where a dropout was bridged
``missing.<channel>``              0/1                1 where that input channel's sample nearest
                                                      the instant is missing (NaN) or over 0.6
                                                      sample periods away (a gap)
=================================  =================  ==========================================
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import numpy.typing as npt

from cranetwin.errors import MissingExtraError, TwinError
from cranetwin.importer.api import Columns, read_columns, read_file
from cranetwin.importer.checks import check_rod_positions
from cranetwin.importer.mapping import Mapping
from cranetwin.importer.payload import MIN_LIFT_KG, LiftError, lift_errors, on_grid
from cranetwin.model import Machine
from cranetwin.samples import SampleArrays
from cranetwin.signal import SmoothingChoice, nominal_period
from cranetwin.twin import ReplayOptions, TwinResult, iter_replay
from cranetwin.twin.consistency import ModelConsistency, ResidualStats
from cranetwin.twin.lifts import Lift, lift_payloads, payload_smear_s, tare_span_s
from cranetwin.twin.observability import ForceObservability, ForceRange

F64 = npt.NDArray[np.float64]
WRENCH = ("fx", "fy", "fz", "mx", "my", "mz")

PayloadColumn = Literal["use", "compare"]
"""What a known payload series (the mapping's ``[payload]`` column) does: ``"use"`` (the
default) — it is the payload of the twin's inverse dynamics where known, the estimate fills
where it is NaN; ``"compare"`` — the twin estimates the payload (or takes a constant
``payload``) and the series is only compared with it, lift by lift (docs/IMPORT.md)."""


def uses_known(known: F64 | None, payload: float | None, payload_column: PayloadColumn) -> bool:
    """Whether the known series goes into the dynamics: there is one, the column is to be
    used, and no constant ``payload`` was given (a constant given explicitly wins; the series
    is then compared with it)."""
    if payload_column not in ("use", "compare"):
        raise TwinError(f"payload column: {payload_column!r}; expected 'use' or 'compare'")
    return known is not None and payload is None and payload_column == "use"


def column_units(machine: Machine, channels: Sequence[str] | None = None,
                 known_payload: bool = False, compared: bool = True) -> dict[str, str]:
    """Every output column name, in order, with its unit (see the module docstring).

    Args:
        machine: The machine.
        channels: The input channels (their ``missing.<channel>`` flags); None = every channel
            of the machine.
        known_payload: With the known payload's column(s).
        compared: With ``payload_error_kg`` too (the series compared with the estimate, not
            used in the dynamics).
    """
    out: dict[str, str] = {"t_s": "s"}
    lin = {j.name: j.kind == "prismatic" for j in machine.joints}

    def ju(name: str, rot: str, pri: str) -> str:
        return pri if lin[name] else rot

    for pre, rot, pri in (("q", "rad", "m"), ("qd", "rad/s", "m/s"), ("qdd", "rad/s^2", "m/s^2")):
        out.update({f"{pre}.{j.name}": ju(j.name, rot, pri) for j in machine.joints})
    cyls = [c.name for c in machine.cylinders]
    for pre, unit in (("rod_s", "m"), ("rod_v", "m/s"), ("p_a", "Pa"), ("p_b", "Pa"),
                      ("force", "N")):
        out.update({f"{pre}.{c}": unit for c in cyls})
    for pre in ("torque_act", "torque_id", "residual"):
        out.update({f"{pre}.{j.name}": ju(j.name, "N*m", "N") for j in machine.joints})
    for j in machine.joints:
        out.update({f"wrench.{j.name}.{k}": ("N" if k[0] == "f" else "N*m") for k in WRENCH})
    out.update({"tip.x": "m", "tip.y": "m", "tip.z": "m", "payload_kg": "kg",
                "payload_std_kg": "kg"})
    if known_payload:
        out["payload_known_kg"] = "kg"
        if compared:
            out["payload_error_kg"] = "kg"

    out["gap"] = "1"
    out.update({f"missing.{c.name}": "1" for c in machine.channels
                if channels is None or c.name in channels})
    return out


def channel_flags(samples: SampleArrays, t_s: F64, period_s: float) -> dict[str, F64]:
    """``missing.<channel>`` per input channel at the instants ``t_s`` (see the table above)."""
    n = samples.t_s.shape[0]
    i = np.searchsorted(samples.t_s, t_s)
    lo = np.clip(i - 1, 0, n - 1)
    hi = np.clip(i, 0, n - 1)
    near = np.where(np.abs(samples.t_s[hi] - t_s) < np.abs(t_s - samples.t_s[lo]), hi, lo)
    far = np.abs(samples.t_s[near] - t_s) > 0.6 * period_s
    return {f"missing.{c}": (far | np.isnan(samples.values[near, j])).astype(np.float64)
            for j, c in enumerate(samples.channels)}


def result_columns(res: TwinResult, machine: Machine) -> dict[str, F64]:
    """A :class:`TwinResult` as named columns (see :func:`column_units`), shape (m,) each."""
    out: dict[str, F64] = {"t_s": res.t_s}
    joints = [j.name for j in machine.joints]
    cyls = [c.name for c in machine.cylinders]
    for pre, arr in (("q", res.q), ("qd", res.qd), ("qdd", res.qdd)):
        out.update({f"{pre}.{n}": arr[:, i] for i, n in enumerate(joints)})
    for pre, arr in (("rod_s", res.rod_s), ("rod_v", res.rod_v), ("p_a", res.p_a),
                     ("p_b", res.p_b), ("force", res.cyl_force)):
        out.update({f"{pre}.{n}": arr[:, i] for i, n in enumerate(cyls)})
    for pre, arr in (("torque_act", res.actuator_torque), ("torque_id", res.id_torque),
                     ("residual", res.residual)):
        out.update({f"{pre}.{n}": arr[:, i] for i, n in enumerate(joints)})
    for i, n in enumerate(joints):
        out.update({f"wrench.{n}.{k}": res.joint_wrench[:, i, c] for c, k in enumerate(WRENCH)})
    tip = res.tip_path(machine) if res.n else np.zeros((0, 3))
    out.update({"tip.x": tip[:, 0], "tip.y": tip[:, 1], "tip.z": tip[:, 2],
                "payload_kg": res.payload_kg, "payload_std_kg": res.payload_std_kg,
                "gap": res.gap.astype(np.float64)})
    return {k: np.ascontiguousarray(v, dtype=np.float64) for k, v in out.items()}


Source = SampleArrays | str | Path | Columns


def load_source(source: Source, machine: Machine,
                mapping: Mapping | str | Path | None = None) -> SampleArrays:
    """Samples from arrays, a file (:func:`read_file`) or columns (:func:`read_columns`)."""
    return load_source_and_payload(source, machine, mapping)[0]


def load_source_and_payload(source: Source, machine: Machine,
                            mapping: Mapping | str | Path | None = None,
                            ) -> tuple[SampleArrays, F64 | None]:
    """:func:`load_source` and the known payload at the samples (the mapping's ``[payload]``
    column; None without one, and for :class:`SampleArrays`)."""
    if isinstance(source, SampleArrays):
        return source, None
    got = (read_file(source, machine, mapping) if isinstance(source, str | Path)
           else read_columns(source, machine, mapping))
    return got.samples, got.payload_kg


def check_samples(samples: SampleArrays, machine: Machine) -> None:
    """Refuse samples the twin would silently clip (rod positions outside the strokes).

    Raises:
        TwinError: One line per channel, naming the likely convention or unit mix-up.
    """
    problems = check_rod_positions(samples, machine)
    if problems:
        raise TwinError("rod positions are not stroke positions:\n" +
                        "\n".join(f"  - {p}" for p in problems))


@dataclass
class ReplayNotes:
    """What a chunked replay learns about its whole window, filled as the chunks pass:
    the range of each cylinder's force and the smoothing choices, for the force
    observability verdicts (:mod:`cranetwin.twin.observability`); with a known payload series
    compared, per output row the time, the known payload, the estimate and its σ and
    systematic σ (``payload``: t, known, estimate; ``payload_std``: σ, σ_b; each shape (m,)
    per chunk), and the smear and tare span of the estimate's lifts (``lift_rule``), for
    :meth:`lifts`."""

    forces: ForceRange
    smoothing: dict[str, SmoothingChoice]
    payload: list[tuple[F64, F64, F64]] = field(default_factory=list)
    residuals: ResidualStats = field(default_factory=ResidualStats)
    payload_std: list[tuple[F64, F64]] = field(default_factory=list)
    lift_rule: tuple[float, float | None] | None = None

    @staticmethod
    def empty() -> ReplayNotes:
        return ReplayNotes(ForceRange(), {})

    def add(self, res: TwinResult, known_kg: F64 | None = None,
            machine: Machine | None = None, sample_period_s: float | None = None,
            payload_window_s: float = 2.0) -> None:
        """Take in a chunk (with ``machine``: also its residuals, for
        :meth:`model_consistency`; with ``known_kg``, the known payload on the chunk's
        instants, shape (m,) [kg]: the payload estimate for :meth:`lifts`, its lifts smeared
        as :func:`cranetwin.twin.lifts.payload_smear_s` of ``sample_period_s`` — the replayed
        samples' period [s]; None: the chunk's median step — and ``payload_window_s`` [s])."""
        self.forces.add(res.cyl_force)
        if machine is not None:
            self.residuals.add(machine, res.t_s, res.q, res.residual, res.id_torque, res.p_a,
                               res.p_b, res.gap)
        if not self.smoothing:
            self.smoothing.update(res.smoothing)
        if known_kg is not None:
            self.payload.append((res.t_s, known_kg, res.payload_kg))
            self.payload_std.append((res.payload_std_kg, res.payload_sys_std_kg))
            if self.lift_rule is None and (sample_period_s is not None or res.n >= 2):
                period = (nominal_period(res.t_s) if sample_period_s is None
                          else sample_period_s)
                self.lift_rule = (payload_smear_s(res, period, payload_window_s),
                                  tare_span_s(res))

    def twin_lifts(self) -> list[Lift] | None:
        """The twin's lifts in the compared payload estimate, as
        :func:`cranetwin.twin.lifts.result_lifts` finds them in the whole result (grab and
        release left out, net of the empty reading, with σ); a lift is where the estimate
        exceeds :data:`cranetwin.importer.payload.MIN_LIFT_KG`, the comparison's least known
        lift (50 kg, as the work cycles' default ``grab_kg`` in the analytics,
        :func:`cranetwin.service.analytics.lift_payload`). None: nothing compared."""
        if not self.payload or self.lift_rule is None:
            return None
        t, _, est = (np.concatenate(x) for x in zip(*self.payload, strict=True))
        std, sys_std = (np.concatenate(x) for x in zip(*self.payload_std, strict=True))
        smear, span = self.lift_rule
        return lift_payloads(t, est, std, smear, MIN_LIFT_KG,
                             payload_sys_std_kg=sys_std, tare_span_s=span)

    def lifts(self) -> list[LiftError] | None:
        """The payload estimate's error per lift against the known payload series, gross and
        net (None: no known payload; :func:`cranetwin.importer.payload.lift_errors` with
        :meth:`twin_lifts`)."""
        if not self.payload:
            return None
        t, known, est = (np.concatenate(x) for x in zip(*self.payload, strict=True))
        return lift_errors(t, known, est, twin_lifts=self.twin_lifts())

    def force_observability(self, machine: Machine) -> tuple[ForceObservability, ...]:
        """Per cylinder, whether the pressures resolve its force over the replayed window."""
        return self.forces.assess(machine, self.smoothing)

    def model_consistency(self, machine: Machine) -> tuple[ModelConsistency, ...]:
        """Per cylinder, whether its pressures agree with the motion's inverse dynamics over
        the replayed window (:mod:`cranetwin.twin.consistency`)."""
        return self.residuals.assess(machine, self.smoothing)


def iter_replay_table(source: Source, machine: Machine,
                      mapping: Mapping | str | Path | None = None, *,
                      payload: float | None = None, grid_hz: float | None = None,
                      options: ReplayOptions | None = None,
                      notes: ReplayNotes | None = None,
                      known_payload_kg: F64 | None = None,
                      payload_column: PayloadColumn = "use") -> Iterator[dict[str, F64]]:
    """Replay samples (or a CSV/Parquet/MDF4 file read with ``mapping``) chunk by chunk.

    Args:
        source: :class:`SampleArrays`, a file path (:func:`cranetwin.importer.read_file`) or
            named columns, e.g. a dict of arrays or a pandas DataFrame
            (:func:`cranetwin.importer.read_columns`).
        machine: The machine.
        mapping: The file's mapping (files only).
        payload: Known payload [kg], or None to estimate it.
        grid_hz: Output rate [Hz], an integer multiple of the sample rate (default: the
            sample rate).
        options: Further replay settings.
        notes: Filled with the window's force ranges and smoothing choices as the chunks
            pass (:class:`ReplayNotes`: which cylinder forces are observable), and with the
            payload estimate against a known payload series (:meth:`ReplayNotes.lifts`).
        known_payload_kg: A known payload series at the samples' times [kg], shape (n,),
            NaN where not known (default: a file's or columns' ``[payload]`` column, if the
            mapping names one): adds ``payload_known_kg``.
        payload_column: :data:`PayloadColumn`: ``"use"`` the series in the inverse dynamics
            where known (the estimate elsewhere; not with a constant ``payload``, which
            wins); ``"compare"`` the twin estimates the payload (or uses ``payload``) and the
            series is compared with it (``payload_error_kg``, :meth:`ReplayNotes.lifts`).

    Yields:
        Consecutive chunks of named columns (:func:`column_units` of the input's channels).

    Raises:
        TwinError: Rod positions outside the strokes (:func:`check_samples`), missing
            channels, too few samples.
        ImportFileError: The file cannot be read as mapped.
    """
    samples, from_file = load_source_and_payload(source, machine, mapping)
    known = from_file if known_payload_kg is None else np.asarray(known_payload_kg, dtype=float)
    if known is not None and known.shape != samples.t_s.shape:
        raise TwinError(f"known payload has shape {known.shape}; the samples {samples.t_s.shape}")
    check_samples(samples, machine)
    if samples.t_s.shape[0] < 4:
        raise TwinError(f"{samples.t_s.shape[0]} sample(s): too few to replay")
    opt = options or ReplayOptions()
    if opt.sample_period_s is None and samples.period_ns:
        opt = ReplayOptions(**{**opt.__dict__, "sample_period_s": samples.period_ns / 1e9})
    period = opt.sample_period_s or nominal_period(samples.t_s, samples.period_ns)
    if grid_hz is None:
        grid_hz = float(round(1.0 / period))
    use = uses_known(known, payload, payload_column)
    gap_s = 5.0 * period if opt.max_gap_s is None else opt.max_gap_s  # the replay's limit
    for res in iter_replay(samples, machine, grid_hz, known if use else payload, opt):
        if res.n:
            cols = result_columns(res, machine)
            grid_known = (None if known is None
                          else on_grid(res.t_s, samples.t_s, known, gap_s))
            if grid_known is not None:
                cols = _with_known(cols, grid_known, not use)
            if notes is not None:
                notes.add(res, None if use else grid_known, machine, period,
                          opt.payload_window_s)
            cols.update(channel_flags(samples, res.t_s, period))
            yield cols


def _with_known(cols: dict[str, F64], known: F64, compared: bool) -> dict[str, F64]:
    """``cols`` with ``payload_known_kg`` (and ``payload_error_kg`` if ``compared``) after
    ``payload_std_kg``."""
    out: dict[str, F64] = {}
    for k, v in cols.items():
        out[k] = v
        if k == "payload_std_kg":
            out["payload_known_kg"] = known
            if compared:
                out["payload_error_kg"] = cols["payload_kg"] - known
    return out


@dataclass(frozen=True)
class ReplayTable:
    """A whole replay as named columns.

    ``pandas.DataFrame(table.columns)`` makes a DataFrame of it.

    Attributes:
        columns: Column name → values, shape (m,) each, in :func:`column_units` order.
        units: Column name → unit.
        lifts: The payload estimate's error per lift against a known payload series
            (None without one, or when it was used rather than compared).
    """

    columns: dict[str, F64]
    units: dict[str, str]
    lifts: list[LiftError] | None = None

    def __getitem__(self, name: str) -> F64:
        return self.columns[name]

    @property
    def n(self) -> int:
        return int(self.columns["t_s"].shape[0])


def replay_table(source: Source, machine: Machine,
                 mapping: Mapping | str | Path | None = None, *, payload: float | None = None,
                 grid_hz: float | None = None, options: ReplayOptions | None = None,
                 known_payload_kg: F64 | None = None,
                 payload_column: PayloadColumn = "use") -> ReplayTable:
    """:func:`iter_replay_table` collected into one :class:`ReplayTable` (a known payload
    series given or mapped: used in the dynamics, or with ``payload_column="compare"`` the
    estimate's error per lift)."""
    samples, known = load_source_and_payload(source, machine, mapping)
    if known_payload_kg is not None:
        known = np.asarray(known_payload_kg, dtype=float)
    notes = ReplayNotes.empty()
    parts = list(iter_replay_table(samples, machine, payload=payload, grid_hz=grid_hz,
                                   options=options, notes=notes, known_payload_kg=known,
                                   payload_column=payload_column))
    units = column_units(machine, samples.channels, known is not None,
                         not uses_known(known, payload, payload_column))
    if not parts:
        raise TwinError("the replay produced no output")
    cols = {k: np.concatenate([p[k] for p in parts]) for k in units}
    return ReplayTable(cols, units, notes.lifts())


def write_table(chunks: Iterator[dict[str, F64]], out: str | Path,
                units: dict[str, str]) -> int:
    """Write replay chunks to ``out`` (``.parquet``: units in each field's metadata; ``.csv``:
    a header row of the column names), one chunk at a time. Returns the number of rows."""
    p = Path(out)
    suf = p.suffix.lower()
    if suf not in (".parquet", ".csv"):
        raise TwinError(f"{p}: output must end in .parquet or .csv")
    rows = 0
    if suf == ".csv":
        with p.open("w", encoding="utf-8", newline="") as fh:
            fh.write(",".join(units) + "\n")
            for ch in chunks:
                arr = np.column_stack([ch[k] for k in units])
                np.savetxt(fh, arr, fmt="%.10g", delimiter=",")
                rows += arr.shape[0]
        return rows
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError as exc:
        raise MissingExtraError("import", "Parquet output") from exc
    schema = pa.schema([pa.field(k, pa.float64(), metadata={"unit": u})
                        for k, u in units.items()])
    with pq.ParquetWriter(p, schema) as w:
        for ch in chunks:
            w.write_table(pa.table({k: ch[k] for k in units}, schema=schema))
            rows += int(ch["t_s"].shape[0])
    return rows
