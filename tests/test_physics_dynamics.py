"""Inverse dynamics, mass matrix and bias forces: Pinocchio agreement and mechanical laws."""

from __future__ import annotations

import numpy as np
import pytest

from cranetwin.model import Machine, load_machine
from cranetwin.physics import (
    bias_forces,
    body_poses,
    forward_dynamics,
    gravity_torques,
    inverse_dynamics,
    joint_torques,
    mass_matrix,
)

pin = pytest.importorskip("pinocchio")

# the same independent Pinocchio chain the benchmark compares against
from cranetwin.bench.dynamics import pinocchio_model  # noqa: E402


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load_machine("patu655")


def random_states(machine: Machine, n: int, seed: int) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    lo = np.array([j.lower for j in machine.joints])
    hi = np.array([j.upper for j in machine.joints])
    q = rng.uniform(lo, hi, size=(n, machine.n_joints))
    qd = rng.normal(0.0, 1.0, size=(n, machine.n_joints))
    qdd = rng.normal(0.0, 3.0, size=(n, machine.n_joints))
    return q, qd, qdd


def rel_err(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a - b)) / max(1.0, float(np.max(np.abs(b)))))


@pytest.mark.parametrize("payload", [0.0, 480.0])
def test_inverse_dynamics_matches_pinocchio(machine: Machine, payload: float) -> None:
    q, qd, qdd = random_states(machine, 200, seed=int(payload) + 1)
    tau, wrench = inverse_dynamics(machine, q, qd, qdd, payload)
    model = pinocchio_model(machine, payload)
    data = model.createData()
    for k in range(q.shape[0]):
        ref = pin.rnea(model, data, q[k], qd[k], qdd[k])
        assert rel_err(tau[k], ref) <= 1e-9
        ref_w = np.array([data.f[i + 1].vector for i in range(machine.n_joints)])
        assert rel_err(wrench[k], ref_w) <= 1e-9


def test_time_varying_payload_matches_per_sample(machine: Machine) -> None:
    q, qd, qdd = random_states(machine, 50, seed=7)
    payload = np.linspace(0.0, 500.0, 50)
    tau, wrench = inverse_dynamics(machine, q, qd, qdd, payload)
    for k in (0, 17, 49):
        t1, w1 = inverse_dynamics(machine, q[k], qd[k], qdd[k], float(payload[k]))
        np.testing.assert_allclose(tau[k], t1[0], rtol=0, atol=1e-9)
        np.testing.assert_allclose(wrench[k], w1[0], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(joint_torques(machine, q, qd, qdd, payload), tau)


def test_mass_matrix_symmetric_positive_definite_and_consistent(machine: Machine) -> None:
    q, qd, qdd = random_states(machine, 100, seed=3)
    m = mass_matrix(machine, q, 300.0)
    np.testing.assert_allclose(m, np.swapaxes(m, 1, 2), rtol=0, atol=1e-9)
    assert np.all(np.linalg.eigvalsh(m) > 0)
    b = bias_forces(machine, q, qd, 300.0)
    tau, _ = inverse_dynamics(machine, q, qd, qdd, 300.0)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", m, qdd) + b, tau, rtol=1e-10, atol=1e-8)
    np.testing.assert_allclose(forward_dynamics(machine, q, qd, tau, 300.0), qdd, atol=1e-8)
    model = pinocchio_model(machine, 300.0)
    data = model.createData()
    for k in range(5):
        ref = pin.crba(model, data, q[k])
        ref = np.triu(ref) + np.triu(ref, 1).T
        assert rel_err(m[k], ref) <= 1e-9


def test_gravity_torques_match_hand_computation(machine: Machine) -> None:
    """Two poses computed by hand from masses, COMs and the chain geometry (boom plane)."""
    g = 9.81
    mp = 250.0
    lift, jib, ext = machine.body("lift_boom"), machine.body("jib_boom"), \
        machine.body("extension_boom")
    tool = machine.load_point.tool_mass_kg
    o2 = np.array([2.881, 0.0216])         # jib joint in the lift-boom frame (x, z)
    o3 = np.array([-0.415, 0.295])         # extension joint in the jib frame
    tip = np.array([2.49, 0.0])            # load point in the extension frame

    def rot(a: float) -> np.ndarray:
        return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])

    for th1, th2, ext_l in ((0.0, 0.0, 0.0), (0.5, -1.2, 0.7)):
        r1 = rot(th1)
        r2 = r1 @ rot(th2)
        p2 = r1 @ o2                                   # jib joint, relative to the lift joint
        p3 = p2 + r2 @ o3                              # extension joint
        c_lift = r1 @ np.array([lift.com_m[0], lift.com_m[2]])
        c_jib = p2 + r2 @ np.array([jib.com_m[0], jib.com_m[2]])
        c_ext = p3 + r2 @ (np.array([ext.com_m[0], ext.com_m[2]]) + [ext_l, 0.0])
        c_tip = p3 + r2 @ (tip + [ext_l, 0.0])
        # torque the actuator supplies about -y (raising positive) = sum m g x (lever arm)
        t1 = g * (lift.mass_kg * c_lift[0] + jib.mass_kg * c_jib[0] + ext.mass_kg * c_ext[0]
                  + (tool + mp) * c_tip[0])
        t2 = g * (jib.mass_kg * (c_jib - p2)[0] + ext.mass_kg * (c_ext - p2)[0]
                  + (tool + mp) * (c_tip - p2)[0])
        t3 = g * (ext.mass_kg + tool + mp) * np.sin(th1 + th2)   # along the telescope axis
        tau = gravity_torques(machine, [0.3, th1, th2, ext_l], mp)[0]
        np.testing.assert_allclose(tau, [0.0, t1, t2, t3], rtol=1e-12, atol=1e-9)


