"""The fixed-step integration loop: hydraulics + multibody forward dynamics, in numba.

Any serial machine: ``nj`` joints, ``nc`` cylinders (each on a revolute or prismatic joint,
directly or through its linkage), ``nd`` torque drives (e.g. a hydraulic slewing/swing motor),
and free joints with neither (end stops at their limits only). Array layouts:
:mod:`cranetwin.sim.layout`. Each step:

1. Operator commands U_cmd(t) (:mod:`cranetwin.sim.scenario`), payload m_p(t), contact force
   F_c(t) at the load point (world frame).
2. Rod positions and moment arms s_k, ds_k/dq from ``physics.kernels.cylinder_kinematics``;
   rod velocities v_k = ds_k/dq · qd.
3. Cylinder forces (paper Eq. 1–2, ``physics.actuator.eq1_cylinder_force``, + end stops) and
   the drive torques give the actuator loads tau_j = Σ F_k·ds_k/dq_j + (T_d − F_fr,d(ω)) (virtual
   work); the contact force adds J_p(q)ᵀ·F_c (J_p the load point's translational Jacobian).
4. Forward dynamics ``M(q)·qdd = tau + J_pᵀ·F_c − h(q, qd)`` with M from
   ``physics.rnea.mass_matrix_rnea_into`` (unit-acceleration columns) and h from
   ``physics.kernels.rnea_into`` (zero acceleration); Paper Eq. 4 solved for qdd.
5. Update. ``semi-implicit`` (default, 1e-4 s as in the paper): symplectic Euler for the
   mechanics (qd += dt·qdd, then q += dt·qd); chamber pressures follow the rod displacement of
   that step through the exact closed-chamber law p − p0 = −B_oil·ln(Ve/Ve0) (so the oil spring
   neither gains nor loses energy), then the valve/relief flows, linearly implicit; exact spool
   lag. ``rk4``: classical
   Runge–Kutta on the whole state (commands held over the step); it conserves energy to ~1e-7
   over 10 s and is used to check the energy balance.

Truth is recorded every ``truth_every`` steps (state, qdd, forces as the step used them), sensor
snapshots at precomputed step indices (see :mod:`cranetwin.sim.sensors`).

Arguments travel as records (named tuples, which numba passes as plain structs):
:class:`SimModel` — the compiled chain and cylinders (``physics.chain``), the cylinder,
circuit, drive and free-joint tables (:mod:`cranetwin.sim.hydraulics`), drive and free joint
indices, sizes, and the passive joints (``Joint.fixed_value``: locked, qdd = 0, the forward
dynamics solved for the other joints); :class:`StepBuffers`, what one evaluation writes;
:class:`Records`, the truth rows and sensor snapshots; and ``sched`` = the scenario's tables
(:class:`cranetwin.sim.scenario.ScenarioTables`, in field order).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import numpy.typing as npt
from numba import njit

import cranetwin.jitcache  # noqa: F401  (first: drops stale numba caches)
from cranetwin.physics.actuator import eq1_cylinder_force, eq2_friction
from cranetwin.physics.chain import CYL_BLOCK, HEADER, JOINT_BLOCK, PRISMATIC
from cranetwin.physics.kernels import cylinder_kinematics, joint_transforms, rnea_into
from cranetwin.physics.rnea import mass_matrix_rnea_into
from cranetwin.sim.hydraulics import (
    C_A1,
    C_A2,
    C_B,
    C_CEND,
    C_FC,
    C_KEND,
    C_QN,
    C_STROKE,
    C_TAU,
    C_V0,
    C_VC,
    G_BHOSE,
    G_BOIL,
    G_KREL,
    G_PMIN,
    G_PREL,
    G_PS,
    G_PT,
    G_PTR,
    S_B,
    S_CLIM,
    S_FC,
    S_HI,
    S_KLIM,
    S_KS,
    S_LO,
    S_TAU,
    S_TLEAK,
    S_TMAX,
    S_UMAX,
    S_VC,
    S_WMAX,
    capacitances,
    end_stop,
    joint_limit,
    pressure_step,
    relief,
    spool_step,
    valve_flows,
)
from cranetwin.sim.layout import L_NC, L_ND, L_NJ, state_offsets

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]


class SimModel(NamedTuple):
    """The machine as the loop reads it (module docstring)."""

    chain: F64
    """Compiled chain (``physics.chain``)."""
    cyl: F64
    """Compiled cylinders (``physics.chain``)."""
    hc: F64
    """Cylinder table (n_c, ``C_*``) (:mod:`cranetwin.sim.hydraulics`)."""
    hg: F64
    """Circuit constants (``G_*``)."""
    hs: F64
    """Drive table (n_d, ``S_*``)."""
    hf: F64
    """Free joints' end stops (n_free, ``S_*``)."""
    dj: I64
    """Joint of each drive (n_d,)."""
    fj: I64
    """Free joints (n_free,)."""
    lay: I64
    """Sizes (:mod:`cranetwin.sim.layout`)."""
    lk: I64
    """Passive joints, locked (n_passive,)."""


