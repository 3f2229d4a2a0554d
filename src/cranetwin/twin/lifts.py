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

The empty reading (a tare, as a crane scale is zeroed with an empty grapple). A constant error of
the forces — a pressure sensor's zero offset or drift — moves the estimate by about the same
amount whether the grapple is loaded or empty, and no averaging over the lift removes it. Between
two lifts the grapple is empty, so the estimate there is that error: the empty reading E is the
mean estimate over the empty stretches next to the lift (from ``smear_s`` + ``margin_s`` after the
previous release to as long before the grab, and the same after the release; at most
``tare_span_s`` on each side, so a slow drift is read near the lift), and σ_E,rand the random
part of its σ (:func:`lift_std` over its own k_E = span/``smear_s``, without σ_b). When
|E| > ``TARE_Z`` · sd(E)/√k_E — sd the estimate's own scatter over the empty stretches: the
instants' σ is an upper bound that holds for every pose and lets a steady offset of 15 % of the
load pass for noise — the reading is an offset, not noise, and the lift's load is the net
reading::

    payload = mean over the lift − E,      σ² = σ_lift,rand² + σ_E,rand²

(the systematic σ_b is the offset E took out). Otherwise E is left alone: it is within its
noise, and subtracting it would only add that noise to the lift. A load lighter than
``threshold_kg`` held between lifts reads as an offset and is taken off the next lifts: give
the known payload (:mod:`cranetwin.twin.known_payload`) for such work. The tare removes an
offset exactly only when the error's effect on the estimate changes little between the empty
and the loaded poses (an offset of the force, not of a lever).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from cranetwin.errors import TwinError
from cranetwin.twin.result import TwinResult

F64 = npt.NDArray[np.float64]

TARE_Z = 2.0
"""An empty reading beyond this many of its standard errors is an offset and is taken off the
lift. The standard error comes from the reading's own scatter over a few independent estimates,
so under noise alone more lifts than a normal 2σ test's 5 % are tared: 11 % of 400 lifts of
block noise in tests/test_lift_tare.py; each such tare adds noise of the reading's σ (no bias),
which the lift's σ then includes."""


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
        empty_kg: The empty reading next to the lift [kg] (module docstring; NaN: no empty
            stretch on either side).
        tare_kg: What was taken off the lift's mean for it [kg] (0: the empty reading was
            within its noise, or none); ``payload_kg`` + ``tare_kg`` is the gross mean.
        tare_std_kg: One-sigma random uncertainty of ``tare_kg`` [kg] (0 with no tare): what
            taking it off adds to each instant's σ (:func:`net_payload`).
    """

    grab_s: float
    release_s: float
    t0_s: float
    t1_s: float
    payload_kg: float
    std_kg: float
    complete: bool
    empty_kg: float = float("nan")
    tare_kg: float = 0.0
    tare_std_kg: float = 0.0


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
                  payload_sys_std_kg: F64 | None = None,
                  tare_span_s: float | None = 30.0) -> list[Lift]:
    """The lifts in a payload estimate and each one's mean with grab and release left out,
    net of the empty reading next to it when that is an offset (module docstring).

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
        tare_span_s: Most of each empty stretch read for the empty reading [s], nearest the
            lift; None: no tare (the gross mean).

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
    skip = smear_s + margin_s
    ok = np.isfinite(m) & np.isfinite(s) & np.isfinite(sb)

    def between(spans: list[tuple[float, float]]) -> npt.NDArray[np.intp]:
        """Indices of the instants with lo <= t <= hi for the (lo, hi) of ``spans`` (in time
        order, disjoint), in index order and with an estimate (``ok``): slices of the sorted
        instants, so each lift costs time in its own length, not the recording's."""
        parts = [np.arange(np.searchsorted(t, lo_s, "left"), np.searchsorted(t, hi_s, "right"))
                 for lo_s, hi_s in spans]
        idx = np.concatenate(parts) if parts else np.zeros(0, dtype=np.intp)
        return idx[ok[idx]]

    def reading(sel: npt.NDArray[np.intp], span_s: float) -> tuple[float, float, float]:
        """Mean of the estimates at the instants ``sel`` (:func:`between`) over ``span_s`` of
        time, the σ of that mean (:func:`lift_std`) and its random part; (NaN, inf, inf)
        where none."""
        if not sel.size:
            return float("nan"), float("inf"), float("inf")
        k = max(1.0, span_s / smear_s)
        rand = np.sqrt(np.maximum(s[sel] * s[sel] - sb[sel] * sb[sel], 0.0))
        return (float(np.mean(m[sel])), lift_std(s[sel], sb[sel], k),
                float(np.mean(rand) / np.sqrt(k)))

    lifts: list[Lift] = []
    for i, (a, b) in enumerate(zip(starts, ends, strict=True)):
        grab_in = a > 0
        release_in = b < t.shape[0] - 1
        t0 = t[a] + (skip if grab_in else smear_s / 2)
        t1 = t[b] - (skip if release_in else smear_s / 2)
        mean, std, rand = reading(between([(t0, t1)]), t1 - t0)
        empty, tare, tare_std = float("nan"), 0.0, 0.0
        if np.isfinite(mean) and tare_span_s is not None:
            # the empty stretches either side, up to tare_span_s nearest the lift
            sides = []
            if grab_in:
                lo = t[ends[i - 1]] + skip if i > 0 else t[0]
                sides.append((max(lo, t[a] - skip - tare_span_s), t[a] - skip))
            if release_in:
                hi = t[starts[i + 1]] - skip if i + 1 < len(starts) else t[-1]
                sides.append((t[b] + skip, min(hi, t[b] + skip + tare_span_s)))
            sides = [(lo_s, hi_s) for lo_s, hi_s in sides if hi_s > lo_s]
            near = between(sides)
            span = sum(hi_s - lo_s for lo_s, hi_s in sides)
            empty, _, rand_e = reading(near, span)
            # the empty reading's standard error from its own scatter over k_E estimates
            se = float(np.std(m[near])) / np.sqrt(max(1.0, span / smear_s)) \
                if near.size else float("inf")
            if abs(empty) > TARE_Z * se:  # an offset, not noise (NaN: no stretch)
                tare, tare_std = empty, rand_e
                mean -= tare
                std = float(np.hypot(rand, rand_e))
        lifts.append(Lift(float(t[a]), float(t[b]), float(t0), float(t1), mean, std,
                          grab_in and release_in, empty, tare, tare_std))
    return lifts


