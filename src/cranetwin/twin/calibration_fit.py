"""The least squares of :mod:`cranetwin.twin.calibration`: the design matrix (mass, Coulomb,
viscous and offset columns per cylinder, low-passed on both sides), the noise-corrected Coulomb
regressor ψ(v) and the coordinate search over each cylinder's Coulomb velocity vc.

Shapes: n instants, nc cylinders, S constant-mass segments; forces [N], velocities [m/s],
masses [kg].
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt
from scipy.optimize import minimize_scalar

from cranetwin import physics
from cranetwin.model import Cylinder

F64 = npt.NDArray[np.float64]

# the coarse grid of the vc search [m/s]
VC_GRID = np.geomspace(5e-4, 0.05, 25)
# largest velocity-noise / vc ratio the Coulomb column is corrected for (calibration docstring)
MAX_NOISE_RATIO = 0.5


def lowpass(x: F64, width: int, passes: int) -> F64:
    """``passes`` moving averages of ``width`` along axis 0, 'valid' part only."""
    for _ in range(passes):
        x = moving_average(x, width)
    return x


def moving_average(x: F64, width: int) -> F64:
    """Moving average along axis 0, 'valid' part only: shape (n − width + 1, …)."""
    if width <= 1:
        return x
    c = np.cumsum(np.concatenate([np.zeros((1,) + x.shape[1:]), x]), axis=0)
    out: F64 = (c[width:] - c[:-width]) / width
    return out


def coulomb_column(v: F64, vc: float, sigma_v: float) -> F64:
    """Coulomb regressor of Eq. 2 at a noisy velocity: ψ(v) = tanh(u) + r²·tanh(u)·sech²(u),
    u = v/vc, r = min(σ_v/vc, ``MAX_NOISE_RATIO``), whose average over Gaussian velocity noise
    of standard deviation σ_v is tanh(v_true/vc) to O(r⁴) (module docstring).

    Args:
        v: Measured velocities [m/s].
        vc: Coulomb velocity [m/s].
        sigma_v: Velocity noise standard deviation [m/s]; 0 gives tanh(v/vc).
    """
    t = np.tanh(v / vc)
    r2 = min(sigma_v / vc, MAX_NOISE_RATIO) ** 2
    out: F64 = t + r2 * t * (1.0 - t * t) if r2 > 0.0 else t
    return out


class Layout(NamedTuple):
    """The fit's data layout: per instant its constant-mass segment ``seg`` (n,) (of
    ``n_seg``) and whether it may be used ``ok`` (n,) (no end stop, payload change, dropout);
    parameters [m_0 … m_{S−1}, Fc_0, b_0, off_0, Fc_1, …] (S = n_seg)."""

    seg: npt.NDArray[np.int64]
    n_seg: int
    ok: npt.NDArray[np.bool_]


def design(vc: F64, v: F64, g: F64, width: int, passes: int, sigma_v: F64,
            lay: Layout) -> F64:
    """Columns [m_0 … m_{S−1}, Fc_0, b_0, off_0, Fc_1, …] stacked over cylinders, each
    low-passed by :func:`lowpass`: shape (n'·nc, S + 3nc). The Coulomb columns are
    :func:`coulomb_column` with the velocity noise ``sigma_v`` [m/s] per cylinder."""
    n, nc = v.shape
    ns = lay.n_seg
    m = n - passes * (max(width, 1) - 1)
    a = np.zeros((m * nc, ns + 3 * nc))
    for c in range(nc):
        rows = slice(c * m, (c + 1) * m)
        for k in range(ns):
            a[rows, k] = lowpass(np.where(lay.seg == k, g[:, c], 0.0), width, passes)
        a[rows, ns + 3 * c] = lowpass(coulomb_column(v[:, c], float(vc[c]),
                                                      float(sigma_v[c])), width, passes)
        a[rows, ns + 1 + 3 * c] = lowpass(v[:, c], width, passes)
        a[rows, ns + 2 + 3 * c] = 1.0
    return a


def good_rows(lay: Layout, width: int, passes: int, nc: int) -> npt.NDArray[np.bool_]:
    """Rows of the stacked design whose low-pass window holds only usable instants."""
    good = lowpass(lay.ok.astype(np.float64), width, passes) > 1.0 - 1e-9
    return np.tile(good, nc)


def residual_before(y: F64, v: F64, cyls: list[Cylinder], c: int, width: int, passes: int,
            lay: Layout) -> F64:
    """Low-passed force residual of cylinder ``c`` with the file's friction, no extra mass, at
    the usable rows [N]."""
    r = lowpass(y[:, c] - physics.friction_force(v[:, c], cyls[c].friction), width, passes)
    out: F64 = r[good_rows(lay, width, passes, 1)]
    return out


class Fixed(NamedTuple):
    """Parameters held at the machine file's values: column index → value, and per cylinder
    whether vc is held (at ``vc0``)."""

    cols: dict[int, float]
    vc: npt.NDArray[np.bool_]


def fit_friction(y: F64, g: F64, v: F64, vc0: F64, filt: tuple[int, int], sigma_v: F64,
         lay: Layout, fixed: Fixed) -> tuple[F64, F64, F64, F64]:
    """Least squares for fixed vc inside a coordinate search over each free cylinder's vc
    (coarse logarithmic grid, then a bounded 1-D minimisation; a second sweep refines
    locally), on the usable rows, the ``fixed`` columns moved to the right-hand side.

    Returns:
        (parameters [m_0 …, Fc_0, b_0, off_0, …] with the fixed ones at their values,
        residual at the usable rows stacked over cylinders [N], vc per cylinder [m/s],
        the design's free columns' covariance per unit residual variance (AᵀA)⁻¹ padded
        with NaN for the fixed ones).
    """
    passes, width = filt
    nc = v.shape[1]
    rows = good_rows(lay, width, passes, nc)
    yv = lowpass(y, width, passes).T.reshape(-1)[rows]
    ncol = lay.n_seg + 3 * nc
    free = np.array([k for k in range(ncol) if k not in fixed.cols], dtype=np.int64)
    fix_idx = np.array(sorted(fixed.cols), dtype=np.int64)
    fix_val = np.array([fixed.cols[k] for k in fix_idx.tolist()])

    def solve(vc: F64) -> tuple[F64, F64, F64]:
        a = design(vc, v, g, width, passes, sigma_v, lay)[rows]
        rhs = yv - (a[:, fix_idx] @ fix_val if fix_idx.size else 0.0)
        af = a[:, free]
        ata = af.T @ af
        xf = np.asarray(np.linalg.solve(ata, af.T @ rhs), dtype=np.float64)
        x = np.empty(ncol)
        x[free] = xf
        x[fix_idx] = fix_val
        return x, rhs - af @ xf, ata

    def sse(vc: F64, c: int, log_vc: float) -> float:
        trial = vc.copy()
        trial[c] = np.exp(log_vc)
        _, r, _ = solve(trial)
        return float(np.dot(r, r))

    vc = vc0.copy()
    log_step = float(np.log(VC_GRID[1] / VC_GRID[0]))
    for sweep in range(2):
        for c in range(nc):
            if fixed.vc[c]:
                continue
            if sweep == 0:   # coarse grid, then refine between the neighbours of the best
                vals = [sse(vc, c, float(np.log(x))) for x in VC_GRID]
                centre = float(np.log(VC_GRID[int(np.argmin(vals))]))
            else:
                centre = float(np.log(vc[c]))
            found = minimize_scalar(lambda lv, c=c: sse(vc, c, lv), method="bounded",
                                    bounds=(centre - log_step, centre + log_step),
                                    options={"xatol": 1e-4})
            vc[c] = float(np.exp(found.x))
    x, r, ata = solve(vc)
    inv = np.full((ncol, ncol), np.nan)
    inv[np.ix_(free, free)] = np.linalg.inv(ata)
    return x, r, vc, inv


def log_dist(vc: float) -> float:
    """Distance of vc from the nearer end of ``VC_GRID`` in log units."""
    return float(min(np.log(vc / VC_GRID[0]), np.log(VC_GRID[-1] / vc)))


def vc_rises(y: F64, g: F64, v: F64, vc: F64, filt: tuple[int, int], sigma_v: F64,
              lay: Layout, c: int, trials: tuple[float, ...]) -> list[float]:
    """How much the residual sum of squares [N²] rises when cylinder ``c``'s vc is moved from
    its fit to each of ``trials`` [m/s] (the linear parameters re-solved, every other vc
    held)."""
    hold = Fixed({}, np.ones(v.shape[1], dtype=bool))
    out = []
    base = None
    for val in (float(vc[c]), *trials):
        trial = vc.copy()
        trial[c] = val
        _, r, _, _ = fit_friction(y, g, v, trial, filt, sigma_v, lay, hold)
        sse = float(np.dot(r, r))
        if base is None:
            base = sse
        else:
            out.append(sse - base)
    return out
