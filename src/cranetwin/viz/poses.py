"""Per-frame data for the 3D view: body poses as column-major 4×4 (meshcat/three.js order),
cylinder pins, tip — from :mod:`cranetwin.physics` kinematics.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from cranetwin.model import Machine
from cranetwin.physics.kinematics import body_poses, cylinder_pins, load_point_position

F64 = npt.NDArray[np.float64]


def column_major(poses: F64) -> F64:
    """Homogeneous transforms, shape (..., 4, 4), flattened column-major to shape (..., 16).

    three.js ``Matrix4.fromArray`` (and meshcat's ``set_transform``) read this order: element
    ``[4*c + r]`` is row r, column c, so the translation sits at indices 12, 13, 14.
    """
    p = np.asarray(poses, dtype=float)
    return np.ascontiguousarray(np.swapaxes(p, -1, -2)).reshape(p.shape[:-2] + (16,))


def frame_arrays(machine: Machine, q: npt.ArrayLike) -> dict[str, Any]:
    """Pose data of ``n`` frames as JSON-ready lists (the twin contract's fields).

    Args:
        machine: Machine description.
        q: Joint positions, shape (n, n_joints) [rad or m].

    Returns:
        ``poses`` {body: (n, 16)}, ``cylinder_pins`` {cylinder: (n, 6) base xyz then rod xyz}
        and ``tip`` (n, 3) [m], as nested lists.
    """
    qa = np.atleast_2d(np.asarray(q, dtype=float))
    poses = column_major(body_poses(machine, qa))
    pins = cylinder_pins(machine, qa)
    tip = load_point_position(machine, qa)
    return {
        "poses": {j.child: poses[:, i].tolist() for i, j in enumerate(machine.joints)},
        "cylinder_pins": {c.name: np.concatenate([pins.base[:, k], pins.rod[:, k]],
                                                 axis=1).tolist()
                          for k, c in enumerate(machine.cylinders)},
        "tip": tip.tolist(),
    }


def rest_q(machine: Machine) -> F64:
    """A tidy parked pose, shape (n_joints,): each joint a fifth of the way into its range from
    the lower limit (the jib folded, the boom low), slew and telescope at zero where allowed."""
    q = np.array([j.lower + 0.2 * (j.upper - j.lower) for j in machine.joints])
    for i, j in enumerate(machine.joints):
        if j.lower <= 0.0 <= j.upper and (j.kind == "prismatic" or i == 0):
            q[i] = 0.0
    return q


def rest_frame(machine: Machine) -> dict[str, Any]:
    """One frame (live-frame shape) of :func:`rest_q`, drawn before any data arrives."""
    q = rest_q(machine)
    f = frame_arrays(machine, q[None, :])
    return {"t": None, "q": q.tolist(), "poses": {k: v[0] for k, v in f["poses"].items()},
            "cylinder_pins": {k: v[0] for k, v in f["cylinder_pins"].items()},
            "tip": f["tip"][0], "payload_kg": 0.0, "utilisation": {}, "cylinder_forces": {}}