class StepBuffers(NamedTuple):
    """What :func:`_eval` writes for one state: rod positions s, moment arms dsdq, rod
    velocities v, cylinder forces (n_c,) [m, m/rad or m/m, m/s, N]; actuator loads tau,
    contact loads tau_ext, accelerations qdd (n_j,); flow (4·n_c,) = [QA, QB, gA, gB] per
    cylinder; dtorque (n_d,) the drives' dT/dt [N·m/s]."""

    s: F64
    dsdq: F64
    v: F64
    force: F64
    tau: F64
    tau_ext: F64
    qdd: F64
    flow: F64
    dtorque: F64


class Records(NamedTuple):
    """Where :func:`run_steps` writes: truth rows every ``truth_every`` steps into ``truth``
    (m, n_t), sensor snapshots at the steps ``snap_steps`` into ``snaps`` (m', n_snap);
    ``idx`` = [next truth row, next snapshot, failed flag]."""

    truth_every: int
    truth: F64
    snap_steps: I64
    snaps: F64
    idx: I64



# flags
F_FRICTION, F_VALVES, F_LOSSES, F_SCHEME = 0, 1, 2, 3
SCHEME_SEMI_IMPLICIT = 0.0
SCHEME_RK4 = 1.0


@njit(cache=True)
def _interp(tk: F64, vk: F64, n: int, t: float, cur: I64, c: int, before: float) -> float:
    """Piecewise-linear knots (held after the last), with a monotone cursor ``cur[c]``."""
    if n == 0:
        return before
    i = cur[c]
    while i + 1 < n and tk[i + 1] <= t:
        i += 1
    cur[c] = i
    if t < tk[0]:
        return before
    if i == n - 1:
        return float(vk[n - 1])
    t0 = tk[i]
    t1 = tk[i + 1]
    if t1 <= t0:
        return float(vk[i + 1])
    w = (t - t0) / (t1 - t0)
    return float(vk[i] + w * (vk[i + 1] - vk[i]))


@njit(cache=True)
def _commands(t, x, s, dj, nd, sched, cur, u_cmd, fext):  # type: ignore[no-untyped-def]
    """Operator commands at time t into ``u_cmd`` (na,) [V] (drives, then cylinders) and the
    contact force into ``fext`` (3,) [N, world frame]; returns the payload [kg].

    A tracked actuator follows its drive joint's position x[dj[a]] or its rod position s.
    Cursors: cur[a] voltage, cur[na + a] target, cur[2·na] payload, cur[2·na + 1] contact.
    """
    u_t, u_v, u_n, r_t, r_v, r_n, gain, umax, pay_t, pay_m, f_t, f_v, f_n = sched
    na = u_cmd.shape[0]
    for a in range(na):
        u = _interp(u_t[a], u_v[a], u_n[a], t, cur, a, 0.0)
        if r_n[a] > 0:
            y = x[dj[a]] if a < nd else s[a - nd]
            r = _interp(r_t[a], r_v[a], r_n[a], t, cur, na + a, r_v[a, 0])
            u += gain[a] * (r - y)
        u_cmd[a] = min(max(u, -umax[a]), umax[a])
    i = cur[2 * na]
    while i + 1 < pay_t.shape[0] and pay_t[i + 1] <= t:
        i += 1
    cur[2 * na] = i
    if f_n > 0:
        for m in range(3):
            fext[m] = _interp(f_t, f_v[m], f_n, t, cur, 2 * na + 1, 0.0)
    return float(pay_m[i])


