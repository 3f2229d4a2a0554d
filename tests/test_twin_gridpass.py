"""The replay's grid stage against the separate physics functions.

`cranetwin.twin.gridpass` computes kinematics (through the tables of `cranetwin.twin.kintable`),
Eq. 1–2, inverse dynamics with the machine's batch kernels, the Eq. 3/4 acceleration correction
and the wrenches. Here every output is recomputed from the replay's
own inputs (rod positions, velocities, pressures, payload) through the public vectorised
physics API, which the physics tests check against Pinocchio.
"""

from __future__ import annotations

import importlib

import numpy as np
import pytest

from cranetwin import physics
from cranetwin.model import Machine, load_machine
from cranetwin.physics import codegen
from cranetwin.physics import kernels as K
from cranetwin.physics.chain import compile_chain
from cranetwin.physics.dynamics import batch_kernels
from cranetwin.signal import inject_uniform_noise
from cranetwin.testing.recordings import make
from cranetwin.twin import ReplayOptions, TwinResult, gridpass, kintable, replay


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load_machine("patu655")


@pytest.fixture(scope="module")
def result(machine: Machine) -> TwinResult:
    syn = make(machine, duration_s=20.0, fine_hz=None, scale=0.6,
               payload=lambda t: 180.0 + 60.0 * np.sin(2 * np.pi * t / 15.0))
    noisy = inject_uniform_noise(syn.samples, machine, 0.01, seed=3)
    return replay(noisy, machine, 1000.0)


def test_kinematics_table_matches_exact_inverse(machine: Machine) -> None:
    p = compile_chain(machine)
    stroke = np.array([c.stroke_m for c in machine.cylinders])
    table = np.empty((len(stroke), kintable.KIN_TABLE_NODES - 1, 6))
    ok = kintable.kinematics_table(p.cyl, stroke, kintable.KIN_TABLE_NODES, table)
    assert ok.all()
    rng = np.random.default_rng(0)
    for k, st in enumerate(stroke):
        s_all = np.concatenate([rng.uniform(0.0, st, 4000), [0.0, st, st / 2048.0]])
        exact = np.array([K.cylinder_motion(p.cyl, k, s) for s in s_all])  # q, s′, s″
        per_m = (kintable.KIN_TABLE_NODES - 1) / st
        tab = np.array([kintable.table_inverse(table, k, per_m, s) for s in s_all])  # q, q′, q″
        np.testing.assert_allclose(tab[:, 0], exact[:, 0], rtol=0, atol=1e-11)  # q [rad or m]
        # the inverse map's derivatives: q′ = 1/s′, q″ = −s″/s′³
        np.testing.assert_allclose(1.0 / tab[:, 1], exact[:, 1], rtol=1e-10)  # ds/dq
        q2 = -exact[:, 2] / exact[:, 1] ** 3
        q2_scale = max(float(np.max(np.abs(q2))), 0.1)  # [rad/m² or 1/m]
        np.testing.assert_allclose(tab[:, 2], q2, rtol=0, atol=1e-7 * q2_scale)
        # the fallback gives the same numbers from the exact inverse
        no = np.zeros(len(stroke), dtype=bool)
        fb = np.array([kintable.inverse_motion(table, no, p.cyl, k, per_m, s) for s in s_all])
        np.testing.assert_allclose(fb[:, 1], 1.0 / exact[:, 1], rtol=1e-14)
        np.testing.assert_allclose(fb[:, 2], q2, rtol=1e-13, atol=1e-15 * q2_scale)


