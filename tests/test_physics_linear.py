"""Linkage kind "linear" (a telescope: s = s0 + q along a prismatic joint): kinematics, the
joint force against Pinocchio, validation with field paths, and a simulate → replay round trip
on the test machine ``tests/data/telescope655.toml``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from cranetwin.errors import MachineFileError
from cranetwin.model import LinearActuator, Machine, load_machine, machine_from_dict
from cranetwin.physics import (
    actuator_torques,
    cylinder_forces_from_torques,
    cylinder_kinematics,
    inverse_dynamics,
    joints_from_cylinders,
    linkage,
    moment_arm_rates,
    reach_problems,
)

TELESCOPE = Path(__file__).parent / "data" / "telescope655.toml"


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load_machine(TELESCOPE)


def _with_s0(machine: Machine, s0: float) -> Machine:
    data: dict[str, Any] = machine.model_dump()
    data["cylinders"][2]["linkage"] = {"kind": "linear", "s0_m": s0}
    return machine_from_dict(data)


def _states(machine: Machine, n: int, seed: int) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    lo = np.array([j.lower for j in machine.joints])
    hi = np.array([j.upper for j in machine.joints])
    return (rng.uniform(lo, hi, size=(n, machine.n_joints)),
            rng.normal(0.0, 0.5, size=(n, machine.n_joints)),
            rng.normal(0.0, 2.0, size=(n, machine.n_joints)))


@pytest.mark.timeout(120)
def test_linear_kind_is_chosen_and_the_file_is_valid(machine: Machine) -> None:
    ext = machine.cylinder("extension")
    assert isinstance(ext.linkage, LinearActuator) and ext.linkage.s0_m == 0.0
    assert linkage.kind_of(machine.joints[3], ext) is linkage.linear
    assert reach_problems(machine) == []


@pytest.mark.timeout(120)
@pytest.mark.parametrize("s0", [0.0, 0.35])
def test_rod_position_is_s0_plus_q_with_unit_arm(machine: Machine, s0: float) -> None:
    m = _with_s0(machine, s0)
    q, _, _ = _states(m, 50, seed=1)
    q[:, 3] = np.linspace(0.0, 1.2 - s0, 50)
    s, arm = cylinder_kinematics(m, q)
    np.testing.assert_allclose(s[:, 2], s0 + q[:, 3], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(arm[:, 2], 1.0)
    np.testing.assert_array_equal(moment_arm_rates(m, q)[:, 2], 0.0)
    back = joints_from_cylinders(m, s, q[:, :1])
    np.testing.assert_allclose(back, q, rtol=0, atol=1e-12)


@pytest.mark.timeout(120)
def test_same_kinematics_as_collinear_pins(machine: Machine) -> None:
    """The built-in crane drives the same telescope by collinear pins (L = 1.5 m + q): an
    independent geometry that must give the same s, arm and joint load."""
    pinned = load_machine("patu655")
    q, _, _ = _states(machine, 200, seed=2)
    s_lin, arm_lin = cylinder_kinematics(machine, q)
    s_pin, arm_pin = cylinder_kinematics(pinned, q)
    np.testing.assert_allclose(s_lin, s_pin, rtol=0, atol=1e-12)
    np.testing.assert_allclose(arm_lin, arm_pin, rtol=0, atol=1e-12)


@pytest.mark.timeout(300)
def test_joint_force_matches_pinocchio_prismatic_joint(machine: Machine) -> None:
    """Pinocchio's RNEA of the same chain (its prismatic joint L) is the independent oracle:
    the twin's inverse dynamics agree with it, and the extension cylinder force that holds the
    telescope is exactly Pinocchio's generalised force on L (moment arm 1)."""
    pin = pytest.importorskip("pinocchio")
    from cranetwin.bench.dynamics import pinocchio_model

    q, qd, qdd = _states(machine, 100, seed=3)
    payload = 250.0
    tau, _ = inverse_dynamics(machine, q, qd, qdd, payload)
    model = pinocchio_model(machine, payload)
    data = model.createData()
    ref = np.array([pin.rnea(model, data, q[k], qd[k], qdd[k]) for k in range(q.shape[0])])
    np.testing.assert_allclose(tau, ref, rtol=1e-9, atol=1e-6)
    force = cylinder_forces_from_torques(machine, q, ref)
    np.testing.assert_allclose(force[:, 2], ref[:, 3], rtol=1e-12, atol=1e-9)
    back = actuator_torques(machine, q, force, ref[:, :1])
    np.testing.assert_allclose(back[:, 3], ref[:, 3], rtol=1e-12, atol=1e-9)
    # by hand, at rest with the telescope horizontal (boom and jib angles 0 rad): no axial
    # gravity component, so no holding force
    still = np.zeros((1, 4))
    flat = pin.rnea(model, data, still[0], still[0], still[0])
    f = cylinder_forces_from_torques(machine, still, flat[None, :])
    assert abs(float(f[0, 2])) < 1e-9


