"""Paper Eq. 1–2, once: the net rod force of a double-acting cylinder with friction.

    Eq. 1   F = pA·A1 − pB·A2 − F_fr(v)
    Eq. 2   F_fr(v) = Fc·tanh(v / vc) + b·v

``eq2_friction`` and ``eq1_cylinder_force`` are the scalar forms, compiled to be inlined into
any ``@njit`` loop (the simulator's integrator, the twin's grid pass, calibration); the array
forms below call them, so every path that computes a cylinder force or a drive's friction
evaluates exactly these two lines. Units: pressures [Pa], areas [m²], velocities [m/s] (or
[rad/s] for a rotary drive's friction), forces [N] (or [N·m]).

With the machine's geometry, the same forces as generalised joint forces by virtual work:
tau_j(k) = F_k·ds_k/dq_j(k) (:func:`actuator_torques`) and back
(:func:`cylinder_forces_from_torques`).

Per-cylinder parameters travel as rows of ``cylinder_params(machine)``, shape (n_cyl, 5),
columns ``A1, A2, FC, VC, B`` (named below).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
from numba import njit

from cranetwin.model import Cylinder, Friction, Machine
from cranetwin.physics.chain import compile_chain
from cranetwin.physics.kinematics import as_columns, as_joint_array, moment_arms

F64 = npt.NDArray[np.float64]

# columns of a cylinder_params row
A1, A2, FC, VC, B = range(5)
N_PARAMS = 5


@njit(cache=True, nogil=True, inline="always")
def eq2_friction(v: float, fc: float, vc: float, b: float) -> float:
    """Eq. 2: F_fr = Fc·tanh(v/vc) + b·v.

    Args:
        v: Rod velocity [m/s] (or joint velocity [rad/s] of a rotary drive).
        fc: Coulomb level Fc [N or N·m].
        vc: Coulomb transition velocity vc [m/s or rad/s], > 0.
        b: Viscous coefficient [N·s/m or N·m·s/rad].

    Returns:
        Friction opposing v [N or N·m].
    """
    return fc * math.tanh(v / vc) + b * v


@njit(cache=True, nogil=True, inline="always")
def eq1_cylinder_force(pa: float, pb: float, v: float, a1: float, a2: float,
                       fc: float, vc: float, b: float) -> float:
    """Eq. 1: F = pA·A1 − pB·A2 − F_fr(v), with F_fr of Eq. 2.

    Args:
        pa, pb: Piston-side and rod-side pressures [Pa].
        v: Rod velocity ds/dt [m/s], > 0 extending.
        a1, a2: Piston and annulus areas [m²].
        fc, vc, b: Friction of Eq. 2.

    Returns:
        Net rod force [N], > 0 pushing (extending).
    """
    return pa * a1 - pb * a2 - eq2_friction(v, fc, vc, b)


@njit(cache=True, nogil=True)
def cylinder_forces_into(pa, pb, v, params, out):  # type: ignore[no-untyped-def]
    """Eq. 1–2 over samples into ``out``.

    Args:
        pa, pb: Chamber pressures, shape (n, n_cyl) [Pa] (any strides).
        v: Rod velocities, shape (n, n_cyl) [m/s].
        params: ``cylinder_params`` rows, shape (n_cyl, 5).
        out: Forces, shape (n, n_cyl) [N].
    """
    for i in range(pa.shape[0]):
        for k in range(params.shape[0]):
            out[i, k] = eq1_cylinder_force(pa[i, k], pb[i, k], v[i, k], params[k, 0],
                                           params[k, 1], params[k, 2], params[k, 3],
                                           params[k, 4])


@njit(cache=True, nogil=True)
def friction_into(v, fc, vc, b, out):  # type: ignore[no-untyped-def]
    """Eq. 2 elementwise over a flat array ``v`` into ``out`` (same shape)."""
    for i in range(v.shape[0]):
        out[i] = eq2_friction(v[i], fc, vc, b)


def cylinder_params(machine: Machine) -> F64:
    """Eq. 1–2 parameters of every cylinder, shape (n_cyl, 5): A1 [m²], A2 [m²], Fc [N],
    vc [m/s], b [N·s/m] (columns ``A1 … B``)."""
    return np.array([[c.area_a_m2, c.area_b_m2, c.friction.coulomb,
                      c.friction.coulomb_velocity, c.friction.viscous]
                     for c in machine.cylinders], dtype=np.float64).reshape(-1, N_PARAMS)


def friction(v: npt.ArrayLike, fc: float, vc: float, b: float) -> F64:
    """Eq. 2 over an array of any shape (see :func:`eq2_friction`)."""
    va = np.ascontiguousarray(v, dtype=np.float64)
    out = np.empty_like(va)
    friction_into(va.reshape(-1), float(fc), float(vc), float(b), out.reshape(-1))
    return out


def cylinder_forces_array(pa: F64, pb: F64, v: F64, params: F64) -> F64:
    """Eq. 1–2 for columns of cylinders: pa, pb, v shape (n, n_cyl), params (n_cyl, 5) ->
    forces (n, n_cyl) [N]."""
    out = np.empty(v.shape)
    cylinder_forces_into(pa, pb, v, params, out)
    return out


def friction_force(v: npt.ArrayLike, friction: Friction) -> F64:
    """Friction of Eq. 2: F_fr = Fc·tanh(v/vc) + b·v.

    Args:
        v: Rod velocity [m/s] (or joint velocity [rad/s] for a torque drive), any shape.
        friction: Fc [N or N·m], vc [m/s or rad/s], b [N·s/m or N·m·s/rad].

    Returns:
        Friction force [N] (or torque [N·m]) opposing v, same shape as v.
    """
    return _friction_array(v, friction.coulomb, friction.coulomb_velocity, friction.viscous)


def cylinder_force(
    pA: npt.ArrayLike, pB: npt.ArrayLike, v: npt.ArrayLike, cylinder: Cylinder
) -> F64:
    """Net rod force of a double-acting cylinder, Eq. 1: F = pA·A1 − pB·A2 − F_fr(v).

    Args:
        pA: Piston-side pressure [Pa], any shape.
        pB: Rod-side pressure [Pa], same shape.
        v: Rod velocity ds/dt [m/s] (> 0 extending), same shape.
        cylinder: The cylinder (areas and friction).

    Returns:
        F [N], > 0 pushing (extending), same shape.
    """
    pa, pb, va = np.broadcast_arrays(np.asarray(pA, dtype=np.float64),
                                     np.asarray(pB, dtype=np.float64),
                                     np.asarray(v, dtype=np.float64))
    params = np.array([[cylinder.area_a_m2, cylinder.area_b_m2, cylinder.friction.coulomb,
                        cylinder.friction.coulomb_velocity, cylinder.friction.viscous]])
    def col(x: F64) -> F64:
        return np.ascontiguousarray(x).reshape(-1, 1)

    return cylinder_forces_array(col(pa), col(pb), col(va), params).reshape(pa.shape)


def cylinder_forces(machine: Machine, pA: npt.ArrayLike, pB: npt.ArrayLike,
                    v: npt.ArrayLike) -> F64:
    """Eq. 1–2 for every cylinder of the machine in one compiled pass.

    Args:
        machine: Machine description (cylinder areas and friction).
        pA, pB: Chamber pressures, shape (n, n_cylinders) [Pa].
        v: Rod velocities, shape (n, n_cylinders) [m/s].

    Returns:
        F, shape (n, n_cylinders) [N], > 0 pushing; as :func:`cylinder_force` per column.
    """
    nc = len(machine.cylinders)
    pa = np.asarray(pA, dtype=np.float64)
    n = pa.shape[0] if pa.ndim == 2 else -1
    pa = as_columns("pA", pa, n, nc)
    pb = as_columns("pB", pB, n, nc)
    va = as_columns("v", v, n, nc)
    return cylinder_forces_array(pa, pb, va, cylinder_params(machine))


def actuator_torques(
    machine: Machine,
    q: npt.ArrayLike,
    cylinder_forces: npt.ArrayLike,
    drive_torques: npt.ArrayLike | None = None,
) -> F64:
    """Generalised joint forces of the actuators: tau_j(k) = F_k·ds_k/dq_j(k), plus drive torques.

    Args:
        machine: Machine description.
        q: Joint positions, shape (n, n_joints) [rad or m].
        cylinder_forces: Rod forces, shape (n, n_cylinders) [N].
        drive_torques: Torques of ``machine.torque_drives`` at their joints, shape
            (n, n_drives) [N·m]; zero when omitted.

    Returns:
        tau, shape (n, n_joints) [N·m or N].
    """
    qa = as_joint_array(machine, q)
    p = compile_chain(machine)
    n = qa.shape[0]
    f = as_columns("cylinder_forces", cylinder_forces, n, p.n_cylinders)
    tau = np.zeros((n, p.n_joints))
    tau[:, p.cylinder_joint] += f * moment_arms(machine, qa)
    if drive_torques is not None:
        d = as_columns("drive_torques", drive_torques, n, len(machine.torque_drives))
        for i, drive in enumerate(machine.torque_drives):
            tau[:, machine.joint_index(drive.joint)] += d[:, i]
    return tau


def cylinder_forces_from_torques(machine: Machine, q: npt.ArrayLike, tau: npt.ArrayLike) -> F64:
    """Rod forces that produce the joint torques ``tau`` (n, n_joints): F_k = tau_j(k)/(ds/dq).

    Returns:
        F, shape (n, n_cylinders) [N]; inf/NaN where a moment arm is zero (dead centre).
    """
    qa = as_joint_array(machine, q)
    ta = as_joint_array(machine, tau, "tau")
    p = compile_chain(machine)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.asarray(ta[:, p.cylinder_joint] / moment_arms(machine, qa), dtype=np.float64)


_friction_array = friction
