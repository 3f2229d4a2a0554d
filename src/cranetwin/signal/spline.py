"""Natural cubic spline interpolation, vectorised over channels (the paper's interpolation step).

The paper interpolates the 100 Hz position and pressure samples with natural splines to restore
the values at each model time step. This is an own implementation so that it runs on shared knots
for many channels at once and evaluates value, first and second derivative in one pass; it is
tested against ``scipy.interpolate.CubicSpline(bc_type="natural")``.

On knot interval i (x_i <= t < x_{i+1}) with dx = t - x_i the spline is
``y_i + b_i dx + c_i dx² + d_i dx³`` where the knot second derivatives M solve the tridiagonal
system ``h_{i-1} M_{i-1} + 2 (h_{i-1} + h_i) M_i + h_i M_{i+1} = 6 (δ_i − δ_{i-1})`` with
δ_i = (y_{i+1} − y_i)/h_i and the natural end conditions M_0 = M_{n-1} = 0.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from numba import njit

from cranetwin.errors import SignalError

F64 = npt.NDArray[np.float64]

_UNIFORM_RTOL = 1e-9


@njit(cache=True)
def _natural_coefficients(x, y, coef):  # type: ignore[no-untyped-def]
    """Knot second derivatives M by the Thomas algorithm on the (diagonally dominant)
    tridiagonal system of the module docstring, natural ends M_0 = M_{n-1} = 0; then the
    pieces coef[i] = (y_i, b_i, c_i, d_i) per channel, shape (n−1, 4, k). Two passes: the
    forward sweep (slopes δ formed on the fly), then the back substitution writing each
    piece as soon as its two end values of M are final. Divisions only per knot (1/h_i,
    1/diag_i), multiplications per channel. Returns False if a value is not finite (coef is
    then undefined)."""
    n = x.shape[0]
    k = y.shape[1]
    if n < 2:  # no piece
        for i in range(n):
            for j in range(k):
                if not abs(y[i, j]) < np.inf:
                    return False
        return True
    ih = np.empty(n - 1)  # 1 / h_i
    for i in range(n - 1):
        ih[i] = 1.0 / (x[i + 1] - x[i])
    m = np.empty((n, k))
    cp = np.zeros(n)  # modified super-diagonal
    prev = np.empty(k)  # δ_{i−1}
    for j in range(k):
        m[0, j] = 0.0
        m[n - 1, j] = 0.0
        prev[j] = (y[1, j] - y[0, j]) * ih[0]
        if not abs(prev[j]) < np.inf:  # a value not finite (NaN or ±inf)
            return False
    for i in range(1, n - 1):
        h0 = x[i] - x[i - 1]
        h1 = x[i + 1] - x[i]
        diag = 2.0 * (h0 + h1)
        if i > 1:
            diag -= h0 * cp[i - 1]
        idiag = 1.0 / diag
        cp[i] = h1 * idiag
        ok = True
        for j in range(k):
            d = (y[i + 1, j] - y[i, j]) * ih[i]
            ok &= abs(d) < np.inf
            if i > 1:
                m[i, j] = (6.0 * (d - prev[j]) - h0 * m[i - 1, j]) * idiag
            else:
                m[i, j] = 6.0 * (d - prev[j]) * idiag
            prev[j] = d
        if not ok:
            return False
    for i in range(n - 2, -1, -1):  # back substitution (m[n−2] is final), then piece i
        if 0 < i < n - 2:
            for j in range(k):
                m[i, j] -= cp[i] * m[i + 1, j]
        h = x[i + 1] - x[i]
        h6 = h / 6.0
        ih6 = ih[i] / 6.0
        for j in range(k):
            d = (y[i + 1, j] - y[i, j]) * ih[i]
            coef[i, 0, j] = y[i, j]
            coef[i, 1, j] = d - h6 * (2.0 * m[i, j] + m[i + 1, j])
            coef[i, 2, j] = 0.5 * m[i, j]
            coef[i, 3, j] = (m[i + 1, j] - m[i, j]) * ih6
    return True


@njit(cache=True)
def _subdivide(c, h, h0, uniform, r, v0, v1, v2):  # type: ignore[no-untyped-def]
    """Spline pieces c (n_int, 4, k) at x_i + j·h_i/r, j = 0 … r−1, into rows i·r + j of v0
    (values) and, when they have rows, v1 (first) and v2 (second derivative)."""
    n_int = c.shape[0]
    k = c.shape[2]
    d1 = v1.shape[0] > 0
    d2 = v2.shape[0] > 0
    for i in range(n_int):
        for j in range(r):
            dx = h0 * j / r if uniform else h[i] * (j / r)
            row = i * r + j
            for m in range(k):
                a0 = c[i, 0, m]
                b = c[i, 1, m]
                c2 = c[i, 2, m]
                d = c[i, 3, m]
                v0[row, m] = a0 + dx * (b + dx * (c2 + dx * d))
                if d1:
                    v1[row, m] = b + dx * (2.0 * c2 + 3.0 * d * dx)
                if d2:
                    v2[row, m] = 2.0 * c2 + 6.0 * d * dx


def natural_pieces(x: F64, y: F64) -> F64:
    """The pieces (n−1, 4, k) of the natural spline through knots x (n,) strictly increasing
    and values y (n, k), as :meth:`NaturalCubicSpline.pieces`, for callers whose knots are
    known good (the replay's regular grid): only the values are checked.

    Raises:
        SignalError: non-finite values.
    """
    coef = np.empty((x.shape[0] - 1, 4, y.shape[1]))
    if not _natural_coefficients(np.ascontiguousarray(x), np.ascontiguousarray(y), coef):
        raise SignalError("spline knots and values must be finite (drop NaN samples first)")
    return coef


def knot_pieces(x: F64, y: F64, splined: list[int]) -> F64:
    """Pieces (n, 4, k) that give the natural spline through knots x (n,) and values y (n, k)
    AT THE KNOTS ONLY, for a grid that is the knots themselves (one grid row per sample).

    Columns ``splined`` are read with their derivatives: they get the natural spline's pieces
    (:func:`natural_pieces`), plus an n-th piece at the end knot (the last piece re-centred
    there: value, slope, curvature of the spline at x_{n-1}). Every other column is read at
    the knots only: piece i is (y_i, 0, 0, 0). Evaluated at dx = 0 on piece i, both give the
    spline's value (and derivatives) at knot i, as :func:`natural_pieces` does, without
    solving for columns whose derivatives no one reads.

    Raises:
        SignalError: non-finite values.
    """
    n, k = y.shape
    if not np.isfinite(y).all():
        raise SignalError("spline knots and values must be finite (drop NaN samples first)")
    coef = np.zeros((n, 4, k))
    coef[:, 0, :] = y
    if splined and n >= 2:
        sp = natural_pieces(x, y[:, splined])
        h = float(x[-1] - x[-2])
        b, c, d = sp[-1, 1], sp[-1, 2], sp[-1, 3]
        coef[: n - 1, 1:, splined] = sp[:, 1:]
        coef[n - 1, 1, splined] = b + h * (2.0 * c + 3.0 * d * h)
        coef[n - 1, 2, splined] = c + 3.0 * d * h
        coef[n - 1, 3, splined] = d
    return coef


class NaturalCubicSpline:
    """Natural cubic spline through knots (x, y), y of one or many channels.

    Args:
        x: Knot abscissae, shape (n,), strictly increasing, n >= 2 [e.g. s].
        y: Knot values, shape (n,) or (n, k) [channel units]; must be finite.

    Raises:
        SignalError: Fewer than two knots, non-increasing x, shape mismatch or non-finite values.

    Outside [x_0, x_{n-1}] the end intervals' cubics are continued (as scipy does).
    """

    def __init__(self, x: npt.ArrayLike, y: npt.ArrayLike) -> None:
        xa = np.ascontiguousarray(x, dtype=np.float64)
        ya = np.asarray(y, dtype=np.float64)
        if xa.ndim != 1 or xa.shape[0] < 2:
            raise SignalError(f"spline needs a 1-D array of at least 2 knots, got shape {xa.shape}")
        self._scalar = ya.ndim == 1
        y2 = ya.reshape(ya.shape[0], -1) if ya.ndim in (1, 2) else None
        if y2 is None or y2.shape[0] != xa.shape[0]:
            raise SignalError(
                f"spline values must have shape (n,) or (n, k) with n = {xa.shape[0]} knots, "
                f"got {ya.shape}")
        h = np.diff(xa)
        if not np.all(h > 0):
            raise SignalError("spline knots must be strictly increasing")
        if not (np.all(np.isfinite(xa)) and np.all(np.isfinite(y2))):
            raise SignalError("spline knots and values must be finite (drop NaN samples first)")
        n, k = y2.shape
        coef = np.empty((n - 1, 4, k))
        _natural_coefficients(xa, np.ascontiguousarray(y2), coef)
        self.x: F64 = xa
        self.k = k
        self._coef = coef.reshape(n - 1, 4 * k)
        self._h0 = float(h[0])
        self._uniform = bool(np.all(np.abs(h - h[0]) <= _UNIFORM_RTOL * h[0] * n))

    @property
    def second_derivative_at_knots(self) -> F64:
        """Knot second derivatives M, shape (n,) or (n, k)."""
        c = self._coef.reshape(-1, 4, self.k)
        last = 2.0 * c[-1, 2] + 6.0 * c[-1, 3] * (self.x[-1] - self.x[-2])
        m = np.vstack([2.0 * c[:, 2], last[None, :]])
        return m[:, 0] if self._scalar else m

    def _interval(self, t: F64) -> npt.NDArray[np.intp]:
        n = self.x.shape[0]
        if self._uniform:
            idx = np.floor((t - self.x[0]) / self._h0).astype(np.intp)
        else:
            idx = np.searchsorted(self.x, t, side="right") - 1
        out: npt.NDArray[np.intp] = np.clip(idx, 0, n - 2)
        return out

    def evaluate(self, t: npt.ArrayLike, derivatives: int = 0) -> list[F64]:
        """Value and derivatives at t.

        Args:
            t: Evaluation points, shape (m,).
            derivatives: Highest derivative order wanted (0, 1 or 2).

        Returns:
            ``derivatives + 1`` arrays [value, d/dt, d²/dt²], each of shape (m,) for a scalar
            spline or (m, k).
        """
        if derivatives not in (0, 1, 2):
            raise SignalError(f"derivatives must be 0, 1 or 2, got {derivatives}")
        ta = np.asarray(t, dtype=np.float64).reshape(-1)
        idx = self._interval(ta)
        c = np.take(self._coef, idx, axis=0).reshape(ta.shape[0], 4, self.k)
        dx = (ta - self.x[idx])[:, None]
        a0, b, c2, d = c[:, 0], c[:, 1], c[:, 2], c[:, 3]
        out = [a0 + dx * (b + dx * (c2 + dx * d))]
        if derivatives >= 1:
            out.append(b + dx * (2.0 * c2 + 3.0 * d * dx))
        if derivatives >= 2:
            out.append(2.0 * c2 + 6.0 * d * dx)
        if self._scalar:
            return [o[:, 0] for o in out]
        return out

    def pieces(self) -> F64:
        """The cubic pieces, shape (n−1, 4, k): on interval i the spline is
        ``c[i, 0] + c[i, 1]·dx + c[i, 2]·dx² + c[i, 3]·dx³`` per channel (module docstring)."""
        out: F64 = self._coef.reshape(-1, 4, self.k)
        return out

    def evaluate_subdivided(self, r: int, derivatives: int = 0) -> list[F64]:
        """Value and derivatives at every knot interval split into ``r`` equal steps.

        The points are x_i + j·h_i/r for each interval i and j = 0 … r−1, then the last knot:
        (n−1)·r + 1 points in increasing order. For a sample-rate-to-grid ratio r this is the whole
        output grid, evaluated as one matrix product per derivative (no per-point search or
        gather), which is what makes 1 kHz replay of 100 Hz data cheap.

        Args:
            r: Steps per knot interval, >= 1.
            derivatives: Highest derivative order (0, 1 or 2).

        Returns:
            ``derivatives + 1`` arrays, each of shape ((n−1)·r + 1,) or ((n−1)·r + 1, k).
        """
        if r < 1 or derivatives not in (0, 1, 2):
            raise SignalError(f"need r >= 1 and derivatives in 0..2, got {r}, {derivatives}")
        n_int = self.x.shape[0] - 1
        k = self.k
        h = np.diff(self.x)[:, None]
        c = self._coef.reshape(n_int, 4, k)
        last = self.evaluate(self.x[-1:], derivatives)
        full = [np.empty((n_int * r + 1, k)) for _ in range(derivatives + 1)]
        for nu in range(derivatives + 1):
            full[nu][-1] = np.asarray(last[nu]).reshape(k)
        empty = np.empty((0, k))
        _subdivide(c, np.ascontiguousarray(h[:, 0]), self._h0, self._uniform, r, full[0],
                   full[1] if derivatives >= 1 else empty, full[2] if derivatives >= 2 else empty)
        return [f[:, 0] if self._scalar else f for f in full]

    def __call__(self, t: npt.ArrayLike, nu: int = 0) -> F64:
        """The ``nu``-th derivative (0, 1 or 2) at t; shape (m,) or (m, k)."""
        return self.evaluate(t, nu)[nu]