@njit(cache=True)
def _contact_loads(chain, q, f, work, out):  # type: ignore[no-untyped-def]
    """Generalised forces out (nj,) = J_p(q)ᵀ·f of a world-frame force f (3,) [N] acting at the
    load point: revolute joint i (axis a_i through o_i, world) gets (a_i × (p − o_i))·f [N·m],
    prismatic a_i·f [N]; joints beyond the load body get 0. ``work``: scratch (nj, 12)."""
    nj = int(chain[0])
    lb = int(chain[4])
    joint_transforms(chain, q, work)
    # world pose of the running body: rotation r (row-major) and origin (px, py, pz)
    r = np.eye(3)
    px = 0.0
    py = 0.0
    pz = 0.0
    ax = np.empty((nj, 3))
    org = np.empty((nj, 3))
    tip = np.zeros(3)
    for i in range(nj):
        o = HEADER + i * JOINT_BLOCK
        npx = px + r[0, 0] * work[i, 9] + r[0, 1] * work[i, 10] + r[0, 2] * work[i, 11]
        npy = py + r[1, 0] * work[i, 9] + r[1, 1] * work[i, 10] + r[1, 2] * work[i, 11]
        npz = pz + r[2, 0] * work[i, 9] + r[2, 1] * work[i, 10] + r[2, 2] * work[i, 11]
        nr = np.empty((3, 3))
        for a in range(3):
            for b in range(3):
                nr[a, b] = (r[a, 0] * work[i, b] + r[a, 1] * work[i, 3 + b]
                            + r[a, 2] * work[i, 6 + b])
        r = nr
        px, py, pz = npx, npy, npz
        for a in range(3):
            ax[i, a] = (r[a, 0] * chain[o + 1] + r[a, 1] * chain[o + 2]
                        + r[a, 2] * chain[o + 3])
        org[i, 0], org[i, 1], org[i, 2] = px, py, pz
        if i == lb:
            for a in range(3):
                tip[a] = (r[a, 0] * chain[5] + r[a, 1] * chain[6] + r[a, 2] * chain[7]
                          + org[i, a])
    for i in range(nj):
        if i > lb:
            out[i] = 0.0
        elif chain[HEADER + i * JOINT_BLOCK] == PRISMATIC:
            out[i] = ax[i, 0] * f[0] + ax[i, 1] * f[1] + ax[i, 2] * f[2]
        else:
            dx = tip[0] - org[i, 0]
            dy = tip[1] - org[i, 1]
            dz = tip[2] - org[i, 2]
            cx = ax[i, 1] * dz - ax[i, 2] * dy
            cy = ax[i, 2] * dx - ax[i, 0] * dz
            cz = ax[i, 0] * dy - ax[i, 1] * dx
            out[i] = cx * f[0] + cy * f[1] + cz * f[2]


@njit(cache=True)
def _solve_spd(m: F64, b: F64, out: F64, lo: F64) -> None:
    """Solve m·out = b for symmetric positive definite m (n, n) by Cholesky (lo: scratch)."""
    n = b.shape[0]
    for i in range(n):
        for j in range(i + 1):
            acc = m[i, j]
            for k in range(j):
                acc -= lo[i, k] * lo[j, k]
            if i == j:
                lo[i, i] = math.sqrt(acc)
            else:
                lo[i, j] = acc / lo[j, j]
    for i in range(n):
        acc = b[i]
        for k in range(i):
            acc -= lo[i, k] * out[k]
        out[i] = acc / lo[i, i]
    for i in range(n - 1, -1, -1):
        acc = out[i]
        for k in range(i + 1, n):
            acc -= lo[k, i] * out[k]
        out[i] = acc / lo[i, i]


