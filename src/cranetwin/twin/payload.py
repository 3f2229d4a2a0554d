"""Payload mass from the pressures: weighted least squares over a sliding window.

The paper assumes the payload known; the twin measures it. The payload is a point mass m at the
load point, so the inverse-dynamics joint loads are affine in m::

    tau_id(q, qd, qdd; m) = tau_0 + m·g,   g = tau_id(…; 1 kg) − tau_id(…; 0 kg)

and the actuator loads computed from the pressures (Eq. 1–2 through the moment arms) should
equal them. Per cylinder joint c (per unit of rod force: g_c = g/arm_c, r_c = r/arm_c), both
sides first averaged over P = 2·prefilter_half + 1 instants ("filter both sides"), then over a
centred window of N instants with weights w_c::

    m̂ = Σ w_c·g_c·r_c / Σ w_c·g_c²,      r = tau_act − tau_0

Its standard error has two parts (the smoothed errors are correlated over many samples, so
neither is the textbook σ²/(N−1))::

    σ_m̂² = σ_p² + σ_e²

* σ_p, the pressure noise propagated through the estimator: raw force noise σ_c (white,
  before any smoothing; the pressure smoother keeps the mean, so only the two moving averages
  matter) gives ``σ_p² = κ(N, P)·Σ w_c²·g_c²·σ_c² / (Σ w_c·g_c²)²`` with κ = Σ_k u_k² / N,
  u = box(N) ∗ box(P)/P the estimator's weight on each raw sample;
* σ_e, every other error, from the window's residual scatter beyond what that noise explains:
  ``σ_e² = max(RSS − N·Σ w_c·σ_c²/P, 0) / (n_eff − 1) / Σ w_c·g_c²``, RSS = Σ w_c·(r_c −
  m̂·g_c)², over n_eff = 1 + n_c·N/P independent errors: N/P per joint in a long window, and
  one when the window lies within the prefilter (the joints' errors then share their cause,
  the accelerations smoothed over the long derivative window that position noise brings).

* σ_b, the sensors' systematic error. ``Channel.accuracy`` is a ± bound a on each pressure
  sensor's whole error; an error uniform within it has σ = a/√3
  (:func:`cranetwin.twin.observability.stated_force_sigma` turns the two chambers' into a
  rod-force σ_s,c per cylinder). The part of the bound the data show as noise averages out
  (σ_c, already in σ_p; uniform noise of σ_c fills ±√3·σ_c); what the bound leaves, ±(a −
  √3·σ_c), may be an offset, a gain error or a coarse staircase, the same over the window,
  which neither averages out nor shows much in the residual scatter. Taken as uniform in it:
  ``σ_b,c = max(σ_s,c − σ_c, 0)`` (:func:`systematic_std`; bounds subtract, not variances:
  a noise estimate 3 % low leaves 3 % of σ_s, not 24 %). It is propagated as a constant
  force error δ_c per cylinder, independent between cylinders: δm̂ = Σ_c δ_c·Σ_k w_c·g_c,k /
  Σ w_c·g_c², hence ``σ_b² = Σ_c σ_b,c²·(Σ_k w_c·g_c,k)² / (Σ w_c·g_c²)²`` and
  σ_m̂² = σ_p² + σ_e² + σ_b². Without a stated accuracy σ_b = 0: the σ then covers random
  error only (the noise the replay estimates from the data and the residual scatter), not an
  offset of the sensors. σ_b is also given on its own (``sys_std_out``,
  ``TwinResult.payload_sys_std_kg``): unlike σ_p and σ_e it does not average down over a lift
  (:mod:`cranetwin.twin.lifts`).

Measured on simulated lifts (docs/ACCURACY.md "Payload uncertainty"): see there for the RMS
of error/σ at 1, 2, 5 % sensor error; the previous σ (the window's scatter over
N·Σ risk_c/σ_c² samples) was 3–9× too small.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt
from numba import njit

from cranetwin.errors import TwinError

F64 = npt.NDArray[np.float64]


class JointLoads(NamedTuple):
    """The regression's inputs at k instants: inverse-dynamics joint loads with 0 and 1 kg of
    payload ``tau0``, ``tau1`` (k, n_joints) [N·m or N], cylinder forces ``force`` (k, n_c) [N]
    and moment arms ``arm`` ds/dq (k, n_c) [m/rad or m/m]."""

    tau0: F64
    tau1: F64
    force: F64
    arm: F64


class PayloadWindow(NamedTuple):
    """The regression's settings: each cylinder's joint index ``joints`` (n_c,), weights 1/σ²
    per cylinder joint (n_c,) [1/N²], the raw force noise ``noise_var`` σ_c² per cylinder
    (n_c,) [N²], the variance of each cylinder's systematic force error ``bias_var`` σ_b,c²
    (n_c,) [N²] (module docstring), the prefilter's and the fit's half windows [instants]."""

    joints: npt.NDArray[np.int64]
    weights: F64
    noise_var: F64
    bias_var: F64
    prefilter_half: int
    half_window: int


@njit(cache=True)
def _moving_sum_cols(x, half, out):  # type: ignore[no-untyped-def]
    """Centred moving sums of x (n, k) over [i − half, i + half] ∩ [0, n), into out (n, k),
    by running sums."""
    n, k = x.shape
    c = np.zeros((n + 1, k))
    for i in range(n):
        for j in range(k):
            c[i + 1, j] = c[i, j] + x[i, j]
    for i in range(n):
        hi = min(i + half + 1, n)
        lo = max(i - half, 0)
        for j in range(k):
            out[i, j] = c[hi, j] - c[lo, j]


@njit(cache=True, inline="always")
def box_gain(n, p):  # type: ignore[no-untyped-def]
    """κ(N, P) = Σ_k u_k² / N for u = box(N) ∗ box(P)/P: the variance of the mean over N
    instants of a P-point moving average of white noise, relative to σ²/N (1 for P = 1,
    ≈ 2N/(3P) for P ≫ N)."""
    a = min(n, p)
    b = max(n, p)
    s = (a - 1.0) * a * (2.0 * a - 1.0) / 3.0 + (b - a + 1.0) * a * a
    return s / (p * p) / n


@njit(cache=True, inline="always")
def _window_estimate(sums, cnt, n_c, p, wsig, bias_var):  # type: ignore[no-untyped-def]
    """Payload [kg] and its standard error (module docstring) from one window's weighted sums
    ``sums`` = (Σ w·g², Σ w·g·r, Σ w·r², Σ w²·g²·σ², then Σ_k w_c·g_c,k per joint c) over
    ``cnt`` instants of ``n_c`` joints after a ``p``-point prefilter, ``wsig`` = Σ w_c·σ_c²,
    ``bias_var`` σ_b,c² per joint; also σ_b alone, the part of the standard error that does
    not average out over time (NaN, inf and inf when the window has no excitation, Σg² = 0)."""
    sgg = sums[0]
    sgr = sums[1]
    if not sgg > 0.0:
        return np.nan, np.inf, np.inf
    m = sgr / sgg
    rss = max(sums[2] - m * sgr, 0.0)
    excess = max(rss - cnt * wsig / p, 0.0)
    n_eff = 1.0 + n_c * cnt / p
    var_e = excess / max(n_eff - 1.0, 1.0) / sgg
    var_p = box_gain(cnt, float(p)) * sums[3] / (sgg * sgg)
    var_b = 0.0
    for c in range(bias_var.shape[0]):
        var_b += bias_var[c] * sums[4 + c] * sums[4 + c]
    var_b /= sgg * sgg
    return m, np.sqrt(var_e + var_p + var_b), np.sqrt(var_b)


@njit(cache=True)
def _window_sums(per, half, pf, n_c, wsig, bias_var, m_out, std_out, sys_out):  # type: ignore[no-untyped-def]
    """The estimate, its σ and its systematic σ_b at every instant from the per-instant sums
    ``per`` (n, 4 + n_c)."""
    n, ns = per.shape
    cp = np.zeros((n + 1, ns))
    for i in range(n):
        for j in range(ns):
            cp[i + 1, j] = cp[i, j] + per[i, j]
    sums = np.empty(ns)
    for i in range(n):
        hi = min(i + half + 1, n)
        lo = max(i - half, 0)
        for j in range(ns):
            sums[j] = cp[hi, j] - cp[lo, j]
        m_out[i], std_out[i], sys_out[i] = _window_estimate(sums, float(hi - lo), float(n_c),
                                                            2 * pf + 1, wsig, bias_var)


@njit(cache=True)
def _windowed_payload(g, r, weights, noise_var, bias_var, pf, half, m_out, std_out, sys_out):  # type: ignore[no-untyped-def]
    n, k = g.shape
    if pf > 0:  # centred moving average of both sides over [i − pf, i + pf]
        gs = np.empty((n, k))
        rs = np.empty((n, k))
        _moving_sum_cols(g, pf, gs)
        _moving_sum_cols(r, pf, rs)
        for i in range(n):
            cnt = float(min(i + pf + 1, n) - max(i - pf, 0))
            for j in range(k):
                gs[i, j] /= cnt
                rs[i, j] /= cnt
    else:
        gs = g
        rs = r
    per = np.empty((n, 4 + k))
    for i in range(n):
        a = 0.0
        b = 0.0
        c = 0.0
        d = 0.0
        for j in range(k):
            wg = gs[i, j] * weights[j]
            a += wg * gs[i, j]
            b += wg * rs[i, j]
            c += rs[i, j] * rs[i, j] * weights[j]
            d += wg * wg * noise_var[j]
            per[i, 4 + j] = wg
        per[i, 0] = a
        per[i, 1] = b
        per[i, 2] = c
        per[i, 3] = d
    _window_sums(per, half, pf, k, np.sum(weights * noise_var), bias_var, m_out, std_out,
                 sys_out)


@njit(cache=True)
def _regression_payload(loads, win, m_out, std_out, sys_out):  # type: ignore[no-untyped-def]
    """g = (t1 − t0)/arm and r = (force·arm − t0)/arm at the cylinder joints (:class:`JointLoads`
    ``loads``, :class:`PayloadWindow` ``win``), then
    :func:`_windowed_payload` (the same operations in the same order, so the same result):
    the running sums of g and r are formed with them, the per-instant window sums with the
    running sums of those, so the data are passed over twice."""
    t0, t1, force, arm = loads
    joints, weights, noise_var, bias_var, pf, half = win
    n, k = arm.shape
    keep = n if pf == 0 else 0  # g, r themselves only without the prefilter
    g = np.empty((keep, k))
    r = np.empty((keep, k))
    cg = np.empty((n + 1, k))
    cr = np.empty((n + 1, k))
    for c in range(k):
        cg[0, c] = 0.0
        cr[0, c] = 0.0
    for i in range(n):
        for c in range(k):
            j = joints[c]
            a = arm[i, c]
            gi = (t1[i, j] - t0[i, j]) / a
            ri = (force[i, c] * a - t0[i, j]) / a
            if keep:
                g[i, c] = gi
                r[i, c] = ri
            cg[i + 1, c] = cg[i, c] + gi
            cr[i + 1, c] = cr[i, c] + ri
    per = np.empty((n, 4 + k))  # per instant: Σ w·g², Σ w·g·r, Σ w·r², Σ w²·g²·σ², w_c·g_c
    for i in range(n):
        hi = min(i + pf + 1, n)
        lo = max(i - pf, 0)
        cnt = float(hi - lo)
        sa = 0.0
        sb = 0.0
        sc = 0.0
        sd = 0.0
        for c in range(k):
            if pf > 0:
                gs = (cg[hi, c] - cg[lo, c]) / cnt
                rs = (cr[hi, c] - cr[lo, c]) / cnt
            else:
                gs = g[i, c]
                rs = r[i, c]
            wg = gs * weights[c]
            sa += wg * gs
            sb += wg * rs
            sc += rs * rs * weights[c]
            sd += wg * wg * noise_var[c]
            per[i, 4 + c] = wg
        per[i, 0] = sa
        per[i, 1] = sb
        per[i, 2] = sc
        per[i, 3] = sd
    _window_sums(per, half, pf, k, np.sum(weights * noise_var), bias_var, m_out, std_out,
                 sys_out)


def systematic_std(stated_std: F64, noise_std: F64) -> F64:
    """σ_b,c = max(σ_s,c − σ_c, 0) per cylinder (module docstring): the stated accuracy's
    force σ ``stated_std`` (n_c,) [N] less the noise estimated from the data ``noise_std``
    (n_c,) [N]; 0 where nothing is stated."""
    s = np.asarray(stated_std, dtype=np.float64)
    n = np.asarray(noise_std, dtype=np.float64)
    return np.maximum(s - n, 0.0)


def _squares(std: F64 | None, n_c: int, name: str) -> F64:
    """σ² per joint, shape (n_c,) (zeros for None).

    Raises:
        TwinError: Not of shape (n_c,).
    """
    if std is None:
        return np.zeros(n_c)
    a = np.asarray(std, dtype=np.float64)
    if a.shape != (n_c,):
        raise TwinError(f"{name} must have shape ({n_c},), got {a.shape}")
    return np.ascontiguousarray(a * a)


def _sys_out(out: F64 | None, k: int) -> F64:
    """The array σ_b is written to: ``out`` (checked: float64, shape (k,), contiguous) or a
    scratch array.

    Raises:
        TwinError: ``out`` is not a contiguous float64 array of shape (k,).
    """
    if out is None:
        return np.empty(k)
    if out.shape != (k,) or out.dtype != np.float64 or not out.flags.c_contiguous:
        raise TwinError(f"sys_std_out must be a contiguous float64 array of shape ({k},)")
    return out


def windowed_payload(g: F64, r: F64, weights: F64, prefilter_half: int, half_window: int,
                     independent_fraction: F64, noise_std: F64 | None = None,
                     bias_std: F64 | None = None,
                     sys_std_out: F64 | None = None) -> tuple[F64, F64]:
    """Sliding-window weighted least-squares payload (module docstring), in one compiled pass.

    g and r are first averaged over centred windows of ``2·prefilter_half + 1`` instants
    ("filter both sides", see the replay), then the estimate at each instant uses the centred
    window of ``2·half_window + 1`` instants (both windows cut at the ends of the data).

    Args:
        g: Joint-load sensitivity to payload, shape (k, n_c) [N·m/kg or N/kg].
        r: Actuator load minus no-payload inverse dynamics, shape (k, n_c) [N·m or N].
        weights: 1/σ² per joint, shape (n_c,) [1/(N·m)²].
        prefilter_half: Half width of the moving average [instants]; 0 for none.
        half_window: Half window of the fit [instants].
        independent_fraction: The pressure smoothers' variance gain risk/σ² per joint, shape
            (n_c,), in (0, 1]; checked, not used by the σ any more (module docstring).
        noise_std: Raw (unsmoothed) noise of r per joint, shape (n_c,) [N·m or N]; None: 0
            (σ from the residual scatter alone).
        bias_std: Systematic (constant over the window) error of r per joint, shape (n_c,)
            [N·m or N]; None: 0 (σ_b = 0: the σ covers random error only).
        sys_std_out: If given, shape (k,): filled with σ_b [kg], the part of σ_m̂ from
            ``bias_std`` (it does not average out over time; inf where g vanishes).

    Returns:
        (m̂, σ_m̂), each shape (k,) [kg]; NaN estimate and inf σ where g vanishes.
    """
    if g.shape != r.shape or g.ndim != 2:
        raise TwinError(f"g {g.shape} and r {r.shape} must both be (k, n_c)")
    if np.shape(independent_fraction) != (g.shape[1],):
        raise TwinError(f"independent_fraction must have shape ({g.shape[1]},)")
    m = np.empty(g.shape[0])
    std = np.empty(g.shape[0])
    nv = _squares(noise_std, g.shape[1], "noise_std")
    bv = _squares(bias_std, g.shape[1], "bias_std")
    sys = _sys_out(sys_std_out, g.shape[0])
    _windowed_payload(np.ascontiguousarray(g, dtype=np.float64),
                      np.ascontiguousarray(r, dtype=np.float64),
                      np.ascontiguousarray(weights, dtype=np.float64),
                      nv, bv, int(prefilter_half), int(half_window), m, std, sys)
    return m, std


def regression_payload(tau0: F64, tau1: F64, force: F64, arm: F64,
                       joints: npt.NDArray[np.int64], weights: F64, prefilter_half: int,
                       half_window: int, independent_fraction: F64,
                       noise_std: F64 | None = None,
                       bias_std: F64 | None = None,
                       sys_std_out: F64 | None = None) -> tuple[F64, F64]:
    """:func:`windowed_payload` from the inverse dynamics at 0 and 1 kg and the cylinder
    forces, in one compiled pass: g = (tau1 − tau0)/arm and r = (F·arm − tau0)/arm at the
    cylinder joints (per unit of rod force: F·arm is the actuator load F·ds/dq).

    Args:
        tau0, tau1: Inverse-dynamics joint loads with 0 and 1 kg of payload, (k, n_joints).
        force: Cylinder forces (Eq. 1–2), (k, n_c) [N].
        arm: Moment arms ds/dq, (k, n_c) [m/rad or m/m].
        joints: Joint index of each cylinder, (n_c,).
        weights, prefilter_half, half_window, independent_fraction: as :func:`windowed_payload`.
        noise_std: Raw noise of each cylinder's force, (n_c,) [N]; None: 0.
        bias_std: Systematic error of each cylinder's force σ_b,c, (n_c,) [N] (from the stated
            accuracy, :func:`cranetwin.twin.observability.stated_force_sigma`); None: 0.
        sys_std_out: If given, shape (k,): filled with σ_b [kg] (:func:`windowed_payload`).

    Returns:
        (m̂, σ_m̂), each shape (k,) [kg].
    """
    if tau0.shape != tau1.shape or force.shape != arm.shape or tau0.shape[0] != arm.shape[0]:
        raise TwinError(f"shapes do not fit: tau {tau0.shape}, {tau1.shape}, "
                        f"force {force.shape}, arm {arm.shape}")
    m = np.empty(arm.shape[0])
    std = np.empty(arm.shape[0])
    c = np.ascontiguousarray
    nv = _squares(noise_std, arm.shape[1], "noise_std")
    bv = _squares(bias_std, arm.shape[1], "bias_std")
    loads = JointLoads(c(tau0, dtype=np.float64), c(tau1, dtype=np.float64),
                       c(force, dtype=np.float64), c(arm, dtype=np.float64))
    win = PayloadWindow(c(joints, dtype=np.int64), c(weights, dtype=np.float64), nv, bv,
                        int(prefilter_half), int(half_window))
    _regression_payload(loads, win, m, std, _sys_out(sys_std_out, arm.shape[0]))
    return m, std
