"""Physics of a machine described as data: kinematics, cylinder forces, inverse dynamics.

Modules (one concept each):

* :mod:`~cranetwin.physics.kinematics` — cylinder rod positions <-> joint coordinates
  (closed-form triangle, four-bar circle intersection, prismatic), moment arms ds/dq, body
  poses, load point and reach, cylinder pins, and ``reach_problems`` (model validation);
* :mod:`~cranetwin.physics.actuator` — cylinder force with friction (paper Eq. 1–2), once, and
  the joint torques it produces;
* :mod:`~cranetwin.physics.dynamics` — inverse dynamics with joint reaction wrenches, mass
  matrix and bias forces (paper Eq. 3–4), vectorised over time, and the machine's batch
  kernels (:func:`~cranetwin.physics.dynamics.batch_kernels`);
* :mod:`~cranetwin.physics.rnea` — RNEA and CRBA for one sample (compiled), the one joint
  transform; :mod:`~cranetwin.physics.codegen` — the same RNEA traced into straight-line batch
  kernels for one machine;
* :mod:`~cranetwin.physics.linkage` — one module per linkage kind (revolute, prismatic,
  four-bar): s, s′, s″ and the inverse;
* :mod:`~cranetwin.physics.kernels` — the compiled loops over cylinders and samples, and the
  single-sample kernels the simulator's own ``@njit`` loop calls;
* :mod:`~cranetwin.physics.layout` — the flat arrays' fields by name;
  :mod:`~cranetwin.physics.chain` builds them (:func:`compile_chain`);
  :mod:`~cranetwin.physics.frames` — rotations and frames.

Dependencies: numpy, numba, ``cranetwin.model`` and ``cranetwin.errors`` only. DESIGN.md says
"numpy only"; numba is the one deliberate exception. Replay must run one hour of 1 kHz data
(3.6 M samples) through inverse dynamics with reaction wrenches in about a second on one
core. Whole-array NumPy over a 4-joint chain costs dozens of passes over memory per sample
(≈ 1–2 µs/sample measured for such formulations); a loop compiled by numba over the samples
does the recursion in registers (see ``cranetwin bench dynamics``). Kernels are compiled with
``cache=True`` so only the first run in an environment pays the compile time.
"""

from __future__ import annotations

import cranetwin.jitcache  # noqa: F401  (first: drops stale numba caches)
from cranetwin.physics.actuator import (
    actuator_torques,
    cylinder_force,
    cylinder_forces,
    cylinder_forces_from_torques,
    friction_force,
)
from cranetwin.physics.chain import ChainParams, compile_chain
from cranetwin.physics.dynamics import (
    acceleration_correction,
    bias_forces,
    forward_dynamics,
    gravity_torques,
    inverse_dynamics,
    joint_torques,
    mass_matrix,
)
from cranetwin.physics.kinematics import (
    CylinderPins,
    body_poses,
    cylinder_kinematics,
    cylinder_lengths,
    cylinder_pins,
    horizontal_reach,
    joint_motion_and_arms,
    joint_motion_from_cylinders,
    joints_from_cylinders,
    load_point_position,
    moment_arm_rates,
    moment_arms,
    reach_problems,
)

__all__ = [
    "acceleration_correction",
    "ChainParams",
    "CylinderPins",
    "actuator_torques",
    "bias_forces",
    "body_poses",
    "compile_chain",
    "cylinder_force",
    "cylinder_forces",
    "cylinder_forces_from_torques",
    "cylinder_kinematics",
    "cylinder_lengths",
    "cylinder_pins",
    "forward_dynamics",
    "friction_force",
    "gravity_torques",
    "horizontal_reach",
    "inverse_dynamics",
    "joint_torques",
    "joint_motion_and_arms",
    "joint_motion_from_cylinders",
    "joints_from_cylinders",
    "load_point_position",
    "mass_matrix",
    "moment_arm_rates",
    "moment_arms",
    "reach_problems",
]
