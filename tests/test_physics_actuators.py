"""Cylinder force (Eq. 1–2), actuator torques (virtual work) and hydraulic equations."""

from __future__ import annotations

import numpy as np
import pytest

from cranetwin.model import Machine, load_machine
from cranetwin.physics import (
    actuator_torques,
    chamber_volumes,
    cylinder_force,
    cylinder_forces_from_torques,
    cylinder_lengths,
    friction_force,
    orifice_flow,
    pressure_rates,
    valve_flows,
)
from cranetwin.physics import hydraulics as H


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
    # the numba twin is the same code
    assert H.cylinder_force_nb(10e6, 1e6, 0.05, a1, a2, 210.0, 0.005, 330.0) == pytest.approx(
        float(cylinder_force(10e6, 1e6, 0.05, lift)), rel=1e-14)


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


def test_orifice_and_valve_flows() -> None:
    qn = 2.16e-8
    assert orifice_flow(qn, 10.0, 3.5e6) == pytest.approx(qn * 10 * np.sqrt(3.5e6))
    assert orifice_flow(qn, 10.0, -3.5e6) == pytest.approx(-qn * 10 * np.sqrt(3.5e6))
    assert orifice_flow(qn, 0.0, 3.5e6) == 0.0
    # ≈ 24 L/min at 35 bar and 10 V for the lift valve (reference)
    assert orifice_flow(qn, 10.0, 35e5) * 60e3 == pytest.approx(24.0, rel=0.03)
    qa, qb = valve_flows(qn, 5.0, 5e6, 2e6, 16e6, 1e5)
    assert qa == pytest.approx(qn * 5 * np.sqrt(11e6))
    assert qb == pytest.approx(qn * 5 * np.sqrt(1.9e6))
    qa, qb = valve_flows(qn, -5.0, 5e6, 2e6, 16e6, 1e5)
    assert qa == pytest.approx(-qn * 5 * np.sqrt(4.9e6))
    assert qb == pytest.approx(-qn * 5 * np.sqrt(14e6))
    for u in (5.0, -5.0):
        np.testing.assert_allclose(H.valve_flows_nb(qn, u, 5e6, 2e6, 16e6, 1e5),
                                   valve_flows(qn, u, 5e6, 2e6, 16e6, 1e5), rtol=1e-15)


def test_pressure_rates_conserve_oil_volume(machine: Machine) -> None:
    hyd = machine.hydraulics
    assert hyd is not None
    lift = machine.cylinder("lift")
    be, vd, a1, a2, st = (hyd.effective_bulk_modulus_pa, hyd.dead_volume_m3, lift.area_a_m2,
                          lift.area_b_m2, lift.stroke_m)
    va, vb = chamber_volumes(vd, a1, a2, st, 0.2)
    assert va == pytest.approx(vd + a1 * 0.2) and vb == pytest.approx(vd + a2 * (st - 0.2))
    # closed valve, rod extending: A expands (pressure falls), B compresses (pressure rises)
    dpa, dpb = pressure_rates(be, vd, a1, a2, st, 0.2, 0.1, 0.0, 0.0)
    assert dpa == pytest.approx(-be / va * a1 * 0.1) and dpb == pytest.approx(be / vb * a2 * 0.1)
    # flow exactly matching the rod motion keeps both pressures constant
    dpa, dpb = pressure_rates(be, vd, a1, a2, st, 0.2, 0.1, a1 * 0.1, a2 * 0.1)
    assert dpa == 0.0 and dpb == 0.0
    np.testing.assert_allclose(H.pressure_rates_nb(be, vd, a1, a2, st, 0.2, 0.1, 1e-4, 2e-4),
                               pressure_rates(be, vd, a1, a2, st, 0.2, 0.1, 1e-4, 2e-4),
                               rtol=1e-15)


def test_actuator_inputs_of_wrong_shape_raise_physics_error(machine: Machine) -> None:
    from cranetwin.errors import PhysicsError

    q = np.zeros((5, 4))
    with pytest.raises(PhysicsError, match=r"cylinder_forces: expected shape \(5, 3\)"):
        actuator_torques(machine, q, np.zeros((5, 2)))
    with pytest.raises(PhysicsError, match=r"drive_torques: expected shape \(5, 1\)"):
        actuator_torques(machine, q, np.zeros((5, 3)), np.zeros((4,)))
    np.testing.assert_array_equal(actuator_torques(machine, q, np.zeros((5, 3)), np.ones(5))[:, 0],
                                  np.ones(5))
