"""Automatic choice of a Savitzky–Golay window from the noise level.

The paper smooths the noisy received data with a Savitzky–Golay filter before interpolating; it
does not say how the window was chosen. Rule used here (documented in docs/ACCURACY.md): σ is
estimated by :func:`cranetwin.signal.noise_level.estimate_noise_std`; for each candidate
(window w, polynomial order p) the smoother is linear with centre weight h₀, so Stein's
unbiased risk estimate (Mallows' C_p) of its mean squared error against the noise-free signal
is ``mean((y − ŷ)²) − σ̂² + 2σ̂²h₀``. The candidate with the least estimated MSE wins; w = 1 (no
smoothing) is always a candidate, so clean data stay untouched. For long recordings the risk
is evaluated on evenly spread segments (≤ ``max_samples``), every candidate of a segment with
one batched inverse FFT. Derivative windows follow Lepski's rule
(:func:`choose_derivative_window`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from cranetwin.errors import SignalError
from cranetwin.signal.noise_level import estimate_noise_std
from cranetwin.signal.savgol import _cores, _sg_operators

F64 = npt.NDArray[np.float64]

DEFAULT_WINDOWS: tuple[int, ...] = (1, 5, 7, 9, 11, 15, 21, 27, 35, 45, 61, 81, 101, 131, 171, 221)
DEFAULT_POLYORDERS: tuple[int, ...] = (1, 3, 5)


@dataclass(frozen=True)
class SmoothingChoice:
    """A Savitzky–Golay window chosen for a signal.

    Attributes:
        window: Window length [samples], odd; 1 means no smoothing.
        polyorder: Polynomial order of the fit.
        sigma: Estimated noise standard deviation [signal unit].
        risk: Estimated mean squared error of the smoothed signal [unit²].
        adaptive: True: the window adapts per sample (:func:`ici_smooth`) up to ``window``.
        model_based: On a cylinder's pressures: its force is estimated from the machine's
            inverse dynamics corrected by the smoothed pressures
            (:mod:`cranetwin.twin.force_model`), not from the smoothed pressures alone.
        step: The quantisation step detected in the channel's samples [signal unit], 0 for
            none (:mod:`cranetwin.signal.quantisation`): the samples are reconstructed through
            their level crossings before they are smoothed, and the channel's error bound is
            at least step/2 (:func:`cranetwin.twin.observability.effective_accuracy`).
        flat: The channel read one value over the whole choice span
            (:func:`cranetwin.signal.quantisation.single_level`): its error is bounded by
            nothing in the data (a cylinder with both pressures flat is flagged not observable,
            :mod:`cranetwin.twin.observability`).
    """

    window: int
    polyorder: int
    sigma: float
    risk: float
    adaptive: bool = False
    model_based: bool = False
    step: float = 0.0
    flat: bool = False


def _segments(n: int, seg: int, max_samples: int) -> list[slice]:
    if n <= max_samples:
        return [slice(0, n)]
    count = max(1, max_samples // seg)
    starts = np.linspace(0, n - seg, count).astype(int)
    return [slice(int(s), int(s) + seg) for s in starts]


def choose_window(
    y: npt.ArrayLike,
    sigma: float | None = None,
    resolution: float = 0.0,
    windows: tuple[int, ...] = DEFAULT_WINDOWS,
    polyorders: tuple[int, ...] = DEFAULT_POLYORDERS,
    max_samples: int = 8_000,
) -> SmoothingChoice:
    """Choose the Savitzky–Golay window minimising Stein's unbiased estimate of the MSE.

    Args:
        y: Uniformly spaced samples of one signal, shape (n,), finite.
        sigma: Noise standard deviation if known; estimated by :func:`estimate_noise_std` if None.
        resolution: Quantisation step of the channel (floor of the noise estimate).
        windows: Candidate odd window lengths [samples].
        polyorders: Candidate polynomial orders.
        max_samples: Evaluate the risk on at most this many samples (evenly spread segments).

    Returns:
        The chosen :class:`SmoothingChoice`.
    """
    ya = np.asarray(y, dtype=np.float64)
    if ya.ndim != 1:
        raise SignalError(f"choose_window takes one signal of shape (n,), got {ya.shape}")
    s = estimate_noise_std(ya, resolution) if sigma is None else float(sigma)
    n = ya.shape[0]
    wmax = max((w for w in windows if w <= n // 2), default=1)
    seg_len = max(8 * wmax, 2000)
    segs = _segments(n, seg_len, max_samples)
    edge = wmax // 2
    cands = tuple((w, p, 0) for w in windows if 1 < w <= wmax for p in polyorders if p < w - 1)
    best = SmoothingChoice(1, 0, s, s * s)  # w = 1: residual 0, h0 = 1 -> risk σ²
    if not cands:
        return best
    sq = np.zeros(len(cands))
    cnt = 0
    for sl in segs:
        seg = ya[sl]
        r = seg[edge : seg.shape[0] - edge][None, :] - _cores(seg, cands, edge)
        sq += np.einsum("ij,ij->i", r, r)
        cnt += r.shape[1]
    for k, (w, p, _) in enumerate(cands):
        h0 = float(_sg_operators(w, p, 0)[0][w // 2])
        risk = float(sq[k]) / cnt - s * s + 2.0 * s * s * h0
        if risk < best.risk:
            best = SmoothingChoice(w, p, s, risk)
    return best


def choose_derivative_window(
    y: npt.ArrayLike,
    sigma: float | None = None,
    resolution: float = 0.0,
    deriv: int = 2,
    polyorder: int = 3,
    windows: tuple[int, ...] = DEFAULT_WINDOWS,
    threshold: float = 2.0,
    max_samples: int = 8_000,
) -> SmoothingChoice:
    """Savitzky–Golay window for estimating a derivative, by Lepski's rule.

    A window good for the values is far too short for a second derivative (noise grows as
    1/w^(2k+1)), and bias cannot be estimated without knowing the derivative, so windows are
    compared with each other: going up from the shortest, window w is accepted while for every
    accepted shorter w' the mean square difference of the two derivative estimates stays within
    ``threshold`` × its pure-noise value σ²·‖h_w − h_w'‖² (h: the filters' coefficients). The
    longest accepted window is returned: the smoothest estimate whose bias is not yet visible
    above the noise.

    Args:
        y: Uniformly spaced samples of one signal, shape (n,).
        sigma: Noise standard deviation (estimated if None).
        resolution: Quantisation step (floor of the noise estimate).
        deriv: Derivative order the window is chosen for (1 or 2).
        polyorder: Polynomial order of the filters.
        windows: Candidate odd windows.
        threshold: Accept while mean square difference <= threshold × noise-only expectation.
        max_samples: Evaluate on at most this many samples (evenly spread segments).

    Returns:
        :class:`SmoothingChoice` (risk = NaN: not estimated for derivatives).
    """
    ya = np.asarray(y, dtype=np.float64)
    s = estimate_noise_std(ya, resolution) if sigma is None else float(sigma)
    n = ya.shape[0]
    cands = [w for w in windows if w > polyorder + 1 and w <= n // 2]
    if not cands:
        return SmoothingChoice(1, 0, s, float("nan"))
    wmax = max(cands)
    segs = _segments(n, max(8 * wmax, 2000), max_samples)
    edge = wmax // 2

    filters = tuple((w, polyorder, deriv) for w in cands)
    allest: F64 = np.concatenate([_cores(ya[sl], filters, edge) for sl in segs], axis=1)

    def est(w: int) -> F64:
        row: F64 = allest[cands.index(w)]
        return row

    def coeffs(w: int) -> F64:
        h = np.zeros(wmax)
        c = _sg_operators(w, polyorder, deriv)[0]
        h[wmax // 2 - w // 2 : wmax // 2 + w // 2 + 1] = c
        return h

    accepted: list[tuple[int, F64, F64]] = []
    for w in cands:
        d = est(w)
        h = coeffs(w)
        ok = all(float(np.mean((d - d2) ** 2)) <= threshold * s * s * float(np.sum((h - h2) ** 2))
                 for _, d2, h2 in accepted)
        if not ok:
            break
        accepted.append((w, d, h))
    return SmoothingChoice(accepted[-1][0], polyorder, s, float("nan"))

