"""Laws of cranetwin.signal: spline, Newton differentiation, smoothing, noise, NRMSE, resampling."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import CubicSpline

from cranetwin.errors import SignalError
from cranetwin.model import load_machine
from cranetwin.samples import SampleArrays
from cranetwin.signal import (
    NaturalCubicSpline,
    choose_window,
    estimate_noise_std,
    ici_smooth,
    inject_uniform_noise,
    newton_derivative,
    nrmse,
    regularize,
    savgol_bank,
    savgol_smooth,
    uniform_grid,
)


def _irregular_knots(n: int, rng: np.random.Generator) -> np.ndarray:
    return np.cumsum(rng.uniform(0.005, 0.015, n))


def test_spline_reproduces_knots_and_has_natural_ends() -> None:
    rng = np.random.default_rng(1)
    x = _irregular_knots(40, rng)
    y = rng.normal(size=(40, 3))
    sp = NaturalCubicSpline(x, y)
    np.testing.assert_allclose(sp(x), y, atol=1e-12)
    d2 = sp(x[[0, -1]], 2)
    np.testing.assert_allclose(d2, 0.0, atol=1e-8 * np.abs(sp(x, 2)).max())
    m = sp.second_derivative_at_knots
    assert m.shape == (40, 3)
    np.testing.assert_allclose(m[[0, -1]], 0.0, atol=1e-9)


@pytest.mark.parametrize("uniform", [True, False])
def test_spline_matches_scipy_natural_cubic_spline(uniform: bool) -> None:
    rng = np.random.default_rng(2)
    x = np.linspace(0.0, 2.0, 201) if uniform else _irregular_knots(201, rng)
    y = np.column_stack([np.sin(7 * x), rng.normal(size=x.shape[0])])
    ref = CubicSpline(x, y, bc_type="natural")
    t = np.linspace(x[0] - 0.01, x[-1] + 0.01, 5003)
    sp = NaturalCubicSpline(x, y)
    val, d1, d2 = sp.evaluate(t, 2)
    np.testing.assert_allclose(val, ref(t), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(d1, ref(t, 1), rtol=1e-8, atol=1e-7)
    np.testing.assert_allclose(d2, ref(t, 2), rtol=1e-7, atol=1e-5)


def test_natural_pieces_equal_the_direct_tridiagonal_solution() -> None:
    """The compiled pieces (reciprocals per knot, multiplications per channel) against the
    textbook form: M from a dense solve of the tridiagonal system, then b, c, d by division;
    many channels of different scales, non-finite values rejected."""
    from cranetwin.signal import natural_pieces

    rng = np.random.default_rng(21)
    x = _irregular_knots(300, rng)
    y = np.column_stack([np.sin(5 * x), 8e6 + 1e5 * rng.normal(size=300).cumsum(),
                         1e-3 * rng.normal(size=300)])
    coef = natural_pieces(x, y)
    n = x.shape[0]
    h = np.diff(x)
    a = np.zeros((n, n))
    rhs = np.zeros((n, y.shape[1]))
    a[0, 0] = a[-1, -1] = 1.0
    for i in range(1, n - 1):
        a[i, i - 1 : i + 2] = [h[i - 1], 2.0 * (h[i - 1] + h[i]), h[i]]
        rhs[i] = 6.0 * ((y[i + 1] - y[i]) / h[i] - (y[i] - y[i - 1]) / h[i - 1])
    m = np.linalg.solve(a, rhs)
    hh = h[:, None]
    want = np.stack([y[:-1], (y[1:] - y[:-1]) / hh - hh * (2.0 * m[:-1] + m[1:]) / 6.0,
                     m[:-1] / 2.0, (m[1:] - m[:-1]) / (6.0 * hh)], axis=1)
    scale = np.abs(want).max(axis=0)
    assert np.all(np.abs(coef - want) <= 1e-12 * scale)
    for bad in (np.nan, np.inf, -np.inf):
        yb = y.copy()
        yb[150, 1] = bad
        with pytest.raises(SignalError):
            natural_pieces(x, yb)


def test_spline_continuity_of_derivatives_at_knots() -> None:
    rng = np.random.default_rng(3)
    x = _irregular_knots(30, rng)
    sp = NaturalCubicSpline(x, rng.normal(size=30))
    eps = 1e-9
    inner = x[1:-1]
    for nu in (0, 1, 2):
        scale = np.abs(sp(x, nu)).max()
        np.testing.assert_allclose(sp(inner - eps, nu), sp(inner + eps, nu), atol=1e-5 * scale)


def test_spline_two_knots_is_linear_and_bad_input_raises() -> None:
    sp = NaturalCubicSpline([0.0, 2.0], [1.0, 5.0])
    np.testing.assert_allclose(sp([0.5, 1.0]), [2.0, 3.0])
    np.testing.assert_allclose(sp([0.5], 1), [2.0])
    with pytest.raises(SignalError):
        NaturalCubicSpline([0.0], [1.0])
    with pytest.raises(SignalError):
        NaturalCubicSpline([0.0, 1.0, 1.0], [1.0, 2.0, 3.0])
    with pytest.raises(SignalError):
        NaturalCubicSpline([0.0, 1.0, 2.0], [1.0, np.nan, 3.0])


def test_spline_interpolation_error_is_fourth_order() -> None:
    errs = []
    for n in (51, 101, 201):
        x = np.linspace(0.0, 1.0, n)
        sp = NaturalCubicSpline(x, np.sin(2 * np.pi * x))
        t = np.linspace(0.2, 0.8, 999)  # away from the natural ends (O(h²) there)
        errs.append(np.abs(sp(t) - np.sin(2 * np.pi * t)).max())
    rates = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert np.all(rates > 3.5)


@pytest.mark.parametrize("half_width,order", [(1, 2), (2, 4)])
def test_newton_derivative_exact_on_polynomials_and_converges(half_width: int, order: int) -> None:
    rng = np.random.default_rng(4)
    t = _irregular_knots(60, rng)
    coeffs = rng.normal(size=order + 1)
    poly = np.polynomial.Polynomial(coeffs)
    np.testing.assert_allclose(newton_derivative(t, poly(t), half_width), poly.deriv()(t),
                               rtol=1e-7, atol=1e-6)
    errs = []
    for h in (0.02, 0.01):
        tt = np.arange(0.0, 1.0, h)
        d = newton_derivative(tt, np.sin(3 * tt), half_width)
        errs.append(np.abs(d - 3 * np.cos(3 * tt))[half_width:-half_width].max())
    assert np.log2(errs[0] / errs[1]) > order - 0.3


def test_newton_derivative_uniform_three_point_is_central_difference() -> None:
    t = np.arange(10) * 0.01
    y = np.random.default_rng(5).normal(size=(10, 2))
    d = newton_derivative(t, y, 1)
    np.testing.assert_allclose(d[1:-1], (y[2:] - y[:-2]) / 0.02, rtol=1e-10)


def test_noise_estimate_recovers_sigma_of_uniform_noise_on_oscillating_signal() -> None:
    rng = np.random.default_rng(6)
    t = np.arange(20000) * 0.01
    clean = 5.0 * np.sin(2 * np.pi * 3.6 * t) + 3.0 * np.sin(2 * np.pi * 0.2 * t)
    a = 0.3
    sig = estimate_noise_std(clean + rng.uniform(-a, a, t.shape[0]))
    assert sig == pytest.approx(a / np.sqrt(3.0), rel=0.03)
    gauss = estimate_noise_std(clean + rng.normal(0.0, 0.2, t.shape[0]))
    assert gauss == pytest.approx(0.2, rel=0.03)
    assert estimate_noise_std(clean * 0.0, resolution=0.01) == pytest.approx(0.01 / np.sqrt(12))


def test_auto_window_reduces_mse_and_leaves_clean_signal_alone() -> None:
    rng = np.random.default_rng(7)
    t = np.arange(6000) * 0.01
    clean = np.sin(2 * np.pi * 0.3 * t) + 0.3 * np.sin(2 * np.pi * 1.3 * t)
    noisy = clean + rng.uniform(-0.3, 0.3, t.shape[0])
    choice = choose_window(noisy)
    assert choice.window > 1
    smooth = savgol_smooth(noisy, choice.window, choice.polyorder)
    mse_in = np.mean((noisy - clean) ** 2)
    mse_out = np.mean((smooth - clean) ** 2)
    assert mse_out < 0.15 * mse_in
    # the estimated risk is close to the achieved MSE, and no window does much better
    assert choice.risk == pytest.approx(mse_out, rel=0.5)
    best = min(np.mean((savgol_smooth(noisy, w, p) - clean) ** 2)
               for w in (15, 21, 27, 35, 45, 61, 81, 101) for p in (1, 3, 5) if p < w - 1)
    assert mse_out < 1.5 * best
    # clean data: whatever is chosen leaves the signal as it was (w = 1 or a bias-free window)
    c = choose_window(clean, resolution=1e-9)
    assert np.abs(savgol_smooth(clean, c.window, c.polyorder) - clean).max() < 1e-5


def test_noise_injection_is_uniform_scaled_by_channel_range_and_seeded() -> None:
    m = load_machine("patu655")
    n = 20000
    ch = ("lift_pA", "lift_s", "slew_angle")
    vals = np.zeros((n, 3))
    vals[5, 0] = np.nan
    s = SampleArrays("m", np.arange(n) * 0.01, ch, vals)
    a = inject_uniform_noise(s, m, 0.05, seed=11)
    b = inject_uniform_noise(s, m, 0.05, seed=11)
    np.testing.assert_array_equal(a.values, b.values)
    assert np.isnan(a.values[5, 0])
    for j, name in enumerate(ch[:2]):
        full = m.channel(name).full_range
        col = a.values[:, j][np.isfinite(a.values[:, j])]
        assert np.abs(col).max() <= 0.05 * full
        assert np.abs(col).max() > 0.049 * full
        assert np.std(col) == pytest.approx(0.05 * full / np.sqrt(3), rel=0.03)
    np.testing.assert_array_equal(a.values[:, 2], 0.0)  # angle is not a noisy quantity


def test_nrmse_definition() -> None:
    truth = np.array([0.0, 1.0, 2.0, 3.0, 4.0])
    est = truth + np.array([0.4, -0.4, 0.4, -0.4, 0.4])
    assert float(nrmse(est, truth)) == pytest.approx(0.1)
    with pytest.raises(SignalError):
        nrmse(np.ones(3), np.ones(3))


def test_regularize_fills_dropouts_and_irregular_times() -> None:
    rng = np.random.default_rng(8)
    t = np.arange(500) * 0.01 + rng.uniform(-0.002, 0.002, 500)
    f = np.sin(2 * np.pi * 0.7 * t)
    vals = np.column_stack([f, 2 * f])
    vals[100:130, 0] = np.nan
    vals[300, 1] = np.nan
    reg = regularize(t, vals, period=0.01)
    np.testing.assert_allclose(np.diff(reg.t), 0.01, rtol=1e-9)
    truth = np.sin(2 * np.pi * 0.7 * reg.t)
    np.testing.assert_allclose(reg.values[:, 0], truth, atol=2e-2)  # bridged a 0.3 s dropout
    np.testing.assert_allclose(reg.values[:90, 0], truth[:90], atol=1e-3)
    np.testing.assert_allclose(reg.values[:, 1], 2 * truth, atol=1e-4)
    gap_t = reg.t[reg.gap[:, 0]]
    assert gap_t.min() > t[99] and gap_t.max() < t[130]
    assert not reg.gap[:, 1].any()
    g = uniform_grid(1.0, 2.0, 1000)
    assert g.shape == (1001,) and g[-1] == pytest.approx(2.0)


@pytest.mark.parametrize("uniform", [True, False])
def test_spline_subdivided_evaluation_equals_pointwise(uniform: bool) -> None:
    rng = np.random.default_rng(9)
    x = np.arange(25) * 0.01 if uniform else _irregular_knots(25, rng)
    sp = NaturalCubicSpline(x, rng.normal(size=(25, 2)))
    r = 10
    pts = np.concatenate([(x[:-1, None] + np.diff(x)[:, None] * np.arange(r) / r).ravel(),
                          x[-1:]])
    fast = sp.evaluate_subdivided(r, 2)
    slow = sp.evaluate(pts, 2)
    for a, b in zip(fast, slow, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-8 * np.abs(b).max())


def test_ici_smoothing_beats_best_fixed_window_on_steps() -> None:
    rng = np.random.default_rng(10)
    t = np.arange(4000) * 0.01
    clean = np.where(t % 8.0 < 4.0, 1.0, -1.0) + 0.3 * np.sin(2 * np.pi * 0.2 * t)
    y = clean + rng.uniform(-0.3, 0.3, t.shape[0])
    sigma = estimate_noise_std(y)
    adaptive = ici_smooth(y, sigma)
    best_fixed = min(np.mean((savgol_smooth(y, w, 3) - clean) ** 2)
                     for w in (5, 7, 9, 11, 15, 21, 27, 35, 45, 61, 81, 101, 131))
    assert np.mean((adaptive - clean) ** 2) < 0.8 * best_fixed
    assert np.mean((adaptive - clean) ** 2) < 0.2 * np.mean((y - clean) ** 2)


@pytest.mark.parametrize("window,polyorder,deriv", [(5, 3, 0), (21, 3, 0), (61, 5, 0),
                                                    (27, 3, 1), (101, 3, 2), (7, 1, 0)])
def test_savgol_smooth_equals_scipy_interp_mode(window: int, polyorder: int, deriv: int) -> None:
    from scipy.signal import savgol_filter

    y = np.random.default_rng(11).normal(size=(400, 2)).cumsum(axis=0)
    ours = savgol_smooth(y, window, polyorder, deriv=deriv, delta=0.01)
    ref = savgol_filter(y, window, polyorder, deriv=deriv, delta=0.01, axis=0, mode="interp")
    np.testing.assert_allclose(ours, ref, rtol=1e-8, atol=1e-8 * np.abs(ref).max())


def test_ici_smooth_pair_equals_stacked_ici() -> None:
    """The compiled early-stopping pass equals ici_select over full Savitzky–Golay stacks of
    the force, applied to pA and pB (edges included)."""
    from cranetwin.signal import ICI_WINDOWS, centre_weight, ici_select, ici_smooth_pair

    rng = np.random.default_rng(3)
    n = 700
    t = np.arange(n) * 0.01
    pa = 8e6 + 3e6 * (t > 2.5) + 4e5 * np.sin(2 * np.pi * 5 * t) + rng.uniform(-4e5, 4e5, n)
    pb = 2e6 + 1e6 * np.cos(2 * np.pi * 0.3 * t) + rng.uniform(-4e5, 4e5, n)
    a1, a2, sigma = 0.0064, 0.0035, 1500.0
    ws = [w for w in ICI_WINDOWS if w == 1 or w > 4]
    ea = np.stack([savgol_smooth(pa, w, 3) for w in ws])
    eb = np.stack([savgol_smooth(pb, w, 3) for w in ws])
    sds = np.array([sigma * np.sqrt(centre_weight(w, 3)) for w in ws])
    k = ici_select(a1 * ea - a2 * eb, sds)
    assert len(set(k.tolist())) > 3  # the rule really adapts here
    want = np.column_stack([ea[k, np.arange(n)], eb[k, np.arange(n)]])
    got = ici_smooth_pair(pa, pb, a1, a2, sigma, tuple(ICI_WINDOWS), 3)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)


@pytest.mark.parametrize("n", [221, 222, 260, 6220])
def test_savgol_bank_equals_scipy_interp_mode_values_and_derivatives(n: int) -> None:
    """Long windows (FFT path) and short ones (direct), values and derivatives, one column and
    several, data as short as the longest window: each output is scipy's mode="interp"."""
    from scipy.ndimage import correlate1d
    from scipy.signal import savgol_filter

    from cranetwin.signal import sg_filter

    rng = np.random.default_rng(12)
    t = np.arange(n) * 0.01
    # a rod-position-like signal: offset, slow motion, uniform noise; a second column unlike it
    base = 0.4 + 0.2 * np.sin(2 * np.pi * 0.05 * t) + 0.03 * np.sin(2 * np.pi * 1.1 * t)
    y = np.column_stack([base + rng.uniform(-0.005, 0.005, n),
                         rng.normal(size=n).cumsum() * 1e3 + 8e6])
    filters = [(221, 5, 0), (171, 5, 0), (131, 3, 1), (131, 3, 2), (101, 3, 2), (41, 3, 0),
               (21, 3, 1), (7, 5, 0), (1, 0, 0)]
    for y_in in (y, y[:, 0]):
        outs = savgol_bank(y_in, filters, delta=0.01)
        assert len(outs) == len(filters)
        for (w, p, d), got in zip(filters, outs, strict=True):
            assert got.shape == y_in.shape
            if w == 1:
                np.testing.assert_array_equal(got, y_in)
                continue
            ref = savgol_filter(y_in, w, p, deriv=d, delta=0.01, axis=0, mode="interp")
            scale = np.abs(ref).max(axis=0)
            # per column, of its largest output; 3e-9: scipy's own 221/5 and 171/5 filters are
            # that ill-conditioned (their coefficients sum to 1 + 3e-9; its edge fits ~7e-10)
            err = np.abs(got - ref).max(axis=0) / scale
            assert np.all(err <= (3e-9 if p == 5 else 1e-9)), (w, p, d, err)
            # interior against direct correlation with the same coefficients (the FFT's rounding)
            half = w // 2
            direct = correlate1d(y_in, sg_filter(w, p, d), axis=0) / 0.01**d
            err = np.abs(got - direct)[half : n - half].max(axis=0, initial=0.0) / scale
            assert np.all(err <= 1e-11), (w, p, d, err)
            np.testing.assert_array_equal(got, savgol_smooth(y_in, w, p, d, 0.01))