def test_power_balance_along_smooth_trajectory(machine: Machine) -> None:
    """sum(tau·qd) = d(T + V)/dt with T = qd·M·qd/2 and V from the body COM heights."""
    mp = 300.0
    t = np.linspace(0.0, 2.0, 4001)
    dt = t[1] - t[0]
    w = np.array([1.3, 2.1, 1.7, 2.9])
    amp = np.array([0.8, 0.4, 0.6, 0.3])
    mid = np.array([0.0, 0.4, -1.2, 0.5])
    q = mid + amp * np.sin(np.outer(t, w))
    qd = amp * w * np.cos(np.outer(t, w))
    qdd = -amp * w**2 * np.sin(np.outer(t, w))
    tau, _ = inverse_dynamics(machine, q, qd, qdd, mp)
    power = np.sum(tau * qd, axis=1)
    kinetic = 0.5 * np.einsum("ni,nij,nj->n", qd, mass_matrix(machine, q, mp), qd)
    poses = body_poses(machine, q)
    grav = np.asarray(machine.machine.gravity_mps2)
    potential = np.zeros(len(t))
    for i, body in enumerate(machine.chain_bodies()):
        com = poses[:, i, :3, :3] @ np.asarray(body.com_m) + poses[:, i, :3, 3]
        potential -= body.mass_kg * com @ grav
    lb = [j.child for j in machine.joints].index(machine.load_point.body)
    tip = poses[:, lb, :3, :3] @ np.asarray(machine.load_point.point_m) + poses[:, lb, :3, 3]
    potential -= (machine.load_point.tool_mass_kg + mp) * tip @ grav
    energy = kinetic + potential
    d_energy = (energy[2:] - energy[:-2]) / (2 * dt)     # central difference, O(dt²)
    scale = float(np.max(np.abs(power)))
    assert scale > 1e3
    assert float(np.max(np.abs(d_energy - power[1:-1]))) <= 1e-5 * scale


def test_bad_shapes_raise_physics_error(machine: Machine) -> None:
    from cranetwin.errors import PhysicsError

    with pytest.raises(PhysicsError, match="expected shape"):
        inverse_dynamics(machine, np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3)))
    with pytest.raises(PhysicsError, match="shapes differ"):
        inverse_dynamics(machine, np.zeros((3, 4)), np.zeros((2, 4)), np.zeros((3, 4)))
    with pytest.raises(PhysicsError, match="payload_kg"):
        inverse_dynamics(machine, np.zeros((3, 4)), np.zeros((3, 4)), np.zeros((3, 4)), -1.0)


def skewed_machine() -> Machine:
    """PATU 655 with tilted joint frames, a tilted axis and full (non-diagonal) inertias."""
    import tomllib
    from importlib import resources

    from cranetwin.model import machine_from_dict

    text = (resources.files("cranetwin") / "machines" / "patu655.toml").read_text("utf-8")
    data = tomllib.loads(text)
    data["machine"]["gravity_mps2"] = [0.3, -0.2, -9.8]
    data["joints"][0]["origin_rpy_rad"] = [0.05, -0.03, 0.2]
    data["joints"][1]["origin_rpy_rad"] = [0.1, 0.0, -0.1]
    data["joints"][3]["axis"] = [0.8, 0.0, 0.6]
    data["joints"][3]["origin_rpy_rad"] = [0.0, 0.2, 0.0]
    for b in data["bodies"]:
        b["com_m"] = [b["com_m"][0], 0.07, b["com_m"][2] + 0.02]
        d = np.diag(np.asarray(b["inertia_kgm2"], dtype=float))
        full = np.diag(d) + 0.1 * min(d) * np.array([[0, 1, 0.5], [1, 0, -0.7], [0.5, -0.7, 0]])
        b["inertia_kgm2"] = full.tolist()
    data["load_point"]["point_m"] = [2.49, 0.05, -0.1]
    return machine_from_dict(data)


