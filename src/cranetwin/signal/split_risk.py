"""Two-fold split risk: LPA-ICI or one fixed Savitzky–Golay window, chosen per signal.

Stein's risk of LPA-ICI with the chosen windows' centre weights is optimistic (the window
choice adapts to the noise it is judged on), so it cannot be set against the fixed window's
Stein risk. Here both smoothers are judged on samples they did not see: each runs on the even
samples and predicts the odd ones in between (cubic midpoint interpolation), and the other way
round. With white noise of variance σ² the expected squared prediction error of a smoother S is
σ² + E(g − S)², g the noise-free signal at the held-out instants, so the noise term is the same
for both and the comparison is one of their errors against the signal, adaptivity included
(the held-out noise is independent of every choice made on the other half).

Each half has half the sample rate, so both smoothers run there with windows of half the
length (:func:`half_window`): the same spans in time, as on the full data.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from cranetwin.signal.ici import ICI_GAMMA, ICI_WINDOWS, ici_smooth_pair
from cranetwin.signal.savgol import savgol_smooth

F64 = npt.NDArray[np.float64]

SPLIT_MAX_SAMPLES = 40_000
"""The split risk is evaluated on at most this many samples (evenly spread segments)."""
SPLIT_SEGMENT = 8_000
"""Samples per segment when a signal is longer than ``SPLIT_MAX_SAMPLES``."""


def half_window(window: int, polyorder: int) -> int:
    """The odd window at half the sample rate covering about the same time as ``window``
    [samples]; 1 where that leaves no more than ``polyorder + 1`` samples."""
    if window <= 1:
        return 1
    half = (window // 2) | 1  # odd, window/2 rounded to an odd number
    return half if half > polyorder + 1 else 1


def midpoint_predict(s: F64) -> F64:
    """Values halfway between consecutive samples of ``s`` (m,): cubic interpolation
    (−1, 9, 9, −1)/16 inside, linear between the first two and the last two samples; (m − 1,)."""
    m = s.shape[0]
    out = np.empty(max(m - 1, 0))
    if m < 2:
        return out
    out[:] = 0.5 * (s[:-1] + s[1:])
    if m >= 4:
        out[1:-1] = (9.0 * (s[1:-2] + s[2:-1]) - (s[:-3] + s[3:])) / 16.0
    return out


def split_errors(y: F64, smoother: Callable[[F64], F64]) -> F64:
    """Errors of predicting each half of ``y`` (n,) from the smoothed other half, (about n − 2,)
    [unit of y]: the odd samples predicted halfway between the smoothed even ones, then the
    even samples (except the first) from the smoothed odd ones.

    ``smoother`` maps samples (m,) to smoothed samples (m,) at half the rate."""
    even = np.ascontiguousarray(y[0::2])
    odd = np.ascontiguousarray(y[1::2])
    p_odd = midpoint_predict(smoother(even))  # at 1, 3, …: odd[: len(even) − 1]
    p_even = midpoint_predict(smoother(odd))  # at 2, 4, …: even[1 : len(odd)]
    out: F64 = np.concatenate([odd[: p_odd.shape[0]] - p_odd,
                               even[1 : 1 + p_even.shape[0]] - p_even])
    return out


def split_risk(y: F64, smoother: Callable[[F64], F64]) -> float:
    """Mean squared error of predicting each half of ``y`` (n,) from the smoothed other half
    (:func:`split_errors`). Its expectation is σ² plus the smoother's mean squared error at the
    held-out instants (module docstring) [unit of y squared]; NaN for fewer than 4 samples.
    """
    e = split_errors(y, smoother)
    return float(e @ e / e.shape[0]) if e.shape[0] else float("nan")


def segments(n: int) -> list[slice]:
    """The samples of a signal of n samples the split risk is judged on: all of them, or
    ``SPLIT_MAX_SAMPLES // SPLIT_SEGMENT`` evenly spread segments of ``SPLIT_SEGMENT``."""
    if n <= SPLIT_MAX_SAMPLES:
        return [slice(0, n)]
    count = SPLIT_MAX_SAMPLES // SPLIT_SEGMENT
    starts = np.linspace(0, n - SPLIT_SEGMENT, count).astype(int)
    return [slice(int(s), int(s) + SPLIT_SEGMENT) for s in starts]


def ici_half(sigma: float, windows: tuple[int, ...], polyorder: int,
             gamma: float = ICI_GAMMA) -> Callable[[F64], F64]:
    """LPA-ICI (``windows`` at the full rate, order ``polyorder``, Γ = ``gamma``, noise
    ``sigma``) as it runs on one half of the samples (:func:`half_window`); the identity where
    fewer than two windows fit."""
    ws = tuple(sorted({half_window(w, polyorder) for w in windows}))

    def ici(x: F64) -> F64:
        use = tuple(w for w in ws if w <= x.shape[0])
        if len(use) < 2:
            return x
        out: F64 = ici_smooth_pair(x, x, 1.0, 0.0, sigma, use, polyorder, gamma)[:, 0]
        return out

    return ici


def fixed_half(window: int, polyorder: int) -> Callable[[F64], F64]:
    """The Savitzky–Golay window ``window`` (full rate; 1 = none) as it runs on one half of
    the samples (:func:`half_window`)."""
    wf = half_window(window, polyorder)

    def fixed(x: F64) -> F64:
        if wf <= 1 or x.shape[0] < wf:
            return x
        out: F64 = savgol_smooth(x, wf, polyorder)
        return out

    return fixed


@dataclass(frozen=True)
class SplitChoice:
    """LPA-ICI against one fixed window on one signal.

    Attributes:
        adaptive: True: LPA-ICI predicts the held-out samples no worse than the fixed window.
        risk_ici: Split risk of LPA-ICI [unit²] (σ² included).
        risk_fixed: Split risk of the fixed window [unit²] (σ² included).
    """

    adaptive: bool
    risk_ici: float
    risk_fixed: float


def ici_or_fixed(y: npt.ArrayLike, sigma: float, window: int, polyorder: int,
                 ici_windows: tuple[int, ...] = ICI_WINDOWS, ici_polyorder: int = 3,
                 gamma: float = ICI_GAMMA) -> SplitChoice:
    """LPA-ICI (windows ``ici_windows``, order ``ici_polyorder``) or the fixed Savitzky–Golay
    window (``window``, ``polyorder``; 1 = none), whichever has the lower split risk
    (:func:`split_risk`) on ``y``; ties go to LPA-ICI. Deterministic.

    Args:
        y: Uniformly spaced samples, shape (n,), finite.
        sigma: Noise standard deviation of ``y`` (for LPA-ICI's intervals) [unit of y].
        window, polyorder: The fixed window and its order, at the full rate.
        ici_windows: LPA-ICI's windows at the full rate.
        ici_polyorder: LPA-ICI's order.
        gamma: LPA-ICI's interval half-width [standard deviations].

    Long signals are judged on evenly spread segments of ``SPLIT_SEGMENT`` samples, at most
    ``SPLIT_MAX_SAMPLES`` in all.
    """
    ya = np.asarray(y, dtype=np.float64)
    ici = ici_half(sigma, ici_windows, ici_polyorder, gamma)
    fixed = fixed_half(window, polyorder)
    segs = segments(ya.shape[0])
    r_ici = float(np.mean([split_risk(ya[s], ici) for s in segs]))
    r_fix = float(np.mean([split_risk(ya[s], fixed) for s in segs]))
    return SplitChoice(not r_fix < r_ici, r_ici, r_fix)
