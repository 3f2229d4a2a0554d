"""The Bobcat 435-class excavator end to end: its description reproduces the source's
kinematics, the simulator obeys the same laws as for the crane (now with a contact force at the
bucket tip), the twin replays it, and the tool force is recovered from the residual."""

from __future__ import annotations

import numpy as np
import pytest

from cranetwin.model import Machine, load_machine
from cranetwin.physics import (
    cylinder_forces,
    cylinder_kinematics,
    gravity_torques,
    inverse_dynamics,
    joints_from_cylinders,
)
from cranetwin.signal import nrmse
from cranetwin.sim import (
    Recording,
    Scenario,
    SensorModel,
    SimOptions,
    load_scenario,
    prepare,
    simulate,
)
from cranetwin.sim.energy import energy_terms
from cranetwin.sim.runner import initial_state
from cranetwin.sim.scenario import InitialState
from cranetwin.twin import replay
from cranetwin.twin.toolload import load_point_jacobian, tool_force

FULL_CONTACT = (4.5, 6.8)     # dig-cycle: contact force held at (4000, 0, 2000) N
ALL_CONTACT = (3.5, 7.5)      # ... including its 1 s ramp up and 0.7 s ramp down


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load_machine("bobcat435")


@pytest.fixture(scope="module")
def dig_ideal(machine: Machine) -> Recording:
    return simulate(machine, load_scenario("dig-cycle", machine=machine.name), duration_s=9.0,
                    seed=3, sensors=SensorModel.ideal())


@pytest.fixture(scope="module")
def dig_noisy(machine: Machine) -> Recording:
    return simulate(machine, load_scenario("dig-cycle", machine=machine.name), duration_s=9.0,
                    seed=3)


def test_joint_ranges_are_the_sources_at_the_cylinder_limits(machine: Machine) -> None:
    # bobcat_param.h / c2j_bobcat.m: boom -63/+66, arm -22/-145, bucket +33.3/-154 deg
    ends = np.array([[0.0, 0.0, 0.0], [c.stroke_m for c in machine.cylinders]])
    q = np.degrees(joints_from_cylinders(machine, ends))
    assert q[0, 1:] == pytest.approx([-63.0, -22.0, 33.3], abs=0.05)
    assert q[1, 1:] == pytest.approx([66.0, -145.0, -153.95], abs=0.05)


def test_truth_obeys_inverse_dynamics_with_the_contact_force(machine: Machine,
                                                            dig_ideal: Recording) -> None:
    tr = dig_ideal.truth
    assert np.abs(tr.contact_force).max() == pytest.approx(4000.0)
    tau, _ = inverse_dynamics(machine, tr.q, tr.qd, tr.qdd, tr.payload_kg)
    jac, _ = load_point_jacobian(machine, tr.q)
    external = np.einsum("nci,nc->ni", jac, tr.contact_force)
    scale = np.abs(tau).max(axis=0)
    assert np.all(np.abs(tau - tr.joint_torque - external).max(axis=0) <= 1e-6 * scale)
    # without the contact term the law visibly fails while digging
    assert np.abs(tau - tr.joint_torque).max() > 1e3


def test_truth_forces_follow_eq_1_2(machine: Machine, dig_ideal: Recording) -> None:
    tr = dig_ideal.truth
    f = cylinder_forces(machine, tr.p_a, tr.p_b, tr.rod_v)
    inside = np.all((tr.rod_s > 0) & (tr.rod_s < [c.stroke_m for c in machine.cylinders]),
                    axis=1)
    assert np.allclose(f[inside], tr.cyl_force[inside], rtol=1e-12, atol=1e-6)


def test_tool_force_from_the_exact_residual_is_the_contact_force(
        machine: Machine, dig_ideal: Recording) -> None:
    tr = dig_ideal.truth
    tau, _ = inverse_dynamics(machine, tr.q, tr.qd, tr.qdd, tr.payload_kg)
    est = tool_force(machine, tr.q, tr.joint_torque - tau)
    assert np.nanmax(np.abs(est.force_n - tr.contact_force)) < 1e-6
    assert np.nanmax(est.misfit) < 1e-6


def _replayed_tool_force(machine: Machine, rec: Recording) -> tuple[np.ndarray, np.ndarray,
                                                                     np.ndarray]:
    res = replay(rec.samples, machine, grid_hz=100.0, payload=0.0)
    tr = rec.truth
    ti = np.searchsorted(tr.t_s, res.t_s - 1e-9)
    est = tool_force(machine, res.q, res.residual)
    return res.t_s, est.force_n, tr.contact_force[ti]


@pytest.mark.timeout(300)
def test_tool_force_from_the_replay_ideal_sensors(machine: Machine,
                                                  dig_ideal: Recording) -> None:
    # measured (seed 3): full contact rms 9 / 21 N (x / z), max 43 / 108 N;
    # incl. the ramps max 195 / 324 N; no contact (1-3 s) rms 26 / 41 N
    t, est, true = _replayed_tool_force(machine, dig_ideal)
    full = (t >= FULL_CONTACT[0]) & (t <= FULL_CONTACT[1])
    err = est[full] - true[full]
    assert np.all(np.sqrt(np.nanmean(err**2, axis=0))[[0, 2]] < [30.0, 60.0])
    assert np.all(np.nanmax(np.abs(err), axis=0)[[0, 2]] < [120.0, 250.0])
    ramps = (t >= ALL_CONTACT[0]) & (t <= ALL_CONTACT[1])
    assert np.nanmax(np.abs(est[ramps] - true[ramps])) < 600.0
    free = (t >= 1.0) & (t <= 3.0)
    assert np.nanmax(np.abs(est[free])) < 250.0