def test_specialised_and_generic_kernels_match_pinocchio_on_skewed_chain() -> None:
    from cranetwin.physics import compile_chain
    from cranetwin.physics.dynamics import rnea_kernels

    m = skewed_machine()
    q, qd, qdd = random_states(m, 100, seed=11)
    payload = np.linspace(0.0, 400.0, 100)
    params = compile_chain(m)
    results = []
    for specialised in (True, False):
        tau = np.empty((100, 4))
        wrench = np.empty((100, 4, 6))
        rnea_kernels(params, specialised)[0](q, qd, qdd, payload, tau, wrench)
        results.append((tau, wrench))
    np.testing.assert_allclose(results[0][0], results[1][0], rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(results[0][1], results[1][1], rtol=1e-12, atol=1e-9)
    for k in (0, 33, 99):
        model = pinocchio_model(m, float(payload[k]))
        data = model.createData()
        ref = pin.rnea(model, data, q[k], qd[k], qdd[k])
        ref_w = np.array([data.f[i + 1].vector for i in range(4)])
        for tau, wrench in results:
            assert rel_err(tau[k], ref) <= 1e-9
            assert rel_err(wrench[k], ref_w) <= 1e-9


def test_inverse_dynamics_writes_into_out_buffers(machine: Machine) -> None:
    from cranetwin.errors import PhysicsError

    q, qd, qdd = random_states(machine, 10, seed=2)
    tau, wrench = np.empty((10, 4)), np.empty((10, 4, 6))
    t1, w1 = inverse_dynamics(machine, q, qd, qdd, 100.0, out=(tau, wrench))
    assert t1 is tau and w1 is wrench
    t2, w2 = inverse_dynamics(machine, q, qd, qdd, 100.0)
    np.testing.assert_array_equal(tau, t2)
    np.testing.assert_array_equal(wrench, w2)
    with pytest.raises(PhysicsError, match="out"):
        inverse_dynamics(machine, q, qd, qdd, out=(np.empty((9, 4)), wrench))


def test_crba_matches_rnea_columns_and_pinocchio_on_skewed_chain() -> None:
    from cranetwin.physics import compile_chain
    from cranetwin.physics import kernels as K

    m = skewed_machine()
    params = compile_chain(m)
    q, _, _ = random_states(m, 50, seed=5)
    crba = mass_matrix(m, q, 210.0)
    model = pinocchio_model(m, 210.0)
    data = model.createData()
    cols = np.empty((4, 4))
    for k in range(50):
        K.mass_matrix_rnea(params.chain, q[k], 210.0, cols)
        assert rel_err(crba[k], cols) <= 1e-12
        ref = pin.crba(model, data, q[k])
        assert rel_err(crba[k], np.triu(ref) + np.triu(ref, 1).T) <= 1e-9


def test_bias_and_forward_dynamics_match_pinocchio(machine: Machine) -> None:
    q, qd, qdd = random_states(machine, 30, seed=9)
    tau = np.random.default_rng(9).normal(0.0, 5e3, (30, 4))
    b = bias_forces(machine, q, qd, 150.0)
    acc = forward_dynamics(machine, q, qd, tau, 150.0)
    model = pinocchio_model(machine, 150.0)
    data = model.createData()
    for k in range(30):
        assert rel_err(b[k], pin.nonLinearEffects(model, data, q[k], qd[k])) <= 1e-9
        assert rel_err(acc[k], pin.aba(model, data, q[k], qd[k], tau[k])) <= 1e-9


def test_acceleration_correction_is_forward_dynamics() -> None:
    """qdd + Δ reproduces forward dynamics when every load is known, and with a joint left
    kinematic the corrected motion reproduces the loads of the other joints (Eq. 3/4)."""
    from cranetwin.model import load_machine
    from cranetwin.physics import (
        acceleration_correction,
        forward_dynamics,
        inverse_dynamics,
        joint_torques,
    )

    m = load_machine("patu655")
    rng = np.random.default_rng(7)
    n = 50
    q = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(0.2, 0.8, n),
                         rng.uniform(-2.0, -0.5, n), rng.uniform(0.1, 1.0, n)])
    qd = rng.normal(0, 0.3, (n, 4))
    qdd = rng.normal(0, 0.5, (n, 4))
    pay = rng.uniform(0, 300, n)
    tau = joint_torques(m, q, qd, rng.normal(0, 0.5, (n, 4)), pay)
    tau_id, _ = inverse_dynamics(m, q, qd, qdd, pay)
    full = qdd + acceleration_correction(m, q, tau - tau_id, pay)
    np.testing.assert_allclose(full, forward_dynamics(m, q, qd, tau, pay), rtol=1e-9, atol=1e-9)
    known = np.array([False, True, True, True])
    resid = tau - tau_id
    resid[:, 0] = np.nan  # slew load unknown: must not matter
    part = qdd + acceleration_correction(m, q, resid, pay, known)
    np.testing.assert_array_equal(part[:, 0], qdd[:, 0])
    np.testing.assert_allclose(joint_torques(m, q, qd, part, pay)[:, 1:], tau[:, 1:],
                               rtol=1e-9, atol=1e-6)