def test_savgol_columns_equal_savgol_bank_per_column() -> None:
    """Per-column filter lists through one batched FFT pair equal savgol_bank column by
    column (FFT and direct windows, values and derivatives, a copy for window 1)."""
    from cranetwin.signal.savgol import savgol_columns

    rng = np.random.default_rng(13)
    n = 1500
    t = np.arange(n) * 0.01
    y = np.column_stack([0.4 + 0.2 * np.sin(2 * np.pi * 0.05 * t) + rng.uniform(-5e-3, 5e-3, n),
                         8e6 + rng.normal(size=n).cumsum() * 1e3,
                         rng.normal(size=n)])
    filters = [[(171, 5, 0), (101, 3, 1), (101, 3, 2)],
               [(221, 5, 0), (21, 3, 1), (1, 0, 0)],
               [(7, 5, 0), (131, 3, 2)]]
    got = savgol_columns(y, filters, delta=0.01)
    for c, col in enumerate(filters):
        want = savgol_bank(y[:, c], col, delta=0.01)
        for g, w in zip(got[c], want, strict=True):
            np.testing.assert_allclose(g, w, rtol=0, atol=1e-13 * np.abs(w).max())
    inner = savgol_columns(y, filters, delta=0.01, edges=(False, False))
    for c, col in enumerate(filters):
        for (w, _, _), g, full in zip(col, inner[c], got[c], strict=True):
            half = w // 2
            np.testing.assert_array_equal(g[half : n - half], full[half : n - half])
            assert np.isnan(g[:half]).all() and np.isnan(g[n - half :]).all()
    with pytest.raises(SignalError):
        savgol_columns(y, filters[:2])
    with pytest.raises(SignalError):
        savgol_columns(y[:100], filters)