def test_fused_pass_agrees_with_separate_physics(machine: Machine, result: TwinResult) -> None:
    res = result
    # kinematics: q from the (clipped) rod positions, qd/qdd by the chain rule
    q_other = res.q[:, [0]]  # slew angle (integrated from the torque here)
    q, qd, _ = physics.joint_motion_from_cylinders(
        machine, res.rod_s, res.rod_v, np.zeros_like(res.rod_v), q_other, res.qd[:, [0]])
    np.testing.assert_allclose(res.q, q, rtol=0, atol=1e-10)
    np.testing.assert_allclose(res.qd, qd, rtol=0, atol=1e-9)
    # Eq. 1–2 and the actuator loads through the moment arms
    f = physics.cylinder_forces(machine, res.p_a, res.p_b, res.rod_v)
    np.testing.assert_allclose(res.cyl_force, f, rtol=1e-12, atol=1e-6)
    tau = physics.actuator_torques(machine, res.q, f)
    cj = [machine.joint_index(c.joint) for c in machine.cylinders]
    np.testing.assert_allclose(res.actuator_torque[:, cj], tau[:, cj], rtol=1e-9, atol=1e-6)
    # inverse dynamics with the estimated payload
    pl = np.nan_to_num(np.maximum(res.payload_kg, 0.0))
    tau_id = physics.joint_torques(machine, res.q, res.qd, res.qdd, pl)
    np.testing.assert_allclose(res.id_torque, tau_id, rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(res.residual, res.actuator_torque - tau_id, rtol=1e-9, atol=1e-6)
    # Eq. 3/4: wrenches at qdd + M_DD(q)⁻¹·r_D with the exact M at every instant (the pass
    # interpolates M_DD⁻¹ between samples: agreement to ~1e-5 of the wrench scale)
    known = np.ones(machine.n_joints, dtype=bool)
    stroke = np.array([c.stroke_m for c in machine.cylinders])
    stop = (res.rod_s <= 0.002) | (res.rod_s >= stroke - 0.002)
    r_use = res.residual.copy()
    r_use[:, cj] = np.where(stop, np.nan, r_use[:, cj])
    dqdd = physics.acceleration_correction(machine, res.q, r_use, pl, known)
    dqdd[res.gap] = 0.0
    _, wrench = physics.inverse_dynamics(machine, res.q, res.qd, res.qdd + dqdd, pl)
    scale = np.max(np.abs(wrench), axis=0)
    err = np.max(np.abs(res.joint_wrench - wrench), axis=0)
    assert np.all(err <= 1e-4 * scale + 1e-6), err / np.maximum(scale, 1e-9)
    # and the correction is really applied: the kinematic wrenches differ by far more
    _, w_kin = physics.inverse_dynamics(machine, res.q, res.qd, res.qdd, pl)
    assert np.max(np.abs(w_kin - wrench)) > 100 * np.max(err)


def test_generic_pass_equals_specialised(machine: Machine, monkeypatch: pytest.MonkeyPatch,
                                         result: TwinResult) -> None:
    syn = make(machine, duration_s=6.0, fine_hz=None, scale=0.6, payload=200.0)
    noisy = inject_uniform_noise(syn.samples, machine, 0.01, seed=4)
    from cranetwin.physics import dynamics

    p = compile_chain(machine)
    assert batch_kernels(p).rnea.__module__.startswith("cranetwin_rnea_")  # generated
    spec = replay(noisy, machine, 1000.0)
    monkeypatch.setattr(dynamics, "batch_kernels",
                        lambda params, specialised=True: dynamics.generic_batch_kernels(params))
    monkeypatch.setattr(importlib.import_module("cranetwin.twin.plan"), "batch_kernels",
                        dynamics.batch_kernels)
    gen = replay(noisy, machine, 1000.0)
    for name in ("q", "qdd", "cyl_force", "id_torque", "residual", "joint_wrench", "payload_kg"):
        a, b = getattr(spec, name), getattr(gen, name)
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-8 * float(np.max(np.abs(a))),
                                   err_msg=name)


def test_kinematic_option_skips_the_correction(machine: Machine) -> None:
    syn = make(machine, duration_s=6.0, fine_hz=None, scale=0.6, payload=200.0)
    noisy = inject_uniform_noise(syn.samples, machine, 0.01, seed=5)
    res = replay(noisy, machine, 1000.0, payload=200.0,
                 options=ReplayOptions(wrench_acceleration="kinematic"))
    _, w = physics.inverse_dynamics(machine, res.q, res.qd, res.qdd, 200.0)
    np.testing.assert_allclose(res.joint_wrench, w, rtol=1e-9, atol=1e-6)


