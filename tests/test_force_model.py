"""Model-based cylinder forces (:mod:`cranetwin.twin.force_model`): inverse dynamics corrected
by the smoothed pressure residual."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import stream_in_random_chunks
from cranetwin.model import Machine, load_machine
from cranetwin.signal import inject_uniform_noise, nrmse
from cranetwin.testing.recordings import make
from cranetwin.twin import ReplayOptions, replay
from cranetwin.twin.force_model import (
    MODEL_SHARE,
    interpolate,
    residual_range,
    smoothed_range,
    wants_model,
)

INNER = slice(1000, -1000)


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load_machine("patu655")




@pytest.mark.timeout(300)
@pytest.mark.parametrize("with_angle", [True, False])
def test_streaming_equals_batch_with_model_forces(machine: Machine, with_angle: bool) -> None:
    s = make(machine, duration_s=14.0, payload=150.0, with_angle=with_angle, fine_hz=None)
    noisy = inject_uniform_noise(s.samples, machine, 0.05, seed=1)
    first = replay(noisy, machine, options=ReplayOptions(model_forces="on"))
    choices = tuple(first.smoothing.values())
    assert all(c.model_based for k, c in first.smoothing.items() if k.endswith("_pA"))
    opt = ReplayOptions(smoothing=choices, sample_period_s=0.01, chunk_samples=700)
    batch = replay(noisy, machine, options=opt)
    streamed = stream_in_random_chunks(noisy, machine, opt, seed=2)
    assert streamed.n == batch.n
    np.testing.assert_array_equal(streamed.t_s, batch.t_s)
    for name in ("cyl_force", "actuator_torque", "residual", "joint_wrench", "payload_kg"):
        a = getattr(streamed, name)
        b = getattr(batch, name)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-8 * np.abs(b).max(), err_msg=name)
    # the model changed the forces (else this test would prove nothing about it)
    off = replay(noisy, machine, options=ReplayOptions(model_forces="off"))
    assert np.abs(off.cyl_force - batch.cyl_force).max() > 1e-3 * np.abs(off.cyl_force).max()


@pytest.mark.timeout(300)
def test_noise_free_run_gives_the_eq12_forces(machine: Machine) -> None:
    s = make(machine, duration_s=12.0, payload=150.0, with_angle=True)
    on = replay(s.samples, machine, grid_hz=1000, options=ReplayOptions(model_forces="on"))
    off = replay(s.samples, machine, grid_hz=1000, options=ReplayOptions(model_forces="off"))
    assert all(c.model_based for k, c in on.smoothing.items() if k.endswith("_pA"))
    span = np.ptp(s.force, axis=0)
    # Eq. 1–2 of the clean pressures, and the truth
    assert np.all(np.abs(on.cyl_force - off.cyl_force)[INNER].max(axis=0) < 1e-2 * span)
    assert np.all(nrmse(on.cyl_force, s.force) < 2e-3)
    # the actuator loads follow the force: F·ds/dq
    np.testing.assert_allclose(on.residual[INNER], on.actuator_torque[INNER]
                               - on.id_torque[INNER], atol=1e-6 * np.abs(on.id_torque).max())


@pytest.mark.timeout(600)
def test_model_forces_beat_pressure_smoothing_on_a_light_crane(machine: Machine) -> None:
    """A crane of the noise family at 0.27× the built-in's loads (same cylinders and
    sensors), ±5 % uniform error of the sensors' full range: the lift and jib forces are
    unresolved by the pressures (σ_F > 20 % of the range), the default picks the model and
    it beats Eq. 1–2 of the LPA-ICI pressures by more than 10 %."""
    from cranetwin.sim import SensorModel, builtin_scenario, simulate
    from cranetwin.sim.family import crane_family, variant_machine
    from cranetwin.sim.sensor_error import inject_error

    variant = crane_family(8)[3]
    assert 0.2 < variant.force_scale < 0.3
    m = variant_machine(machine, variant)
    sc = builtin_scenario("log-loading", duration_s=30.0,
                          payload_kg=300.0 * variant.force_scale)
    rec = simulate(m, sc, seed=0, sensors=SensorModel.ideal(100.0), wrenches=False)
    noisy = inject_error(rec.samples, m, 0.05, 0, "uniform", "full")
    auto = replay(noisy, m, grid_hz=100.0)
    off = replay(noisy, m, grid_hz=100.0, options=ReplayOptions(model_forces="off"))
    idx = np.searchsorted(rec.truth.t_s, auto.t_s - 1e-9)
    truth = rec.truth.cyl_force[idx]
    chosen = {k: c.model_based for k, c in auto.smoothing.items() if k.endswith("_pA")}
    assert chosen["lift_pA"] and chosen["jib_pA"]
    e_auto = nrmse(auto.cyl_force, truth)[:2]
    e_off = nrmse(off.cyl_force, truth)[:2]
    assert np.all(e_auto < 0.9 * e_off), (e_auto, e_off)


def test_rule_and_ranges() -> None:
    assert wants_model(MODEL_SHARE * 110.0, 100.0) and not wants_model(MODEL_SHARE * 90.0, 100.0)
    assert wants_model(1.0, 0.0) and not wants_model(0.0, 0.0)
    # interior: half on each side; at the start and the end of the recording a whole window
    assert residual_range(1000, 1500, 400, 10_000, False) == (600, 1900)
    assert residual_range(0, 10, 400, 10_000, False) == (0, 800)
    assert residual_range(9990, 10_000, 400, 10_000, True) == (9199, 9999)
    assert residual_range(9990, 10_000, 0, 10_000, True) == (9990, 9999)
    # block means over window // 2 samples: (0.5, 2.5, 4.5, 6)
    assert smoothed_range(np.arange(7.0), 5) == 5.5 and smoothed_range(np.zeros(0), 5) == 0.0
    corr = np.array([[0.0], [10.0], [20.0]])
    np.testing.assert_allclose(interpolate(corr, 5, 11)[:, 0], np.arange(11) * 2.0)
    np.testing.assert_array_equal(interpolate(corr, 1, 3), corr)