@pytest.mark.timeout(120)
def test_linear_on_a_revolute_joint_is_reported_with_its_path(machine: Machine) -> None:
    data: dict[str, Any] = machine.model_dump()
    data["cylinders"][0]["linkage"] = {"kind": "linear", "s0_m": 0.1}
    m = machine_from_dict(data)
    problems = reach_problems(m)
    assert any(p.startswith("cylinders.0.linkage:") and "prismatic joint" in p
               for p in problems), problems


@pytest.mark.timeout(120)
def test_unknown_linkage_kind_and_bad_field_name_their_paths(machine: Machine) -> None:
    data: dict[str, Any] = machine.model_dump()
    data["cylinders"][2]["linkage"] = {"kind": "telescope", "s0_m": 0.0}
    with pytest.raises(MachineFileError) as e1:
        machine_from_dict(data)
    assert any(p.startswith("cylinders.2.linkage") and "four_bar" in p and "linear" in p
               for p in e1.value.problems), e1.value.problems
    data["cylinders"][2]["linkage"] = {"kind": "linear", "s0_m": "far"}
    with pytest.raises(MachineFileError) as e2:
        machine_from_dict(data)
    assert any(p.startswith("cylinders.2.linkage.linear.s0_m") for p in e2.value.problems), \
        e2.value.problems


@pytest.mark.timeout(120)
def test_rod_outside_stroke_over_the_joint_range_is_reported(machine: Machine) -> None:
    problems = reach_problems(_with_s0(machine, 0.5))  # s runs 0.5 … 1.7 m, stroke 1.2 m
    assert any(p.startswith("cylinders.2.linkage:") and "needs 1.5 … 2.7 m" in p
               for p in problems), problems
    assert reach_problems(_with_s0(machine, 0.0)) == []


@pytest.mark.timeout(600)
def test_simulate_then_replay_recovers_the_telescope(machine: Machine) -> None:
    from cranetwin.sim import builtin_scenario, simulate
    from cranetwin.twin import replay

    rec = simulate(machine, builtin_scenario("random", duration_s=8.0), wrenches=False)
    res = replay(rec.samples, machine, grid_hz=100.0)
    tr = rec.truth
    t = res.t_s
    inner = (t > t[0] + 0.5) & (t < t[-1] - 0.5)
    q_true = np.interp(t, tr.t_s, tr.q[:, 3])
    f_true = np.interp(t, tr.t_s, tr.cyl_force[:, 2])
    assert float(np.ptp(q_true)) > 0.2  # the scenario moves the telescope (0.43 m)
    # measured: 0.45 mm and 1.8 % (27 N rms of 1534 N)
    assert float(np.max(np.abs(res.q[inner, 3] - q_true[inner]))) < 2e-3
    # the twin's force on L is the cylinder force itself (moment arm 1)
    np.testing.assert_allclose(res.actuator_torque[:, 3], res.cyl_force[:, 2], rtol=1e-12)
    scale = max(1.0, float(np.max(np.abs(f_true[inner]))))
    rms = float(np.sqrt(np.mean((res.cyl_force[inner, 2] - f_true[inner]) ** 2)))
    assert rms / scale < 0.05


@pytest.mark.timeout(120)
def test_every_kind_is_dispatched(machine: Machine) -> None:
    """Each kind in the registry reaches its own module through the compiled dispatchers (a
    kind added to KINDS without its dispatch branches returns NaN here)."""
    from cranetwin.physics.chain import compile_chain
    from cranetwin.physics.layout import C_JOINT, C_KIND, cyl_block

    modules = {k.KIND: k for k in linkage.KINDS}
    seen = set()
    for m in (machine, load_machine("patu655"), load_machine("bobcat435")):
        p = compile_chain(m)
        for k in range(p.n_cylinders):
            o = cyl_block(k)
            mod = modules[int(p.cyl[o + C_KIND])]
            seen.add(mod)
            joint = m.joints[int(p.cyl[o + C_JOINT])]
            for q in np.linspace(joint.lower, joint.upper, 7):
                got = linkage.state(p.cyl, o, float(q))
                assert np.all(np.isfinite(got)) and got == mod.state(p.cyl, o, float(q))
                s = got[0]
                assert linkage.inverse(p.cyl, o, s) == mod.inverse(p.cyl, o, s)
                assert linkage.motion(p.cyl, o, s) == mod.motion(p.cyl, o, s)
    assert seen == set(linkage.KINDS)
