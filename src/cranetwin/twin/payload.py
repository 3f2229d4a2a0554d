"""Payload mass from the pressures: weighted least squares over a sliding window.

The paper assumes the payload known; the twin measures it. The payload is a point mass m at the
load point, so the inverse-dynamics joint loads are affine in m::

    tau_id(q, qd, qdd; m) = tau_0 + m·g,   g = tau_id(…; 1 kg) − tau_id(…; 0 kg)

and the actuator loads computed from the pressures (Eq. 1–2 through the moment arms) should
equal them. Over a centred window of N instants and the cylinder-driven joints c, with weights
w_c = 1/σ_c² (σ_c: error of that joint's actuator load), the estimate and its standard error are::

    m̂ = Σ w_c·g_c·r_c / Σ w_c·g_c²,      r = tau_act − tau_0
    σ_m̂² = [Σ w_c·(r_c − m̂·g_c)² / (n_eff − 1)] / Σ w_c·g_c²

with n_eff the number of independent errors in the window (samples × joints × the smoothing's
variance reduction), because interpolated and smoothed samples are correlated.
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
    per cylinder joint (n_c,), the prefilter's and the fit's half windows [instants] and the
    independent errors per instant summed over the joints ``frac_sum``."""

    joints: npt.NDArray[np.int64]
    weights: F64
    prefilter_half: int
    half_window: int
    frac_sum: float


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
def _window_estimate(sgg, sgr, srr, n_eff):  # type: ignore[no-untyped-def]
    """Payload [kg] and its standard error from one window's weighted sums Σg², Σg·r, Σr² and
    its effective number of independent samples (NaN and inf when the window has no
    excitation, Σg² = 0)."""
    if not sgg > 0.0:
        return np.nan, np.inf
    m = sgr / sgg
    rss = max(srr - m * sgr, 0.0)
    return m, np.sqrt(rss / max(n_eff - 1.0, 1.0) / sgg)


@njit(cache=True)
def _windowed_payload(g, r, weights, pf, half, frac_sum, m_out, std_out):  # type: ignore[no-untyped-def]
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
    per = np.empty((n, 3))
    for i in range(n):
        a = 0.0
        b = 0.0
        c = 0.0
        for j in range(k):
            wg = gs[i, j] * weights[j]
            a += wg * gs[i, j]
            b += wg * rs[i, j]
            c += rs[i, j] * rs[i, j] * weights[j]
        per[i, 0] = a
        per[i, 1] = b
        per[i, 2] = c
    sums = np.empty((n, 3))
    _moving_sum_cols(per, half, sums)
    for i in range(n):
        cnt = float(min(i + half + 1, n) - max(i - half, 0))
        m_out[i], std_out[i] = _window_estimate(sums[i, 0], sums[i, 1], sums[i, 2],
                                                cnt * frac_sum)


@njit(cache=True)
def _regression_payload(loads, win, m_out, std_out):  # type: ignore[no-untyped-def]
    """g = (t1 − t0)/arm and r = (force·arm − t0)/arm at the cylinder joints (:class:`JointLoads`
    ``loads``, :class:`PayloadWindow` ``win``), then
    :func:`_windowed_payload` (the same operations in the same order, so the same result):
    the running sums of g and r are formed with them, the per-instant window sums with the
    running sums of those, so the data are passed over twice."""
    t0, t1, force, arm = loads
    joints, weights, pf, half, frac_sum = win
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
    cp = np.empty((n + 1, 3))  # running sums of Σ w·g², Σ w·g·r, Σ w·r²
    cp[0, 0] = 0.0
    cp[0, 1] = 0.0
    cp[0, 2] = 0.0
    for i in range(n):
        hi = min(i + pf + 1, n)
        lo = max(i - pf, 0)
        cnt = float(hi - lo)
        sa = 0.0
        sb = 0.0
        sc = 0.0
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
        cp[i + 1, 0] = cp[i, 0] + sa
        cp[i + 1, 1] = cp[i, 1] + sb
        cp[i + 1, 2] = cp[i, 2] + sc
    for i in range(n):
        hi = min(i + half + 1, n)
        lo = max(i - half, 0)
        m_out[i], std_out[i] = _window_estimate(cp[hi, 0] - cp[lo, 0], cp[hi, 1] - cp[lo, 1],
                                                cp[hi, 2] - cp[lo, 2], float(hi - lo) * frac_sum)


def windowed_payload(g: F64, r: F64, weights: F64, prefilter_half: int, half_window: int,
                     independent_fraction: F64) -> tuple[F64, F64]:
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
        independent_fraction: Independent errors per instant per joint, shape (n_c,), in (0, 1].

    Returns:
        (m̂, σ_m̂), each shape (k,) [kg]; NaN estimate and inf σ where g vanishes.
    """
    if g.shape != r.shape or g.ndim != 2:
        raise TwinError(f"g {g.shape} and r {r.shape} must both be (k, n_c)")
    m = np.empty(g.shape[0])
    std = np.empty(g.shape[0])
    _windowed_payload(np.ascontiguousarray(g, dtype=np.float64),
                      np.ascontiguousarray(r, dtype=np.float64),
                      np.ascontiguousarray(weights, dtype=np.float64), int(prefilter_half),
                      int(half_window), float(np.sum(independent_fraction)), m, std)
    return m, std


def regression_payload(tau0: F64, tau1: F64, force: F64, arm: F64,
                       joints: npt.NDArray[np.int64], weights: F64, prefilter_half: int,
                       half_window: int, independent_fraction: F64) -> tuple[F64, F64]:
    """:func:`windowed_payload` from the inverse dynamics at 0 and 1 kg and the cylinder
    forces, in one compiled pass: g = (tau1 − tau0)/arm and r = (F·arm − tau0)/arm at the
    cylinder joints (per unit of rod force: F·arm is the actuator load F·ds/dq).

    Args:
        tau0, tau1: Inverse-dynamics joint loads with 0 and 1 kg of payload, (k, n_joints).
        force: Cylinder forces (Eq. 1–2), (k, n_c) [N].
        arm: Moment arms ds/dq, (k, n_c) [m/rad or m/m].
        joints: Joint index of each cylinder, (n_c,).
        weights, prefilter_half, half_window, independent_fraction: as :func:`windowed_payload`.

    Returns:
        (m̂, σ_m̂), each shape (k,) [kg].
    """
    if tau0.shape != tau1.shape or force.shape != arm.shape or tau0.shape[0] != arm.shape[0]:
        raise TwinError(f"shapes do not fit: tau {tau0.shape}, {tau1.shape}, "
                        f"force {force.shape}, arm {arm.shape}")
    m = np.empty(arm.shape[0])
    std = np.empty(arm.shape[0])
    c = np.ascontiguousarray
    loads = JointLoads(c(tau0, dtype=np.float64), c(tau1, dtype=np.float64),
                       c(force, dtype=np.float64), c(arm, dtype=np.float64))
    win = PayloadWindow(c(joints, dtype=np.int64), c(weights, dtype=np.float64),
                        int(prefilter_half), int(half_window),
                        float(np.sum(independent_fraction)))
    _regression_payload(loads, win, m, std)
    return m, std
