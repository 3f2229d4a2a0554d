"""Accuracy of one replay on data the twin was not tuned on: one case of the noise family.

A case is one crane of the family (:mod:`cranetwin.sim.family`), one scenario, one sample rate
and one sensor-error model (:func:`cranetwin.sim.sensor_error.inject_error`). For it
:func:`evaluate_case` replays the noisy samples with the default settings (per cylinder LPA-ICI
or the SURE fixed window on the pressures, :func:`cranetwin.signal.split_risk.ici_or_fixed`;
model-based forces where the pressures cannot resolve the force,
:mod:`cranetwin.twin.force_model`), again without model-based forces (Eq. 1–2 of the smoothed
pressures only) and again with each fixed Savitzky–Golay window on the pressures
(:data:`FIXED_WINDOWS`, order 3, pressure-only, everything else as chosen by default), and
measures against the simulator's truth at the sample instants (grid = sample rate, so the
default and the fixed windows are compared on the same instants):

* per cylinder the force NRMSE of the default and of every fixed window (the best fixed one in
  hindsight is the yardstick of "never worse than the best fixed window by more than 10 %");
* the rod-position NRMSE and the input's (the noisy positions themselves);
* the force's range as a share of the cylinder's full-pressure force A_A·p_supply (the
  targets apply from 10 %) and the replay's observability verdict
  (:mod:`cranetwin.twin.observability`);
* the payload's z = (estimate − truth)/σ over steady lifts (payload on, no grab or release
  within 1.5 s), of the estimate net of its lift's empty reading
  (:func:`cranetwin.twin.lifts.net_payload`; also of the gross estimate, for comparison), and
  each complete lift's mean (:mod:`cranetwin.twin.lifts`) against the truth.

Given ``stated`` (the machine with the sensors' stated accuracy, as a data sheet gives it:
:func:`cranetwin.sim.sensor_error.data_sheet`) the default is replayed once more with it and
scored the same way (:attr:`CaseResult.stated`): the stated accuracy enters the observability
flag, the choice of model-based forces and the payload's σ (:mod:`cranetwin.twin.payload`);
the fixed windows and the pressure-only replay do not use it and are shared.

NRMSE = RMSE / (max − min of the truth) over the run (:func:`cranetwin.signal.nrmse`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from cranetwin.errors import TwinError
from cranetwin.model import Machine
from cranetwin.samples import SampleArrays
from cranetwin.signal import SmoothingChoice, nrmse
from cranetwin.signal.window import DEFAULT_WINDOWS
from cranetwin.twin.lifts import (
    lift_payloads,
    net_payload,
    payload_smear_s,
    result_lifts,
    tare_span_s,
)
from cranetwin.twin.options import ReplayOptions
from cranetwin.twin.replay import replay
from cranetwin.twin.result import TwinResult

F64 = npt.NDArray[np.float64]

FIXED_WINDOWS: tuple[int, ...] = DEFAULT_WINDOWS
"""Fixed pressure windows compared with the default [samples] (1 = no smoothing)."""
STEADY_AWAY_S = 1.5
"""Payload z is taken where no grab or release lies within this [s]."""
LIFT_THRESHOLD = 0.3
"""A lift is where the estimate exceeds this share of the scenario's nominal payload."""


class CaseTruth(Protocol):
    """The simulator's truth on a grid that holds the sample instants
    (:class:`cranetwin.sim.Truth` has it)."""

    @property
    def t_s(self) -> F64: ...
    @property
    def rod_s(self) -> F64: ...
    @property
    def cyl_force(self) -> F64: ...
    @property
    def payload_kg(self) -> F64: ...


@dataclass(frozen=True)
class CaseSpec:
    """What a case is.

    Attributes:
        crane: The family member's name.
        scenario: Scenario name.
        rate_hz: Sample rate [Hz].
        error: Error model (``uniform``, ``gaussian``, ``quantised``, ``biased``).
        scale: Normalisation of the error: ``full`` (sensor range) or ``recorded``.
        level: e as a fraction (0.05 = ±5 %).
        seed: Seed of the error.
        nominal_payload_kg: The scenario's nominal payload (0: none), for lift detection.
    """

    crane: str
    scenario: str
    rate_hz: float
    error: str
    scale: str
    level: float
    seed: int
    nominal_payload_kg: float