@pytest.mark.timeout(300)
def test_tool_force_from_the_replay_noisy_sensors(machine: Machine,
                                                  dig_noisy: Recording) -> None:
    # default sensor model (noise 5e-4 of range, bias, dropouts, jitter); measured (seed 3):
    # full contact rms 21 / 53 N, max 92 / 262 N; incl. ramps max 405 / 685 N
    t, est, true = _replayed_tool_force(machine, dig_noisy)
    full = (t >= FULL_CONTACT[0]) & (t <= FULL_CONTACT[1])
    err = est[full] - true[full]
    assert np.all(np.sqrt(np.nanmean(err**2, axis=0))[[0, 2]] < [80.0, 150.0])
    assert np.all(np.nanmax(np.abs(err), axis=0)[[0, 2]] < [300.0, 600.0])
    mean = np.nanmean(est[full], axis=0)
    assert mean[[0, 2]] == pytest.approx([4000.0, 2000.0], rel=0.02)


# measured (seed 1, 100 Hz grid): ideal sensors — q NRMSE ≤ 7e-5, max 2.5e-4 rad; force NRMSE
# 1.4 / 0.66 / 0.16 % (boom / arm / bucket), max 4.9 % of range at the boom's rod reversals
# (its published Coulomb friction, 15.3 kN, switches within ±5 mm/s); bucket load median
# 150.1 kg (5–95 %: 149.5–150.9). Default sensor model — q NRMSE ≤ 1.3e-3; force NRMSE
# 6.0 / 1.8 / 0.52 % (the noisy rod speed flips the boom's Coulomb friction); 150.6 kg
# (147.9–152.2).
FREE_AIR_BOUNDS = {
    "ideal": (2e-4, [0.03, 0.015, 0.005], 2.0),
    "default": (3e-3, [0.12, 0.04, 0.012], 5.0),
}


@pytest.mark.timeout(300)
@pytest.mark.parametrize("sensors", ["ideal", "default"])
def test_free_air_replay_positions_forces_and_bucket_load(machine: Machine,
                                                         sensors: str) -> None:
    model = SensorModel.ideal() if sensors == "ideal" else SensorModel()
    rec = simulate(machine, load_scenario("free-air", machine=machine.name), seed=1,
                   sensors=model)
    res = replay(rec.samples, machine, grid_hz=100.0)
    tr = rec.truth
    ti = np.searchsorted(tr.t_s, res.t_s - 1e-9)
    inner = (res.t_s > 0.5) & (res.t_s < res.t_s[-1] - 0.5)
    q_bound, force_bound, payload_bound = FREE_AIR_BOUNDS[sensors]
    assert np.all(nrmse(res.q[inner], tr.q[ti][inner]) < q_bound)
    assert np.all(nrmse(res.cyl_force[inner], tr.cyl_force[ti][inner]) < force_bound)
    # the 150 kg bucket load, estimated by the twin's payload regression
    assert np.nanmedian(res.payload_kg[inner]) == pytest.approx(150.0, abs=payload_bound)


POSE = (0.0, 0.294398, -0.918903, 0.026456)    # rods at 0.45, 0.15, 0.10 m


def _pressures(machine: Machine, sc: Scenario, factor_a: list[float]) -> SimOptions:
    prep = prepare(machine)
    lay = prep.layout
    x0 = initial_state(prep, sc, SimOptions())
    pa = x0[lay.x_pa:lay.x_pa + lay.nc] * np.asarray(factor_a)
    pb = x0[lay.x_pb:lay.x_pb + lay.nc]
    return SimOptions(initial_pressures_pa=(tuple(pa), tuple(pb)))


def test_static_holding_pressures_balance_gravity(machine: Machine) -> None:
    sc = Scenario(name="hold", duration_s=6.0, initial=InitialState(q=POSE, payload_kg=150.0))
    opts = _pressures(machine, sc, [1.02, 0.97, 1.05])   # off equilibrium, valves closed
    tr = simulate(machine, sc, options=opts, sensors=SensorModel.ideal(), wrenches=False).truth
    late = tr.t_s > 4.5
    a1 = np.array([c.area_a_m2 for c in machine.cylinders])
    a2 = np.array([c.area_b_m2 for c in machine.cylinders])
    f_hyd = (tr.p_a[late] * a1 - tr.p_b[late] * a2).mean(axis=0)
    q_end = tr.q[late].mean(axis=0)[None, :]
    g = gravity_torques(machine, q_end, 150.0)
    _, dsdq = cylinder_kinematics(machine, q_end)
    f_static = g[0, 1:] / dsdq[0]
    coulomb = np.array([c.friction.coulomb for c in machine.cylinders])
    assert np.all(np.abs(f_hyd - f_static) <= coulomb), (f_hyd, f_static)


def test_energy_is_conserved_without_losses(machine: Machine) -> None:
    # friction, valves and relief/leakage off; swinging, and the arm ringing on its oil springs
    sc = Scenario(name="energy", duration_s=4.0,
                  initial=InitialState(q=POSE, qd=(0.3, 0.0, 0.0, 0.0), payload_kg=150.0))
    base = _pressures(machine, sc, [1.1, 0.9, 1.2])
    opts = SimOptions(scheme="rk4", friction=False, valves=False, hydraulic_losses=False,
                      initial_pressures_pa=base.initial_pressures_pa)
    rec = simulate(machine, sc, options=opts, sensors=SensorModel.ideal(), wrenches=False)
    e = energy_terms(machine, rec.truth, opts.hydraulics)
    swing = max(np.ptp(e["kinetic"]), np.ptp(e["gravity"]))
    drift = np.abs(e["total"] - e["total"][0]).max()
    assert swing > 20.0
    assert drift <= 1e-4 * swing
