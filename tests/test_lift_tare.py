"""The empty reading next to a lift (a tare, :mod:`cranetwin.twin.lifts`): a constant error of
the payload estimate — a pressure sensor's zero offset — is read between lifts, where the
grapple is empty, and taken off the lift's mean when it exceeds its noise; within its noise the
lift is left as it was."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from conftest import offset_pressures
from cranetwin.model import Machine, load_machine
from cranetwin.signal import inject_uniform_noise
from cranetwin.testing.recordings import make

F64 = npt.NDArray[np.float64]

SMEAR_S = 2.0
LOAD_KG = 200.0
# empty 0–8 s, a lift 8–20 s, empty 20–30 s, a lift 30–42 s, empty to 50 s
LIFTS_S = ((8.0, 20.0), (30.0, 42.0))


def _profile(t: F64) -> F64:
    out = np.zeros_like(t)
    for a, b in LIFTS_S:
        out[(t >= a) & (t < b)] = LOAD_KG
    return out


def _estimate(offset_kg: float, sigma_kg: float, seed: int) -> tuple[F64, F64, F64]:
    """Instants, an estimate (the profile + offset + noise independent per smear width) and
    its σ, at 100 Hz over 50 s."""
    t = np.arange(0.0, 50.0, 0.01)
    rng = np.random.default_rng(seed)
    blocks = rng.standard_normal(int(np.ceil(t[-1] / SMEAR_S)) + 1) * sigma_kg
    noise = blocks[(t // SMEAR_S).astype(int)]
    return t, _profile(t) + offset_kg + noise, np.full_like(t, sigma_kg)


@pytest.mark.timeout(30)
def test_an_offset_beyond_the_noise_is_taken_off_every_lift() -> None:
    from cranetwin.twin.lifts import lift_payloads

    t, m, s = _estimate(offset_kg=30.0, sigma_kg=2.0, seed=1)
    lifts = lift_payloads(t, m, s, SMEAR_S, threshold_kg=60.0)
    gross = lift_payloads(t, m, s, SMEAR_S, threshold_kg=60.0, tare_span_s=None)
    assert [lf.complete for lf in lifts] == [True, True]
    for lf, g in zip(lifts, gross, strict=True):
        assert lf.tare_kg == pytest.approx(30.0, abs=4.0)
        assert lf.empty_kg == lf.tare_kg
        assert lf.payload_kg + lf.tare_kg == pytest.approx(g.payload_kg, rel=1e-12)
        assert abs(lf.payload_kg - LOAD_KG) < 4.0 * lf.std_kg
        assert abs(g.payload_kg - LOAD_KG) > 10.0 * g.std_kg  # gross: off by the offset
        assert (g.tare_kg, g.payload_kg) == (0.0, pytest.approx(g.payload_kg))


@pytest.mark.timeout(60)
def test_an_empty_reading_within_its_noise_is_left_alone() -> None:
    """No offset: over many noise draws a lift is tared rarely (a 2σ test on a standard error
    from few estimates: about 11 %), an untared lift's mean is the gross mean, and the tared
    ones are not biased one way."""
    from cranetwin.twin.lifts import lift_payloads

    tared: list[float] = []
    total = 0
    for seed in range(200):
        t, m, s = _estimate(offset_kg=0.0, sigma_kg=2.0, seed=seed)
        gross = lift_payloads(t, m, s, SMEAR_S, threshold_kg=60.0, tare_span_s=None)
        for lf, g in zip(lift_payloads(t, m, s, SMEAR_S, threshold_kg=60.0), gross,
                         strict=True):
            total += 1
            if lf.tare_kg != 0.0:
                tared.append(lf.tare_kg)
            else:
                assert lf.payload_kg == g.payload_kg and lf.std_kg == g.std_kg
    assert total == 400
    assert 0 < len(tared) <= 60, len(tared)  # at most 15 %: far more would be taring noise
    assert abs(float(np.mean(tared))) < 1.0  # σ = 2 kg: both signs


@pytest.mark.timeout(30)
def test_no_empty_stretch_no_tare() -> None:
    """Loaded from the first instant to the last: no empty reading (NaN), nothing taken off."""
    from cranetwin.twin.lifts import lift_payloads

    t = np.arange(0.0, 20.0, 0.01)
    m = np.full_like(t, LOAD_KG + 30.0)
    lf, = lift_payloads(t, m, np.full_like(t, 2.0), SMEAR_S, threshold_kg=60.0)
    assert not lf.complete and np.isnan(lf.empty_kg) and lf.tare_kg == 0.0
    assert lf.payload_kg == pytest.approx(LOAD_KG + 30.0)


@settings(max_examples=40, deadline=None)
@given(c1=st.floats(10.0, 50.0), c2=st.floats(-50.0, -10.0), seed=st.integers(0, 1000))
@pytest.mark.timeout(60)
def test_net_lift_mean_does_not_depend_on_a_constant_offset(c1: float, c2: float,
                                                            seed: int) -> None:
    """Two offsets, each well beyond the noise (σ = 1 kg) and below the threshold's margin:
    the same lifts, the same net means."""
    from cranetwin.twin.lifts import lift_payloads

    t, m, s = _estimate(offset_kg=0.0, sigma_kg=1.0, seed=seed)
    a = lift_payloads(t, m + c1, s, SMEAR_S, threshold_kg=100.0)
    b = lift_payloads(t, m + c2, s, SMEAR_S, threshold_kg=100.0)
    assert len(a) == len(b) == 2
    for la, lb in zip(a, b, strict=True):
        assert la.tare_kg != 0.0 and lb.tare_kg != 0.0
        assert la.payload_kg == pytest.approx(lb.payload_kg, abs=1e-9)
        assert la.std_kg == pytest.approx(lb.std_kg, rel=1e-12)


def _steady(t: F64) -> npt.NDArray[np.bool_]:
    """Instants of the loaded profile at least two smear widths from a grab or a release."""
    return np.any([(t > a + 2 * SMEAR_S) & (t < b - 2 * SMEAR_S) for a, b in LIFTS_S], axis=0)


@pytest.mark.timeout(60)
def test_each_instant_of_a_tared_lift_is_net_of_the_offset_with_the_tares_sigma() -> None:
    """An offset of 15 σ: the gross instants' z is about 15; the net instants (the gross less
    the lift's tare, σ with the tare's) have RMS z near 1 over many draws, and everything
    outside the lifts is the gross estimate unchanged."""
    from cranetwin.twin.lifts import lift_payloads, net_payload

    z_net: list[F64] = []
    z_gross: list[F64] = []
    for seed in range(100):
        t, m, s = _estimate(offset_kg=30.0, sigma_kg=2.0, seed=seed)
        lifts = lift_payloads(t, m, s, SMEAR_S, threshold_kg=60.0)
        assert all(lf.tare_kg != 0.0 and lf.tare_std_kg > 0.0 for lf in lifts)
        net, std = net_payload(t, m, s, lifts)
        on = _steady(t)
        z_net.append((net[on] - LOAD_KG) / std[on])
        z_gross.append((m[on] - LOAD_KG) / s[on])
        inside = np.any([(t >= lf.grab_s) & (t <= lf.release_s) for lf in lifts], axis=0)
        assert np.array_equal(net[~inside], m[~inside]) and np.array_equal(std[~inside], s[~inside])
        for lf in lifts:
            sel = (t >= lf.grab_s) & (t <= lf.release_s)
            assert np.allclose(net[sel], m[sel] - lf.tare_kg, rtol=0, atol=1e-12)
            assert np.allclose(std[sel], np.hypot(2.0, lf.tare_std_kg), rtol=1e-12)
    rms_net = float(np.sqrt(np.mean(np.concatenate(z_net) ** 2)))
    rms_gross = float(np.sqrt(np.mean(np.concatenate(z_gross) ** 2)))
    assert rms_gross > 12.0
    assert 0.8 < rms_net < 1.25, rms_net


@pytest.mark.timeout(30)
def test_net_instants_drop_the_systematic_sigma_and_untared_lifts_stay_gross() -> None:
    """With a stated systematic σ_b the tared instants' σ is their random part with the tare's
    (the offset σ_b stood for is taken off); a lift that is not tared is returned as it was."""
    from cranetwin.twin.lifts import lift_payloads, net_payload

    t, m, s = _estimate(offset_kg=30.0, sigma_kg=2.0, seed=3)
    sb = np.full_like(t, 1.2)
    lifts = lift_payloads(t, m, s, SMEAR_S, threshold_kg=60.0, payload_sys_std_kg=sb)
    net, std = net_payload(t, m, s, lifts, sb)
    for lf in lifts:
        sel = (t >= lf.grab_s) & (t <= lf.release_s)
        assert np.allclose(std[sel], np.hypot(1.6, lf.tare_std_kg), rtol=1e-12)  # √(2² − 1.2²)
    untared = lift_payloads(t, m, s, SMEAR_S, threshold_kg=60.0, tare_span_s=None)
    net, std = net_payload(t, m, s, untared, sb)
    assert np.array_equal(net, m) and np.array_equal(std, s)


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load_machine("patu655")


@pytest.mark.timeout(300)
def test_a_pressure_sensor_offset_is_taken_off_the_replayed_lifts(machine: Machine) -> None:
    """Two lifts of 150 kg with an empty grapple between them; every pressure sensor with a
    constant offset within ±1 % of its range (four draws) and a little noise: the gross lift
    means are off by the offsets, the net ones are within 3 % and within 3σ."""
    from cranetwin.twin import replay
    from cranetwin.twin.lifts import result_lifts

    def payload(t: F64) -> F64:
        return np.where(((t >= 6.0) & (t < 18.0)) | ((t >= 26.0) & (t < 38.0)), 150.0, 0.0)

    s = make(machine, duration_s=44.0, payload=payload, with_angle=True, scale=0.5,
             fine_hz=None)
    worst_gross = 0.0
    for seed in range(4):
        noisy = inject_uniform_noise(offset_pressures(s.samples, machine, 0.01, seed),
                                     machine, 0.001, seed=seed)
        res = replay(noisy, machine)
        lifts = [lf for lf in result_lifts(res, 0.01, threshold_kg=45.0) if lf.complete]
        assert len(lifts) == 2, lifts
        for lf in lifts:
            gross = lf.payload_kg + lf.tare_kg
            worst_gross = max(worst_gross, abs(gross - 150.0) / 150.0)
            assert abs(lf.payload_kg - 150.0) < max(0.03 * 150.0, 3.0 * lf.std_kg), lf
    assert worst_gross > 0.05  # the offsets did matter


@pytest.mark.timeout(300)
def test_no_tare_on_a_coarse_staircase(machine: Machine) -> None:
    """Pressures and positions quantised to steps of 10 % of their range: the replay
    recognises the staircase, and its lifts are not tared (the error differs between the
    empty and the loaded levels); the same lifts with an offset instead are."""
    from cranetwin.sim.sensor_error import inject_error
    from cranetwin.twin import replay
    from cranetwin.twin.lifts import result_lifts

    def payload(t: F64) -> F64:
        return np.where(((t >= 6.0) & (t < 18.0)) | ((t >= 26.0) & (t < 38.0)), 150.0, 0.0)

    s = make(machine, duration_s=44.0, payload=payload, with_angle=True, scale=0.5,
             fine_hz=None)
    res = replay(inject_error(s.samples, machine, 0.05, 0, "quantised", "full"), machine)
    assert any(c.step > 0 for c in res.smoothing.values())
    lifts = result_lifts(res, 0.01, threshold_kg=45.0)
    assert lifts and all(lf.tare_kg == 0.0 and np.isnan(lf.empty_kg) for lf in lifts)
    off = replay(inject_uniform_noise(offset_pressures(s.samples, machine, 0.01, 0), machine,
                                      0.001, seed=0), machine)
    assert not any(c.step > 0 for c in off.smoothing.values())
    assert any(lf.tare_kg != 0.0 for lf in result_lifts(off, 0.01, threshold_kg=45.0))
