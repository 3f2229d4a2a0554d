"""Cylinder force (Eq. 1–2) and actuator torques (virtual work)."""

from __future__ import annotations

import numpy as np
import pytest

from cranetwin.model import Machine, load_machine
from cranetwin.physics import (
    actuator,
    actuator_torques,
    cylinder_force,
    cylinder_forces_from_torques,
    cylinder_lengths,
    friction_force,
)


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load_machine("patu655")


def test_cylinder_force_eq1_eq2(machine: Machine) -> None:
    lift = machine.cylinder("lift")
    pa = np.array([10e6, 2e6, 0.0])
    pb = np.array([1e6, 8e6, 0.0])
    v = np.array([0.05, -0.02, 0.0])
    a1, a2 = np.pi / 4 * 0.1**2, np.pi / 4 * (0.1**2 - 0.056**2)
    fr = 210.0 * np.tanh(v / 0.005) + 330.0 * v
    np.testing.assert_allclose(cylinder_force(pa, pb, v, lift), pa * a1 - pb * a2 - fr,
                               rtol=1e-14)
    # friction opposes motion, is odd in v, and tends to Fc + b·v at speed
    vv = np.linspace(-1, 1, 201)
    f = friction_force(vv, lift.friction)
    assert np.all(f * vv >= 0)
    np.testing.assert_allclose(f, -friction_force(-vv, lift.friction), atol=1e-12)
    assert abs(friction_force(0.5, lift.friction) - (210.0 + 165.0)) < 1e-6
    # the scalar form every compiled loop inlines is the one the array forms evaluate
    assert actuator.eq1_cylinder_force(10e6, 1e6, 0.05, a1, a2, 210.0, 0.005, 330.0) == (
        float(cylinder_force(10e6, 1e6, 0.05, lift)))


def test_actuator_torques_obey_virtual_work(machine: Machine) -> None:
    rng = np.random.default_rng(5)
    q = np.column_stack([rng.uniform(-1, 1, 20), rng.uniform(0.0, 1.2, 20),
                         rng.uniform(-2.5, -0.3, 20), rng.uniform(0.1, 1.0, 20)])
    f = rng.uniform(-5e4, 5e4, (20, 3))
    drive = rng.uniform(-5e3, 5e3, (20, 1))
    tau = actuator_torques(machine, q, f, drive)
    np.testing.assert_allclose(tau[:, 0], drive[:, 0])
    # tau · dq = F · ds for a small virtual displacement
    dq = rng.normal(0, 1e-6, q.shape)
    ds = cylinder_lengths(machine, q + dq) - cylinder_lengths(machine, q - dq)
    work_joints = np.sum(tau[:, 1:] * 2 * dq[:, 1:], axis=1)
    np.testing.assert_allclose(work_joints, np.sum(f * ds, axis=1), rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(cylinder_forces_from_torques(machine, q, tau), f, rtol=1e-12)


def test_actuator_inputs_of_wrong_shape_raise_physics_error(machine: Machine) -> None:
    from cranetwin.errors import PhysicsError

    q = np.zeros((5, 4))
    with pytest.raises(PhysicsError, match=r"cylinder_forces: expected shape \(5, 3\)"):
        actuator_torques(machine, q, np.zeros((5, 2)))
    with pytest.raises(PhysicsError, match=r"drive_torques: expected shape \(5, 1\)"):
        actuator_torques(machine, q, np.zeros((5, 3)), np.zeros((4,)))
    np.testing.assert_array_equal(actuator_torques(machine, q, np.zeros((5, 3)), np.ones(5))[:, 0],
                                  np.ones(5))
