"""Stages of the replay as pure functions of arrays: the cylinder states at the samples, the
derivative filters, and the spline layout (which spline column feeds which grid quantity).

:class:`cranetwin.twin.replay.TwinStream` buffers the samples and calls these and
:func:`cranetwin.twin.gridpass.grid_pass`; :mod:`cranetwin.twin.slew` and
:mod:`cranetwin.twin.payload` are the other stages.
"""

from __future__ import annotations

import math
from typing import Literal, NamedTuple

import numpy as np
import numpy.typing as npt
from numba import njit

from cranetwin.physics import actuator
from cranetwin.signal import SmoothingChoice
from cranetwin.twin import kintable
from cranetwin.twin.channels import ChannelMap
from cranetwin.twin.gridpass import Quantities

I64 = npt.NDArray[np.int64]


class SampleColumns(NamedTuple):
    """Columns of the smoothed sample rows: per cylinder its rod position ``s``, pressures
    ``pa`` and ``pb`` (n_c,), and where the rates (``v0 + k``) and accelerations (``a0 + k``)
    of the rod positions start."""

    s: I64
    pa: I64
    pb: I64
    v0: int
    a0: int


@njit(cache=True, nogil=True, error_model="numpy")
def cylinder_states(sm, col, cy, q, qd, qdd, cs):  # type: ignore[no-untyped-def]
    """Per sample row of the smoothed channels ``sm`` (columns: :class:`SampleColumns`
    ``col``): rod positions clipped to [0, stroke], the cylinder joints' q, qd, qdd through
    the kinematics tables (:class:`cranetwin.twin.gridpass.Cylinders` ``cy``) into q, qd, qdd
    (n, n_joints), and the states row cs (n, 5·n_c) = [q, qd, qdd of the cylinder joints,
    moment arms ds/dq, forces (Eq. 1–2, :func:`cranetwin.physics.actuator.eq1_cylinder_force`)].
    Returns the number of samples whose position does not fit the geometry (q not finite)."""
    nc = col.s.shape[0]
    bad = 0
    for i in range(sm.shape[0]):
        row_bad = False
        for k in range(nc):
            s = min(max(sm[i, col.s[k]], 0.0), cy.stroke[k])
            j = cy.joint[k]
            vk = sm[i, col.v0 + k]
            qj, w, acc, d1 = kintable.joint_motion(
                cy.table, cy.table_ok, cy.cyl, k, cy.table.shape[1] / cy.stroke[k], s, vk,
                sm[i, col.a0 + k])
            q[i, j] = qj
            qd[i, j] = w
            qdd[i, j] = acc
            cs[i, k] = qj
            cs[i, nc + k] = w
            cs[i, 2 * nc + k] = acc
            cs[i, 3 * nc + k] = d1
            p = cy.params[k]
            cs[i, 4 * nc + k] = actuator.eq1_cylinder_force(
                sm[i, col.pa[k]], sm[i, col.pb[k]], vk, p[0], p[1], p[2], p[3], p[4])
            if not math.isfinite(qj):
                row_bad = True
        if row_bad:
            bad += 1
    return bad


@njit(cache=True, nogil=True)
def unpack_states(st, joints, theta, theta_joint, q, qd, qdd, arm, force):  # type: ignore[no-untyped-def]
    """Rows of :func:`cylinder_states` back into q, qd, qdd (n, n_joints; zero but the
    cylinder joints and, if theta_joint >= 0, q of that joint = theta), arm and force
    (n, n_c)."""
    nc = joints.shape[0]
    nj = q.shape[1]
    for i in range(st.shape[0]):
        for j in range(nj):
            q[i, j] = 0.0
            qd[i, j] = 0.0
            qdd[i, j] = 0.0
        for k in range(nc):
            j = joints[k]
            q[i, j] = st[i, k]
            qd[i, j] = st[i, nc + k]
            qdd[i, j] = st[i, 2 * nc + k]
            arm[i, k] = st[i, 3 * nc + k]
            force[i, k] = st[i, 4 * nc + k]
        if theta_joint >= 0:
            q[i, theta_joint] = theta[i]


