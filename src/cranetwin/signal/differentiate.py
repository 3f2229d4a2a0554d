"""Numerical differentiation of sampled signals by Newton's divided-difference formula.

The paper computes the rod velocity from the received positions "with the Newton formula": the
derivative of Newton's interpolating polynomial through the samples around each point. Here the
stencil is the ``2·half_width + 1`` samples centred on each sample (shifted inwards at the ends),
so irregular timestamps are handled exactly. For uniform spacing and ``half_width = 1`` this is the
central difference (y_{i+1} − y_{i−1}) / 2h, of error O(h²); ``half_width = 2`` gives the O(h⁴)
five-point formula.

With Newton's form P(x) = Σ_k f[x_0..x_k] · ω_k(x), ω_k(x) = Π_{j<k} (x − x_j), the derivative is
P'(x) = Σ_k f[x_0..x_k] · ω_k'(x); both the divided differences and ω_k' are accumulated level by
level, vectorised over all samples.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from cranetwin.errors import SignalError

F64 = npt.NDArray[np.float64]


def newton_derivative(t: npt.ArrayLike, y: npt.ArrayLike, half_width: int = 1) -> F64:
    """First derivative of samples by Newton's divided-difference formula.

    Args:
        t: Sample times, shape (n,), strictly increasing [s].
        y: Samples, shape (n,) or (n, k) [unit]; finite.
        half_width: Samples on each side of the point in the stencil (1: 3-point, 2: 5-point).

    Returns:
        dy/dt at each sample, same shape as y [unit/s].

    Raises:
        SignalError: If t is not strictly increasing, shapes disagree or n < 2·half_width + 1.
    """
    ta = np.asarray(t, dtype=np.float64)
    ya = np.asarray(y, dtype=np.float64)
    scalar = ya.ndim == 1
    y2 = ya.reshape(ya.shape[0], -1)
    n = ta.shape[0]
    width = 2 * half_width + 1
    if half_width < 1:
        raise SignalError(f"half_width must be >= 1, got {half_width}")
    if ta.ndim != 1 or y2.shape[0] != n:
        raise SignalError(f"t shape {ta.shape} and y shape {ya.shape} disagree")
    if n < width:
        raise SignalError(f"need at least {width} samples for half_width {half_width}, got {n}")
    if not np.all(np.diff(ta) > 0):
        raise SignalError("sample times must be strictly increasing")
    i = np.arange(n)
    start = np.clip(i - half_width, 0, n - width)
    nodes = start[:, None] + np.arange(width)[None, :]  # (n, width)
    xs = ta[nodes]  # (n, width)
    x = ta[:, None]  # evaluation point (the sample itself)
    # divided-difference table: level k holds f[x_j .. x_{j+k}] for j = 0 .. width-1-k
    dd = y2[nodes]  # (n, width, k)
    omega = np.ones((n, 1))  # ω_k(x)
    domega = np.zeros((n, 1))  # ω_k'(x)
    deriv = np.zeros((n, y2.shape[1]))
    for level in range(1, width):
        dd = (dd[:, 1:] - dd[:, :-1]) / (xs[:, level:] - xs[:, :-level])[:, :, None]
        # ω_level = ω_{level-1} · (x − x_{level-1})
        diff = x - xs[:, level - 1 : level]
        domega = domega * diff + omega
        omega = omega * diff
        deriv += dd[:, 0] * domega
    return deriv[:, 0] if scalar else deriv