def test_savgol_bank_rejects_bad_windows() -> None:
    y = np.zeros(100)
    with pytest.raises(SignalError):
        savgol_bank(y, [(101, 3, 0)])
    with pytest.raises(SignalError):
        savgol_bank(y, [(20, 3, 0)])
    with pytest.raises(SignalError):
        savgol_bank(y, [(5, 5, 0)])
    with pytest.raises(SignalError):
        savgol_bank(y, [(1, 0, 1)])
    with pytest.raises(SignalError):
        savgol_bank(np.zeros((100, 2, 2)), [(5, 3, 0)])


@pytest.mark.parametrize("n,polyorder,gamma", [(5000, 3, 1.5), (700, 3, 0.7), (300, 1, 3.0),
                                               (132, 3, 1.5), (131, 3, 1.5), (40, 3, 1.5),
                                               (9, 3, 1.5), (600, 1, 0.3)])
def test_ici_smooth_pair_equals_stacked_ici_on_random_data(n: int, polyorder: int,
                                                           gamma: float) -> None:
    """The compiled pass (prefix sums for polyorder <= 3) against the plain algorithm: full
    Savitzky–Golay stacks (scipy-equal, edges included), ici_select on the force, then pA, pB
    at the chosen windows; random steps and noise, short data where every sample is an edge."""
    from cranetwin.signal import ICI_WINDOWS, centre_weight, ici_select, ici_smooth_pair

    rng = np.random.default_rng(n + polyorder)
    steps = np.cumsum(rng.normal(0.0, 2e6, n) * (rng.uniform(size=n) < 0.01))
    pa = 9e6 + steps + np.cumsum(rng.normal(0.0, 3e4, n)) + rng.uniform(-3e5, 3e5, n)
    pb = 2e6 + 0.3 * steps + rng.uniform(-3e5, 3e5, n)
    a1, a2, sigma = 0.0064, 0.0035, 1400.0
    ws = [w for w in ICI_WINDOWS if (w == 1 or w > polyorder + 1) and w <= n]
    ea = np.stack([savgol_smooth(pa, w, polyorder) for w in ws])
    eb = np.stack([savgol_smooth(pb, w, polyorder) for w in ws])
    sds = np.array([sigma * np.sqrt(centre_weight(w, polyorder)) for w in ws])
    k = ici_select(a1 * ea - a2 * eb, sds, gamma)
    if n >= 300:
        assert len(set(k.tolist())) > 3  # the rule really adapts here
    want = np.column_stack([ea[k, np.arange(n)], eb[k, np.arange(n)]])
    got = ici_smooth_pair(pa, pb, a1, a2, sigma, ICI_WINDOWS, polyorder, gamma)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9 * np.abs(want).max())


