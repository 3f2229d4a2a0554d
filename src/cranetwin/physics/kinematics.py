"""Kinematics vectorised over time: cylinder rod positions <-> joint coordinates, moment arms,
body poses, load point and reach, cylinder pin points, and the kinematic validation of a machine.

All functions take the machine description (data) and arrays shaped (n, ...): ``q`` has shape
(n, n_joints) [rad or m] in the order of ``machine.joints``; a single sample of shape
(n_joints,) is accepted and treated as n = 1. Cylinders are in the order of
``machine.cylinders``; rod position s = pin-to-pin length − closed length [m].

Geometry (see :mod:`cranetwin.model.schema` for frames):

* direct cylinder on a revolute joint — closed-form triangle: with the base pin b (parent) and
  rod pin r (child) in the joint frame, ``|Rot(q)·r − b|² = K0 − 2·rho·cos(q − phi)``, so
  ``ds/dq = rho·sin(q − phi)/length`` and ``q = phi ± acos((K0 − length²)/(2·rho))``;
* direct cylinder on a prismatic joint — ``length² = |d|² + 2(d·e)·q + q²``;
* linear actuator along a prismatic joint (a telescope) — ``s = s0 + q``, moment arm 1;
* four-bar (the jib) — rod end E from the intersection of circle(D, |DE|) and circle(F(q), |EF|)
  on the side ``FourBar.branch`` selects; the inverse intersects circle(C, length) with
  circle(D, |DE|) for E, then circle(O, |OF|) with circle(E, |EF|) for F, on the branches
  that the forward map takes over the joint's range.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from cranetwin.errors import ModelError, PhysicsError
from cranetwin.model import WORLD, FourBar, Machine
from cranetwin.physics import kernels as K
from cranetwin.physics.chain import (
    choose_inverse_branches,
    compile_chain,
    cylinder_geometry,
    joint_frame_point,
    plane_basis,
    rpy_matrix,
)

F64 = npt.NDArray[np.float64]


def as_joint_array(machine: Machine, q: npt.ArrayLike, name: str = "q") -> F64:
    """``q`` as a C-contiguous float64 array of shape (n, n_joints).

    Raises:
        PhysicsError: wrong shape or non-finite values.
    """
    a = np.ascontiguousarray(q, dtype=np.float64)
    nj = machine.n_joints
    if a.ndim == 1:
        a = a.reshape(1, -1)
    if a.ndim != 2 or a.shape[1] != nj:
        raise PhysicsError(f"{name}: expected shape (n, {nj}) or ({nj},), got {np.shape(q)}")
    if not np.all(np.isfinite(a)):
        raise PhysicsError(f"{name}: contains NaN or infinite values")
    return a


def as_columns(name: str, x: npt.ArrayLike, n: int, k: int) -> F64:
    """``x`` as a float64 array of shape (n, k); (n,) is accepted when k = 1.

    Raises:
        PhysicsError: any other shape.
    """
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 1 and k == 1 and a.shape[0] == n:
        a = a.reshape(n, 1)
    if a.shape != (n, k):
        raise PhysicsError(f"{name}: expected shape ({n}, {k}), got {np.shape(x)}")
    return a


def cylinder_lengths(machine: Machine, q: npt.ArrayLike) -> F64:
    """Cylinder rod positions s = pin distance − closed length.

    Args:
        machine: Machine description.
        q: Joint positions, shape (n, n_joints) [rad or m].

    Returns:
        s, shape (n, n_cylinders) [m]; NaN where a linkage cannot assemble.
    """
    s, _ = cylinder_kinematics(machine, q)
    return s


def moment_arms(machine: Machine, q: npt.ArrayLike) -> F64:
    """Analytic moment arms ds_k/dq_j(k) of each cylinder k w.r.t. the joint j(k) it drives.

    Actuator torque or force at that joint is tau = F·ds/dq (virtual work), so the jib
    (ds/dq < 0) has a negative lever.

    Args:
        machine: Machine description.
        q: Joint positions, shape (n, n_joints) [rad or m].

    Returns:
        ds/dq, shape (n, n_cylinders) [m/rad or m/m].
    """
    _, d = cylinder_kinematics(machine, q)
    return d


def cylinder_kinematics(machine: Machine, q: npt.ArrayLike) -> tuple[F64, F64]:
    """Rod positions s and moment arms ds/dq together (one pass), both (n, n_cylinders)."""
    p = compile_chain(machine)
    qa = as_joint_array(machine, q)
    s = np.empty((qa.shape[0], p.n_cylinders))
    d = np.empty_like(s)
    K.cylinder_kinematics_batch(p.cyl, qa, s, d)
    return s, d


def moment_arm_rates(machine: Machine, q: npt.ArrayLike) -> F64:
    """Analytic second derivatives d²s_k/dq_j(k)² (the rate of change of the moment arms).

    Args:
        machine: Machine description.
        q: Joint positions, shape (n, n_joints) [rad or m].

    Returns:
        d²s/dq², shape (n, n_cylinders) [m/rad² or 1/m].
    """
    return _kinematics2(machine, as_joint_array(machine, q))[2]


def _kinematics2(machine: Machine, qa: F64) -> tuple[F64, F64, F64]:
    p = compile_chain(machine)
    shape = (qa.shape[0], p.n_cylinders)
    s, d1, d2 = np.empty(shape), np.empty(shape), np.empty(shape)
    K.cylinder_kinematics2_batch(p.cyl, qa, s, d1, d2)
    return s, d1, d2


def joint_motion_from_cylinders(
    machine: Machine,
    s: npt.ArrayLike,
    v: npt.ArrayLike,
    a: npt.ArrayLike,
    q_other: npt.ArrayLike | None = None,
    qd_other: npt.ArrayLike | None = None,
    qdd_other: npt.ArrayLike | None = None,
) -> tuple[F64, F64, F64]:
    """Joint positions, velocities and accelerations from rod positions, velocities and
    accelerations: qd = v/s', qdd = (a − s''·qd²)/s' (chain rule on s = s(q)).

    Args:
        machine: Machine description.
        s, v, a: Rod positions [m], velocities [m/s], accelerations [m/s²], shape
            (n, n_cylinders).
        q_other, qd_other, qdd_other: The joints no cylinder drives (see
            :func:`joints_from_cylinders`); zeros when omitted.

    Returns:
        (q, qd, qdd), each shape (n, n_joints).

    Raises:
        PhysicsError: as :func:`joints_from_cylinders`, or shapes that differ.
    """
    q, qd, qdd, _ = joint_motion_and_arms(machine, s, v, a, q_other, qd_other, qdd_other)
    return q, qd, qdd


def joint_motion_and_arms(
    machine: Machine,
    s: npt.ArrayLike,
    v: npt.ArrayLike,
    a: npt.ArrayLike,
    q_other: npt.ArrayLike | None = None,
    qd_other: npt.ArrayLike | None = None,
    qdd_other: npt.ArrayLike | None = None,
) -> tuple[F64, F64, F64, F64]:
    """:func:`joint_motion_from_cylinders` plus the moment arms ds/dq, in one fused pass
    (inverse kinematics, s' and s'' and the chain rule per sample, no temporaries).

    Args:
        machine: Machine description.
        s, v, a: Rod positions [m], velocities [m/s], accelerations [m/s²], shape
            (n, n_cylinders).
        q_other, qd_other, qdd_other: The joints no cylinder drives; zeros when omitted.

    Returns:
        (q, qd, qdd), each shape (n, n_joints), and ds/dq, shape (n, n_cylinders) [m/rad or
        m/m] (what :func:`cylinder_kinematics` returns as its second array).

    Raises:
        PhysicsError: as :func:`joints_from_cylinders`, or shapes that differ.
    """
    p = compile_chain(machine)
    sa = np.ascontiguousarray(s, dtype=np.float64)
    if sa.ndim != 2 or sa.shape[1] != p.n_cylinders:
        q = joints_from_cylinders(machine, s, q_other)  # shape handling and its errors
        sa = np.ascontiguousarray(np.reshape(sa, (q.shape[0], p.n_cylinders)))
    n = sa.shape[0]
    va = np.ascontiguousarray(as_columns("v", v, n, p.n_cylinders), dtype=np.float64)
    aa = np.ascontiguousarray(as_columns("a", a, n, p.n_cylinders), dtype=np.float64)
    cj = p.cylinder_joint
    free = [j for j in range(p.n_joints) if j not in set(cj.tolist())]
    q = np.zeros((n, p.n_joints))
    qd = np.zeros_like(q)
    qdd = np.zeros_like(q)
    for arr, other, name in ((q, q_other, "q_other"), (qd, qd_other, "qd_other"),
                             (qdd, qdd_other, "qdd_other")):
        if other is not None:
            arr[:, free] = as_columns(name, other, n, len(free))
    arm = np.empty((n, p.n_cylinders))
    K.cylinder_motion_batch(p.cyl, sa, va, aa, q, qd, qdd, arm)
    if not np.all(np.isfinite(q[:, cj])):
        joints_from_cylinders(machine, sa, q_other)  # raises the descriptive PhysicsError
    return q, qd, qdd, arm


def joints_from_cylinders(
    machine: Machine, s: npt.ArrayLike, q_other: npt.ArrayLike | None = None
) -> F64:
    """Joint positions from cylinder rod positions (inverse of :func:`cylinder_lengths`).

    Args:
        machine: Machine description.
        s: Rod positions, shape (n, n_cylinders) [m].
        q_other: Positions of the joints no cylinder drives (e.g. the slew angle), in chain
            order, shape (n, n_free) or (n,) when n_free = 1 [rad or m]; zeros when omitted.

    Returns:
        q, shape (n, n_joints) [rad or m]. Revolute angles are wrapped to the period nearest the
        middle of the joint's limits.

    Raises:
        PhysicsError: wrong shapes, or a rod position the geometry cannot produce.
    """
    p = compile_chain(machine)
    sa = np.ascontiguousarray(s, dtype=np.float64)
    if sa.ndim == 1 and p.n_cylinders != 1:
        sa = sa.reshape(1, -1)
    if sa.ndim == 1:
        sa = sa.reshape(-1, 1)
    if sa.ndim != 2 or sa.shape[1] != p.n_cylinders:
        raise PhysicsError(f"s: expected shape (n, {p.n_cylinders}), got {np.shape(s)}")
    n = sa.shape[0]
    free = [j for j in range(p.n_joints) if j not in set(p.cylinder_joint.tolist())]
    q = np.zeros((n, p.n_joints))
    if q_other is not None:
        q[:, free] = as_columns(
            f"q_other (joints {[machine.joints[j].name for j in free]})", q_other, n, len(free))
    col = np.empty(n)
    for k in range(p.n_cylinders):
        K.cylinder_joint_batch(p.cyl, k, np.ascontiguousarray(sa[:, k]), col)
        bad = ~np.isfinite(col)
        if bad.any():
            i = int(np.argmax(bad))
            cyl = machine.cylinders[k]
            raise PhysicsError(
                f"cylinder {cyl.name!r}: rod position s = {sa[i, k]!r} m (sample {i}, "
                f"{int(bad.sum())} sample(s) in all) cannot be reached by the geometry; "
                f"expected about 0 … {cyl.stroke_m} m")
        q[:, p.cylinder_joint[k]] = col
    return q


# ----------------------------------------------------------------------------------------------
# poses


def body_poses(machine: Machine, q: npt.ArrayLike) -> F64:
    """World poses of the chain bodies (body i = child of joint i).

    Args:
        machine: Machine description.
        q: Joint positions, shape (n, n_joints) [rad or m].

    Returns:
        Homogeneous transforms body->world, shape (n, n_joints, 4, 4) [m].
    """
    qa = as_joint_array(machine, q)
    out = np.empty((qa.shape[0], machine.n_joints, 4, 4))
    K.body_poses_batch(compile_chain(machine).chain, qa, out)
    return out


def _apply(t: F64, point: F64) -> F64:
    return np.asarray(t[..., :3, :3] @ point + t[..., :3, 3], dtype=np.float64)


def _body_index(machine: Machine, name: str) -> int:
    return [j.child for j in machine.joints].index(name)


def load_point_position(machine: Machine, q: npt.ArrayLike) -> F64:
    """World position of the load point (tip), shape (n, 3) [m]."""
    poses = body_poses(machine, q)
    lp = machine.load_point
    return _apply(poses[:, _body_index(machine, lp.body)], np.asarray(lp.point_m, dtype=float))


def horizontal_reach(machine: Machine, q: npt.ArrayLike) -> F64:
    """Distance of the load point from the first joint's axis (the slew axis), shape (n,) [m].

    This is the reach of the rated-load chart when the first joint is the vertical slew.
    """
    tip = load_point_position(machine, q)
    j0 = machine.joints[0]
    a = rpy_matrix(j0.origin_rpy_rad) @ np.asarray(j0.axis, dtype=float)
    rel = tip - np.asarray(j0.origin_m, dtype=float)
    perp = rel - (rel @ a)[:, None] * a
    return np.asarray(np.linalg.norm(perp, axis=1), dtype=np.float64)


class CylinderPins(NamedTuple):
    """World positions of cylinder pin points, each shape (n, n_cylinders, 3) [m].

    Attributes:
        base: Base pin (on the driven joint's parent body).
        rod: Rod-end pin (on the child body, or the four-bar's rod end E).
        pivot: Four-bar pivot D on the parent body (NaN for direct cylinders).
        coupler: Four-bar coupler pin F on the child body (NaN for direct cylinders).
    """

    base: F64
    rod: F64
    pivot: F64
    coupler: F64


def cylinder_pins(machine: Machine, q: npt.ArrayLike) -> CylinderPins:
    """World positions of every cylinder's pins, for drawing cylinders and linkages.

    Args:
        machine: Machine description.
        q: Joint positions, shape (n, n_joints) [rad or m].
    """
    p = compile_chain(machine)
    qa = as_joint_array(machine, q)
    n = qa.shape[0]
    poses = body_poses(machine, qa)
    eye = np.broadcast_to(np.eye(4), (n, 4, 4))
    shape = (n, p.n_cylinders, 3)
    base, rod = np.empty(shape), np.empty(shape)
    pivot, coupler = np.full(shape, np.nan), np.full(shape, np.nan)
    pts = np.empty((n, 4))
    for k, cyl in enumerate(machine.cylinders):
        ji = int(p.cylinder_joint[k])
        joint = machine.joints[ji]
        parent = eye if joint.parent == WORLD else poses[:, ji - 1]
        child = poses[:, ji]
        base[:, k] = _apply(parent, np.asarray(cyl.base_pin_m, dtype=float))
        lk = cyl.linkage
        if not isinstance(lk, FourBar):  # pinned directly, or a linear actuator's drawn pins
            rod[:, k] = _apply(child, np.asarray(cyl.rod_pin_m, dtype=float))
            continue
        # joint frame (before the joint's motion) in the world
        jf = np.eye(4)
        jf[:3, :3] = rpy_matrix(joint.origin_rpy_rad)
        jf[:3, 3] = joint.origin_m
        jworld = parent @ jf
        a = np.asarray(joint.axis, dtype=float)
        e1, e2 = plane_basis(a)
        w = float(joint_frame_point(joint, cyl.base_pin_m) @ a)
        K.four_bar_points_batch(p.cyl, k, np.ascontiguousarray(qa[:, ji]), pts)
        e_joint = pts[:, 0, None] * e1 + pts[:, 1, None] * e2 + w * a
        rod[:, k] = np.einsum("nij,nj->ni", jworld[:, :3, :3], e_joint) + jworld[:, :3, 3]
        pivot[:, k] = _apply(parent, np.asarray(lk.pivot_m, dtype=float))
        coupler[:, k] = _apply(child, np.asarray(lk.coupler_pin_m, dtype=float))
    return CylinderPins(base, rod, pivot, coupler)


# ----------------------------------------------------------------------------------------------
# validation


def _fmt_q(kind: str, q: float) -> str:
    return f"{np.degrees(q):.1f}°" if kind == "revolute" else f"{q:.3f} m"


def reach_problems(machine: Machine, tolerance: float = 0.005) -> list[str]:
    """Kinematic problems of a machine description, one ``"field.path: message"`` per problem.

    Checked per cylinder: the linkage can be built (four-bar on a revolute joint, pins in one
    plane normal to the joint axis); the geometry can produce the whole stroke over a full turn
    of the joint (or its range, for a prismatic joint); inside the joint limits the linkage
    assembles and the rod stays within [0, stroke] (± ``tolerance``·stroke, at least 1 mm, for
    end-stop and pin-clearance rounding in published geometry); the working range
    (joint limits ∩ stroke) is not empty, has no dead centre (moment arm ≠ 0) and the inverse
    kinematics returns to the same joint position there.

    A joint limit narrower than what the stroke allows is not a problem: the working range is
    the intersection.
    """
    problems: list[str] = []
    for k, cyl in enumerate(machine.cylinders):
        path = f"cylinders.{k}"
        tolerance_m = max(1e-3, tolerance * cyl.stroke_m)
        ji = machine.joint_index(cyl.joint)
        joint = machine.joints[ji]
        geo_path = f"{path}.linkage" if cyl.linkage is not None else f"{path}.base_pin_m"
        try:
            block = cylinder_geometry(machine, cyl)
        except ModelError as exc:
            problems.append(f"{path}.linkage: {exc}")
            continue
        if isinstance(cyl.linkage, FourBar):
            a = np.asarray(joint.axis, dtype=float)
            w = [float(joint_frame_point(joint, cyl.base_pin_m) @ a),
                 float(joint_frame_point(joint, cyl.linkage.pivot_m) @ a),
                 float(np.asarray(cyl.linkage.coupler_pin_m) @ a)]
            if max(w) - min(w) > 1e-6:
                problems.append(
                    f"{path}.linkage: base pin, pivot and coupler pin must lie in one plane "
                    f"normal to the axis of joint {joint.name!r} (axial offsets {w} m)")
                continue
        lim = np.linspace(joint.lower, joint.upper, 2001)
        choose_inverse_branches(block, lim)
        arr = np.concatenate(([1.0], block))
        need = f"{cyl.closed_length_m:g} … {cyl.closed_length_m + cyl.stroke_m:g} m"
        full = (np.linspace(-np.pi, np.pi, 7201) if joint.kind == "revolute"
                else lim)
        s_full = np.array([K.cylinder_state(arr, 0, float(x))[0] for x in full])
        ok = np.isfinite(s_full)
        turn = "a full turn" if joint.kind == "revolute" else "the range"
        if not ok.any():
            problems.append(f"{geo_path}: the linkage cannot assemble at any position of joint "
                            f"{joint.name!r}")
            continue
        lo, hi = float(s_full[ok].min()), float(s_full[ok].max())
        if lo > tolerance_m or hi < cyl.stroke_m - tolerance_m:
            problems.append(
                f"{geo_path}: pin-to-pin length spans only {lo + cyl.closed_length_m:.4g} … "
                f"{hi + cyl.closed_length_m:.4g} m over {turn} of joint {joint.name!r}; "
                f"the cylinder needs {need} (closed length + stroke)")
            continue
        s_lim = np.array([K.cylinder_state(arr, 0, float(x)) for x in lim])
        bad = ~np.isfinite(s_lim[:, 0])
        if bad.any():
            problems.append(
                f"{geo_path}: the linkage cannot assemble for joint {joint.name!r} at "
                f"{_fmt_q(joint.kind, float(lim[bad][0]))} (inside its limits "
                f"{_fmt_q(joint.kind, joint.lower)} … {_fmt_q(joint.kind, joint.upper)})")
            continue
        s_min, s_max = float(s_lim[:, 0].min()), float(s_lim[:, 0].max())
        if s_min < -tolerance_m or s_max > cyl.stroke_m + tolerance_m:
            problems.append(
                f"{path}: rod position runs {s_min:.4g} … {s_max:.4g} m inside the limits of "
                f"joint {joint.name!r} ({_fmt_q(joint.kind, joint.lower)} … "
                f"{_fmt_q(joint.kind, joint.upper)}); expected within 0 … {cyl.stroke_m:g} m: "
                f"narrow the joint limits to the cylinder's end stops")
        work = (s_lim[:, 0] >= 0.0) & (s_lim[:, 0] <= cyl.stroke_m)
        if not work.any():
            problems.append(f"{path}: no position of joint {joint.name!r} inside its limits "
                            f"puts the rod inside its stroke (0 … {cyl.stroke_m:g} m)")
            continue
        arms = s_lim[work, 1]
        if np.any(np.abs(arms) < 1e-3) or np.any(np.sign(arms) != np.sign(arms[0])):
            at = lim[work][int(np.argmin(np.abs(arms)))]
            problems.append(
                f"{geo_path}: the moment arm vanishes (dead centre) at joint {joint.name!r} = "
                f"{_fmt_q(joint.kind, float(at))} inside the working range; the cylinder cannot "
                f"drive the joint there")
            continue
        back = np.array([K.cylinder_joint(arr, 0, float(x)) for x in s_lim[work, 0]])
        err = np.abs(back - lim[work])
        if not np.all(np.isfinite(back)) or float(np.nanmax(err)) > 1e-6:
            problems.append(f"{geo_path}: the inverse kinematics is ambiguous over the working "
                            f"range of joint {joint.name!r} (linkage changes branch)")
    return problems
