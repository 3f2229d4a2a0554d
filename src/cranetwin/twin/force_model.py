"""Model-based cylinder forces where the pressures alone cannot resolve the force.

Eq. 1–2 turn the chamber pressures into the cylinder force, F = A_A·p_A − A_B·p_B − friction.
When the pressure sensors' error is a large share of the force's range (a light boom behind
0–250 bar sensors), no smoothing of the pressures beats it: a window long enough to average
the noise flattens the force. But the twin also knows the machine: the inverse dynamics (RNEA)
of the smoothed joint motion with the payload estimate give the force each cylinder must
exert, F_model = τ_id,j / (ds/dq) at its joint j. The model misses what the smoothed
accelerations miss (the hydraulic transients at valve steps) and what the payload estimate
gets wrong; the pressures see those. The estimate is the complementary filter::

    F = F_model + S(F_raw − F_model)

with F_raw Eq. 1–2 from the unsmoothed (regularised) pressures at the smoothed rod velocity
(a pressure channel on a coarse lattice reconstructed through its level crossings first, as
the smoothing does: :func:`raw_pressures`) and S LPA-ICI on the residual
(:func:`cranetwin.signal.ici_smooth_pair`, windows up to ``max(MODEL_WINDOWS)`` samples,
order ``MODEL_POLYORDER``, Γ = ``MODEL_GAMMA``): the residual is near zero between
transients, so S takes long windows there (far longer than the force itself allows) and short
ones at the transients. Where the model has no force (a rod in its end stop, whose reaction
the pressures do not show; a non-finite moment arm) F_model is the pressure-smoothed force
instead.

Which cylinders use it is decided with the smoothing windows
(:func:`cranetwin.twin.channels.choose_smoothing`, ``ReplayOptions.model_forces``): with
``"auto"``, those whose per-sample force error σ_F exceeds ``MODEL_SHARE`` (20 %) of the
force range (the observability flag's criterion, :mod:`cranetwin.twin.observability`, at twice
its share). On the noise family (docs/ACCURACY.md, "Noise family") the model-based force's
NRMSE against the pressure-only one's grows with that share: median 0.6–0.85× above 20 %,
about 1.0× at 10–20 %, 1.0–1.2× below 10 %, hence the rule (chosen on that family). The
replay then checks each cylinder's choice by a held-out prediction risk
(:mod:`cranetwin.twin.model_choice`) and switches it where the other force predicts better by
more than two standard errors.

Shapes: n samples, n_c cylinders; SI units (N, m, kg).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from cranetwin.signal import SmoothingChoice, ici_smooth_pair
from cranetwin.signal.quantisation import CONTEXT, reconstruct_columns
from cranetwin.signal.window import DEFAULT_WINDOWS
from cranetwin.twin.observability import RESOLVABLE_SHARE

if TYPE_CHECKING:
    from cranetwin.twin.plan import ReplayPlan

F64 = npt.NDArray[np.float64]
B = npt.NDArray[np.bool_]

MODEL_WINDOWS: tuple[int, ...] = DEFAULT_WINDOWS + (301, 401, 601, 801)
"""LPA-ICI windows of the residual F_raw − F_model [samples]."""
MODEL_POLYORDER = 2
"""Polynomial order of the residual's fits."""
MODEL_GAMMA = 2.0
"""The residual's ICI confidence half-width [standard deviations]."""
MODEL_SHARE = 2 * RESOLVABLE_SHARE
"""``"auto"``: a cylinder's force is model-based when σ_F exceeds this share of its range
(twice the observability flag's: between 10 and 20 % the model-based force was no better
than the pressures' on the noise family, above 20 % it was 0.6–0.85× their NRMSE)."""


def wants_model(sigma_n: float, range_n: float) -> bool:
    """The ``"auto"`` rule: per-sample force error σ_F [N] above ``MODEL_SHARE`` of the force
    range [N] (a constant force counts as unresolved when σ_F > 0)."""
    if not range_n > 0:
        return sigma_n > 0
    return sigma_n > MODEL_SHARE * range_n


