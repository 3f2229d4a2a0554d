"""The replay output: motion and loads of the machine on the model's time grid."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from cranetwin.errors import TwinError
from cranetwin.model import Machine
from cranetwin.signal import SmoothingChoice

if TYPE_CHECKING:
    from cranetwin.twin.consistency import ModelConsistency
    from cranetwin.twin.observability import ForceObservability

F64 = npt.NDArray[np.float64]
B = npt.NDArray[np.bool_]


@dataclass(frozen=True)
class TwinResult:
    """Everything the twin reconstructs, on a uniform grid of m instants.

    Joints in ``machine.joints`` order (PATU 655: theta0, theta1, theta2, L); cylinders in
    ``machine.cylinders`` order (lift, jib, extension).

    Attributes:
        t_s: Grid times, shape (m,) [s, timebase of the samples].
        q: Joint positions, shape (m, n_joints) [rad or m].
        qd: Joint velocities, shape (m, n_joints) [rad/s or m/s].
        qdd: Joint accelerations, shape (m, n_joints) [rad/s² or m/s²].
        rod_s: Rod positions (smoothed, interpolated), shape (m, n_cyl) [m].
        rod_v: Rod velocities, shape (m, n_cyl) [m/s].
        p_a: Piston-side pressures, shape (m, n_cyl) [Pa].
        p_b: Rod-side pressures, shape (m, n_cyl) [Pa].
        cyl_force: Cylinder forces, Eq. 1–2 (friction at rod_v), shape (m, n_cyl) [N].
        actuator_torque: Joint loads of the actuators: F·ds/dq for cylinders, measured drive
            torque minus drive friction for torque drives, shape (m, n_joints) [N·m or N].
        id_torque: Inverse-dynamics joint loads of (q, qd, qdd) with the payload used
            (``payload_kg``), shape (m, n_joints) [N·m or N].
        residual: actuator_torque − id_torque, shape (m, n_joints); what the model does not
            explain (sensor noise, friction and model errors, wrong payload).
        joint_wrench: Joint reaction wrenches [fx, fy, fz, mx, my, mz] in the child body's frame
            at the joint origin (``physics.inverse_dynamics`` convention), shape
            (m, n_joints, 6) [N, N·m]: the load history of the structure.
        payload_kg: Payload used (given: a constant, or a series where it is known; else
            estimated by sliding-window least squares), shape (m,) [kg].
        payload_std_kg: One-sigma uncertainty of the estimate, shape (m,) [kg] (0 where
            given).
        payload_sys_std_kg: The systematic part of ``payload_std_kg``, σ_b, shape (m,) [kg]:
            what the pressure sensors' stated accuracy leaves beyond their noise
            (:mod:`cranetwin.twin.payload`), which does not average out over a lift
            (:mod:`cranetwin.twin.lifts`); 0 without a stated accuracy and where given.
        gap: True where an input channel had to be bridged across a dropout, shape (m,).
        smoothing: The Savitzky–Golay choice per working channel name.
    """

    t_s: F64
    q: F64
    qd: F64
    qdd: F64
    rod_s: F64
    rod_v: F64
    p_a: F64
    p_b: F64
    cyl_force: F64
    actuator_torque: F64
    id_torque: F64
    residual: F64
    joint_wrench: F64
    payload_kg: F64
    payload_std_kg: F64
    payload_sys_std_kg: F64
    gap: B
    smoothing: dict[str, SmoothingChoice] = field(default_factory=dict)

    @property
    def n(self) -> int:
        """Number of grid instants m."""
        return int(self.t_s.shape[0])

    def body_poses(self, machine: Machine) -> F64:
        """World poses of the chain bodies, shape (m, n_joints, 4, 4) (computed on demand)."""
        from cranetwin.physics import body_poses

        return body_poses(machine, self.q)

    def force_observability(self, machine: Machine) -> tuple[ForceObservability, ...]:
        """Per cylinder, whether the pressures resolve its force over this result's window
        (:mod:`cranetwin.twin.observability`): the per-sample force error against the range
        of ``cyl_force``."""
        from cranetwin.twin.observability import ForceRange

        rng = ForceRange()
        rng.add(self.cyl_force)
        return rng.assess(machine, self.smoothing)

    def model_consistency(self, machine: Machine) -> tuple[ModelConsistency, ...]:
        """Per cylinder, whether its pressures agree with the inverse dynamics of the motion
        beyond what sensor noise explains (:mod:`cranetwin.twin.consistency`): a wrong bore,
        friction, pin offset or swapped chambers in the machine file or the mapping."""
        from cranetwin.twin.consistency import assess

        return assess(machine, self.t_s, self.q, self.residual, self.id_torque, self.p_a,
                      self.p_b, self.gap, self.smoothing)

    def tip_path(self, machine: Machine) -> F64:
        """World position of the load point, shape (m, 3) [m] (computed on demand)."""
        from cranetwin.physics import load_point_position

        return load_point_position(machine, self.q)

    @staticmethod
    def concat(parts: Sequence[TwinResult]) -> TwinResult:
        """Join consecutive results (e.g. the chunks of a stream) into one.

        Raises:
            TwinError: No parts, or parts not in increasing time order.
        """
        if not parts:
            raise TwinError("nothing to concatenate: no replay output")
        for a, b in zip(parts, parts[1:], strict=False):
            if a.n and b.n and not b.t_s[0] > a.t_s[-1]:
                raise TwinError("results to concatenate must follow each other in time")
        arrays = {f.name: np.concatenate([getattr(p, f.name) for p in parts])
                  for f in fields(TwinResult) if f.name != "smoothing"}
        return TwinResult(**arrays, smoothing=dict(parts[0].smoothing))
