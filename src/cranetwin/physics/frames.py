"""Rotations and frames of a machine description: roll-pitch-yaw matrices, axis rotations, the
plane normal to an axis, points in a joint's frame."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from cranetwin.model import Joint

F64 = npt.NDArray[np.float64]


def rpy_matrix(rpy: tuple[float, float, float] | F64) -> F64:
    """Rotation matrix of roll-pitch-yaw angles (XYZ fixed axes): Rz(yaw)·Ry(pitch)·Rx(roll)."""
    r, p, y = (float(v) for v in rpy)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    return np.asarray(rz @ ry @ rx, dtype=np.float64)


def axis_rotation(axis: F64, angle: F64) -> F64:
    """Rotation matrices about a unit ``axis`` (3,) by ``angle`` (n,) [rad] -> (n, 3, 3)."""
    a = np.asarray(axis, dtype=np.float64)
    th = np.asarray(angle, dtype=np.float64)
    c, s = np.cos(th), np.sin(th)
    v = 1.0 - c
    k = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    out = (c[:, None, None] * np.eye(3) + s[:, None, None] * k
           + v[:, None, None] * np.outer(a, a))
    return np.asarray(out, dtype=np.float64)


def plane_basis(axis: F64) -> tuple[F64, F64]:
    """Two unit vectors (e1, e2) spanning the plane normal to ``axis`` with e1 × e2 = axis."""
    a = np.asarray(axis, dtype=np.float64)
    trial = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    e1 = trial - a * float(a @ trial)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    return e1, e2


def joint_frame_point(joint: Joint, point_parent: tuple[float, float, float]) -> F64:
    """A point given in the joint's parent frame, expressed in the joint frame [m]."""
    r0 = rpy_matrix(joint.origin_rpy_rad)
    return np.asarray(r0.T @ (np.asarray(point_parent) - np.asarray(joint.origin_m)),
                      dtype=np.float64)