@njit(cache=True, inline="always")
def _eval(model, x, payload, fext, flags, buf, scr, kin_ready):  # type: ignore[no-untyped-def]
    """Everything the state implies: kinematics, forces, accelerations, chamber flows.

    ``kin_ready``: s and dsdq already hold the kinematics of x (skip recomputing them).
    Inlined into its callers: as a separate function, unpacking the ``model`` and ``scr`` tuples
    at every step cost ≈ 10 % of the loop (reference counting); inlined, it runs as fast as
    the former fixed-size 4-joint loop.
    ``scr`` = (mm, hb, lo, wr, work, e, zero, rhs): scratch of the forward dynamics.

    Writes the :class:`StepBuffers` ``buf``: s, dsdq, v, force (nc,), tau (actuator loads),
    tau_ext (J_pᵀ·F_c, only while the contact force is not zero), qdd (nj,),
    flow (4·nc,) = [QA, QB, gA, gB] per cylinder (valve + relief, into the chamber, and their
    −∂/∂p), dtorque (nd,) the drives' dT/dt [N·m/s].
    """
    chain, cyl, hc, hg, hs, hf, dj, fj, lay, lk = model
    mm, hb, lo, wr, work, e, zero, rhs = scr
    s, dsdq, v, force, tau, tau_ext, qdd, flow, dtorque = buf
    nj = lay[L_NJ]
    nc = lay[L_NC]
    nd = lay[L_ND]
    x_pa, x_pb, x_u, x_ts, _ = state_offsets(lay)
    q = x[0:nj]
    qd = x[nj:2 * nj]
    if not kin_ready:
        cylinder_kinematics(cyl, q, s, dsdq)
    for j in range(nj):
        tau[j] = 0.0
    fric = flags[F_FRICTION] > 0.0
    valves = flags[F_VALVES] > 0.0
    losses = flags[F_LOSSES] > 0.0
    for k in range(nc):
        jk = int(cyl[1 + k * CYL_BLOCK + 1])
        vk = dsdq[k] * qd[jk]
        v[k] = vk
        pa = x[x_pa + k]
        pb = x[x_pb + k]
        if fric:
            f = eq1_cylinder_force(pa, pb, vk, hc[k, C_A1], hc[k, C_A2], hc[k, C_FC],
                                   hc[k, C_VC], hc[k, C_B])
        else:
            f = pa * hc[k, C_A1] - pb * hc[k, C_A2]
        f += end_stop(s[k], vk, hc[k, C_STROKE], hc[k, C_KEND], hc[k, C_CEND])
        force[k] = f
        tau[jk] += f * dsdq[k]
        qa = 0.0
        qb = 0.0
        ga = 0.0
        gb = 0.0
        if valves:
            qa, qb, ga, gb = valve_flows(hc[k, C_QN], x[x_u + nd + k], pa, pb, hg[G_PS],
                                         hg[G_PT], hg[G_PTR])
        if losses:
            ra, dra = relief(pa, hg[G_PREL], hg[G_KREL])
            rb, drb = relief(pb, hg[G_PREL], hg[G_KREL])
            qa += ra
            qb += rb
            ga += dra
            gb += drb
        flow[4 * k] = qa
        flow[4 * k + 1] = qb
        flow[4 * k + 2] = ga
        flow[4 * k + 3] = gb
    for d in range(nd):
        jd = dj[d]
        w = qd[jd]
        torque = x[x_ts + d]
        tq = torque
        if fric:
            tq -= eq2_friction(w, hs[d, S_FC], hs[d, S_VC], hs[d, S_B])
        tq += joint_limit(q[jd], w, hs[d, S_LO], hs[d, S_HI], hs[d, S_KLIM], hs[d, S_CLIM])
        tau[jd] += tq
        w_cmd = x[x_u + d] / hs[d, S_UMAX] * hs[d, S_WMAX] if valves else 0.0
        dt_d = hs[d, S_KS] * (w_cmd - w)
        if losses:
            dt_d -= torque / hs[d, S_TLEAK]
        dtorque[d] = dt_d
    for m in range(fj.shape[0]):
        jf = fj[m]
        tau[jf] += joint_limit(q[jf], qd[jf], hf[m, S_LO], hf[m, S_HI], hf[m, S_KLIM],
                               hf[m, S_CLIM])
    contact = fext[0] != 0.0 or fext[1] != 0.0 or fext[2] != 0.0
    if contact:      # tau_ext is only read (below) when there is contact
        _contact_loads(chain, q, fext, work, tau_ext)
    # forward dynamics: M qdd = tau + J_pᵀ F_c − h   (Eq. 4)
    mass_matrix_rnea_into(chain, q, payload, mm, (zero, e, hb, wr, work))
    rnea_into(chain, q, qd, zero, payload, 1.0, hb, wr, work)
    if contact:
        for j in range(nj):
            rhs[j] = tau[j] + tau_ext[j] - hb[j]
    else:
        for j in range(nj):
            rhs[j] = tau[j] - hb[j]
    for m in range(lk.shape[0]):  # passive joints are locked: qdd = 0, the rest reduced
        j = lk[m]
        for i in range(nj):
            mm[i, j] = 0.0
            mm[j, i] = 0.0
        mm[j, j] = 1.0
        rhs[j] = 0.0
    _solve_spd(mm, rhs, qdd, lo)


