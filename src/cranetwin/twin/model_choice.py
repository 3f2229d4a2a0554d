"""Model-based or pressure-only force, chosen per cylinder by a two-fold split risk.

With ``ReplayOptions.model_forces="auto"`` each cylinder's force is either Eq. 1–2 of the
smoothed pressures ("pressure-only") or the model-based estimate F_model + S(F_raw − F_model)
(:mod:`cranetwin.twin.force_model`). Both are judged as the pressure smoothing's choice is
(:mod:`cranetwin.signal.split_risk`): each smoother runs on the even samples and predicts the
odd ones, and the other way round, against the raw hydraulic force of the held-out samples.
The pressure-only prediction smooths A_A·p_A − A_B·p_B; the model-based one smooths the
residual (A_A·p_A − A_B·p_B) − (F_model + friction) and adds F_model + friction back at the
held-out instants. Both predict the same held-out values, whose noise is the same additive
term for both, so the lower risk is the lower error against the noise-free Eq. 1–2 force
(not against what the pressures do not show: a friction the model of Eq. 1–2 misses is
invisible to it).

The σ_F rule (:func:`cranetwin.twin.force_model.wants_model`, made with the smoothing
windows) stays the first choice; :func:`choose_model` switches a cylinder only where the other
force's risk is lower by more than ``MODEL_Z`` standard errors of the paired difference. On the
noise family (docs/ACCURACY.md, "Model-based or pressure-only by a held-out risk") every
switch allowed (Z = 0) served the lift and jib as well but made 95 forces worse by > 5 %
against 59 better, mostly extensions; with Z = 2 force > 1.1 × the best fixed window went
13 → 9 of 672 and 31 forces got worse by > 5 %, 26 better.

F_model needs the inverse dynamics of the smoothed motion with the payload: a pilot of the
replay's sample stage over the choice span (:func:`pilot_forces`: the smoothing choices'
rows, the joint motion, the payload estimate over its window, RNEA with and without 1 kg at
the load point), on the same evenly spread segments the split risk uses
(:func:`cranetwin.signal.split_risk.segments`, at most ``SPLIT_MAX_SAMPLES`` samples). It
differs from the replay's F_model in three ways, stated as approximations: the integrated
free joints (a slew from its torque) stand at 0 (their centrifugal load on the boom is
missing), a known payload series counts as unknown (the estimate is used), and each segment's
ends cut the smoothing and payload windows. F_model depends on the positions and, through the
payload (a regression over ``payload_window_s``), on all pressures, the held-out ones
included: the leak is one parameter per window of hundreds of samples. Cost: 47–88 ms of CPU
per choice on the replay benchmark's hour of 100 Hz data (≈ 7 % of its replay).
"""

from __future__ import annotations

from dataclasses import replace
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from cranetwin.errors import TwinError
from cranetwin.signal import ICI_WINDOWS, SmoothingChoice
from cranetwin.signal.quantisation import reconstruct_columns
from cranetwin.signal.split_risk import fixed_half, ici_half, segments, split_errors
from cranetwin.twin.force_model import (
    MODEL_GAMMA,
    MODEL_POLYORDER,
    MODEL_WINDOWS,
    model_forces,
)
from cranetwin.twin.plan import ReplayPlan
from cranetwin.twin.stages import (
    eq12,
    estimate_payload,
    margins,
    payload_regressors,
    payload_weights,
    sample_states,
    smooth_rows,
)

F64 = npt.NDArray[np.float64]

MODEL_Z = 2.0
"""The split risk overrides the σ_F rule's choice only when the other force's risk is lower
by more than this many standard errors of the difference."""


