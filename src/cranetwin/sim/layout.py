"""Where each quantity sits in the simulator's flat arrays, for any machine topology.

A machine has ``nj`` joints, ``nc`` cylinders and ``nd`` torque drives; its actuators are
ordered drives first, then cylinders (both in machine order), ``na = nd + nc``. The compiled
loop keeps three flat arrays whose column blocks are named here once:

State ``x`` (n_x,)::

    q (nj) | qd (nj) | pA (nc) | pB (nc) | spool voltages U (na, actuator order) |
    drive torques T (nd)

Truth row (n_t,), recorded every ``truth_every`` steps::

    t | q (nj) | qd (nj) | qdd (nj) | rod s (nc) | rod v (nc) | pA (nc) | pB (nc) |
    cylinder force (nc) | drive torque (nd) | actuator joint loads (nj) | payload | U_cmd (na) |
    contact force at the load point (3, world frame)

Sensor snapshot row (n_snap,), at each sampling instant::

    pA (nc) | pB (nc) | s (nc) | drive torque (nd) | q (nj)

For the PATU 655 (nj = 4, nc = 3, nd = 1) these are the layouts the 4-joint simulator had
(n_x = 19, truth 38 columns + the contact force, snapshots 14).

The loop reads the sizes from ``lay``, an int64 array indexed by the ``L_*`` constants.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from numba import njit

from cranetwin.model import Machine

L_NJ, L_NC, L_ND = range(3)
N_LAY = 3


@dataclass(frozen=True)
class Layout:
    """Column blocks of the state, truth and snapshot arrays (module docstring).

    Attributes:
        nj: Joints. nc: Cylinders. nd: Torque drives.
    """

    nj: int
    nc: int
    nd: int

    @property
    def na(self) -> int:
        """Actuators (drives then cylinders)."""
        return self.nd + self.nc

    # state
    @property
    def x_q(self) -> int:
        return 0

    @property
    def x_qd(self) -> int:
        return self.nj

    @property
    def x_pa(self) -> int:
        return 2 * self.nj

    @property
    def x_pb(self) -> int:
        return 2 * self.nj + self.nc

    @property
    def x_u(self) -> int:
        return 2 * self.nj + 2 * self.nc

    @property
    def x_ts(self) -> int:
        return self.x_u + self.na

    @property
    def n_x(self) -> int:
        return self.x_ts + self.nd

    # truth
    def truth_blocks(self) -> list[tuple[str, int]]:
        """(name, width) of the truth row's blocks, in order."""
        nj, nc, nd = self.nj, self.nc, self.nd
        return [("t_s", 1), ("q", nj), ("qd", nj), ("qdd", nj), ("rod_s", nc), ("rod_v", nc),
                ("p_a", nc), ("p_b", nc), ("cyl_force", nc), ("drive_torque", nd),
                ("joint_torque", nj), ("payload_kg", 1), ("u", self.na), ("contact_force", 3)]

    def truth_offset(self, name: str) -> int:
        """First column of truth block ``name``."""
        col = 0
        for n, w in self.truth_blocks():
            if n == name:
                return col
            col += w
        raise KeyError(name)

    @property
    def n_t(self) -> int:
        return sum(w for _, w in self.truth_blocks())

    # snapshots
    @property
    def snap_pa(self) -> int:
        return 0

    @property
    def snap_pb(self) -> int:
        return self.nc

    @property
    def snap_s(self) -> int:
        return 2 * self.nc

    @property
    def snap_torque(self) -> int:
        return 3 * self.nc

    @property
    def snap_q(self) -> int:
        return 3 * self.nc + self.nd

    @property
    def n_snap(self) -> int:
        return self.snap_q + self.nj

    def array(self) -> npt.NDArray[np.int64]:
        """The sizes as the compiled loop reads them (``L_*`` indices)."""
        out = np.zeros(N_LAY, dtype=np.int64)
        out[L_NJ], out[L_NC], out[L_ND] = self.nj, self.nc, self.nd
        return out


@njit(cache=True, nogil=True)
def state_offsets(lay):  # type: ignore[no-untyped-def]
    """Offsets in the state vector of the compiled loop, from :meth:`Layout.array` ``lay``:
    ``(x_pa, x_pb, x_u, x_ts, n_x)``, as :class:`Layout`'s properties of the same names."""
    nj = lay[L_NJ]
    nc = lay[L_NC]
    nd = lay[L_ND]
    x_pa = 2 * nj
    x_pb = x_pa + nc
    x_u = x_pb + nc
    x_ts = x_u + nd + nc
    return x_pa, x_pb, x_u, x_ts, x_ts + nd


def layout_of(machine: Machine) -> Layout:
    """The layout of ``machine``'s arrays."""
    return Layout(nj=machine.n_joints, nc=len(machine.cylinders), nd=len(machine.torque_drives))
