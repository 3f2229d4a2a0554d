"""Coarse quantisation (:mod:`cranetwin.signal.quantisation`): the lattice is found on lattice
data and never on continuous data; the reconstruction stays in the cells, recovers the crossings
and is local (blocks with its context equal the whole record); the replay reconstructs such
channels, takes half the step as their error bound and streams as it replays in one go."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from conftest import stream_in_random_chunks
from cranetwin.model import Machine, load_machine
from cranetwin.samples import SampleArrays
from cranetwin.signal.quantisation import (
    _MAX_LEVELS,
    CONTEXT,
    MIN_STEP_TOLS,
    REL_TOL,
    detect_lattice,
    reconstruct,
)
from cranetwin.testing.recordings import Synthetic, make
from cranetwin.twin import ReplayOptions, replay
from cranetwin.twin.channels import detected_steps
from cranetwin.twin.observability import effective_accuracy, stated_force_sigma


def _walk(moves: list[int], start: int) -> np.ndarray:
    return start + np.cumsum(np.asarray(moves, dtype=np.int64))


@settings(max_examples=200, deadline=None)
@given(moves=st.lists(st.sampled_from([-1, 0, 0, 0, 1]), min_size=16, max_size=400),
       exponent=st.integers(-6, 7), mantissa=st.floats(1.0, 9.99),
       start=st.integers(-1000, 1000), frac=st.floats(0.0, 0.999),
       as_float32=st.booleans())
def test_lattice_data_give_their_step(moves: list[int], exponent: int, mantissa: float,
                                      start: int, frac: float, as_float32: bool) -> None:
    """Any samples o + k·h that visit two neighbouring levels and repeat levels (at most half
    as many levels as samples) give back h (to rounding), in float64 or stored as float32."""
    h = mantissa * 10.0**exponent
    k = _walk(moves, start)
    assume(np.unique(k).shape[0] >= 2 and np.any(np.abs(np.diff(k)) == 1))
    assume(2 * np.unique(k).shape[0] <= k.shape[0])
    y = (frac + k) * h
    if as_float32:
        y = y.astype(np.float32).astype(np.float64)
    lat = detect_lattice(y)
    assert lat is not None
    # to rounding: within two level tolerances (REL_TOL·max|y|; float64 data: far closer)
    tol = 2 * REL_TOL * float(np.max(np.abs(y))) if as_float32 else 1e-9 * h
    assert abs(lat.step - h) <= tol
    assert lat.levels == np.unique(k).shape[0]


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(8, 3000),
       model=st.sampled_from(["uniform", "gaussian", "biased", "signal", "clusters"]),
       scale=st.floats(1e-6, 1e7), resolution=st.sampled_from([0.0, 1e-3]))
def test_continuous_noisy_data_are_not_a_lattice(seed: int, n: int, model: str, scale: float,
                                                 resolution: float) -> None:
    """Noisy continuous data (uniform, Gaussian, offset plus noise, a signal plus noise, two
    levels blurred by noise; also after the sensor's own fine quantisation below the detectable
    step) are never taken for a lattice."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 100.0
    base = scale * (1.0 + 0.5 * np.sin(0.7 * t))
    if model == "uniform":
        y = base + rng.uniform(-0.05, 0.05, n) * scale
    elif model == "gaussian":
        y = base + rng.standard_normal(n) * 0.05 * scale
    elif model == "biased":
        y = base + 0.025 * scale * (rng.uniform(-1, 1) + rng.uniform(-1, 1, n))
    elif model == "signal":
        y = base + rng.standard_normal(n) * 1e-3 * scale
    else:  # two levels with noise: dense enough that neighbouring values merge within tol
        y = scale * (1.0 + 1e-4 * rng.integers(0, 2, n) + 1e-5 * rng.uniform(-1, 1, n))
    if resolution:  # a fine quantisation, far below what the tolerance can tell apart
        step = 0.1 * MIN_STEP_TOLS * REL_TOL * float(np.max(np.abs(y)))
        y = np.round(y / step) * step
    assert detect_lattice(y) is None


def test_single_level_gaps_and_short_data() -> None:
    """One level gives no step; NaN and inf are ignored; too few samples give no verdict."""
    assert detect_lattice(np.full(100, 2.5e6)) is None
    y = np.r_[np.zeros(40), np.full(40, 25.0), [np.nan] * 5, np.full(20, 50.0), [np.inf]]
    lat = detect_lattice(y)
    assert lat is not None and lat.step == 25.0 and lat.levels == 3
    assert detect_lattice(np.array([0.0, 1.0, 1.0, 0.0])) is None
    assert detect_lattice(np.full(10, np.nan)) is None