@pytest.mark.parametrize("n", [2, 3, 10, 1001, 20000])
def test_compiled_median_and_rank_pair_are_exact_order_statistics(n: int) -> None:
    """The histogram selections against sorting: continuous values, heavy ties, far
    outliers (nearly every value in one bucket), adjacent ranks in different buckets."""
    from cranetwin.signal.noise_level import _median, _rank_pair

    rng = np.random.default_rng(n)
    cases = [rng.normal(size=n), rng.integers(0, 4, n).astype(float),
             np.concatenate([rng.normal(size=n - 1), [1e12]]), np.round(rng.normal(size=n), 1),
             np.concatenate([np.zeros(n // 2), np.ones(n - n // 2)])]
    for a in cases:
        srt = np.sort(a)
        assert _median(a) == np.median(a)
        for r in sorted({0, max(n // 2 - 1, 0), n - 2}):
            assert _rank_pair(a, r) == (srt[r], srt[r + 1])


def _old_noise_std(y: np.ndarray, resolution: float = 0.0, order: int = 4) -> float:
    """The numpy formulation of estimate_noise_std (reference for the compiled one)."""
    from math import comb

    d = np.diff(y, n=order)
    centre = float(np.median(d))
    robust = 1.4826 * float(np.median(np.abs(d - centre)))
    kept = d[np.abs(d - centre) <= 4.0 * robust] if robust > 0 else d
    spread = float(np.sqrt(np.mean((kept - centre) ** 2))) if kept.size else 0.0
    return max(spread / np.sqrt(comb(2 * order, order)), resolution / np.sqrt(12.0))


def _old_choose_window(y: np.ndarray, sigma: float) -> tuple[int, int, float]:
    """choose_window by direct convolution per candidate (reference for the FFT version)."""
    from cranetwin.signal import sg_filter
    from cranetwin.signal.window import DEFAULT_POLYORDERS, DEFAULT_WINDOWS

    n = y.shape[0]
    wmax = max((w for w in DEFAULT_WINDOWS if w <= n // 2), default=1)
    seg = max(8 * wmax, 2000)
    starts = [0] if n <= 8000 else np.linspace(0, n - seg, 8000 // seg).astype(int).tolist()
    segs = [y[s : s + seg] if n > 8000 else y for s in starts]
    edge = wmax // 2
    best = (1, 0, sigma * sigma)
    for w in DEFAULT_WINDOWS:
        for p in DEFAULT_POLYORDERS:
            if w <= 1 or w > wmax or p >= w - 1:
                continue
            h = sg_filter(w, p)
            sq = 0.0
            cnt = 0
            for s in segs:
                core = np.convolve(s, h[::-1], mode="valid")[edge - w // 2 :]
                core = core[: s.shape[0] - 2 * edge]
                r = s[edge : s.shape[0] - edge] - core
                sq += float(r @ r)
                cnt += r.shape[0]
            risk = sq / cnt - sigma**2 + 2 * sigma**2 * float(h[w // 2])
            if risk < best[2]:
                best = (w, p, risk)
    return best


@pytest.mark.parametrize("n", [300, 5000, 60000])
def test_noise_estimate_and_window_choice_equal_direct_formulation(n: int) -> None:
    """Compiled noise estimate (histogram medians) and FFT risk evaluation give the numpy
    formulation's sigma and window (risk to rounding), long data (segments) and short."""
    rng = np.random.default_rng(n)
    t = np.arange(n) * 0.01
    clean = 0.4 + 0.2 * np.sin(2 * np.pi * 0.07 * t) + 0.02 * np.sin(2 * np.pi * 1.7 * t)
    for noise in (0.002, 0.01):
        y = clean + rng.uniform(-noise, noise, n)
        sigma = estimate_noise_std(y)
        assert sigma == pytest.approx(_old_noise_std(y), rel=1e-12)
        ch = choose_window(y)
        w, p, risk = _old_choose_window(y, sigma)
        assert (ch.window, ch.polyorder) == (w, p)
        assert ch.risk == pytest.approx(risk, rel=1e-9)
    q = np.round(rng.normal(size=n) * 3.0) / 3.0  # few distinct values: ties in the medians
    assert estimate_noise_std(q) == pytest.approx(_old_noise_std(q), rel=1e-12)


def test_natural_pieces_equal_the_spline_class_and_reject_nan() -> None:
    from cranetwin.signal import NaturalCubicSpline, natural_pieces

    rng = np.random.default_rng(11)
    x = np.arange(50) * 0.01
    y = rng.normal(size=(50, 3))
    np.testing.assert_array_equal(natural_pieces(x, y), NaturalCubicSpline(x, y).pieces())
    y[7, 1] = np.nan
    with pytest.raises(SignalError):
        natural_pieces(x, y)
