"""Flat parameter arrays of a machine's serial chain and cylinders, built once per machine.

The numba kernels read a machine from two float64 arrays so that they can run inside another
``@njit`` function (the simulator's integration loop): ``chain`` (header + one block per
joint) and ``cyl`` (one block per cylinder), laid out as :mod:`cranetwin.physics.layout`
names; each cylinder's linkage fields are written by its kind's module
(:mod:`cranetwin.physics.linkage`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from cranetwin.model import Cylinder, Machine
from cranetwin.physics import linkage
from cranetwin.physics.frames import axis_rotation, joint_frame_point, plane_basis, rpy_matrix
from cranetwin.physics.layout import (
    C_CENTRE,
    C_CLOSED,
    C_JOINT,
    C_KIND,
    C_STROKE,
    CYL_BLOCK,
    GRAVITY,
    HEADER,
    J_AXIS,
    J_FIRST_MOMENT,
    J_INERTIA,
    J_KIND,
    J_MASS,
    J_ORIGIN,
    J_ROT,
    JOINT_BLOCK,
    LOAD_BODY,
    LOAD_POINT,
    N_JOINTS,
    PRISMATIC,
    REVOLUTE,
    TOOL_MASS,
    cyl_block,
    joint_block,
)

F64 = npt.NDArray[np.float64]

CYL_REVOLUTE = linkage.revolute.KIND
CYL_PRISMATIC = linkage.prismatic.KIND
CYL_FOUR_BAR = linkage.four_bar.KIND

__all__ = ["CYL_BLOCK", "CYL_FOUR_BAR", "CYL_PRISMATIC", "CYL_REVOLUTE", "HEADER",
           "JOINT_BLOCK", "PRISMATIC", "REVOLUTE", "ChainParams", "axis_rotation",
           "choose_inverse_branches", "compile_chain", "cylinder_geometry", "joint_frame_point",
           "plane_basis", "rpy_matrix"]


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


def _inertia_about_origin(mass: float, com: F64, inertia_com: F64) -> F64:
    c = np.asarray(com, dtype=np.float64)
    return np.asarray(inertia_com + mass * (float(c @ c) * np.eye(3) - np.outer(c, c)),
                      dtype=np.float64)


def _chain_array(machine: Machine) -> F64:
    nj = machine.n_joints
    out = np.zeros(HEADER + nj * JOINT_BLOCK)
    out[N_JOINTS] = nj
    out[GRAVITY] = machine.machine.gravity_mps2
    lp = machine.load_point
    load_body = [j.child for j in machine.joints].index(lp.body)
    out[LOAD_BODY] = load_body
    out[LOAD_POINT] = lp.point_m
    out[TOOL_MASS] = lp.tool_mass_kg
    for i, (joint, body) in enumerate(zip(machine.joints, machine.chain_bodies(), strict=True)):
        b = out[joint_block(i):joint_block(i + 1)]
        b[J_KIND] = REVOLUTE if joint.kind == "revolute" else PRISMATIC
        b[J_AXIS] = joint.axis
        b[J_ROT] = rpy_matrix(joint.origin_rpy_rad).ravel()
        b[J_ORIGIN] = joint.origin_m
        m = body.mass_kg
        com = np.asarray(body.com_m, dtype=np.float64)
        io = _inertia_about_origin(m, com, np.asarray(body.inertia_kgm2, dtype=np.float64))
        mc = m * com
        if i == load_body and lp.tool_mass_kg > 0:
            r = np.asarray(lp.point_m, dtype=np.float64)
            io = io + _inertia_about_origin(lp.tool_mass_kg, r, np.zeros((3, 3)))
            mc = mc + lp.tool_mass_kg * r
            m = m + lp.tool_mass_kg
        b[J_MASS] = m
        b[J_FIRST_MOMENT] = mc
        b[J_INERTIA] = io.ravel()
    return out


def cylinder_geometry(machine: Machine, cyl: Cylinder) -> F64:
    """One cylinder block (CYL_BLOCK,) without the inverse branches (they need the forward
    map: :func:`choose_inverse_branches`).

    Raises:
        ModelError: no linkage kind combines the cylinder with its joint.
    """
    ji = machine.joint_index(cyl.joint)
    joint = machine.joints[ji]
    kind = linkage.kind_of(joint, cyl)
    b = np.zeros(CYL_BLOCK)
    b[C_KIND] = kind.KIND
    b[C_JOINT] = ji
    b[C_CLOSED] = cyl.closed_length_m
    b[C_STROKE] = cyl.stroke_m
    b[C_CENTRE] = 0.5 * (joint.lower + joint.upper)
    for field in _BRANCHES:
        b[field] = 1.0
    b[linkage.four_bar.BRANCH_E] = 1.0
    kind.fill(b, joint, cyl, joint_frame_point(joint, cyl.base_pin_m))
    return b


_BRANCHES = (linkage.revolute.SIGMA, linkage.four_bar.SIGMA_E, linkage.four_bar.SIGMA_F)
"""Block fields of the inverse branches, in the order of ``linkage.branch_signs``."""


def choose_inverse_branches(block: F64, grid: F64) -> None:
    """Set the inverse branches of one cylinder block (in place) from the forward map.

    The branch signs are sampled over ``grid`` (joint positions, usually the joint's range);
    samples where the rod is inside its stroke count first. The majority sign is kept, so the
    inverse is exact wherever the forward map does not pass a dead centre; ``reach_problems``
    reports ranges where it does.
    """
    cyl = np.concatenate(([1.0], block))
    o = cyl_block(0)
    signs = np.array([linkage.branch_signs(cyl, o, float(q)) for q in grid])
    s = np.array([linkage.state(cyl, o, float(q))[0] for q in grid])
    ok = np.isfinite(s)
    inside = ok & (s >= -1e-9) & (s <= block[C_STROKE] + 1e-9)
    use = inside if inside.any() else ok
    if not use.any():
        return
    picked = signs[use]
    for col, field in enumerate(_BRANCHES):
        total = float(np.sum(picked[:, col]))
        block[field] = 1.0 if total >= 0 else -1.0


def _cyl_array(machine: Machine) -> F64:
    nc = len(machine.cylinders)
    out = np.zeros(1 + nc * CYL_BLOCK)
    out[0] = nc
    for k, cyl in enumerate(machine.cylinders):
        block = cylinder_geometry(machine, cyl)
        joint = machine.joints[int(block[C_JOINT])]
        grid = np.linspace(joint.lower, joint.upper, 2001)
        choose_inverse_branches(block, grid)
        out[cyl_block(k):cyl_block(k + 1)] = block
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
