"""Savitzky–Golay filters: centre filters, edge operators and their application.

The edges are handled as scipy's ``mode="interp"``: one polynomial fitted to the first/last w
samples, evaluated there. Windows from ``FFT_MIN_WINDOW`` up are applied by FFT
(:func:`savgol_bank` shares one forward FFT among a signal's values and derivatives), shorter
ones by direct correlation; each equals the direct formulation to rounding (≲ 1e-12 relative).
Samples are uniformly spaced; ``delta`` [s] scales derivatives.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache

import numpy as np
import numpy.typing as npt
from scipy import fft as sp_fft
from scipy.ndimage import correlate1d
from scipy.signal import savgol_coeffs

from cranetwin.errors import SignalError

F64 = npt.NDArray[np.float64]


@lru_cache(maxsize=512)
def _sg_operators(window: int, polyorder: int, deriv: int) -> tuple[F64, F64, F64]:
    """(centre filter h (w,), left-edge operator (w//2, w), right-edge operator (w//2, w)) for
    unit sample spacing; the edge operators fit one polynomial to the first/last w samples and
    evaluate it (or its derivative) there, exactly as scipy's ``mode="interp"``."""
    half = window // 2
    h = np.asarray(savgol_coeffs(window, polyorder, deriv=deriv, use="dot"), dtype=np.float64)
    x = (np.arange(window) - half) / max(half, 1)  # scaled to [-1, 1] for conditioning
    vander = np.vander(x, polyorder + 1, increasing=True)  # (w, p+1)
    fit = np.linalg.pinv(vander)  # coefficients from samples, (p+1, w)
    k = np.arange(polyorder + 1)
    fall = np.ones(polyorder + 1)  # k!/(k-deriv)!
    for d in range(deriv):
        fall = fall * np.maximum(k - d, 0)
    powers = np.maximum(k - deriv, 0)

    def at(xs: F64) -> F64:
        basis = fall[None, :] * xs[:, None] ** powers[None, :]
        return np.asarray(basis @ fit / max(half, 1) ** deriv, dtype=np.float64)

    left = at(x[:half])
    right = at(x[window - half :])
    return h, left, right


def sg_filter(window: int, polyorder: int, deriv: int = 0) -> F64:
    """Centre Savitzky–Golay filter h, shape (window,), unit spacing: the smoothed value at an
    interior sample i is ``Σ_j h[j]·y[i − window//2 + j]`` (cached)."""
    if window <= 1:
        return np.ones(1)
    return _sg_operators(window, polyorder, deriv)[0]


def _check_sg(window: int, polyorder: int, deriv: int, n: int) -> None:
    if window <= 1:
        if deriv:
            raise SignalError("a derivative needs a window > 1")
        return
    if window % 2 == 0 or polyorder >= window:
        raise SignalError(f"window must be odd and > polyorder, got {window}, {polyorder}")
    if n < window:
        raise SignalError(f"{n} samples are fewer than the window {window}")


FFT_MIN_WINDOW = 41
"""Windows from this length [samples] up are applied by FFT (:func:`savgol_bank`); shorter
ones by direct correlation (faster for them, measured on 6000-sample blocks)."""


@lru_cache(maxsize=64)
def _fft_len(n: int) -> int:
    return int(sp_fft.next_fast_len(n, real=True))


@lru_cache(maxsize=256)
def _sg_spectrum(window: int, polyorder: int, deriv: int, nfft: int) -> npt.NDArray[np.complex128]:
    """Real FFT of the reversed centre filter zero-padded to ``nfft`` (cached)."""
    h = _sg_operators(window, polyorder, deriv)[0]
    spec: npt.NDArray[np.complex128] = sp_fft.rfft(h[::-1], nfft)
    return spec


def savgol_bank(y: npt.ArrayLike, filters: Sequence[tuple[int, int, int]],
                delta: float = 1.0) -> list[F64]:
    """Several Savitzky–Golay outputs of the same samples in one pass: output ``i`` equals
    ``savgol_smooth(y, *filters[i], delta=delta)`` (to rounding, ~1e-12 relative).

    Filters of window >= :data:`FFT_MIN_WINDOW` share one real FFT of the samples minus their
    column means c (added back as c·Σh, so the FFT's rounding scales with the signal's
    variation, not its offset; Σh is 1 for values, 0 for derivatives, up to the rounding of
    scipy's coefficients, ~3e-9 for long windows); each then costs one inverse FFT
    instead of a ``window``-long correlation per sample. Only the interior samples come from
    the FFT (its length is >= n, so no circular wrap reaches them); the ``window//2`` samples
    at each end are the polynomial fits of ``mode="interp"``, as in :func:`savgol_smooth`.
    Shorter windows use direct correlation.

    Args:
        y: Uniformly spaced samples, shape (n,) or (n, k); filtered along axis 0.
        filters: ``(window, polyorder, deriv)`` per output (odd window, polyorder < window;
            window 1 = a copy, deriv 0 only).
        delta: Sample spacing [s] (scales derivatives by 1/delta**deriv).

    Returns:
        One array per filter, each of the shape of ``y``.

    Raises:
        SignalError: ``y`` is not 1-D or 2-D; a window is even, not above its polyorder, or
            longer than the data.
    """
    ya = np.asarray(y, dtype=np.float64)
    if ya.ndim not in (1, 2):
        raise SignalError(f"Savitzky–Golay smoothing takes shape (n,) or (n, k), got {ya.shape}")
    n = ya.shape[0]
    for w, p, d in filters:
        _check_sg(w, p, d, n)
    outs: list[F64] = []
    spec: npt.NDArray[np.complex128] | None = None
    nfft = 0
    yt = ya.reshape(n, -1).T  # (k, n): the FFTs run along contiguous rows after the centring
    centre = np.zeros((yt.shape[0], 1))
    for w, p, d in filters:
        if w <= 1:
            outs.append(ya.copy())
            continue
        h, left, right = _sg_operators(w, p, d)
        half = w // 2
        out: F64
        if w >= FFT_MIN_WINDOW:
            if spec is None:
                nfft = _fft_len(n)
                centre = yt.mean(axis=1, keepdims=True)
                spec = sp_fft.rfft(yt - centre, nfft, axis=1)
            full = sp_fft.irfft(spec * _sg_spectrum(w, p, d, nfft), nfft, axis=1)
            mid = np.empty(yt.shape)
            np.add(full[:, w - 1 : n], float(h.sum()) * centre, out=mid[:, half : n - half])
            out = mid.T.reshape(ya.shape)
        else:
            out = correlate1d(ya, h, axis=0, mode="nearest")
        o2 = out.reshape(n, -1)
        y2 = ya.reshape(n, -1)
        o2[:half] = left @ y2[:w]
        o2[n - half :] = right @ y2[n - w :]
        if d:
            out /= delta**d
        outs.append(out)
    return outs


def savgol_columns(y: npt.ArrayLike, filters: Sequence[Sequence[tuple[int, int, int]]],
                   delta: float = 1.0,
                   edges: tuple[bool, bool] = (True, True)) -> list[list[F64]]:
    """:func:`savgol_bank` with filters of its own for each column, all columns' FFTs in one
    batched forward and one batched inverse transform: ``out[c][i]`` equals
    ``savgol_bank(y[:, c], filters[c], delta)[i]`` (to rounding).

    Args:
        y: Uniformly spaced samples, shape (n, k).
        filters: Per column, ``(window, polyorder, deriv)`` per output (as :func:`savgol_bank`).
        delta: Sample spacing [s].
        edges: Whether the ``window//2`` samples at the (start, end) are wanted; False leaves
            them NaN (a caller that discards them saves the end fits).

    Returns:
        Per column, one array (n,) per filter.

    Raises:
        SignalError: ``y`` is not 2-D, ``filters`` is not one list per column, or a window is
            even, not above its polyorder, or longer than the data.
    """
    ya = np.asarray(y, dtype=np.float64)
    if ya.ndim != 2 or ya.shape[1] != len(filters):
        raise SignalError(f"savgol_columns needs (n, k) samples and k filter lists, got "
                          f"{ya.shape} and {len(filters)}")
    n = ya.shape[0]
    for col in filters:
        for w, p, d in col:
            _check_sg(w, p, d, n)
    yt = np.ascontiguousarray(ya.T)  # (k, n)
    fft_rows = [(c, f) for c, col in enumerate(filters) for f in col if f[0] >= FFT_MIN_WINDOW]
    full: F64 | None = None
    centre = np.zeros((yt.shape[0], 1))
    nfft = 0
    if fft_rows:
        nfft = _fft_len(n)
        used = sorted({c for c, _ in fft_rows})
        centre = yt.mean(axis=1, keepdims=True)
        spec = sp_fft.rfft(yt[used] - centre[used], nfft, axis=1)
        at = {c: i for i, c in enumerate(used)}
        prod = np.empty((len(fft_rows), spec.shape[1]), dtype=np.complex128)
        for r, (c, (w, p, d)) in enumerate(fft_rows):
            np.multiply(spec[at[c]], _sg_spectrum(w, p, d, nfft), out=prod[r])
        full = sp_fft.irfft(prod, nfft, axis=1)
    outs: list[list[F64]] = []
    r = 0
    for c, col in enumerate(filters):
        yc = yt[c]
        res: list[F64] = []
        for w, p, d in col:
            if w <= 1:
                res.append(yc.copy())
                continue
            h, left, right = _sg_operators(w, p, d)
            half = w // 2
            out = np.empty(n)
            if w >= FFT_MIN_WINDOW:
                assert full is not None
                np.add(full[r, w - 1 : n], float(h.sum()) * centre[c, 0],
                       out=out[half : n - half])
                r += 1
            else:
                out[:] = correlate1d(yc, h, mode="nearest")
            out[:half] = left @ yc[:w] if edges[0] else np.nan
            out[n - half :] = right @ yc[n - w :] if edges[1] else np.nan
            if d:
                out /= delta**d
            res.append(out)
        outs.append(res)
    return outs


def savgol_smooth(y: npt.ArrayLike, window: int, polyorder: int, deriv: int = 0,
                  delta: float = 1.0) -> F64:
    """Savitzky–Golay smoothing (or derivative) along axis 0, edges by one polynomial fit to
    the first/last window (the same result as ``scipy.signal.savgol_filter(mode="interp")``,
    with the filters cached: the twin smooths many short blocks). Long windows go by FFT
    (:func:`savgol_bank`, which also gives several outputs of one signal at once).

    Args:
        y: Uniformly spaced samples, shape (n,) or (n, k).
        window: Odd window length [samples]; 1 returns a copy (deriv must then be 0).
        polyorder: Polynomial order, < window.
        deriv: Derivative order of the fitted polynomial (0 = smoothed values).
        delta: Sample spacing [s] (scales derivatives).
    """
    return savgol_bank(y, ((window, polyorder, deriv),), delta)[0]


@lru_cache(maxsize=64)
def _centred_spectra(filters: tuple[tuple[int, int, int], ...],
                     nfft: int) -> tuple[npt.NDArray[np.complex128], F64]:
    """Real FFTs (len(filters), nfft//2+1) of the centre filters laid out circularly so that
    output i of the circular correlation is ``Σ_j h[j]·y[i − w//2 + j]``, and the filters'
    coefficient sums (cached)."""
    taps = np.zeros((len(filters), nfft))
    sums = np.empty(len(filters))
    for k, (w, p, d) in enumerate(filters):
        h = _sg_operators(w, p, d)[0]
        idx = (np.arange(w) - w // 2) % nfft
        taps[k, idx] = h[::-1]  # correlation = convolution with the reversed filter
        sums[k] = float(h.sum())
    spec: npt.NDArray[np.complex128] = sp_fft.rfft(taps, axis=1)
    return spec, sums


def _cores(y: F64, filters: tuple[tuple[int, int, int], ...], edge: int) -> F64:
    """Outputs ``Σ h[j]·y[i − w//2 + j]`` of several centre filters at samples
    edge … n−edge−1 (needs edge >= every w//2), shape (len(filters), n − 2·edge): one FFT of
    y minus its mean c (added back as c·Σh), one batched inverse FFT."""
    n = y.shape[0]
    nfft = _fft_len(n)
    spec, sums = _centred_spectra(filters, nfft)
    c = float(y.mean())
    full = sp_fft.irfft(sp_fft.rfft(y - c, nfft)[None, :] * spec, nfft, axis=1)
    out: F64 = full[:, edge : n - edge] + sums[:, None] * c
    return out


def centre_weight(window: int, polyorder: int) -> float:
    """h0 of the smoothing filter (= its noise variance gain)."""
    if window <= 1:
        return 1.0
    return float(_sg_operators(window, polyorder, 0)[0][window // 2])