@njit(cache=True)
def _deriv(model, x, payload, fext, u_cmd, flags, dx, buf, scr):  # type: ignore[no-untyped-def]
    """dx/dt of the whole state (for the RK4 scheme) into dx; ``buf``: :class:`StepBuffers`."""
    _, _, hc, hg, hs, _, _, _, lay, _ = model
    s, _, v, _, _, _, qdd, flow, dtorque = buf
    nj = lay[L_NJ]
    nc = lay[L_NC]
    nd = lay[L_ND]
    x_pa, x_pb, x_u, x_ts, _ = state_offsets(lay)
    _eval(model, x, payload, fext, flags, buf, scr, False)
    for j in range(nj):
        dx[j] = x[nj + j]
        dx[nj + j] = qdd[j]
    for k in range(nc):
        ca, cb = capacitances(s[k], hc[k, C_A1], hc[k, C_A2], hc[k, C_STROKE], hc[k, C_V0],
                              hg[G_BOIL], hg[G_BHOSE])
        dx[x_pa + k] = (flow[4 * k] - hc[k, C_A1] * v[k]) / ca
        dx[x_pb + k] = (flow[4 * k + 1] + hc[k, C_A2] * v[k]) / cb
        dx[x_u + nd + k] = (u_cmd[nd + k] - x[x_u + nd + k]) / hc[k, C_TAU]
    for d in range(nd):
        dx[x_u + d] = (u_cmd[d] - x[x_u + d]) / hs[d, S_TAU]
        dx[x_ts + d] = dtorque[d]


