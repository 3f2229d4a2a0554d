"""Uniform time grids, regularisation of irregular / gappy samples, and resampling by spline."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from cranetwin.errors import SignalError
from cranetwin.signal.spline import NaturalCubicSpline

F64 = npt.NDArray[np.float64]
B = npt.NDArray[np.bool_]


def uniform_grid(t0: float, t1: float, hz: float) -> F64:
    """Times t0, t0 + 1/hz, … up to t1 (inclusive within 1e-9 of a step), shape (m,) [s]."""
    if hz <= 0 or not t1 >= t0:
        raise SignalError(f"grid needs hz > 0 and t1 >= t0, got hz={hz}, [{t0}, {t1}]")
    m = int(np.floor((t1 - t0) * hz + 1e-9)) + 1
    return t0 + np.arange(m, dtype=np.float64) / hz


def nominal_period(t: npt.ArrayLike, period_ns: int | None = None) -> float:
    """The sample period [s]: the one the source carried (``period_ns`` [ns], e.g.
    ``SampleArrays.period_ns``) when given, else the median spacing of the strictly increasing
    times t, shape (n,) [s]. The only estimate of a sample period in ``signal`` and ``twin``.

    Raises:
        SignalError: ``period_ns`` is not positive; or, estimating, fewer than 2 times or
            times not strictly increasing.
    """
    if period_ns is not None:
        if period_ns <= 0:
            raise SignalError(f"period_ns must be positive, got {period_ns}")
        return period_ns * 1e-9
    ta = np.asarray(t, dtype=np.float64)
    if ta.shape[0] < 2:
        raise SignalError("need at least 2 samples to find the sample period")
    dt = np.diff(ta)
    if not np.all(dt > 0):
        raise SignalError("sample times must be strictly increasing")
    return float(np.median(dt))


@dataclass(frozen=True)
class Regular:
    """Samples on a uniform time grid.

    Attributes:
        t: Uniform times, shape (n,) [s].
        values: Shape (n, k); filled by spline where the input had NaN or no sample.
        gap: Shape (n, k), True strictly inside a run between consecutive valid samples of
            that channel longer than ``max_gap_s`` (values there are bridged across a dropout).
    """

    t: F64
    values: F64
    gap: B


def regularize(t: npt.ArrayLike, values: npt.ArrayLike, period: float | None = None,
               max_gap_s: float | None = None, origin: float | None = None) -> Regular:
    """Put irregular samples with dropouts (NaN) onto a uniform grid, per channel by spline.

    Args:
        t: Sample times, shape (n,), strictly increasing [s].
        values: Shape (n, k) [channel units]; NaN = missing.
        period: Grid spacing [s]; the median spacing if None.
        max_gap_s: Gaps longer than this are flagged (default 5 periods).
        origin: The grid is ``origin + k·period`` (k integer) so that pieces of one stream land on
            one grid; t_0 if None.

    Returns:
        :class:`Regular` on the grid points within [t_0, t_{n-1}]. Fast path: input already
        uniform on that grid and without NaN -> returned unchanged.

    Raises:
        SignalError: A channel with fewer than 2 valid samples, or non-increasing times.
    """
    ta = np.asarray(t, dtype=np.float64)
    va = np.asarray(values, dtype=np.float64)
    if va.ndim != 2 or va.shape[0] != ta.shape[0]:
        raise SignalError(f"values shape {va.shape} does not match times shape {ta.shape}")
    p = nominal_period(ta) if period is None else float(period)
    gap_limit = 5.0 * p if max_gap_s is None else float(max_gap_s)
    dt = np.diff(ta)
    finite = np.isfinite(va)
    o = float(ta[0]) if origin is None else float(origin)
    aligned = abs((ta[0] - o) / p - round((ta[0] - o) / p)) <= 1e-6
    if aligned and np.all(np.abs(dt - p) <= 1e-6 * p) and finite.all():
        return Regular(ta, va, np.zeros(va.shape, dtype=bool))
    k0 = int(np.ceil((ta[0] - o) / p - 1e-9))
    k1 = int(np.floor((ta[-1] - o) / p + 1e-9))
    if k1 < k0:
        raise SignalError("no grid point falls within the sample times")
    grid = o + np.arange(k0, k1 + 1, dtype=np.float64) * p
    out = np.empty((grid.shape[0], va.shape[1]))
    gap = np.zeros(out.shape, dtype=bool)
    # channels valid at the same samples share their knots: one spline for all of them (the
    # spline's arithmetic is per column, so each column is what a spline of its own gives);
    # a dropout of one channel then costs one more spline, not one per channel
    groups: dict[bytes, list[int]] = {}
    for j in range(va.shape[1]):
        groups.setdefault(finite[:, j].tobytes(), []).append(j)
    for cols in groups.values():  # in order of each group's first channel
        ok = finite[:, cols[0]]
        if ok.sum() < 2:
            raise SignalError(f"channel {cols[0]} has fewer than 2 valid samples")
        tj = ta[ok]
        out[:, cols] = NaturalCubicSpline(tj, va[ok][:, cols])(grid)
        pos = np.clip(np.searchsorted(tj, grid), 1, tj.shape[0] - 1)
        lo, hi = tj[pos - 1], tj[pos]
        gap[:, cols] = ((hi - lo > gap_limit) & (grid > lo) & (grid < hi))[:, None]
    return Regular(grid, out, gap)