def test_long_records_take_the_subset_shortcut_exactly() -> None:
    """Over 2·2·_MAX_LEVELS samples a strided subset rejects continuous data early; a lattice
    with as many levels as the detection accepts is still found (the subset cannot show more
    levels than the whole)."""
    n = 4 * 2 * _MAX_LEVELS + 7
    rng = np.random.default_rng(5)
    assert detect_lattice(1e6 + rng.uniform(-1e5, 1e5, n)) is None
    levels = int(1.0 / (MIN_STEP_TOLS * REL_TOL)) - 100  # near the most from 0 up
    k = np.arange(n) % levels  # a sawtooth: each level visited 8 times
    lat = detect_lattice(k * 0.01)
    h = 0.01
    assert lat is not None and lat.step == pytest.approx(h, rel=1e-9)


def _staircase(n: int = 3000, h: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(n) / 100.0
    x = 0.5 + 0.4 * np.sin(0.3 * t)
    return x, np.round(x / h) * h


def test_reconstruction_stays_in_the_cells_and_recovers_the_crossings() -> None:
    """Inside every sample's cell; on a slow sinusoid over 9 levels a fifth of the staircase's
    RMS error (the crossings are known to half a sample, the levels only to ±h/2; what is left
    is mostly at the turning points, where the peak's height within its cell is not known)."""
    x, q = _staircase()
    r = reconstruct(q, 0.1)
    assert np.all(np.abs(r - q) <= 0.05 + 1e-15)
    rms_q = np.sqrt(np.mean((q - x) ** 2))
    rms_r = np.sqrt(np.mean((r - x) ** 2))
    assert rms_r < 0.2 * rms_q
    # a level held longer than 2·reach is a rest: the cell centre in its middle
    hold = np.r_[np.zeros(50), np.ones(500), np.zeros(50)]
    r = reconstruct(hold, 1.0, reach=100)
    assert np.all(r[200:400] == 1.0) and r[50] == pytest.approx(0.5 + 0.5 * 0.5 / 100, abs=1e-12)


@settings(max_examples=50, deadline=None)
@given(lo=st.integers(0, 2900), width=st.integers(1, 2900), reach=st.integers(1, 150))
def test_reconstruction_of_a_block_with_context_equals_the_whole(lo: int, width: int,
                                                                 reach: int) -> None:
    """The value at a sample depends only on the samples within 2·reach of it: a block with
    that much context on each side (or reaching the data's end) gives the same values."""
    _, q = _staircase()
    q[700:705] = np.nan
    whole = reconstruct(q, 0.1, reach)
    a, b = lo, min(q.shape[0], lo + width)
    ca, cb = max(0, a - 2 * reach), min(q.shape[0], b + 2 * reach)
    part = reconstruct(q[ca:cb], 0.1, reach)
    np.testing.assert_array_equal(part[a - ca : b - ca], whole[a:b])


def test_only_a_lattice_coarser_than_the_declared_resolution_counts() -> None:
    """A channel on its declared resolution is the sensor as described (not reconstructed);
    twice it or more is a coarse quantisation."""
    _, q = _staircase()
    cols = np.vstack([q, q, np.linspace(0.0, 1.0, q.shape[0])])
    assert detected_steps(cols, (0.1, 0.05, 0.1)) == (0.0, pytest.approx(0.1), 0.0)


def test_effective_accuracy_is_the_larger_bound() -> None:
    assert effective_accuracy(None, 0.0) is None
    assert effective_accuracy(None, 2.0) == 1.0
    assert effective_accuracy(3.0, 2.0) == 3.0
    assert effective_accuracy(0.5, 2.0) == 1.0
    assert effective_accuracy(0.5, 0.0) == 0.5


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load_machine("patu655")


def _quantised(machine: Machine, share: float = 0.1,
               duration_s: float = 14.0) -> tuple[Synthetic, SampleArrays]:
    s = make(machine, duration_s=duration_s, payload=150.0, with_angle=True, fine_hz=None)
    smp = s.samples
    values = smp.values.copy()
    for ch in machine.channels:
        if ch.quantity in ("pressure_a", "pressure_b", "position") and ch.name in smp.channels:
            j = smp.channels.index(ch.name)
            assert ch.full_range is not None
            step = share * ch.full_range
            values[:, j] = np.round(values[:, j] / step) * step
    return s, dataclasses.replace(smp, values=values)




@pytest.mark.timeout(300)
def test_replay_reconstructs_quantised_channels_and_streams_as_the_batch(
        machine: Machine) -> None:
    """Quantised pressures and positions (steps of 10 % of the sensor range, no accuracy
    stated): every one is detected with its step; the rods come closer to the truth than the
    staircase; the flag and the payload σ carry ±step/2; the stream equals the batch."""
    s, q = _quantised(machine)
    first = replay(q, machine)
    for ch in machine.channels:
        if ch.name in first.smoothing and ch.quantity in ("pressure_a", "position"):
            assert ch.full_range is not None
            col = q.column(ch.name)
            if np.unique(col).shape[0] >= 2:
                assert first.smoothing[ch.name].step == pytest.approx(0.1 * ch.full_range)
    assert stated_force_sigma(machine, 0) == 0.0  # nothing stated ...
    steps = {n: c.step for n, c in first.smoothing.items()}
    assert stated_force_sigma(machine, 0, steps) > 0.0  # ... the step is the bound
    # the flag's floor and the payload σ carry the systematic part (nothing stated: else 0)
    verdicts = first.force_observability(machine)
    assert verdicts[0].systematic_n > 0 and verdicts[0].source == "stated accuracy"
    assert np.nanmax(first.payload_sys_std_kg) > 0
    choices = tuple(first.smoothing.values())
    opt = ReplayOptions(smoothing=choices, sample_period_s=0.01, chunk_samples=700)
    batch = replay(q, machine, options=opt)
    streamed = stream_in_random_chunks(q, machine, opt, seed=3)
    assert streamed.n == batch.n
    for name in ("cyl_force", "rod_s", "payload_kg", "payload_std_kg"):
        a, b = getattr(streamed, name), getattr(batch, name)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-8 * np.nanmax(np.abs(b)), err_msg=name)
    # reconstructing beats smoothing the staircase (the same replay, steps dropped)
    plain = tuple(dataclasses.replace(c, step=0.0) for c in choices)
    stair = replay(q, machine, options=ReplayOptions(smoothing=plain, sample_period_s=0.01))
    truth = s.s[np.clip(np.searchsorted(s.t, batch.t_s - 1e-9), 0, s.t.shape[0] - 1)]
    err_r = np.sqrt(np.nanmean((batch.rod_s - truth) ** 2))
    err_s = np.sqrt(np.nanmean((stair.rod_s - truth) ** 2))
    assert err_r < 0.7 * err_s