@dataclass(frozen=True)
class CylinderScore:
    """One cylinder in one case (NRMSE as fractions).

    Attributes:
        cylinder: Name.
        force: Force NRMSE of the default.
        fixed: Force NRMSE per fixed pressure window (:data:`FIXED_WINDOWS` order).
        position: Rod-position NRMSE of the replay.
        position_input: Rod-position NRMSE of the noisy samples.
        range_share: True force range / (A_A · supply pressure).
        observable: The replay's verdict (:mod:`cranetwin.twin.observability`).
        error_share: Its per-sample force error / replayed force range.
        pressure_only: Force NRMSE of the default without model-based forces
            (``ReplayOptions(model_forces="off")``: the default's pressures, Eq. 1–2).
        model_based: The default chose the model-based force for this cylinder
            (:mod:`cranetwin.twin.force_model`).
        systematic_share: The verdict's systematic floor / replayed force range (0 without a
            stated accuracy); ``error_share`` > ``RESOLVABLE_SHARE`` alone is the flag
            without the floor.
    """

    cylinder: str
    force: float
    fixed: tuple[float, ...]
    position: float
    position_input: float
    range_share: float
    observable: bool
    error_share: float
    pressure_only: float = float("nan")
    model_based: bool = False
    systematic_share: float = 0.0

    @property
    def best_fixed(self) -> tuple[int, float]:
        """(window, NRMSE) of the best fixed window in hindsight."""
        i = int(np.nanargmin(self.fixed))
        return FIXED_WINDOWS[i], self.fixed[i]


@dataclass(frozen=True)
class CaseResult:
    """Scores of one case.

    Attributes:
        spec: The case.
        cylinders: Per cylinder (machine order).
        z_sq_sum, z_count: Σ z² and the number of steady-lift instants (pooled RMS z), z of
            the estimate net of its lift's empty reading
            (:func:`cranetwin.twin.lifts.net_payload`).
        lift_errors: Per complete lift, (mean estimate − truth) / truth.
        lift_z: Per complete lift, (mean estimate − truth) / its stated σ.
        lift_z_all_random: The same with the lift σ that takes all of the instants' σ as
            averaging down over the lift (:func:`cranetwin.twin.lifts.lift_payloads` without
            the systematic part; the lift σ before the data sheet was used), for comparison.
        stated: The same scores of the replay given the sensors' stated accuracy (None: not
            run); its cylinders share ``fixed``, ``position_input`` and ``pressure_only``.
        gross_z_sq_sum: Σ z² of the gross estimate and its σ on the same instants.
    """

    spec: CaseSpec
    cylinders: tuple[CylinderScore, ...]
    z_sq_sum: float = 0.0
    z_count: int = 0
    lift_errors: tuple[float, ...] = field(default_factory=tuple)
    lift_z: tuple[float, ...] = field(default_factory=tuple)
    stated: CaseResult | None = None
    lift_z_all_random: tuple[float, ...] = field(default_factory=tuple)
    gross_z_sq_sum: float = 0.0

    @property
    def rms_z(self) -> float:
        """RMS of the payload z over the steady-lift instants (NaN without any)."""
        return float(np.sqrt(self.z_sq_sum / self.z_count)) if self.z_count else float("nan")

    @property
    def rms_z_gross(self) -> float:
        """The same of the gross estimate (NaN without any instant)."""
        return (float(np.sqrt(self.gross_z_sq_sum / self.z_count)) if self.z_count
                else float("nan"))

    def as_json(self) -> dict[str, Any]:
        """Plain numbers (NaN → None)."""
        def num(x: float) -> float | None:
            return round(float(x), 6) if np.isfinite(x) else None
        return {"spec": asdict(self.spec),
                "cylinders": [{"cylinder": c.cylinder, "force": num(c.force),
                               "fixed": dict(zip(FIXED_WINDOWS, map(num, c.fixed), strict=True)),
                               "best_fixed_window": c.best_fixed[0],
                               "best_fixed": num(c.best_fixed[1]),
                               "position": num(c.position),
                               "position_input": num(c.position_input),
                               "range_share": num(c.range_share), "observable": c.observable,
                               "error_share": num(c.error_share),
                               "pressure_only": num(c.pressure_only),
                               "model_based": c.model_based,
                               "systematic_share": num(c.systematic_share)}
                              for c in self.cylinders],
                "rms_z": num(self.rms_z), "rms_z_gross": num(self.rms_z_gross),
                "z_count": self.z_count,
                "lift_errors": [num(x) for x in self.lift_errors],
                "lift_z": [num(x) for x in self.lift_z],
                "lift_z_all_random": [num(x) for x in self.lift_z_all_random],
                "stated": None if self.stated is None else self.stated.as_json()}