def net_payload(t_s: F64, payload_kg: F64, payload_std_kg: F64, lifts: list[Lift],
                payload_sys_std_kg: F64 | None = None) -> tuple[F64, F64]:
    """The estimate at each instant net of its lift's empty reading, with its σ.

    From grab to release of each tared lift (``tare_kg`` ≠ 0) the instant's estimate is the
    gross one less the tare, and its σ the instant's random part and the tare's::

        net = estimate − E,      σ_net² = max(σ² − σ_b², 0) + σ_E,rand²

    (the offset E took out is the systematic σ_b, as for the lift's mean in
    :func:`lift_payloads`). Elsewhere both are the gross estimate's. The tare is read after the
    release as well as before the grab, so this needs the lift's whole neighbourhood: it is a
    result of the whole recording, not of a live stream.

    Args:
        t_s: Instants, shape (m,) [s], increasing.
        payload_kg: The estimate, shape (m,) [kg].
        payload_std_kg: Its one-sigma uncertainty, shape (m,) [kg].
        lifts: The lifts found in it (:func:`lift_payloads` on the same arrays).
        payload_sys_std_kg: The systematic part of ``payload_std_kg``, shape (m,) [kg];
            None: 0.

    Returns:
        (net estimate, its σ), each shape (m,) [kg]: new arrays.
    """
    t = np.asarray(t_s, dtype=np.float64)
    net = np.array(payload_kg, dtype=np.float64)
    std = np.array(payload_std_kg, dtype=np.float64)
    sb = None if payload_sys_std_kg is None else np.asarray(payload_sys_std_kg, np.float64)
    for lf in lifts:
        if lf.tare_kg == 0.0:
            continue
        sl = slice(np.searchsorted(t, lf.grab_s, "left"), np.searchsorted(t, lf.release_s, "right"))
        net[sl] -= lf.tare_kg
        var = std[sl] * std[sl] - (0.0 if sb is None else sb[sl] * sb[sl])
        std[sl] = np.sqrt(np.maximum(var, 0.0) + lf.tare_std_kg * lf.tare_std_kg)
    return net, std


def steady_mask(t_s: F64, lifts: list[Lift]) -> npt.NDArray[np.bool_]:
    """Instants inside a lift's steady part (the instants its payload was averaged over).

    Args:
        t_s: Instants, shape (m,) [s], increasing.
        lifts: Lifts found in an estimate on these instants (:func:`lift_payloads`).

    Returns:
        Shape (m,): True where t0_s <= t <= t1_s of some lift.
    """
    t = np.asarray(t_s, dtype=np.float64)
    out = np.zeros(t.shape, dtype=bool)
    for lf in lifts:  # t increasing: each lift is a slice (time linear in the length)
        out[np.searchsorted(t, lf.t0_s, "left"):np.searchsorted(t, lf.t1_s, "right")] = True
    return out


def tare_span_s(result: TwinResult) -> float | None:
    """The ``tare_span_s`` of :func:`lift_payloads` for a replay's estimate: 30 s, or None (no
    tare) where the replay recognised a coarse staircase on a channel
    (:attr:`cranetwin.signal.SmoothingChoice.step` > 0, :mod:`cranetwin.signal.quantisation`):
    its error differs from level to level, so the empty reading is not the loaded one's error
    and taking it off adds a second draw of it (on the noise family's quantised cases the lift
    means' mean error went from +8.5 % to +14.4 % with the tare)."""
    return None if any(c.step > 0 for c in result.smoothing.values()) else 30.0


def result_lifts(result: TwinResult, sample_period_s: float, threshold_kg: float,
                 payload_window_s: float = 2.0) -> list[Lift]:
    """:func:`lift_payloads` of a replay's estimate (its smear from its smoothing choices, its
    systematic σ kept apart, its tare as :func:`tare_span_s`)."""
    return lift_payloads(result.t_s, result.payload_kg, result.payload_std_kg,
                         payload_smear_s(result, sample_period_s, payload_window_s),
                         threshold_kg, payload_sys_std_kg=result.payload_sys_std_kg,
                         tare_span_s=tare_span_s(result))