def test_uniform_noise_is_not_reconstructed(machine: Machine) -> None:
    """Noisy data are not on a lattice: no channel gets a step (their replay is unchanged)."""
    from cranetwin.signal import inject_uniform_noise

    s = make(machine, duration_s=6.0, payload=150.0, with_angle=True, fine_hz=None)
    res = replay(inject_uniform_noise(s.samples, machine, 0.05, seed=1), machine)
    assert all(c.step == 0.0 for c in res.smoothing.values())


@pytest.mark.timeout(300)
def test_model_based_forces_take_the_reconstructed_pressures_and_stream_as_the_batch(
        machine: Machine) -> None:
    """Quantised pressures with every force model-based: F_raw of the residual is Eq. 1–2 of
    the reconstruction the smoothing used (:func:`force_model.raw_pressures`: a block with the
    reconstruction's context equals the whole record's reconstruction, not the staircase), and
    the stream, whose chunks reconstruct their own blocks, equals the batch at every seam."""
    from cranetwin.twin import TwinStream
    from cranetwin.twin.force_model import raw_context, raw_pressures

    _, q = _quantised(machine, duration_s=40.0)  # long enough for seams inside
    first = replay(q, machine, options=ReplayOptions(model_forces="on"))
    choices = tuple(first.smoothing.values())
    opt = ReplayOptions(smoothing=choices, sample_period_s=0.01, chunk_samples=700)
    plan = TwinStream(machine, q.channels, opt).plan
    cols = list(plan.cmap.p_a) + list(plan.cmap.p_b)
    steps = [choices[j].step for j in cols]
    assert all(c.model_based for k, c in first.smoothing.items() if k.endswith("_pA"))
    assert sum(h > 0 for h in steps) >= 2
    ctx = raw_context(plan, choices)
    assert ctx == CONTEXT
    p = np.stack([q.column(plan.cmap.names[j]) for j in cols], axis=1)
    lo, hi = 500, 900
    got = raw_pressures(plan, choices, p[lo - ctx : hi + ctx], ctx, hi - lo)
    for k, h in enumerate(steps):
        want = reconstruct(p[:, k], h)[lo:hi] if h > 0 else p[lo:hi, k]
        np.testing.assert_array_equal(got[:, k], want)
    moved = [k for k, h in enumerate(steps) if h > 0 and np.any(got[:, k] != p[lo:hi, k])]
    assert moved  # the staircase was replaced (else the comparison shows nothing)
    # not model-based: no context, the regularised pressures as they are
    plain = tuple(dataclasses.replace(c, model_based=False) for c in choices)
    assert raw_context(plan, plain) == 0
    np.testing.assert_array_equal(raw_pressures(plan, plain, p[lo:hi], 0, hi - lo), p[lo:hi])
    # the residual's windows reach far only where its noise σ is large: each force gets its
    # step's σ (±h/2 uniform on A_A·p_A), so that the chunks' residual ranges reach their edges
    loud = list(choices)
    for c, (ia, ib) in enumerate(zip(plan.cmap.p_a, plan.cmap.p_b, strict=True)):
        s = machine.cylinders[c].area_a_m2 * choices[ia].step / np.sqrt(12.0)
        if s > 0:
            loud[ia] = dataclasses.replace(choices[ia], sigma=s)
            loud[ib] = dataclasses.replace(choices[ib], sigma=s)
    opt = dataclasses.replace(opt, smoothing=tuple(loud))
    batch = replay(q, machine, options=opt)
    streamed = stream_in_random_chunks(q, machine, opt, seed=4)
    assert streamed.n == batch.n
    for name in ("cyl_force", "actuator_torque", "residual", "joint_wrench", "payload_kg"):
        a, b = getattr(streamed, name), getattr(batch, name)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-8 * np.nanmax(np.abs(b)), err_msg=name)