def smoothed_range(force: F64, window: int) -> float:
    """Range [N] of a force (n,) [N] after smoothing over ``window`` samples, as the range of
    its means over consecutive blocks of ``window // 2`` samples (about the noise gain of a
    Savitzky–Golay fit of order 2–3 over the window; O(n), for the ``"auto"`` rule on a
    whole recording). 0 for no samples."""
    n = force.shape[0]
    if n == 0:
        return 0.0
    b = min(max(1, window // 2), n)
    if b == 1:
        return float(np.ptp(force))
    full = n - n % b
    means = force[:full].reshape(-1, b).mean(axis=1)
    if full < n:
        means = np.append(means, force[full:].mean())
    return float(np.ptp(means))


def model_cylinders(plan: ReplayPlan, choices: tuple[SmoothingChoice, ...]) -> B:
    """(n_c,) which cylinders' forces are model-based (their pA choice says so)."""
    return np.array([choices[i].model_based for i in plan.cmap.p_a], dtype=np.bool_)


def model_half(plan: ReplayPlan, choices: tuple[SmoothingChoice, ...] | None) -> int:
    """Samples the residual smoothing reaches on each side (0 when no force is model-based)."""
    if choices is None or not model_cylinders(plan, choices).any():
        return 0
    return max(MODEL_WINDOWS) // 2


def pressure_steps(plan: ReplayPlan, choices: tuple[SmoothingChoice, ...]) -> tuple[float, ...]:
    """(2·n_c,) the detected quantisation step [Pa] of each pressure channel (pA then pB per
    cylinder, :attr:`SmoothingChoice.step`) of a model-based cylinder; 0 for the others and
    where none was detected."""
    use = model_cylinders(plan, choices)
    pa = [choices[j].step if u else 0.0 for j, u in zip(plan.cmap.p_a, use, strict=True)]
    pb = [choices[j].step if u else 0.0 for j, u in zip(plan.cmap.p_b, use, strict=True)]
    return tuple(pa + pb)


def raw_context(plan: ReplayPlan, choices: tuple[SmoothingChoice, ...] | None) -> int:
    """Samples of context on each side of the residual's range that :func:`raw_pressures`
    needs: the reconstruction's (:data:`cranetwin.signal.quantisation.CONTEXT`) where a
    model-based cylinder's pressure channel is quantised, else 0."""
    if choices is None or not model_half(plan, choices):
        return 0
    return CONTEXT if any(h > 0 for h in pressure_steps(plan, choices)) else 0


def raw_pressures(plan: ReplayPlan, choices: tuple[SmoothingChoice, ...], block: F64,
                  lead: int, m: int) -> F64:
    """The pressures F_raw is Eq. 1–2 of, at m samples, (m, 2·n_c) [Pa] (pA then pB per
    cylinder): rows ``lead`` … ``lead + m − 1`` of ``block``, regularised pressures in that
    layout (nb, 2·n_c) [Pa] with :func:`raw_context` samples of context on each side of those
    rows (fewer only at the data's ends), each quantised channel of a model-based cylinder
    reconstructed through its level crossings as the smoothing reconstructs it
    (:func:`cranetwin.signal.quantisation.reconstruct_columns`): with that context the values
    equal the whole record's, so the stream's seams do not show."""
    out: F64 = reconstruct_columns(block, pressure_steps(plan, choices))[lead : lead + m]
    return out


def model_forces(plan: ReplayPlan, tau: F64, arm: F64, rod_s: F64, fallback: F64) -> F64:
    """F_model (n, n_c) [N]: the inverse-dynamics load of each cylinder's joint, τ_id (n, n_j)
    [N·m or N], over its moment arm ds/dq (n, n_c) [m/rad or 1]; ``fallback`` (n, n_c) where
    the rod (positions ``rod_s`` (n, n_c) [m]) is within the end-stop margin or the quotient
    is not finite."""
    cy = plan.cylinders
    with np.errstate(divide="ignore", invalid="ignore"):
        f = tau[:, plan.cyl_joint] / arm
    stop = (rod_s <= cy.stop_margin) | (rod_s >= cy.stroke - cy.stop_margin)
    out: F64 = np.where(stop | ~np.isfinite(f), fallback, f)
    return out


def residual_correction(raw_f: F64, f_model: F64, sigma: F64, use: B) -> F64:
    """S(F_raw − F_model) (n, n_c) [N] for the cylinders in ``use`` (0 for the others), from
    Eq. 1–2 of the raw pressures ``raw_f`` (:func:`raw_pressures`) and the model forces
    (n, n_c) [N]; ``sigma`` (n_c,) the raw force noise [N] (module docstring). Non-finite
    residuals (a dropout's edges) count as 0."""
    out = np.zeros(raw_f.shape)
    zero = np.zeros(raw_f.shape[0])
    for k in np.flatnonzero(use):
        r = np.nan_to_num(raw_f[:, k] - f_model[:, k], nan=0.0, posinf=0.0, neginf=0.0)
        out[:, k] = ici_smooth_pair(r, zero, 1.0, 0.0, max(float(sigma[k]), 0.0),
                                    MODEL_WINDOWS, MODEL_POLYORDER, MODEL_GAMMA)[:, 0]
    return out


def residual_range(ka: int, kb: int, half: int, n_total: int, last: bool) -> tuple[int, int]:
    """Samples [r0, r1] (inclusive) whose residuals a chunk smooths for its outputs at samples
    [ka, kb) (kb itself too when there): ``half`` on each side, and at least the longest
    window (2·half + 1) where the range touches the recording's start or, in the last chunk,
    its end, so the end fits see the same samples as a whole-recording pass."""
    r0 = max(0, ka - half)
    r1 = min(n_total - 1, kb + half)
    if half == 0:
        return r0, r1
    w = 2 * half + 1
    if r0 == 0:
        r1 = min(n_total - 1, max(r1, w - 1))
    if last and r1 == n_total - 1:
        r0 = max(0, min(r0, n_total - w))
    return r0, r1


def interpolate(corr: F64, r: int, n: int) -> F64:
    """The corrections at samples (ns, n_c) linearly at grid rows 0 … n − 1 (row g in
    sample interval g // r)."""
    if r == 1:
        return corr[:n]
    g = np.arange(n)
    s0 = g // r
    fr = ((g - s0 * r) / r)[:, None]
    s1 = np.minimum(s0 + 1, corr.shape[0] - 1)
    out: F64 = corr[s0] + fr * (corr[s1] - corr[s0])
    return out
