"""Model-based or pressure-only force per cylinder by the two-fold split risk
(:mod:`cranetwin.twin.model_choice`)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from cranetwin.model import Machine, load_machine
from cranetwin.samples import SampleArrays
from cranetwin.signal import SmoothingChoice, inject_uniform_noise, nrmse
from cranetwin.testing.recordings import make
from cranetwin.twin import ReplayOptions, TwinResult, TwinStream, replay
from cranetwin.twin.model_choice import MODEL_Z, ModelRisks, model_risks
from cranetwin.twin.plan import ReplayPlan


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load_machine("patu655")


def _pressure_pairs(res_smoothing: dict[str, SmoothingChoice]) -> dict[str, bool]:
    return {k[: -len("_pA")]: c.model_based
            for k, c in res_smoothing.items() if k.endswith("_pA")}


@pytest.mark.timeout(300)
def test_resolved_forces_stay_pressure_only(machine: Machine) -> None:
    """±0.5 % of the sensors' range on the built-in crane: the pressures resolve every force,
    the model's errors (smoothed accelerations, payload) dominate its residual: the
    pressure-only force predicts the held-out samples better, by far, and is chosen."""
    s = make(machine, duration_s=14.0, payload=150.0, with_angle=True, fine_hz=None)
    noisy = inject_uniform_noise(s.samples, machine, 0.005, seed=1)
    res = replay(noisy, machine)
    assert not any(_pressure_pairs(res.smoothing).values())
    risks = _risks(machine, noisy, res, None)
    assert np.all(risks.model > 1.2 * risks.pressure), risks
    assert np.all(risks.model - risks.pressure > MODEL_Z * risks.se), risks


def _light_crane(machine: Machine) -> tuple[Machine, float, Any, SampleArrays]:
    """A crane of the noise family at 0.27× the built-in's loads (same cylinders and sensors),
    30 s of log loading at 100 Hz with ±5 % uniform error of the sensors' full range: σ_F
    exceeds 20 % of every force range (the σ_F rule flags all three); its payload [kg], the
    simulator's recording and the noisy samples."""
    from cranetwin.sim import SensorModel, builtin_scenario, simulate
    from cranetwin.sim.family import crane_family, variant_machine
    from cranetwin.sim.sensor_error import inject_error

    variant = crane_family(8)[3]
    assert 0.2 < variant.force_scale < 0.3
    m = variant_machine(machine, variant)
    kg = 300.0 * variant.force_scale
    sc = builtin_scenario("log-loading", duration_s=30.0, payload_kg=kg)
    rec = simulate(m, sc, seed=0, sensors=SensorModel.ideal(100.0), wrenches=False)
    return m, kg, rec, inject_error(rec.samples, m, 0.05, 0, "uniform", "full")


def _risks(m: Machine, noisy: SampleArrays, res: TwinResult,
           payload: float | None) -> ModelRisks:
    opt = ReplayOptions(sample_period_s=0.01)
    plan = ReplayPlan.of(m, noisy.channels, opt)
    cols = [noisy.channels.index(c) for c in plan.cmap.names]
    risks = model_risks(plan, tuple(res.smoothing.values()), noisy.values[:, cols], 0.01,
                        payload)
    assert risks is not None
    return risks


@pytest.mark.timeout(600)
def test_a_right_model_is_chosen_and_a_wrong_one_is_not(machine: Machine) -> None:
    """On the light crane the model with the estimated payload predicts the held-out jib
    force better by more than ``MODEL_Z`` standard errors and the lift and jib forces stay
    model-based (better than pressure-only against the truth); told a known payload ten times
    the true one, F_model is wrong by the payload's weight, every cylinder's pressure-only
    force predicts better by more than ``MODEL_Z`` standard errors and is chosen, though the
    σ_F rule flags them all (and it is better against the truth)."""
    m, kg, rec, noisy = _light_crane(machine)
    right = replay(noisy, m, grid_hz=100.0)
    assert all(_pressure_pairs(right.smoothing).values())
    good = _risks(m, noisy, right, None)
    assert good.pressure[1] - good.model[1] > MODEL_Z * good.se[1], good
    wrong = replay(noisy, m, grid_hz=100.0, payload=10.0 * kg)
    assert not any(_pressure_pairs(wrong.smoothing).values())
    bad = _risks(m, noisy, wrong, 10.0 * kg)
    assert np.all(bad.model - bad.pressure > MODEL_Z * bad.se), bad
    forced = replay(noisy, m, grid_hz=100.0, payload=10.0 * kg,
                    options=ReplayOptions(model_forces="on"))
    idx = np.searchsorted(rec.truth.t_s, wrong.t_s - 1e-9)
    truth = rec.truth.cyl_force[idx]
    assert np.all(nrmse(wrong.cyl_force, truth) < nrmse(forced.cyl_force, truth))


@pytest.mark.timeout(600)
def test_the_stream_chooses_as_the_batch(machine: Machine) -> None:
    """A stream choosing on the whole recording (choose_after_s beyond its end) makes the
    batch's choices, the model-based flags the split risk overrode included; twice the same."""
    m, kg, _, noisy = _light_crane(machine)
    opt = ReplayOptions(grid_hz=100.0, sample_period_s=0.01, choose_after_s=100.0)
    batch = replay(noisy, m, options=opt, payload=10.0 * kg)
    again = replay(noisy, m, options=opt, payload=10.0 * kg)
    assert not any(_pressure_pairs(batch.smoothing).values())
    st = TwinStream(m, noisy.channels, opt, 10.0 * kg)
    st.push(noisy)
    last = st.flush()
    assert st._choices is not None and last is not None
    # (repr: a NaN risk is its own equal there)
    assert ([repr(c) for c in batch.smoothing.values()] == [repr(c) for c in st._choices]
            == [repr(c) for c in again.smoothing.values()])