def test_a_reading_that_never_changes_is_flat() -> None:
    """One value throughout (NaN and inf ignored, float32 storage too) is flat; a second level,
    a tiny noise or too few samples are not."""
    from cranetwin.signal.quantisation import FLAT_MIN_SAMPLES, single_level

    n = FLAT_MIN_SAMPLES
    assert single_level(np.full(n, 2.5e6))
    assert single_level(np.r_[np.full(n, 2.5e6), [np.nan, np.inf]])
    assert single_level(np.full(n, 2.5e6, dtype=np.float32).astype(np.float64))
    assert not single_level(np.full(n - 1, 2.5e6))
    assert not single_level(np.r_[np.full(n, 2.5e6), [2.5e6 + 1.0]])
    assert not single_level(2.5e6 + np.random.default_rng(0).normal(0.0, 1.0, n))
    assert not single_level(np.full(n, np.nan))


@pytest.mark.timeout(120)
def test_a_cylinder_whose_pressures_never_change_is_not_observable(machine: Machine) -> None:
    """Both chamber pressures of the extension read one value (a 25 bar staircase on a small
    idle force): its model-based force takes its shape from the dynamics, so only the flat
    readings say the sensors saw nothing of it; it is flagged for them. One flat chamber (a
    return line at tank pressure) is not flagged for it, and no other cylinder is."""
    s = make(machine, duration_s=8.0, payload=150.0, with_angle=True, fine_hz=None)
    smp = s.samples
    ext = machine.cylinders[2].name
    names = {ch.quantity: ch.name for ch in machine.channels if ch.source == ext}
    values = smp.values.copy()
    for q in ("pressure_a", "pressure_b"):
        values[:, smp.channels.index(names[q])] = 2.5e6
    flat = dataclasses.replace(smp, values=values)
    res = replay(flat, machine, options=ReplayOptions(model_forces="on"))
    verdicts = {v.cylinder: v for v in res.force_observability(machine)}
    assert verdicts[ext].flat and not verdicts[ext].observable
    assert "flat pressures" in verdicts[ext].causes
    assert "one value throughout" in verdicts[ext].message()
    assert verdicts[ext].as_json()["flat"] is True
    assert not any(v.flat for name, v in verdicts.items() if name != ext)
    one = smp.values.copy()
    one[:, smp.channels.index(names["pressure_b"])] = 2.5e6
    res1 = replay(dataclasses.replace(smp, values=one), machine,
                  options=ReplayOptions(model_forces="on"))
    assert res1.smoothing[names["pressure_b"]].flat
    assert not any(v.flat for v in res1.force_observability(machine))