def truth_rows(truth_t: F64, t: F64) -> npt.NDArray[np.intp]:
    """Rows of a truth grid at the instants ``t`` (which it must hold to 1 µs).

    Raises:
        TwinError: An instant is not on the truth grid.
    """
    idx = np.clip(np.searchsorted(truth_t, t - 1e-9), 0, truth_t.shape[0] - 1)
    if np.abs(truth_t[idx] - t).max() > 1e-6:
        raise TwinError("the truth grid does not contain the replay's instants")
    return idx


def fixed_choices(default: dict[str, SmoothingChoice], machine: Machine,
                  window: int) -> tuple[SmoothingChoice, ...]:
    """The default choices with every pressure pair on one fixed window (order 3, or none)."""
    pressures = {ch.name for ch in machine.channels
                 if ch.quantity in ("pressure_a", "pressure_b")}
    out = []
    for name, c in default.items():
        if name in pressures:
            out.append(SmoothingChoice(window, 3 if window > 1 else 0, c.sigma, float("nan"),
                                       step=c.step))
        else:
            out.append(c)
    return tuple(out)


def _pressure_a(machine: Machine, cylinder: int) -> str:
    """The name of a cylinder's pA channel."""
    name = machine.cylinders[cylinder].name
    return next(ch.name for ch in machine.channels
                if ch.source == name and ch.quantity == "pressure_a")


def _payload_scores(res: TwinResult, truth_p: F64, spec: CaseSpec) -> tuple[
        float, float, int, list[float], list[float], list[float]]:
    """Σ z² of the net and of the gross estimate, count, lift errors, lift z and lift z with
    all of σ divided by √k (:attr:`CaseResult.lift_z_all_random`)."""
    steady = np.ones(res.n, dtype=bool)
    for c in np.flatnonzero(np.diff(truth_p) != 0):
        steady &= np.abs(res.t_s - res.t_s[c]) > STEADY_AWAY_S
    ok = steady & (truth_p > 0) & np.isfinite(res.payload_kg) & (res.payload_std_kg > 0)
    gross = (res.payload_kg[ok] - truth_p[ok]) / res.payload_std_kg[ok]
    errors: list[float] = []
    zs: list[float] = []
    z0: list[float] = []
    net, net_std = res.payload_kg, res.payload_std_kg
    if spec.nominal_payload_kg > 0:
        period, thr = 1.0 / spec.rate_hz, LIFT_THRESHOLD * spec.nominal_payload_kg
        all_random = lift_payloads(res.t_s, res.payload_kg, res.payload_std_kg,
                                   payload_smear_s(res, period), thr,
                                   tare_span_s=tare_span_s(res))
        lifts = result_lifts(res, period, thr)
        net, net_std = net_payload(res.t_s, res.payload_kg, res.payload_std_kg, lifts,
                                   res.payload_sys_std_kg)
        for lf, lf0 in zip(lifts, all_random, strict=True):
            sel = (res.t_s >= lf.t0_s) & (res.t_s <= lf.t1_s)
            if not lf.complete or not np.isfinite(lf.payload_kg) or not sel.any():
                continue
            true = float(np.mean(truth_p[sel]))
            if true <= 0:
                continue
            errors.append((lf.payload_kg - true) / true)
            zs.append((lf.payload_kg - true) / lf.std_kg)
            z0.append((lf.payload_kg - true) / lf0.std_kg)
    z = (net[ok] - truth_p[ok]) / net_std[ok]
    return (float(np.sum(z**2)), float(np.sum(gross**2)), int(z.shape[0]), errors, zs, z0)


