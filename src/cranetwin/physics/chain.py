"""Flat parameter arrays of a machine's serial chain and cylinders, built once per machine.

The numba kernels (:mod:`cranetwin.physics.kernels`) read a machine from two float64 arrays so
that they can run inside another ``@njit`` function (the simulator's integration loop):

``chain`` (header + one block per joint, chain order)::

    [0] n_joints   [1:4] gravity [m/s²] (world frame)   [4] load body index (chain order)
    [5:8] load point in the load body's frame [m]        [8] tool mass [kg] (already lumped
    into the load body's block below)
    per joint i, at HEADER + i*JOINT_BLOCK:
    [0] kind (0 revolute, 1 prismatic)   [1:4] axis (joint frame)   [4:13] R0 row-major
    (joint frame in the parent frame)    [13:16] origin p0 [m] (parent frame)
    [16] mass [kg]   [17:20] first moment m·c [kg·m]   [20:29] inertia about the body-frame
    origin [kg·m²], row-major (body i = child of joint i, tool mass included)

``cyl`` (header + one block per cylinder, order of ``machine.cylinders``)::

    [0] n_cylinders
    per cylinder k, at 1 + k*CYL_BLOCK:
    [0] kind (0 direct on revolute, 1 direct on prismatic, 2 four-bar on revolute)
    [1] joint index   [2] closed length [m]   [3] stroke [m]   [4] wrap centre [rad]
    direct revolute:  [5] K0 [m²]  [6] rho [m²]  [7] phi [rad]  [8] inverse branch sigma
                      (pin distance² = K0 − 2·rho·cos(q − phi))
    direct prismatic: [5] d·e [m]  [6] |d|² [m²]  [8] sigma   (distance² = |d|² + 2(d·e)q + q²)
    four-bar (2-D coordinates in the joint plane, joint axis out of the plane):
                      [9:11] C  [11:13] D  [13:15] F at q = 0  [15] |D→E|  [16] |E→F|
                      [17] branch of E (forward)  [18] sigma_E, [19] sigma_F (inverse branches)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from cranetwin.errors import ModelError
from cranetwin.model import Cylinder, Joint, Machine

F64 = npt.NDArray[np.float64]

HEADER = 9
JOINT_BLOCK = 29
CYL_BLOCK = 20

REVOLUTE = 0
PRISMATIC = 1
CYL_REVOLUTE = 0
CYL_PRISMATIC = 1
CYL_FOUR_BAR = 2


@dataclass(frozen=True, eq=False)
class ChainParams:
    """A machine compiled to the flat arrays the kernels read (see the module docstring).

    Attributes:
        chain: Chain parameters, shape (HEADER + n_joints·JOINT_BLOCK,).
        cyl: Cylinder parameters, shape (1 + n_cylinders·CYL_BLOCK,).
        n_joints: Number of joints.
        n_cylinders: Number of cylinders.
        cylinder_joint: Joint index driven by each cylinder, shape (n_cylinders,).
    """

    chain: F64
    cyl: F64
    n_joints: int
    n_cylinders: int
    cylinder_joint: npt.NDArray[np.int64]


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


def _inertia_about_origin(mass: float, com: F64, inertia_com: F64) -> F64:
    c = np.asarray(com, dtype=np.float64)
    return np.asarray(inertia_com + mass * (float(c @ c) * np.eye(3) - np.outer(c, c)),
                      dtype=np.float64)


def _chain_array(machine: Machine) -> F64:
    nj = machine.n_joints
    out = np.zeros(HEADER + nj * JOINT_BLOCK)
    out[0] = nj
    out[1:4] = machine.machine.gravity_mps2
    lp = machine.load_point
    load_body = [j.child for j in machine.joints].index(lp.body)
    out[4] = load_body
    out[5:8] = lp.point_m
    out[8] = lp.tool_mass_kg
    for i, (joint, body) in enumerate(zip(machine.joints, machine.chain_bodies(), strict=True)):
        o = HEADER + i * JOINT_BLOCK
        out[o] = REVOLUTE if joint.kind == "revolute" else PRISMATIC
        out[o + 1:o + 4] = joint.axis
        out[o + 4:o + 13] = rpy_matrix(joint.origin_rpy_rad).ravel()
        out[o + 13:o + 16] = joint.origin_m
        m = body.mass_kg
        com = np.asarray(body.com_m, dtype=np.float64)
        io = _inertia_about_origin(m, com, np.asarray(body.inertia_kgm2, dtype=np.float64))
        mc = m * com
        if i == load_body and lp.tool_mass_kg > 0:
            r = np.asarray(lp.point_m, dtype=np.float64)
            io = io + _inertia_about_origin(lp.tool_mass_kg, r, np.zeros((3, 3)))
            mc = mc + lp.tool_mass_kg * r
            m = m + lp.tool_mass_kg
        out[o + 16] = m
        out[o + 17:o + 20] = mc
        out[o + 20:o + 29] = io.ravel()
    return out


def _wrap_near(q: F64, centre: float) -> F64:
    return np.asarray(q + 2 * np.pi * np.round((centre - q) / (2 * np.pi)), dtype=np.float64)


def cylinder_geometry(machine: Machine, cyl: Cylinder) -> F64:
    """One cylinder block (CYL_BLOCK,) without the inverse branches (they need the forward map).

    Raises:
        ModelError: the cylinder's kind of joint and linkage cannot be combined.
    """
    ji = machine.joint_index(cyl.joint)
    joint = machine.joints[ji]
    b = np.zeros(CYL_BLOCK)
    b[1] = ji
    b[2] = cyl.closed_length_m
    b[3] = cyl.stroke_m
    b[4] = 0.5 * (joint.lower + joint.upper)
    b[8] = 1.0
    b[17] = 1.0
    b[18] = 1.0
    b[19] = 1.0
    a = np.asarray(joint.axis, dtype=np.float64)
    c = joint_frame_point(joint, cyl.base_pin_m)
    if cyl.linkage is not None:
        if joint.kind != "revolute":
            raise ModelError(f"cylinder {cyl.name!r}: a four-bar linkage needs a revolute joint")
        lk = cyl.linkage
        e1, e2 = plane_basis(a)
        d = joint_frame_point(joint, lk.pivot_m)
        f = np.asarray(lk.coupler_pin_m, dtype=np.float64)  # child frame = joint frame at q = 0
        b[0] = CYL_FOUR_BAR
        b[9:11] = (c @ e1, c @ e2)
        b[11:13] = (d @ e1, d @ e2)
        b[13:15] = (f @ e1, f @ e2)
        b[15] = lk.pivot_link_m
        b[16] = lk.coupler_link_m
        b[17] = lk.branch
    elif joint.kind == "revolute":
        r = np.asarray(cyl.rod_pin_m, dtype=np.float64)
        ac, ar = float(a @ c), float(a @ r)
        b[0] = CYL_REVOLUTE
        b[5] = float(r @ r + c @ c) - 2 * ac * ar
        p = float(c @ r) - ac * ar
        qq = float(c @ np.cross(a, r))
        b[6] = np.hypot(p, qq)
        b[7] = np.arctan2(qq, p)
    else:
        r0 = rpy_matrix(joint.origin_rpy_rad)
        d_vec = (np.asarray(joint.origin_m) + r0 @ np.asarray(cyl.rod_pin_m)
                 - np.asarray(cyl.base_pin_m))
        e = r0 @ a
        b[0] = CYL_PRISMATIC
        b[5] = float(d_vec @ e)
        b[6] = float(d_vec @ d_vec)
    return b


def _cyl_array(machine: Machine) -> F64:
    from cranetwin.physics.kernels import choose_inverse_branches

    nc = len(machine.cylinders)
    out = np.zeros(1 + nc * CYL_BLOCK)
    out[0] = nc
    for k, cyl in enumerate(machine.cylinders):
        block = cylinder_geometry(machine, cyl)
        joint = machine.joints[int(block[1])]
        grid = np.linspace(joint.lower, joint.upper, 2001)
        choose_inverse_branches(block, grid)
        out[1 + k * CYL_BLOCK:1 + (k + 1) * CYL_BLOCK] = block
    return out


_CACHE: dict[int, tuple[Machine, ChainParams]] = {}


def compile_chain(machine: Machine) -> ChainParams:
    """Build (once per machine object, then cached) the flat arrays the kernels read.

    Args:
        machine: A validated machine description (serial chain, load point on a chain body).

    Returns:
        The machine's :class:`ChainParams`.
    """
    hit = _CACHE.get(id(machine))
    if hit is not None and hit[0] is machine:
        return hit[1]
    params = ChainParams(
        chain=_chain_array(machine),
        cyl=_cyl_array(machine),
        n_joints=machine.n_joints,
        n_cylinders=len(machine.cylinders),
        cylinder_joint=np.array([machine.joint_index(c.joint) for c in machine.cylinders],
                                dtype=np.int64),
    )
    if len(_CACHE) >= 32:
        _CACHE.pop(next(iter(_CACHE)))
    _CACHE[id(machine)] = (machine, params)
    return params
