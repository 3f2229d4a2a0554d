"""What a replay of one machine and channel set keeps fixed: the plan every stage reads.

Built once per :class:`cranetwin.twin.replay.TwinStream` from the machine, the recording's
channels and the options: channel columns, cylinder and free-joint records, kinematics tables,
the machine's batch kernels, and which free joints are integrated from their torque.

Smoothed sample rows (the stream's buffer, width ``plan.width``)::

    nch working channels | one angle column per integrated joint | rates | accelerations

(rates and accelerations of the derivative channels: rod positions, then the angles sent).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from cranetwin.model import Machine
from cranetwin.physics import actuator
from cranetwin.physics.chain import compile_chain
from cranetwin.physics.dynamics import BatchKernels, batch_kernels
from cranetwin.twin import gridpass, kintable
from cranetwin.twin.channels import ChannelMap
from cranetwin.twin.options import END_STOP_MARGIN_M, ReplayOptions
from cranetwin.twin.stages import SampleColumns, spline_layout

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]


def hold_values(machine: Machine, free: tuple[int, ...]) -> F64:
    """Per free joint the value it is held at when its angle is neither sent nor integrated
    [rad or m]: a passive joint's ``fixed_value``, else 0 (the reference pose)."""
    return np.array([machine.joints[j].fixed_value or 0.0 for j in free])


@dataclass(frozen=True)
class ReplayPlan:
    """Constants of a replay (module docstring).

    Attributes:
        machine, opt, cmap: The machine, options and channel map.
        cols: Working-order indices of the channels in the recording's columns.
        nch, nd: Working channels; derivative channels (rod positions, angles sent).
        integrated: Torque drives (indices) whose joint angle is integrated from the torque:
            every drive without an angle channel.
        drive_joints, drive_free: Per torque drive its joint, and that joint's index among
            the free joints.
        free: Joints no cylinder drives, in joint order.
        cyl_joint: Joint of each cylinder (n_c,).
        sample_cols: Columns of the smoothed rows (:class:`cranetwin.twin.stages.SampleColumns`).
        qi: The grid stage's quantity table.
        cylinders, free_joints: The grid stage's records.
        kernels: The machine's batch kernels (RNEA, mass matrix).
        use_cs: The cylinder states at the samples that the integration computed serve the
            chunks (one free joint, integrated; rates from the Savitzky–Golay filters).
    """

    machine: Machine
    opt: ReplayOptions
    cmap: ChannelMap
    cols: list[int]
    nch: int
    nd: int
    integrated: tuple[int, ...]
    drive_joints: tuple[int, ...]
    drive_free: tuple[int, ...]
    free: tuple[int, ...]
    cyl_joint: I64
    sample_cols: SampleColumns
    qi: gridpass.Quantities
    cylinders: gridpass.Cylinders
    free_joints: gridpass.FreeJoints
    kernels: BatchKernels
    use_cs: bool
    layout: tuple[list[int], list[int], I64, I64]
    """:func:`cranetwin.twin.stages.spline_layout` of this plan."""

    @property
    def n_int(self) -> int:
        """Number of integrated joints (their angle columns follow the channels)."""
        return len(self.integrated)

    @property
    def width(self) -> int:
        """Columns of a smoothed sample row."""
        return self.nch + self.n_int + 2 * self.nd

    @staticmethod
    def of(machine: Machine, channels: tuple[str, ...], opt: ReplayOptions) -> ReplayPlan:
        """:meth:`build`, the constants kept per machine and channel set: a replay of a few
        seconds (the twin worker's spans) otherwise spends about a tenth of its time on the
        kinematics tables and the rest of the plan. Only ``generated_kernels`` and ``velocity``
        of the options enter the constants; the plan returned carries ``opt`` itself."""
        key = (id(machine), channels, opt.generated_kernels, opt.velocity)
        with _PLANS_LOCK:
            hit = _PLANS.get(key)
        if hit is None or hit[0] is not machine:  # (the machine is held: its id is not reused)
            plan = ReplayPlan.build(machine, channels, opt)
            with _PLANS_LOCK:
                if len(_PLANS) >= MAX_PLANS:
                    del _PLANS[next(iter(_PLANS))]
                _PLANS[key] = (machine, plan)
            return plan
        return hit[1] if hit[1].opt == opt else replace(hit[1], opt=opt)

    @staticmethod
    def build(machine: Machine, channels: tuple[str, ...], opt: ReplayOptions) -> ReplayPlan:
        """The plan of a replay of ``machine`` from a recording with ``channels`` (every
        constant computed anew; :meth:`of` keeps them)."""
        cmap = ChannelMap.build(machine, channels)
        nch = len(cmap.names)
        nd = len(cmap.derivative_channels)
        drives = machine.torque_drives
        drive_joints = tuple(machine.joint_index(d.joint) for d in drives)
        # every drive without an angle channel: its joint is integrated from its torque
        integrated = tuple(d for d, a in enumerate(cmap.angles) if a is None)
        cyl_joint = [machine.joint_index(c.joint) for c in machine.cylinders]
        free = tuple(j for j in range(machine.n_joints) if j not in cyl_joint)
        n_int = len(integrated)
        sample_cols = SampleColumns(np.array(cmap.s, dtype=np.int64),
                                    np.array(cmap.p_a, dtype=np.int64),
                                    np.array(cmap.p_b, dtype=np.int64), nch + n_int,
                                    nch + n_int + nd)
        params = compile_chain(machine)
        stroke = np.array([c.stroke_m for c in machine.cylinders])
        table = np.empty((len(machine.cylinders), kintable.KIN_TABLE_NODES - 1, 6))
        table_ok = kintable.kinematics_table(params.cyl, stroke, kintable.KIN_TABLE_NODES, table)
        drive_friction = np.zeros((len(free), 3))
        drive_friction[:, 1] = 1.0
        for d in drives:
            f = d.friction
            drive_friction[free.index(machine.joint_index(d.joint))] = (
                f.coulomb, f.coulomb_velocity, f.viscous)
        cyl_joint_arr = np.array(cyl_joint, dtype=np.int64)
        qi = gridpass.Quantities.of(len(machine.cylinders), len(free))
        drive_free = tuple(free.index(j) for j in drive_joints)
        return ReplayPlan(
            machine=machine, opt=opt, cmap=cmap, cols=[channels.index(n) for n in cmap.names],
            nch=nch, nd=nd, integrated=integrated, drive_joints=drive_joints,
            drive_free=drive_free, free=free, cyl_joint=cyl_joint_arr,
            sample_cols=sample_cols, qi=qi,
            cylinders=gridpass.Cylinders(params.cyl, table, table_ok,
                                         actuator.cylinder_params(machine), stroke,
                                         cyl_joint_arr, END_STOP_MARGIN_M),
            free_joints=gridpass.FreeJoints(np.array(free, dtype=np.int64), drive_friction,
                                            hold_values(machine, free)),
            kernels=batch_kernels(params, opt.generated_kernels),
            use_cs=n_int == 1 and opt.velocity == "spline" and len(free) == 1,
            layout=spline_layout(cmap, nch, opt.velocity, integrated, qi, drive_free))


MAX_PLANS = 32
"""Plans :meth:`ReplayPlan.of` keeps (oldest dropped first): one per machine description and
channel set in use."""
_PLANS: dict[tuple[int, tuple[str, ...], bool, str], tuple[Machine, ReplayPlan]] = {}
_PLANS_LOCK = threading.Lock()