def test_generated_mass_matrix_and_payload_pass_agree_with_generic(machine: Machine) -> None:
    p = compile_chain(machine)
    rng = np.random.default_rng(7)
    n = 500
    q = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(0.0, 1.2, n),
                         rng.uniform(-2.5, 0.0, n), rng.uniform(0.0, 1.5, n)])
    qd = rng.normal(0, 0.5, (n, 4))
    qdd = rng.normal(0, 2.0, (n, 4))
    pl = rng.uniform(0, 500, n)
    mm = np.empty((n, 4, 4))
    both = [batch_kernels(p), physics.dynamics.generic_batch_kernels(p)]
    for kernels in both:
        kernels.mass_matrix(q, pl, mm)
        np.testing.assert_allclose(mm, physics.mass_matrix(machine, q, pl), rtol=1e-12,
                                   atol=1e-9)
    for fn in (k.rnea_payload for k in both):
        t0 = np.empty((n, 4))
        t1 = np.empty((n, 4))
        fn(q, qd, qdd, t0, t1)
        np.testing.assert_allclose(t0, physics.joint_torques(machine, q, qd, qdd, 0.0),
                                   rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(t1, physics.joint_torques(machine, q, qd, qdd, 1.0),
                                   rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(t1, physics.joint_torques(machine, q, qd, qdd, 1.0),
                                   rtol=1e-12, atol=1e-9)


def test_tracer_folds_axis_rotations_and_shares_common_terms(machine: Machine) -> None:
    chain = compile_chain(machine).chain
    lines, _, _ = codegen.trace_rnea(chain)
    # every PATU 655 axis lies along a frame axis: no 1 − cos terms, and no x + (1 − x)
    assert not any("(1.0) - c" in x for x in lines)
    tr = codegen._Tracer()
    first, taus1, w1 = codegen.trace_rnea(chain, tracer=tr)
    again, taus2, w2 = codegen.trace_rnea(chain, tracer=tr)
    assert first and not again  # the same pass traced twice adds nothing
    assert taus1 == taus2 and w1 == w2
    # a pass differing only in its accelerations shares the velocity terms
    nj = int(chain[0])
    acc, _, _ = codegen.trace_rnea(chain, qdd=[f"a{i}" for i in range(nj)], tracer=tr)
    assert 0 < len(acc) < len(first)


def test_linear_wrench_pass_adds_the_acceleration_part(machine: Machine) -> None:
    """wrench(q, qd, qdd + Δ) = wrench(q, qd, qdd) + wrench(q, 0, Δ) without gravity: what the
    grid stage's linear pass relies on (RNEA is affine in the accelerations), for the
    generated and the generic kernel, on the rows asked for only."""
    rng = np.random.default_rng(3)
    n = 200
    q = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(0.0, 1.2, n),
                         rng.uniform(-2.5, 0.0, n), rng.uniform(0.0, 1.5, n)])
    qd, qdd, dq = (rng.normal(0, 1.0, (n, 4)) for _ in range(3))
    _, w_full = physics.inverse_dynamics(machine, q, qd, qdd + dq, 300.0)
    _, w0 = physics.inverse_dynamics(machine, q, qd, qdd, 300.0)
    p = compile_chain(machine)
    rows = np.ones(n, dtype=bool)
    rows[::7] = False
    for kernels in (batch_kernels(p), physics.dynamics.generic_batch_kernels(p)):
        wl = w0.copy()
        kernels.rnea_lin(q, dq, np.full(n, 300.0), rows, wl)
        np.testing.assert_allclose(wl[rows], w_full[rows], rtol=1e-12, atol=1e-8)
        np.testing.assert_array_equal(wl[~rows], w0[~rows])


def test_dd_inverse_batch_inverts_the_measured_block() -> None:
    rng = np.random.default_rng(11)
    n = 300
    a = rng.normal(size=(n, 4, 4))
    mm = a @ a.transpose(0, 2, 1) + 0.5 * np.eye(4)
    mm[7, 1, 1] = -1.0  # not positive definite in the block
    mm[9, 2, 0] = mm[9, 0, 2] = np.nan
    full = np.array([0, 1, 2])  # joint 3 not measured
    minv = np.empty((n, 3, 3))
    ok = np.empty(n, dtype=bool)
    gridpass.dd_inverse_batch(mm, full, minv, ok)
    good = np.ones(n, dtype=bool)
    good[[7, 9]] = False
    np.testing.assert_array_equal(ok, good)
    block = mm[good][:, :3, :3]
    np.testing.assert_allclose(minv[good], np.linalg.inv(block), rtol=1e-10,
                               atol=1e-12 * float(np.abs(np.linalg.inv(block)).max()))
    assert np.all(minv[~good] == 0.0)
