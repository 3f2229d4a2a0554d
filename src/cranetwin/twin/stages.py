"""Stages of the replay at the sample instants, as pure functions of a
:class:`cranetwin.twin.plan.ReplayPlan` and arrays: smoothing (:func:`smooth_rows`), the
cylinder states (:func:`cylinder_states`, :func:`sample_states`, :func:`joint_motion`), Eq. 1–2
(:func:`eq12`), the payload regression's weights and estimate (:func:`payload_weights`,
:func:`estimate_payload`), the derivative filters and the spline layout (which spline column
feeds which grid quantity).

:class:`cranetwin.twin.replay.TwinStream` buffers the samples and calls these,
:func:`cranetwin.twin.slew.integrate_free_joints` and :func:`cranetwin.twin.chunk.chunk`.
Shapes: n samples, n_j joints, n_c cylinders; units SI (m, rad, Pa, N, N·m, kg).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Literal, NamedTuple

import numpy as np
import numpy.typing as npt
from numba import njit

from cranetwin import physics
from cranetwin.errors import PhysicsError, TwinError
from cranetwin.physics import actuator
from cranetwin.signal import (
    ICI_WINDOWS,
    SmoothingChoice,
    ici_smooth_pair,
    savgol_smooth,
)
from cranetwin.signal.quantisation import CONTEXT as RECONSTRUCT_CONTEXT
from cranetwin.signal.quantisation import reconstruct_columns
from cranetwin.signal.savgol import savgol_columns
from cranetwin.twin import kintable
from cranetwin.twin.channels import ChannelMap
from cranetwin.twin.gridpass import Quantities
from cranetwin.twin.observability import systematic_force_sigma
from cranetwin.twin.payload import regression_payload

if TYPE_CHECKING:
    from cranetwin.twin.plan import ReplayPlan

F64 = npt.NDArray[np.float64]
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
                  integrated: tuple[int, ...], qi: Quantities,
                  drive_free: tuple[int, ...]) -> tuple[list[int], list[int], I64, I64]:
    """Which spline column feeds which grid quantity: (position columns, spline columns of the
    smoothed samples, src, der) (quantity table: :mod:`cranetwin.twin.gridpass`).

    The smoothed sample rows hold the ``n_channels`` working channels, the integrated angles
    (one column per integrated drive, in ``integrated`` order), then the rates and
    accelerations of the derivative channels (rod positions, angles sent).
    Rates and accelerations are splined from those (``velocity="spline"``), or come from
    Newton's divided differences of the positions, appended after the listed columns, and that
    spline's derivative (``"newton"``). An integrated angle takes its rate and acceleration
    from its own spline.

    Args:
        cm: The channel map; n_channels: its number of working channels.
        velocity: As ``ReplayOptions.velocity``.
        integrated: The torque drives (indices) whose angle is integrated.
        qi: The quantity table's layout.
        drive_free: Per torque drive, its joint's index among the free joints.
    """
    nc = len(cm.s)
    nd = len(cm.derivative_channels)
    rod_s, rod_v, rod_a = (slice(o, o + nc) for o in (qi.s, qi.v, qi.a))
    # per drive: the column of its angle (an angle channel, the integrated one, or none)
    n_int = len(integrated)
    theta_cols = [a if a is not None else
                  (n_channels + integrated.index(d) if d in integrated else None)
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
        rates = [n_channels + n_int + i for i in range(nd)]
        accs = [n_channels + n_int + nd + i for i in range(nd)]
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
        elif d not in integrated:  # its rate and acceleration from the derivative filters
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


def smooth_rows(plan: ReplayPlan, choices: tuple[SmoothingChoice, ...], raw: F64, dt: float,
                edges: tuple[bool, bool]) -> F64:
    """Smoothed sample rows (:mod:`cranetwin.twin.plan` layout; the integrated angles' columns
    NaN) from regularised rows ``raw`` (n, nch) with period dt [s].

    Pressure pairs chosen adaptive get LPA-ICI decided on their force; other channels their
    Savitzky–Golay window; every derivative channel its value, rate and acceleration from one
    batched filter bank (``edges``: whether the rows reach within a window of the data's
    start, end: only there are the end fits needed). A channel on a coarse lattice
    (:attr:`SmoothingChoice.step` > 0) is reconstructed through its level crossings first
    (:func:`cranetwin.signal.quantisation.reconstruct_columns`; :func:`margins` adds its
    context)."""
    nch = plan.nch
    raw = reconstruct_columns(raw, [c.step for c in choices[:nch]])
    dcols = list(plan.cmap.derivative_channels)
    out = np.empty((raw.shape[0], plan.width))
    written: set[int] = set()  # the rest is NaN (the integrated angles' columns)
    groups: dict[tuple[int, int], list[int]] = {}
    in_bank = set(dcols)  # position channels: value and rates from one filter bank
    for j, choice in enumerate(choices[:nch]):
        if choice.adaptive:
            continue
        if choice.window > 1 and raw.shape[0] < choice.window:
            raise TwinError(f"{raw.shape[0]} samples are fewer than the smoothing window "
                            f"{choice.window}")
        if j not in in_bank:
            groups.setdefault((choice.window, choice.polyorder), []).append(j)
    for ci, cyl in enumerate(plan.machine.cylinders):
        ia, ib = plan.cmap.p_a[ci], plan.cmap.p_b[ci]
        ch = choices[ia]
        if ch.adaptive:
            ws = tuple(w for w in ICI_WINDOWS if w <= ch.window)
            out[:, [ia, ib]] = ici_smooth_pair(raw[:, ia], raw[:, ib], cyl.area_a_m2,
                                               cyl.area_b_m2, ch.sigma, ws, ch.polyorder)
            written.update((ia, ib))
    for (w, p), cols in groups.items():
        out[:, cols] = savgol_smooth(raw[:, cols], w, p)
        written.update(cols)
    bank: list[list[tuple[int, int, int]]] = []
    for i, j in enumerate(dcols):
        w, p = derivative_filter(choices[nch + i], raw.shape[0])
        cv = choices[j]
        bank.append([(cv.window, cv.polyorder, 0), (w, p, 1), (w, p, 2)])
    if bank:  # every position channel's value, rate and acceleration: one batched FFT
        outs = savgol_columns(raw[:, dcols], bank, delta=dt, edges=edges)
        v0, a0 = plan.sample_cols.v0, plan.sample_cols.a0
        for i, j in enumerate(dcols):
            out[:, j], out[:, v0 + i], out[:, a0 + i] = outs[i]
            written.update((j, v0 + i, a0 + i))
    unset = [c for c in range(out.shape[1]) if c not in written]
    if unset:
        out[:, unset] = np.nan
    return out


def clip_rods(plan: ReplayPlan, s: F64) -> F64:
    """Rod positions (n, n_c) [m] clipped to [0, stroke], as a new C-contiguous array."""
    out: F64 = np.maximum(s, 0.0)
    np.minimum(out, plan.cylinders.stroke, out=out)
    return out


def joint_motion(plan: ReplayPlan, s: F64, v: F64, a: F64,
                 q_other: F64) -> tuple[F64, F64, F64, F64]:
    """q, qd, qdd (n, n_j) and moment arms ds/dq (n, n_c) from rod positions s (within the
    strokes), rates v and accelerations a (n, n_c), the free joints at q_other (n, n_free),
    in one pass through the kinematics tables.

    Raises:
        TwinError: A rod position does not fit the machine geometry.
    """
    n = s.shape[0]
    nj = plan.machine.n_joints
    q = np.zeros((n, nj))
    qd = np.zeros((n, nj))
    qdd = np.zeros((n, nj))
    if q_other.shape[1]:
        q[:, list(plan.free)] = q_other
    arm = np.empty((n, len(plan.machine.cylinders)))
    cy = plan.cylinders
    kintable.table_motion_batch(cy.table, cy.table_ok, cy.cyl, np.ascontiguousarray(s),
                                np.ascontiguousarray(v), np.ascontiguousarray(a), q, qd, qdd,
                                arm)
    if not np.all(np.isfinite(q[:, plan.cyl_joint])):
        try:  # the descriptive error
            physics.joint_motion_and_arms(plan.machine, s, v, a,
                                          q_other if q_other.shape[1] else None)
        except PhysicsError as exc:
            raise TwinError(f"rod positions do not fit the machine geometry: {exc}") from exc
        raise TwinError("rod positions do not fit the machine geometry")
    return q, qd, qdd, arm


def eq12(plan: ReplayPlan, pa: F64, pb: F64, v: F64) -> F64:
    """Eq. 1–2 for every cylinder, (n, n_c) [N] (as physics.cylinder_forces)."""
    out = np.empty(v.shape)
    actuator.cylinder_forces_into(pa, pb, v, plan.cylinders.params, out)
    return out


def sample_states(plan: ReplayPlan, sm: F64) -> tuple[F64, F64, F64, F64, F64, F64]:
    """q, qd, qdd (n, n_j; free joints at 0, passive ones at their fixed value), cylinder
    forces, moment arms (n, n_c) and the cylinder states rows (:func:`cylinder_states`,
    (n, 5·n_c)) from smoothed rows ``sm``, in one compiled pass."""
    n = sm.shape[0]
    nj = plan.machine.n_joints
    nc = len(plan.machine.cylinders)
    q = np.zeros((n, nj))
    qd = np.zeros((n, nj))
    qdd = np.zeros((n, nj))
    cs = np.empty((n, 5 * nc))
    fj = plan.free_joints
    if np.any(fj.hold):
        q[:, fj.joint] = fj.hold
    col = plan.sample_cols
    if cylinder_states(sm, col, plan.cylinders, q, qd, qdd, cs):  # the descriptive error
        joint_motion(plan, clip_rods(plan, sm[:, col.s]), sm[:, col.v0 : col.v0 + nc],
                     sm[:, col.a0 : col.a0 + nc], np.zeros((n, nj - nc)))
        raise TwinError("rod positions do not fit the machine geometry")
    return q, qd, qdd, cs[:, 4 * nc :], cs[:, 3 * nc : 4 * nc], cs


def payload_weights(plan: ReplayPlan,
                    choices: tuple[SmoothingChoice, ...]) -> tuple[F64, F64, F64, F64]:
    """Weights 1/σ² per cylinder joint (n_c,), the independent errors per sample of each
    (n_c,), the raw noise of each cylinder's hydraulic force (n_c,) [N], from the pressures'
    smoothing choices, and the systematic force error σ_b,F each cylinder's pressure sensors
    leave beyond that noise (n_c,) [N] (stated accuracy or half a detected quantisation step,
    :func:`cranetwin.twin.observability.systematic_force_sigma`; 0 where neither)."""
    m = plan.machine
    weights = np.empty(len(m.cylinders))
    frac = np.empty(len(m.cylinders))
    noise = np.empty(len(m.cylinders))
    for c, cyl in enumerate(m.cylinders):
        ch = choices[plan.cmap.p_a[c]]
        noise[c] = max(ch.sigma, 0.0)
        weights[c] = 1.0 / (max(ch.risk, 0.0) + cyl.friction.coulomb ** 2)
        # independent errors per sample ≈ the smoother's variance gain, risk/σ²
        frac[c] = float(np.clip(ch.risk / ch.sigma**2, 1e-3, 1.0)) if ch.sigma > 0 else 1.0
    steps = {name: c.step for name, c in zip(plan.cmap.names, choices, strict=False)}
    return weights, frac, noise, systematic_force_sigma(m, noise, steps)


def payload_regressors(plan: ReplayPlan, motion: tuple[F64, F64, F64]) -> tuple[F64, F64]:
    """Inverse-dynamics joint loads (t0, t1) (n, n_j) at motion = (q, qd, qdd) (n, n_j)
    without payload and with 1 kg at the load point: with payload m they are
    t0 + m·(t1 − t0)."""
    q, qd, qdd = motion
    nj = plan.machine.n_joints
    t0 = np.empty((q.shape[0], nj))  # joint loads without payload
    t1 = np.empty((q.shape[0], nj))  # and with 1 kg at the load point
    c = np.ascontiguousarray
    plan.kernels.rnea_payload(c(q), c(qd), c(qdd), t0, t1)
    return t0, t1


def estimate_payload(plan: ReplayPlan, motion: tuple[F64, F64, F64], f: F64, arm: F64,
                     setting: tuple[F64, F64, int, int, F64, F64],
                     regressors: tuple[F64, F64] | None = None,
                     sys_std_out: F64 | None = None) -> tuple[F64, F64]:
    """Payload and its standard error (n,) [kg] at every instant of motion = (q, qd, qdd)
    (n, n_j) (windows cut at its ends) from the cylinder forces f and moment arms (n, n_c);
    setting = (weights, independent fractions, prefilter half, half window, raw force noise
    per cylinder [N], systematic force error per cylinder [N]) (:mod:`cranetwin.twin.payload`,
    :func:`payload_weights`); ``regressors``: the :func:`payload_regressors` of ``motion`` if
    already computed. The σ includes what the pressure sensors' stated accuracy (or half a
    detected quantisation step) leaves beyond the estimated noise as a systematic force error
    per cylinder (:func:`cranetwin.twin.observability.systematic_force_sigma`; none stated or
    detected: random error only); ``sys_std_out`` (n,), if given, receives that part of the σ
    alone [kg] (it does not average out over a lift, :mod:`cranetwin.twin.lifts`)."""
    t0, t1 = payload_regressors(plan, motion) if regressors is None else regressors
    weights, frac, pf, half, noise, systematic = setting
    return regression_payload(t0, t1, f, arm, plan.cyl_joint, weights, pf, half, frac, noise,
                              systematic, sys_std_out)


def margins(choices: tuple[SmoothingChoice, ...] | None, nch: int, period: float,
            payload_window_s: float) -> tuple[int, int, int]:
    """(smoothing half window (with a quantised channel's reconstruction reach), payload half
    window, prefilter width) [samples].

    The prefilter is the moving average applied to the payload regression's force and
    regressor alike: the longest derivative window. The accelerations are smoothed over it,
    the pressures are not; low-passing both removes the mismatch ("filter both sides"),
    which otherwise biases the estimate by tens of kg in fast motion."""
    hw = 0 if choices is None else max(c.window // 2 for c in choices)
    if choices is not None and any(c.step > 0 for c in choices[:nch]):
        hw += RECONSTRUCT_CONTEXT  # the reconstruction's context (:func:`smooth_rows`)
    half = max(1, int(round(payload_window_s / period / 2)))
    pf = 1 if choices is None else max([1] + [c.window for c in choices[nch:]])
    return hw, half, pf

