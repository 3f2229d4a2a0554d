"""Payload per lift: the sliding-window estimate averaged over each lift, grab and release left out.

The payload estimate at an instant (:mod:`cranetwin.twin.payload`) is a least-squares fit over
a centred window of ``payload_window_s`` after a moving average over the longest derivative
window, so a grab or a release (a step of the true payload) reaches the estimate as a ramp
``smear_s`` = window + prefilter wide, centred on the step. A mean over every instant of a
lift therefore takes in half of each ramp and reads low (2–4 % on the simulated log-loading
cycles). Here each step is found where the estimate crosses ``threshold_kg`` (a step of S
crosses it within the ramp), and the ``smear_s`` (plus ``margin_s``) after the grab and before
the release are left out of the lift's mean.

The lift's σ (:func:`lift_std`): the instants' σ (:attr:`TwinResult.payload_std_kg`) share
their data within ``smear_s``, so a lift of steady length D holds k = max(1, D/smear_s)
independent estimates, and their random part averages down by √k. Their systematic part σ_b
(:attr:`TwinResult.payload_sys_std_kg`: the sensors' stated accuracy beyond their noise, an
offset or gain the same all lift long) does not::

    σ_lift² = mean(σ_rand)²/k + mean(σ_b)²,      σ_rand = sqrt(max(σ² − σ_b², 0))

(mean(σ_b) bounds the σ of the lift mean of a constant force error from above: the error's
effect varies a little with the pose). Other errors common to the lift, such as a model
error, are in each instant's σ through the residual scatter and are divided by √k with it.
Without a stated accuracy σ_b = 0 and σ_lift = mean σ/√k.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from cranetwin.errors import TwinError
from cranetwin.twin.result import TwinResult

F64 = npt.NDArray[np.float64]


class Lift(NamedTuple):
    """One lift: the load carried between a grab and a release.

    Attributes:
        grab_s, release_s: Where the estimate crossed the threshold upward and downward [s]
            (the recording's start or end when the lift was already on or still on).
        t0_s, t1_s: The steady part whose estimates were averaged [s] (t0 > t1: none).
        payload_kg: Mean estimate over the steady part [kg] (NaN: no steady part, the lift
            was shorter than two smear widths).
        std_kg: One-sigma uncertainty of that mean [kg] (:func:`lift_std`; inf with no
            steady part).
        complete: Both the grab and the release lie inside the recording.
    """

    grab_s: float
    release_s: float
    t0_s: float
    t1_s: float
    payload_kg: float
    std_kg: float
    complete: bool


def payload_smear_s(result: TwinResult, sample_period_s: float,
                    payload_window_s: float = 2.0) -> float:
    """Width of the ramp a payload step becomes in the estimate [s]: the payload window plus
    the prefilter (the longest derivative window among ``result.smoothing``)."""
    deriv = [c.window for name, c in result.smoothing.items() if name.endswith("'")]
    return payload_window_s + max(deriv, default=1) * sample_period_s


def lift_std(std_kg: F64, sys_std_kg: F64, n_independent: float) -> float:
    """σ of a lift's mean payload [kg] (module docstring) from its instants' σ and systematic
    σ_b, each shape (j,) [kg], over ``n_independent`` = k independent estimates."""
    rand = np.sqrt(np.maximum(std_kg * std_kg - sys_std_kg * sys_std_kg, 0.0))
    return float(np.hypot(np.mean(rand) / np.sqrt(n_independent), np.mean(sys_std_kg)))


def lift_payloads(t_s: F64, payload_kg: F64, payload_std_kg: F64, smear_s: float,
                  threshold_kg: float, margin_s: float = 0.25,
                  payload_sys_std_kg: F64 | None = None) -> list[Lift]:
    """The lifts in a payload estimate and each one's mean with grab and release left out.

    Args:
        t_s: Instants, shape (m,) [s], increasing.
        payload_kg: The estimate, shape (m,) [kg] (NaN: no estimate there; taken as empty).
        payload_std_kg: Its one-sigma uncertainty, shape (m,) [kg].
        smear_s: Width of a step's ramp in the estimate [s] (:func:`payload_smear_s`).
        threshold_kg: A lift is where the estimate exceeds this [kg]: above the empty hook's
            scatter, below the smallest load to count (e.g. 5 % of the rated load).
        margin_s: Further time left out after the ramp [s].
        payload_sys_std_kg: The systematic part of ``payload_std_kg``, shape (m,) [kg];
            None: 0 (every error averages down over the lift).

    Returns:
        The lifts in time order.

    Raises:
        TwinError: Arrays of different lengths, or a non-positive smear or threshold.
    """
    t = np.asarray(t_s, dtype=np.float64)
    m = np.asarray(payload_kg, dtype=np.float64)
    s = np.asarray(payload_std_kg, dtype=np.float64)
    sb = np.zeros(s.shape) if payload_sys_std_kg is None else \
        np.asarray(payload_sys_std_kg, dtype=np.float64)
    if not t.shape == m.shape == s.shape == sb.shape or t.ndim != 1:
        raise TwinError(f"t {t.shape}, payload {m.shape}, std {s.shape} and systematic std "
                        f"{sb.shape} must be equal (m,)")
    if not smear_s > 0 or not threshold_kg > 0:
        raise TwinError("smear_s and threshold_kg must be positive")
    on = np.nan_to_num(m, nan=-np.inf) > threshold_kg
    if not on.any():
        return []
    edges = np.flatnonzero(np.diff(on.astype(np.int8)))
    starts = list(edges[~on[edges]] + 1)  # first instant above
    ends = list(edges[on[edges]])  # last instant above
    if on[0]:
        starts.insert(0, 0)
    if on[-1]:
        ends.append(t.shape[0] - 1)
    lifts: list[Lift] = []
    skip = smear_s + margin_s
    for a, b in zip(starts, ends, strict=True):
        grab_in = a > 0
        release_in = b < t.shape[0] - 1
        t0 = t[a] + (skip if grab_in else smear_s / 2)
        t1 = t[b] - (skip if release_in else smear_s / 2)
        sel = (t >= t0) & (t <= t1) & np.isfinite(m) & np.isfinite(s) & np.isfinite(sb)
        if sel.any():
            mean = float(np.mean(m[sel]))
            std = lift_std(s[sel], sb[sel], max(1.0, (t1 - t0) / smear_s))
        else:
            mean, std = float("nan"), float("inf")
        lifts.append(Lift(float(t[a]), float(t[b]), float(t0), float(t1), mean, std,
                          grab_in and release_in))
    return lifts


def steady_mask(t_s: F64, lifts: list[Lift]) -> npt.NDArray[np.bool_]:
    """Instants inside a lift's steady part (the instants its payload was averaged over).

    Args:
        t_s: Instants, shape (m,) [s].
        lifts: Lifts found in an estimate on these instants (:func:`lift_payloads`).

    Returns:
        Shape (m,): True where t0_s <= t <= t1_s of some lift.
    """
    t = np.asarray(t_s, dtype=np.float64)
    out = np.zeros(t.shape, dtype=bool)
    for lf in lifts:
        out |= (t >= lf.t0_s) & (t <= lf.t1_s)
    return out


def result_lifts(result: TwinResult, sample_period_s: float, threshold_kg: float,
                 payload_window_s: float = 2.0) -> list[Lift]:
    """:func:`lift_payloads` of a replay's estimate (its smear from its smoothing choices, its
    systematic σ kept apart)."""
    return lift_payloads(result.t_s, result.payload_kg, result.payload_std_kg,
                         payload_smear_s(result, sample_period_s, payload_window_s),
                         threshold_kg, payload_sys_std_kg=result.payload_sys_std_kg)