def evaluate_case(noisy: SampleArrays, machine: Machine, truth: CaseTruth,
                  spec: CaseSpec, stated: Machine | None = None) -> CaseResult:
    """Replay one case (default, pressure-only default, every fixed pressure window; and the
    default given the stated accuracy) and score it.

    Args:
        noisy: The samples with the error injected, at ``spec.rate_hz``.
        machine: The crane (the same description the samples were simulated with).
        truth: The simulator's truth on a grid holding the sample instants.
        spec: The case.
        stated: ``machine`` with the sensors' stated accuracy (module docstring); None: not
            run.
    """
    res = replay(noisy, machine, grid_hz=spec.rate_hz)
    rows = truth_rows(truth.t_s, res.t_s)
    true_f = truth.cyl_force[rows]
    fixed = []
    for w in FIXED_WINDOWS:
        opts = ReplayOptions(smoothing=fixed_choices(res.smoothing, machine, w))
        rw = replay(noisy, machine, grid_hz=spec.rate_hz, payload=0.0, options=opts)
        fixed.append(nrmse(rw.cyl_force, true_f))
    plain = replay(noisy, machine, grid_hz=spec.rate_hz,
                   options=ReplayOptions(model_forces="off"))
    pressure_only = nrmse(plain.cyl_force, true_f)
    names = {c.name: c for c in machine.channels}
    pos_cols = [next(n for n, c in names.items()
                     if c.source == cyl.name and c.quantity == "position")
                for cyl in machine.cylinders]
    raw_s = np.column_stack([noisy.column(n) for n in pos_cols])
    pos_in = nrmse(raw_s, truth.rod_s[truth_rows(truth.t_s, noisy.t_s)])
    shared = (tuple(tuple(float(f[k]) for f in fixed) for k in range(len(machine.cylinders))),
              pos_in, pressure_only)
    out = _scored(res, machine, truth, spec, shared)
    if stated is None:
        return out
    again = replay(noisy, stated, grid_hz=spec.rate_hz)
    return replace(out, stated=_scored(again, stated, truth, spec, shared))


def _scored(res: TwinResult, machine: Machine, truth: CaseTruth, spec: CaseSpec,
            shared: tuple[tuple[tuple[float, ...], ...], F64, F64]) -> CaseResult:
    """The scores of one default replay ``res``; ``shared`` = (the fixed windows' NRMSE per
    cylinder, the input's position NRMSE (n_c,), the pressure-only NRMSE (n_c,))."""
    fixed, pos_in, pressure_only = shared
    rows = truth_rows(truth.t_s, res.t_s)
    true_f = truth.cyl_force[rows]
    force = nrmse(res.cyl_force, true_f)
    pos = nrmse(res.rod_s, truth.rod_s[rows])
    verdicts = res.force_observability(machine)
    supply = machine.hydraulics.supply_pressure_pa if machine.hydraulics else float("nan")
    span = np.nanmax(true_f, axis=0) - np.nanmin(true_f, axis=0)
    cyls = tuple(CylinderScore(
        cyl.name, float(force[k]), fixed[k], float(pos[k]),
        float(pos_in[k]), float(span[k] / (cyl.area_a_m2 * supply)), verdicts[k].observable,
        float(verdicts[k].share), float(pressure_only[k]),
        res.smoothing[_pressure_a(machine, k)].model_based, float(verdicts[k].systematic_share))
        for k, cyl in enumerate(machine.cylinders))
    zsq, gross, zn, errs, lz, lz0 = _payload_scores(res, truth.payload_kg[rows], spec)
    return CaseResult(spec, cyls, zsq, zn, tuple(errs), tuple(lz), lift_z_all_random=tuple(lz0),
                      gross_z_sq_sum=gross)
