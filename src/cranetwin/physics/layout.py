"""Array layouts the compiled kernels read, in one place: the chain array, the cylinder array
and the per-cylinder Eq. 1–2 parameters, with a name for every field.

``chain`` (float64, header + one block per joint in chain order)::

    header  N_JOINTS, GRAVITY (3) [m/s², world frame], LOAD_BODY (chain index), LOAD_POINT (3)
            [m, load body frame], TOOL_MASS [kg] (already lumped into the load body's block)
    joint i at HEADER + i·JOINT_BLOCK:
            J_KIND (REVOLUTE | PRISMATIC), J_AXIS (3, joint frame), J_ROT (9, R0 row-major: the
            joint frame in the parent frame), J_ORIGIN (3) [m, parent frame], J_MASS [kg],
            J_FIRST_MOMENT (3) m·c [kg·m], J_INERTIA (9) about the body-frame origin [kg·m²]
            (body i = child of joint i, tool mass included)

``cyl`` (float64, ``[n_cylinders]`` + one block per cylinder, order of ``machine.cylinders``)::

    cylinder k at cyl_block(k) = 1 + k·CYL_BLOCK:
            C_KIND (a linkage kind id, :mod:`cranetwin.physics.linkage`), C_JOINT (joint index),
            C_CLOSED [m] (pin distance at s = 0), C_STROKE [m], C_CENTRE [rad] (inverse angles
            are wrapped near it), then C_PARAMS … the linkage kind's own fields (its module
            names them)

A field of one element is an offset (``chain[HEADER + i·JOINT_BLOCK + J_MASS]``), one of
several a ``slice`` (``chain[GRAVITY]``; for a joint block ``block[J_AXIS]``).
"""

from __future__ import annotations

from numba import njit

# chain header
N_JOINTS = 0
GRAVITY = slice(1, 4)
GRAVITY_X = 1
LOAD_BODY = 4
LOAD_POINT = slice(5, 8)
LOAD_POINT_X = 5
TOOL_MASS = 8
HEADER = 9

# joint block
J_KIND = 0
J_AXIS = slice(1, 4)
J_AXIS_X = 1
J_ROT = slice(4, 13)
J_ROT_0 = 4
J_ORIGIN = slice(13, 16)
J_ORIGIN_X = 13
J_MASS = 16
J_FIRST_MOMENT = slice(17, 20)
J_FIRST_MOMENT_X = 17
J_INERTIA = slice(20, 29)
J_INERTIA_0 = 20
JOINT_BLOCK = 29

REVOLUTE = 0
PRISMATIC = 1

# cylinder block
C_KIND = 0
C_JOINT = 1
C_CLOSED = 2
C_STROKE = 3
C_CENTRE = 4
C_PARAMS = 5
CYL_BLOCK = 20


@njit(cache=True, nogil=True, inline="always")
def joint_block(i: int) -> int:
    """Offset of joint i's block in ``chain``."""
    return HEADER + i * JOINT_BLOCK


@njit(cache=True, nogil=True, inline="always")
def cyl_block(k: int) -> int:
    """Offset of cylinder k's block in ``cyl``."""
    return 1 + k * CYL_BLOCK