def pilot_forces(plan: ReplayPlan, choices: tuple[SmoothingChoice, ...], raw: F64,
                 period: float, payload_kg: float | None) -> tuple[F64, F64, F64]:
    """On regularised rows ``raw`` (n, nch) [working order] with period [s]: the raw hydraulic
    force A_A·p_A − A_B·p_B (n, n_c), the raw Eq. 1–2 force at the smoothed rod velocity
    (n, n_c) and F_model (n, n_c) [N] (module docstring; a constant known payload [kg] or
    None: estimated).

    Raises:
        TwinError: Fewer rows than a smoothing window, or rods outside the geometry.
    """
    cm = plan.cmap
    nc = len(plan.machine.cylinders)
    sm = smooth_rows(plan, choices, raw, period, (True, True))
    q, qd, qdd, f, arm, _ = sample_states(plan, sm)
    motion = (q, qd, qdd)
    t0, t1 = payload_regressors(plan, motion)
    if payload_kg is not None:
        mass = np.full(q.shape[0], float(payload_kg))
    else:
        weights, frac, noise, systematic = payload_weights(plan, choices)
        _, half, pf = margins(choices, plan.nch, period, plan.opt.payload_window_s)
        est, _ = estimate_payload(plan, motion, f, arm,
                                  (weights, frac, pf // 2, half, noise, systematic), (t0, t1))
        mass = est
    pl = np.nan_to_num(np.maximum(mass, 0.0))
    tau = t0 + pl[:, None] * (t1 - t0)
    col = plan.sample_cols
    f_model = model_forces(plan, tau, arm, sm[:, col.s], f)
    rec = reconstruct_columns(raw, [c.step for c in choices[: plan.nch]])
    pa = np.ascontiguousarray(rec[:, list(cm.p_a)])
    pb = np.ascontiguousarray(rec[:, list(cm.p_b)])
    area_a = np.array([c.area_a_m2 for c in plan.machine.cylinders])
    area_b = np.array([c.area_b_m2 for c in plan.machine.cylinders])
    hyd: F64 = pa * area_a - pb * area_b
    raw_f = eq12(plan, pa, pb, np.ascontiguousarray(sm[:, col.v0 : col.v0 + nc]))
    return hyd, raw_f, f_model


class ModelRisks(NamedTuple):
    """Split risks of one recording's cylinders, (n_c,) each.

    Attributes:
        pressure: Mean squared held-out error of the pressure-only force [N²] (σ² included).
        model: The same of the model-based force [N²].
        se: Standard error of ``pressure − model`` [N²]: the paired squared-error differences'
            standard deviation over √(held-out samples) (as if independent: the noise term
            2·e·(b − a) that dominates them is white).
    """

    pressure: F64
    model: F64
    se: F64


def model_risks(plan: ReplayPlan, choices: tuple[SmoothingChoice, ...], raw: F64,
                period: float, payload_kg: float | None) -> ModelRisks | None:
    """Split risks (pressure-only, model-based) per cylinder and the standard error of their
    difference (:class:`ModelRisks`) of predicting the held-out raw force (module docstring)
    on ``raw`` (n, nch); None where the pilot cannot run (too few rows for a window, rods
    outside the geometry)."""
    nc = len(plan.machine.cylinders)
    diffs: list[list[F64]] = [[] for _ in range(nc)]
    r_p = np.zeros(nc)
    r_m = np.zeros(nc)
    segs = segments(raw.shape[0])
    for s in segs:
        try:
            hyd, raw_f, f_model = pilot_forces(plan, choices, np.ascontiguousarray(raw[s]),
                                               period, payload_kg)
        except TwinError:
            return None
        for k in range(nc):
            ch = choices[plan.cmap.p_a[k]]
            if ch.adaptive:
                ws = tuple(w for w in ICI_WINDOWS if w <= ch.window)
                press = ici_half(ch.sigma, ws, ch.polyorder)
            else:
                press = fixed_half(ch.window, ch.polyorder)
            resid = np.nan_to_num(raw_f[:, k] - f_model[:, k], nan=0.0, posinf=0.0,
                                  neginf=0.0)
            e_p = split_errors(np.ascontiguousarray(hyd[:, k]), press)
            e_m = split_errors(resid, ici_half(max(ch.sigma, 0.0), MODEL_WINDOWS,
                                               MODEL_POLYORDER, MODEL_GAMMA))
            r_p[k] += float(e_p @ e_p) / max(e_p.shape[0], 1)
            r_m[k] += float(e_m @ e_m) / max(e_m.shape[0], 1)
            diffs[k].append(e_p * e_p - e_m * e_m)
    se = np.array([float(np.std(d) / np.sqrt(max(d.shape[0], 1)))
                   for d in (np.concatenate(x) for x in diffs)])
    return ModelRisks(r_p / len(segs), r_m / len(segs), se)


def choose_model(plan: ReplayPlan, choices: tuple[SmoothingChoice, ...], raw: F64,
                 period: float, payload_kg: float | None) -> tuple[SmoothingChoice, ...]:
    """The choices with ``model_based`` switched on each cylinder's pressure pair where the
    split risk (:func:`model_risks`) shows the other force better by more than ``MODEL_Z``
    standard errors; as ``choices`` set it (the σ_F rule,
    :func:`cranetwin.twin.force_model.wants_model`) elsewhere and where the pilot cannot run.
    Deterministic; a function of the choice span's rows alone, so a stream and a batch replay
    of the same span choose alike."""
    risks = model_risks(plan, choices, raw, period, payload_kg)
    if risks is None:
        return choices
    out = list(choices)
    gain = risks.pressure - risks.model  # > 0: the model-based force predicts better
    for k, (ia, ib) in enumerate(zip(plan.cmap.p_a, plan.cmap.p_b, strict=True)):
        use = choices[ia].model_based
        if use and gain[k] < -MODEL_Z * risks.se[k]:
            use = False
        elif not use and gain[k] > MODEL_Z * risks.se[k]:
            use = True
        out[ia] = replace(out[ia], model_based=use)
        out[ib] = replace(out[ib], model_based=use)
    return tuple(out)