def derivative_filter(choice: SmoothingChoice, n_samples: int | None = None) -> tuple[int, int]:
    """(window, polynomial order) of the Savitzky–Golay filters that give a position channel's
    rate and acceleration from its derivative channel's smoothing choice: a window of 1 (no
    smoothing chosen) means 5, the order is at least 3 (an acceleration needs it) and below
    the window, and the window is cut to the largest odd length within ``n_samples``."""
    w = choice.window if choice.window > 1 else 5
    if n_samples is not None:
        w = min(w, n_samples - (1 - n_samples % 2))
    return w, min(max(choice.polyorder, 3), w - 1)


def spline_layout(cm: ChannelMap, n_channels: int, velocity: Literal["spline", "newton"],
                  integrated: int | None, qi: Quantities,
                  drive_free: list[int]) -> tuple[list[int], list[int], I64, I64]:
    """Which spline column feeds which grid quantity: (position columns, spline columns of the
    smoothed samples, src, der) (quantity table: :mod:`cranetwin.twin.gridpass`).

    The smoothed sample rows hold the ``n_channels`` working channels, the integrated angle,
    then the rates and accelerations of the derivative channels (rod positions, angles sent).
    Rates and accelerations are splined from those (``velocity="spline"``), or come from
    Newton's divided differences of the positions, appended after the listed columns, and that
    spline's derivative (``"newton"``). An integrated angle takes its rate and acceleration
    from its own spline.

    Args:
        cm: The channel map; n_channels: its number of working channels.
        velocity: As ``ReplayOptions.velocity``.
        integrated: The torque drive (index) whose angle is integrated, or None.
        qi: The quantity table's layout.
        drive_free: Per torque drive, its joint's index among the free joints.
    """
    nc = len(cm.s)
    nd = len(cm.derivative_channels)
    rod_s, rod_v, rod_a = (slice(o, o + nc) for o in (qi.s, qi.v, qi.a))
    # per drive: the column of its angle (an angle channel, the integrated one, or none)
    theta_cols = [a if a is not None else (n_channels if d == integrated else None)
                  for d, a in enumerate(cm.angles)]
    pos_cols = list(cm.s) + [c for c in theta_cols if c is not None]
    cols: list[int] = list(pos_cols)
    src = np.full(qi.size, -1, dtype=np.int64)
    der = np.zeros_like(src)
    src[rod_s] = np.arange(nc)
    n_torques = sum(t is not None for t in cm.torques)
    base = len(cols) + len(cm.p_a) + len(cm.p_b) + n_torques  # Newton rates (after cols)
    if velocity == "newton":
        src[rod_v] = base + np.arange(nc)
        src[rod_a] = base + np.arange(nc)
        der[rod_a] = 1
    else:
        rates = [n_channels + 1 + i for i in range(nd)]
        accs = [n_channels + 1 + nd + i for i in range(nd)]
        src[rod_v] = len(cols) + np.arange(nc)
        src[rod_a] = len(cols) + nd + np.arange(nc)
        cols += rates + accs
    rank = nc  # the angle's index among pos_cols
    for d, col in enumerate(theta_cols):
        if col is None:
            continue  # held at 0
        th = qi.free + 3 * drive_free[d]
        src[th] = rank
        if velocity == "newton":
            src[th + 1 : th + 3] = base + rank
            der[th + 2] = 1
        elif d != integrated:  # its rate and acceleration from the derivative filters
            di = cm.derivative_channels.index(col)
            src[th + 1] = len(pos_cols) + di
            src[th + 2] = len(pos_cols) + nd + di
        else:
            src[th + 1 : th + 3] = rank
            der[th + 1] = 1
            der[th + 2] = 2
        rank += 1
    src[qi.pa : qi.pa + nc] = len(cols) + np.arange(nc)
    cols += list(cm.p_a)
    src[qi.pb : qi.pb + nc] = len(cols) + np.arange(nc)
    cols += list(cm.p_b)
    for d, t in enumerate(cm.torques):
        if t is not None:
            src[qi.torque + drive_free[d]] = len(cols)
            cols.append(t)
    return pos_cols, cols, src, der
