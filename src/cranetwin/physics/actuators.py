"""Actuator forces: cylinder force with friction (paper Eq. 1–2) and the joint torques they
produce through the moment arms (virtual work)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from cranetwin.model import Cylinder, Friction, Machine
from cranetwin.physics import actuator
from cranetwin.physics.chain import compile_chain
from cranetwin.physics.kinematics import as_columns, as_joint_array, moment_arms

F64 = npt.NDArray[np.float64]


def friction_force(v: npt.ArrayLike, friction: Friction) -> F64:
    """Friction of Eq. 2: F_fr = Fc·tanh(v/vc) + b·v.

    Args:
        v: Rod velocity [m/s] (or joint velocity [rad/s] for a torque drive), any shape.
        friction: Fc [N or N·m], vc [m/s or rad/s], b [N·s/m or N·m·s/rad].

    Returns:
        Friction force [N] (or torque [N·m]) opposing v, same shape as v.
    """
    return actuator.friction(v, friction.coulomb, friction.coulomb_velocity, friction.viscous)


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

    return actuator.cylinder_forces_array(col(pa), col(pb), col(va), params).reshape(pa.shape)


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
    return actuator.cylinder_forces_array(pa, pb, va, actuator.cylinder_params(machine))


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
