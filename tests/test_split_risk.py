"""Laws of cranetwin.signal.split_risk: LPA-ICI or one fixed window by the two-fold split risk."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pytest

from cranetwin.model import load_machine
from cranetwin.signal import choose_window, estimate_noise_std, ici_smooth_pair, savgol_smooth
from cranetwin.signal.split_risk import (
    SPLIT_MAX_SAMPLES,
    half_window,
    ici_or_fixed,
    midpoint_predict,
    split_risk,
)
from cranetwin.twin.channels import ChannelMap, choose_smoothing

F64 = npt.NDArray[np.float64]


def _true_errors(y: F64, clean: F64) -> tuple[float, float]:
    """(MSE of LPA-ICI, MSE of the SURE fixed window) against the noise-free signal."""
    sigma = estimate_noise_std(y)
    ch = choose_window(y, sigma=sigma)
    ici = ici_smooth_pair(y, y, 1.0, 0.0, sigma)[:, 0]
    fixed = savgol_smooth(y, ch.window, ch.polyorder) if ch.window > 1 else y
    return float(np.mean((ici - clean) ** 2)), float(np.mean((fixed - clean) ** 2))


def _steps(seed: int) -> tuple[F64, F64]:
    rng = np.random.default_rng(seed)
    t = np.arange(6000) * 0.01
    clean = np.where(t % 8.0 < 4.0, 1.0, -1.0) + 0.3 * np.sin(2 * np.pi * 0.2 * t)
    return clean + rng.uniform(-0.3, 0.3, t.shape[0]), clean


def _slow(seed: int) -> tuple[F64, F64]:
    rng = np.random.default_rng(seed)
    t = np.arange(6000) * 0.01
    clean = np.sin(2 * np.pi * 0.05 * t) + 0.5 * np.sin(2 * np.pi * 0.13 * t + 1.0)
    return clean + rng.normal(0.0, 1.0, t.shape[0]), clean


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_sharp_steps_choose_ici_and_it_is_the_better(seed: int) -> None:
    y, clean = _steps(seed)
    sigma = estimate_noise_std(y)
    ch = choose_window(y, sigma=sigma)
    got = ici_or_fixed(y, sigma, ch.window, ch.polyorder)
    assert got.adaptive
    e_ici, e_fixed = _true_errors(y, clean)
    assert e_ici < e_fixed  # the choice agrees with the truth


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_slow_signal_in_heavy_noise_chooses_the_long_fixed_window(seed: int) -> None:
    y, clean = _slow(seed)
    sigma = estimate_noise_std(y)
    ch = choose_window(y, sigma=sigma)
    assert ch.window >= 101  # SURE takes a long window here
    got = ici_or_fixed(y, sigma, ch.window, ch.polyorder)
    assert not got.adaptive
    e_ici, e_fixed = _true_errors(y, clean)
    assert e_fixed < e_ici


def test_split_risk_is_noise_variance_plus_the_smoothers_error() -> None:
    """E split risk = σ² + the smoother's MSE at the held-out instants: with the noise-free
    half handed back (a perfect smoother) it is σ² up to the interpolation's error, with no
    smoothing at all it is σ² + σ²·Σ interpolation weights² = σ²(1 + 164/256)."""
    rng = np.random.default_rng(5)
    n = 200_000
    t = np.arange(n) * 0.01
    clean = np.sin(2 * np.pi * 0.1 * t)
    noise = rng.normal(0.0, 0.1, n)
    y = clean + noise
    halves: dict[int, F64] = {0: clean[0::2], 1: clean[1::2]}

    def perfect(x: F64) -> F64:
        return halves[0] if np.array_equal(x, y[0::2]) else halves[1]

    assert split_risk(y, perfect) == pytest.approx(0.01, rel=0.02)
    assert split_risk(y, lambda x: x) == pytest.approx(0.01 * (1.0 + 164.0 / 256.0), rel=0.02)


def test_midpoint_prediction_is_exact_for_cubics_and_half_windows_keep_the_span() -> None:
    x = np.arange(12, dtype=np.float64)
    p = 0.3 * x**3 - x**2 + 2.0 * x - 1.0
    mid = x[:-1] + 0.5
    want = 0.3 * mid**3 - mid**2 + 2.0 * mid - 1.0
    np.testing.assert_allclose(midpoint_predict(p)[1:-1], want[1:-1], rtol=0, atol=1e-10)
    lin = 2.0 * x + 1.0
    np.testing.assert_allclose(midpoint_predict(lin), 2.0 * mid + 1.0, rtol=0, atol=1e-12)
    assert [half_window(w, 3) for w in (1, 5, 7, 9, 21, 131, 221)] == [1, 1, 1, 5, 11, 65, 111]
    assert half_window(5, 1) == 3


def test_choice_is_deterministic_on_long_signals() -> None:
    y, _ = _steps(7)
    long = np.tile(y, (2 * SPLIT_MAX_SAMPLES) // y.shape[0] + 1)
    a = ici_or_fixed(long, 0.17, 45, 3)
    b = ici_or_fixed(long.copy(), 0.17, 45, 3)
    assert a == b


def test_choose_smoothing_takes_the_split_choice_per_cylinder() -> None:
    """On the pressures: a cylinder whose force steps keeps LPA-ICI, one whose force is slow
    under heavy noise gets its SURE window (not adaptive); True and False are unchanged."""
    m = load_machine("patu655")
    names = tuple(ch.name for ch in m.channels)
    cmap = ChannelMap.build(m, names)
    n = 6000
    vals = np.zeros((n, len(cmap.names)))
    rng = np.random.default_rng(3)
    t = np.arange(n) * 0.01
    steps, _ = _steps(4)
    slow, _ = _slow(4)
    for c in range(len(m.cylinders)):
        sig = steps if c == 0 else slow
        vals[:, cmap.p_a[c]] = 50e5 + 20e5 * sig  # force: a1·pA − a2·pB
        vals[:, cmap.p_b[c]] = 20e5
        vals[:, cmap.s[c]] = 0.3 + 0.05 * np.sin(0.3 * t) + rng.normal(0.0, 1e-4, n)
    for j in range(len(cmap.names)):
        if j not in (*cmap.p_a, *cmap.p_b, *cmap.s):
            vals[:, j] = 0.1 * np.sin(0.2 * t)
    got = choose_smoothing(m, cmap, vals, adaptive="choose", model="off")
    assert got[cmap.p_a[0]].adaptive and got[cmap.p_b[0]].adaptive
    assert not got[cmap.p_a[1]].adaptive and got[cmap.p_a[1]].window >= 101
    on = choose_smoothing(m, cmap, vals, adaptive=True, model="off")
    off = choose_smoothing(m, cmap, vals, adaptive=False, model="off")
    assert all(on[cmap.p_a[c]].adaptive for c in range(len(m.cylinders)))
    assert not any(off[cmap.p_a[c]].adaptive for c in range(len(m.cylinders)))