@njit(cache=True)
def run_steps(model, sched, flags, dt, x, span, rec, cur):  # type: ignore[no-untyped-def]
    """Advance the state ``x`` in place over steps i0 … i1−1 (global step indices).

    Args:
        model: :class:`SimModel` (module docstring).
        sched: Scenario tables (u_t, u_v, u_n, r_t, r_v, r_n, gain, umax, pay_t, pay_m, f_t,
            f_v, f_n).
        flags: ``F_*`` switches. dt: Step [s]. x: State (n_x,) (:mod:`~cranetwin.sim.layout`).
        span: (i0, i1, n_steps). rec: :class:`Records` (truth rows, sensor snapshots).
        cur: Scenario cursors (2·na + 2,).

    Records truth rows at every step index divisible by ``truth_every`` and sensor snapshots
    at ``snap_steps`` (``idx`` = [next truth row, next snapshot]), including step ``n_steps``
    (the final state) when i1 == n_steps. Raises nothing: a non-finite state stops the loop
    and leaves ``idx[2] = 1`` (checked by the caller).
    """
    chain, cyl, hc, hg, hs, hf, dj, fj, lay, lk = model
    i0, i1, n_steps = span
    truth_every, truth, snap_steps, snaps, idx = rec
    nj = lay[L_NJ]
    nc = lay[L_NC]
    nd = lay[L_ND]
    na = nd + nc
    x_pa, x_pb, x_u, x_ts, n_x = state_offsets(lay)
    # truth columns (layout.Layout.truth_blocks)
    t_q = 1
    t_qd = t_q + nj
    t_qdd = t_qd + nj
    t_s = t_qdd + nj
    t_v = t_s + nc
    t_pa = t_v + nc
    t_pb = t_pa + nc
    t_f = t_pb + nc
    t_ts = t_f + nc
    t_tau = t_ts + nd
    t_pay = t_tau + nj
    t_u = t_pay + 1
    t_fc = t_u + na
    # snapshot columns (layout.Layout.snap_*)
    sn_s = 2 * nc
    sn_ts = 3 * nc
    sn_q = sn_ts + nd
    s = np.empty(nc)
    dsdq = np.empty(nc)
    v = np.empty(nc)
    force = np.empty(nc)
    tau = np.empty(nj)
    tau_ext = np.zeros(nj)
    qdd = np.empty(nj)
    flow = np.empty(4 * nc)
    dtorque = np.empty(nd)
    buf = StepBuffers(s, dsdq, v, force, tau, tau_ext, qdd, flow, dtorque)
    scr = (np.empty((nj, nj)), np.empty(nj), np.zeros((nj, nj)), np.empty((nj, 6)),
           np.empty((nj, 12)), np.empty(nj), np.zeros(nj), np.empty(nj))
    u_cmd = np.empty(na)
    fext = np.zeros(3)
    s_new = np.empty(nc)
    dsdq_new = np.empty(nc)
    q_new = np.empty(nj)
    rk4 = flags[F_SCHEME] == SCHEME_RK4
    k1 = np.empty(n_x)
    k2 = np.empty(n_x)
    k3 = np.empty(n_x)
    k4 = np.empty(n_x)
    xt = np.empty(n_x)
    last = i1 + 1 if i1 == n_steps else i1
    # kinematics of the current state (the operator tracks rod positions); carried over steps
    cylinder_kinematics(cyl, x[0:nj], s, dsdq)
    for i in range(i0, last):
        t = i * dt
        payload = _commands(t, x, s, dj, nd, sched, cur, u_cmd, fext)
        _eval(model, x, payload, fext, flags, buf, scr, True)
        ok = True
        for j in range(nj):
            if not math.isfinite(qdd[j]):
                ok = False
        if not ok:
            idx[2] = 1
            return
        if i % truth_every == 0 and idx[0] < truth.shape[0]:
            r = idx[0]
            truth[r, 0] = t
            for j in range(nj):
                truth[r, t_q + j] = x[j]
                truth[r, t_qd + j] = x[nj + j]
                truth[r, t_qdd + j] = qdd[j]
                truth[r, t_tau + j] = tau[j]
            for a in range(na):
                truth[r, t_u + a] = u_cmd[a]
            for k in range(nc):
                truth[r, t_s + k] = s[k]
                truth[r, t_v + k] = v[k]
                truth[r, t_pa + k] = x[x_pa + k]
                truth[r, t_pb + k] = x[x_pb + k]
                truth[r, t_f + k] = force[k]
            for d in range(nd):
                truth[r, t_ts + d] = x[x_ts + d]
            truth[r, t_pay] = payload
            for m in range(3):
                truth[r, t_fc + m] = fext[m]
            idx[0] = r + 1
        while idx[1] < snap_steps.shape[0] and snap_steps[idx[1]] == i:
            r = idx[1]
            for k in range(nc):
                snaps[r, k] = x[x_pa + k]
                snaps[r, nc + k] = x[x_pb + k]
                snaps[r, sn_s + k] = s[k]
            for d in range(nd):
                snaps[r, sn_ts + d] = x[x_ts + d]
            for j in range(nj):
                snaps[r, sn_q + j] = x[j]
            idx[1] = r + 1
        if i == n_steps:
            break
        if rk4:
            _deriv(model, x, payload, fext, u_cmd, flags, k1, buf, scr)
            for m in range(n_x):
                xt[m] = x[m] + 0.5 * dt * k1[m]
            _deriv(model, xt, payload, fext, u_cmd, flags, k2, buf, scr)
            for m in range(n_x):
                xt[m] = x[m] + 0.5 * dt * k2[m]
            _deriv(model, xt, payload, fext, u_cmd, flags, k3, buf, scr)
            for m in range(n_x):
                xt[m] = x[m] + dt * k3[m]
            _deriv(model, xt, payload, fext, u_cmd, flags, k4, buf, scr)
            for m in range(n_x):
                x[m] += dt / 6.0 * (k1[m] + 2.0 * k2[m] + 2.0 * k3[m] + k4[m])
            for k in range(nc):
                x[x_pa + k] = max(x[x_pa + k], hg[G_PMIN])
                x[x_pb + k] = max(x[x_pb + k], hg[G_PMIN])
            cylinder_kinematics(cyl, x[0:nj], s, dsdq)
        else:
            # symplectic Euler for the mechanics
            for j in range(nj):
                x[nj + j] += dt * qdd[j]
                q_new[j] = x[j] + dt * x[nj + j]
            cylinder_kinematics(cyl, q_new, s_new, dsdq_new)
            for k in range(nc):
                ca, cb = capacitances(s[k], hc[k, C_A1], hc[k, C_A2], hc[k, C_STROKE],
                                      hc[k, C_V0], hg[G_BOIL], hg[G_BHOSE])
                ca1, cb1 = capacitances(s_new[k], hc[k, C_A1], hc[k, C_A2], hc[k, C_STROKE],
                                        hc[k, C_V0], hg[G_BOIL], hg[G_BHOSE])
                # piston motion: exact closed-chamber law p = p0 − B·ln(Ve/Ve0) (Ve = B·C),
                # which keeps the oil-spring energy exact; then valve/relief flows
                pa = x[x_pa + k] - hg[G_BOIL] * math.log(ca1 / ca)
                pb = x[x_pb + k] - hg[G_BOIL] * math.log(cb1 / cb)
                # flows linearised about the pressure after the displacement (Q − g·Δp)
                qa = flow[4 * k] - flow[4 * k + 2] * (pa - x[x_pa + k])
                qb = flow[4 * k + 1] - flow[4 * k + 3] * (pb - x[x_pb + k])
                x[x_pa + k] = pressure_step(pa, qa, flow[4 * k + 2], ca1, dt, hg[G_PMIN])
                x[x_pb + k] = pressure_step(pb, qb, flow[4 * k + 3], cb1, dt, hg[G_PMIN])
                x[x_u + nd + k] = spool_step(x[x_u + nd + k], u_cmd[nd + k], hc[k, C_TAU], dt)
            for d in range(nd):
                # drive torque rate with the updated speed (symplectic pairing)
                jd = dj[d]
                w_old = x[nj + jd] - dt * qdd[jd]
                dtorque[d] += hs[d, S_KS] * (w_old - x[nj + jd])
                x[x_ts + d] += dt * dtorque[d]
                x[x_u + d] = spool_step(x[x_u + d], u_cmd[d], hs[d, S_TAU], dt)
            for j in range(nj):
                x[j] = q_new[j]
            for k in range(nc):
                s[k] = s_new[k]
                dsdq[k] = dsdq_new[k]
        if flags[F_LOSSES] > 0.0:
            # each drive's relief valve caps its torque
            for d in range(nd):
                x[x_ts + d] = min(max(x[x_ts + d], -hs[d, S_TMAX]), hs[d, S_TMAX])
