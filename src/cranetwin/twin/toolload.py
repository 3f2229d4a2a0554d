"""Tool load: the external force on the tool that the joint-load residual implies.

The paper's model (Eq. 3–4) has no external force: the twin's residual
``r = actuator_torque − id_torque`` (shape (n, n_joints)) is the generalised force the
pressures imply beyond gravity, inertia and the payload model. If the only thing the model
misses is a force F [N] acting on the tool at the load point p (a bucket tip in the soil),
the dynamics read M·q̈ + h = τ_act + J_p(q)ᵀ·F, hence

    J_p(q)ᵀ·F = −r,

J_p (3, n_joints) being the load point's translational Jacobian: column i is a_i × (p − o_i)
for a revolute joint (world axis a_i through o_i) and a_i for a prismatic one.

The working arm's joints (those driven by cylinders) all turn about parallel axes, so they only
see F's component in the arm's plane (normal n = their common axis): with plane basis
(e1, e2), the in-plane force f = (f1, f2) solves, in the least-squares sense,

    A·f = −r_arm,   A = [J_pᵀ·e1, J_pᵀ·e2]  (k, 2),  k = number of arm joints,

and F = f1·e1 + f2·e2 (the out-of-plane component is not observable from these joints and is
reported as 0). With k = 3 (boom, arm, bucket) the system is over-determined: the least-squares
misfit tells how well one tip force explains the residual. Where A is near rank-deficient
(the tip on the line through the arm's joints, ``sigma_min`` → 0) the estimate is not defined;
it is NaN below ``min_sigma_m``.

The residual also carries everything else the model misses (friction errors, acceleration
noise from differentiated positions, payload error), so the estimate is only as good as the
residual in the arm's joints: see ``tests/test_excavator.py`` for the measured accuracy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from cranetwin.model import Machine
from cranetwin.physics import body_poses

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class ToolForce:
    """Estimated external force on the tool.

    Attributes:
        force_n: Force on the tool at the load point, world frame, shape (n, 3) [N]; NaN where
            the arm's Jacobian is near singular or the residual is not finite.
        sigma_min_m: Smallest singular value of A (module docstring), shape (n,) [m]: the
            shortest lever of a unit in-plane force about the arm joints.
        misfit: Least-squares residual norm ‖A·f + r_arm‖, shape (n,) [N·m or N]: the part
            of the arm joints' residual that no tip force explains (0 for two arm joints).
        joints: Indices of the arm joints used, shape (k,).
    """

    force_n: F64
    sigma_min_m: F64
    misfit: F64
    joints: npt.NDArray[np.int64]


def load_point_jacobian(machine: Machine, q: npt.ArrayLike) -> tuple[F64, F64]:
    """Translational Jacobian of the load point and its world position.

    Args:
        machine: Machine description.
        q: Joint positions, shape (n, n_joints) [rad or m].

    Returns:
        (J shape (n, 3, n_joints) [m/rad or m/m], p shape (n, 3) [m]); columns of joints
        beyond the load body are 0.
    """
    poses = body_poses(machine, q)
    n, nj = poses.shape[0], machine.n_joints
    lb = [j.child for j in machine.joints].index(machine.load_point.body)
    p = poses[:, lb, :3, :3] @ np.asarray(machine.load_point.point_m) + poses[:, lb, :3, 3]
    jac = np.zeros((n, 3, nj))
    for i, joint in enumerate(machine.joints[:lb + 1]):
        axis = poses[:, i, :3, :3] @ np.asarray(joint.axis, dtype=np.float64)
        if joint.kind == "prismatic":
            jac[:, :, i] = axis
        else:
            jac[:, :, i] = np.cross(axis, p - poses[:, i, :3, 3])
    return jac, p


def arm_joints(machine: Machine) -> npt.NDArray[np.int64]:
    """Joints driven by cylinders up to the load body, in chain order (the working arm)."""
    lb = [j.child for j in machine.joints].index(machine.load_point.body)
    driven = {c.joint for c in machine.cylinders}
    return np.array([i for i, j in enumerate(machine.joints[:lb + 1]) if j.name in driven],
                    dtype=np.int64)


def tool_force(machine: Machine, q: npt.ArrayLike, residual: npt.ArrayLike, *,
               joints: npt.ArrayLike | None = None, min_sigma_m: float = 0.05) -> ToolForce:
    """The tool force at the load point that best explains the arm joints' residual.

    Args:
        machine: Machine description (load point = where the force acts).
        q: Joint positions, shape (n, n_joints) [rad or m].
        residual: Actuator loads − inverse dynamics (``TwinResult.residual``), shape
            (n, n_joints) [N·m or N].
        joints: Joint indices to use (default :func:`arm_joints`); their axes must be parallel
            (revolute) or lie in the plane normal to them (prismatic).
        min_sigma_m: Below this smallest singular value of A [m] the force is NaN.

    Returns:
        :class:`ToolForce`.

    Raises:
        ValueError: fewer than two joints, or no revolute joint among them to define the plane.
    """
    qa = np.asarray(q, dtype=np.float64)
    r = np.asarray(residual, dtype=np.float64)
    idx = arm_joints(machine) if joints is None else np.asarray(joints, dtype=np.int64)
    if idx.shape[0] < 2:
        raise ValueError(f"need at least two arm joints to resolve an in-plane force, got {idx}")
    revolute = [int(i) for i in idx if machine.joints[int(i)].kind == "revolute"]
    if not revolute:
        raise ValueError("no revolute joint among the arm joints to define the arm's plane")
    jac, _ = load_point_jacobian(machine, qa)
    poses = body_poses(machine, qa)
    normal = poses[:, revolute[0], :3, :3] @ np.asarray(machine.joints[revolute[0]].axis)
    e1, e2 = _plane_basis(normal)
    jt = np.transpose(jac[:, :, idx], (0, 2, 1))               # (n, k, 3) = J_armᵀ
    a = np.stack([np.einsum("nkc,nc->nk", jt, e1), np.einsum("nkc,nc->nk", jt, e2)], axis=2)
    b = -r[:, idx]
    u, sv, vt = np.linalg.svd(a, full_matrices=False)          # a (n, k, 2)
    sigma_min = sv[:, -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        f2 = np.einsum("nji,nj->ni", vt, np.einsum("nkj,nk->nj", u, b) / sv)
    misfit = np.linalg.norm(np.einsum("nkj,nj->nk", a, f2) - b, axis=1)
    force = f2[:, :1] * e1 + f2[:, 1:] * e2
    bad = (sigma_min < min_sigma_m) | ~np.all(np.isfinite(b), axis=1)
    force[bad] = np.nan
    return ToolForce(force_n=force, sigma_min_m=sigma_min, misfit=misfit, joints=idx)


def _plane_basis(normal: F64) -> tuple[F64, F64]:
    """Per-sample unit vectors (e1, e2), each (n, 3), spanning the plane normal to ``normal``
    (n, 3): e1 = the horizontal direction in the plane when gravity is along z (the arm's
    reach), e2 = normal × e1."""
    nrm = normal / np.linalg.norm(normal, axis=1, keepdims=True)
    trial = np.where(np.abs(nrm[:, 2:3]) < 0.9, np.array([[0.0, 0.0, 1.0]]),
                     np.array([[1.0, 0.0, 0.0]]))
    e2 = trial - nrm * np.sum(nrm * trial, axis=1, keepdims=True)
    e2 /= np.linalg.norm(e2, axis=1, keepdims=True)
    e1 = np.cross(e2, nrm)
    return e1, e2
