"""The fixed-step integration loop: hydraulics + 4-DOF multibody forward dynamics, in numba.

State x (N_X,): q (4), qd (4), pA (3), pB (3), spool voltages U (4: slew, lift, jib, extension),
slewing drive torque T (1). Each step:

1. Operator commands U_cmd(t) (:mod:`cranetwin.sim.scenario`), payload m_p(t).
2. Rod positions and moment arms s_k, ds_k/dq from ``physics.kernels.cylinder_kinematics``;
   rod velocities v_k = ds_k/dq · qd.
3. Cylinder forces (Eq. 1–2 + end stops) and the slewing torque give the actuator loads
   tau_j = Σ F_k·ds_k/dq_j + (T − F_fr,slew) (virtual work).
4. Forward dynamics ``M(q)·qdd = tau − h(q, qd)`` with M and h from ``physics.kernels.rnea_into``
   (unit-acceleration columns for M, zero acceleration for h; Paper Eq. 4 solved for qdd).
5. Update. ``semi-implicit`` (default, 1e-4 s as in the paper): symplectic Euler for the
   mechanics (qd += dt·qdd, then q += dt·qd); chamber pressures follow the rod displacement of
   that step through the exact closed-chamber law p − p0 = −B_oil·ln(Ve/Ve0) (so the oil spring
   neither gains nor loses energy), then the valve/relief flows, linearly implicit; exact spool
   lag. ``rk4``: classical
   Runge–Kutta on the whole state (commands held over the step); it conserves energy to ~1e-7
   over 10 s and is used to check the energy balance.

Truth is recorded every ``truth_every`` steps (state, qdd, forces as the step used them), sensor
snapshots at precomputed step indices (see :mod:`cranetwin.sim.sensors`).
"""

from __future__ import annotations

import hashlib
import math
import os
from pathlib import Path

import numpy as np
import numpy.typing as npt
from numba import njit

from cranetwin.physics import chain as chain_module
from cranetwin.physics import kernels as kernels_module
from cranetwin.physics.kernels import cylinder_kinematics, rnea_into
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
    S_FC,
    S_KS,
    S_TAU,
    S_TLEAK,
    S_TMAX,
    S_UMAX,
    S_VC,
    S_WMAX,
    capacitances,
    end_stop,
    friction,
    pressure_step,
    relief,
    slew_limit,
    spool_step,
    valve_flows,
)
from cranetwin.sim.sensors import SNAP_PA, SNAP_PB, SNAP_Q, SNAP_S, SNAP_SLEW_TORQUE

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]


def _drop_stale_cache() -> None:
    """Delete this module's numba cache when a module it compiles in has changed.

    numba keys a cached function on its own source file only, but the loop below inlines the
    physics kernels and the hydraulic kernels: after either changes, the cached loop would
    silently run the old code. A stamp of those sources next to the cache decides.
    """
    here = Path(__file__).resolve()
    deps = [here, here.with_name("hydraulics.py"), here.with_name("sensors.py"),
            Path(kernels_module.__file__).resolve(), Path(chain_module.__file__).resolve()]
    digest = hashlib.sha256(b"".join(p.read_bytes() for p in deps)).hexdigest()
    cache_dirs = [here.parent / "__pycache__"]
    if os.environ.get("NUMBA_CACHE_DIR"):
        cache_dirs.append(Path(os.environ["NUMBA_CACHE_DIR"]))
    for d in cache_dirs:
        stamp = d / "engine.deps-stamp"
        try:
            if stamp.exists() and stamp.read_text() == digest:
                continue
            for f in d.rglob("engine.*.nb[ic]"):
                f.unlink(missing_ok=True)
            d.mkdir(parents=True, exist_ok=True)
            stamp.write_text(digest)
        except OSError:      # read-only install: numba then compiles in memory anyway
            continue


_drop_stale_cache()

NJ = 4
NC = 3
X_Q, X_QD, X_PA, X_PB, X_U, X_TS = 0, 4, 8, 11, 14, 18
N_X = 19
# truth columns
T_T, T_Q, T_QD, T_QDD, T_S, T_V, T_PA, T_PB, T_F, T_TS, T_TAU, T_PAY, T_U = (
    0, 1, 5, 9, 13, 16, 19, 22, 25, 28, 29, 33, 34)
N_T = 38
# flags
F_FRICTION, F_VALVES, F_LOSSES, F_SCHEME = 0, 1, 2, 3
SCHEME_SEMI_IMPLICIT = 0.0
SCHEME_RK4 = 1.0
# scratch layout: rows of a (N_SCR, 12) work matrix
N_SCRATCH_VEC = 16


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
def _commands(t: float, x: F64, s: F64, u_t: F64, u_v: F64, u_n: I64, r_t: F64, r_v: F64,
              r_n: I64, gain: F64, umax: F64, pay_t: F64, pay_m: F64, cur: I64,
              u_cmd: F64) -> float:
    """Operator commands at time t into ``u_cmd`` (4,) [V]; returns the payload [kg]."""
    for a in range(4):
        u = _interp(u_t[a], u_v[a], u_n[a], t, cur, a, 0.0)
        if r_n[a] > 0:
            y = x[X_Q] if a == 0 else s[a - 1]
            r = _interp(r_t[a], r_v[a], r_n[a], t, cur, 4 + a, r_v[a, 0])
            u += gain[a] * (r - y)
        u_cmd[a] = min(max(u, -umax[a]), umax[a])
    i = cur[8]
    while i + 1 < pay_t.shape[0] and pay_t[i + 1] <= t:
        i += 1
    cur[8] = i
    return float(pay_m[i])


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


@njit(cache=True)
def _eval(chain: F64, cyl: F64, hc: F64, hg: F64, hs: F64, cj: I64, sj: int, x: F64,
          payload: float, u_cmd: F64, flags: F64, s: F64, dsdq: F64, v: F64, force: F64,
          tau: F64, qdd: F64, flow: F64, mm: F64, hb: F64, lo: F64, wr: F64, work: F64,
          e: F64, zero: F64, rhs: F64, kin_ready: bool) -> float:
    """Everything the state implies: kinematics, forces, accelerations, chamber flows.

    ``kin_ready``: s and dsdq already hold the kinematics of x (skip recomputing them).

    Writes s, dsdq, v, force (3,), tau, qdd (4,), flow (12,) = [QA, QB, gA, gB] per cylinder
    (valve + relief, into the chamber, and their −∂/∂p), returns the slewing dT/dt [N·m/s].
    """
    q = x[X_Q:X_Q + NJ]
    qd = x[X_QD:X_QD + NJ]
    if not kin_ready:
        cylinder_kinematics(cyl, q, s, dsdq)
    for j in range(NJ):
        tau[j] = 0.0
    fric = flags[F_FRICTION] > 0.0
    valves = flags[F_VALVES] > 0.0
    losses = flags[F_LOSSES] > 0.0
    for k in range(NC):
        jk = cj[k]
        vk = dsdq[k] * qd[jk]
        v[k] = vk
        pa = x[X_PA + k]
        pb = x[X_PB + k]
        f = pa * hc[k, C_A1] - pb * hc[k, C_A2]
        if fric:
            f -= friction(vk, hc[k, C_FC], hc[k, C_VC], hc[k, C_B])
        f += end_stop(s[k], vk, hc[k, C_STROKE], hc[k, C_KEND], hc[k, C_CEND])
        force[k] = f
        tau[jk] += f * dsdq[k]
        qa = 0.0
        qb = 0.0
        ga = 0.0
        gb = 0.0
        if valves:
            qa, qb, ga, gb = valve_flows(hc[k, C_QN], x[X_U + 1 + k], pa, pb, hg[G_PS],
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
    w = qd[sj]
    torque = x[X_TS]
    tq = torque
    if fric:
        tq -= friction(w, hs[S_FC], hs[S_VC], hs[S_B])
    tq += slew_limit(q[sj], w, hs)
    tau[sj] += tq
    w_cmd = x[X_U] / hs[S_UMAX] * hs[S_WMAX] if valves else 0.0
    dtorque = hs[S_KS] * (w_cmd - w)
    if losses:
        dtorque -= torque / hs[S_TLEAK]
    # forward dynamics: M qdd = tau - h   (Eq. 4)
    for j in range(NJ):
        for i in range(NJ):
            e[i] = 0.0
        e[j] = 1.0
        rnea_into(chain, q, zero, e, payload, 0.0, hb, wr, work)
        for i in range(NJ):
            mm[i, j] = hb[i]
    for i in range(NJ):
        for j in range(i + 1, NJ):
            a = 0.5 * (mm[i, j] + mm[j, i])
            mm[i, j] = a
            mm[j, i] = a
    rnea_into(chain, q, qd, zero, payload, 1.0, hb, wr, work)
    for j in range(NJ):
        rhs[j] = tau[j] - hb[j]
    _solve_spd(mm, rhs, qdd, lo)
    return float(dtorque)


@njit(cache=True)
def _deriv(chain: F64, cyl: F64, hc: F64, hg: F64, hs: F64, cj: I64, sj: int, x: F64,
           payload: float, u_cmd: F64, flags: F64, dx: F64, s: F64, dsdq: F64, v: F64,
           force: F64, tau: F64, qdd: F64, flow: F64, mm: F64, hb: F64, lo: F64, wr: F64,
           work: F64, e: F64, zero: F64, rhs: F64) -> None:
    """dx/dt of the whole state (for the RK4 scheme)."""
    dtorque = _eval(chain, cyl, hc, hg, hs, cj, sj, x, payload, u_cmd, flags, s, dsdq, v, force,
                    tau, qdd, flow, mm, hb, lo, wr, work, e, zero, rhs, False)
    for j in range(NJ):
        dx[X_Q + j] = x[X_QD + j]
        dx[X_QD + j] = qdd[j]
    for k in range(NC):
        ca, cb = capacitances(s[k], hc[k, C_A1], hc[k, C_A2], hc[k, C_STROKE], hc[k, C_V0],
                              hg[G_BOIL], hg[G_BHOSE])
        dx[X_PA + k] = (flow[4 * k] - hc[k, C_A1] * v[k]) / ca
        dx[X_PB + k] = (flow[4 * k + 1] + hc[k, C_A2] * v[k]) / cb
        dx[X_U + 1 + k] = (u_cmd[1 + k] - x[X_U + 1 + k]) / hc[k, C_TAU]
    dx[X_U] = (u_cmd[0] - x[X_U]) / hs[S_TAU]
    dx[X_TS] = dtorque


@njit(cache=True)
def run_steps(chain: F64, cyl: F64, hc: F64, hg: F64, hs: F64, cj: I64, sj: int, flags: F64,
              dt: float, x: F64, i0: int, i1: int, n_steps: int, truth_every: int,
              truth: F64, snap_steps: I64, snaps: F64, idx: I64, cur: I64, u_t: F64, u_v: F64,
              u_n: I64, r_t: F64, r_v: F64, r_n: I64, gain: F64, umax: F64, pay_t: F64,
              pay_m: F64) -> None:
    """Advance the state ``x`` in place over steps i0 … i1−1 (global step indices).

    Records truth rows at every step index divisible by ``truth_every`` and sensor snapshots
    at ``snap_steps`` (``idx`` = [next truth row, next snapshot]), including step ``n_steps``
    (the final state) when i1 == n_steps. Raises nothing: a non-finite state stops the loop
    and leaves ``idx[2] = 1`` (checked by the caller).
    """
    s = np.empty(NC)
    dsdq = np.empty(NC)
    v = np.empty(NC)
    force = np.empty(NC)
    tau = np.empty(NJ)
    qdd = np.empty(NJ)
    flow = np.empty(4 * NC)
    mm = np.empty((NJ, NJ))
    hb = np.empty(NJ)
    lo = np.zeros((NJ, NJ))
    wr = np.empty((NJ, 6))
    work = np.empty((NJ, 12))
    e = np.empty(NJ)
    zero = np.zeros(NJ)
    rhs = np.empty(NJ)
    u_cmd = np.empty(4)
    s_new = np.empty(NC)
    dsdq_new = np.empty(NC)
    q_new = np.empty(NJ)
    rk4 = flags[F_SCHEME] == SCHEME_RK4
    k1 = np.empty(N_X)
    k2 = np.empty(N_X)
    k3 = np.empty(N_X)
    k4 = np.empty(N_X)
    xt = np.empty(N_X)
    last = i1 + 1 if i1 == n_steps else i1
    # kinematics of the current state (the operator tracks rod positions); carried over steps
    cylinder_kinematics(cyl, x[X_Q:X_Q + NJ], s, dsdq)
    for i in range(i0, last):
        t = i * dt
        payload = _commands(t, x, s, u_t, u_v, u_n, r_t, r_v, r_n, gain, umax, pay_t, pay_m,
                            cur, u_cmd)
        dtorque = _eval(chain, cyl, hc, hg, hs, cj, sj, x, payload, u_cmd, flags, s, dsdq, v,
                        force, tau, qdd, flow, mm, hb, lo, wr, work, e, zero, rhs, True)
        ok = True
        for j in range(NJ):
            if not math.isfinite(qdd[j]):
                ok = False
        if not ok:
            idx[2] = 1
            return
        if i % truth_every == 0 and idx[0] < truth.shape[0]:
            r = idx[0]
            truth[r, T_T] = t
            for j in range(NJ):
                truth[r, T_Q + j] = x[X_Q + j]
                truth[r, T_QD + j] = x[X_QD + j]
                truth[r, T_QDD + j] = qdd[j]
                truth[r, T_TAU + j] = tau[j]
                truth[r, T_U + j] = u_cmd[j]
            for k in range(NC):
                truth[r, T_S + k] = s[k]
                truth[r, T_V + k] = v[k]
                truth[r, T_PA + k] = x[X_PA + k]
                truth[r, T_PB + k] = x[X_PB + k]
                truth[r, T_F + k] = force[k]
            truth[r, T_TS] = x[X_TS]
            truth[r, T_PAY] = payload
            idx[0] = r + 1
        while idx[1] < snap_steps.shape[0] and snap_steps[idx[1]] == i:
            r = idx[1]
            for k in range(NC):
                snaps[r, SNAP_PA + k] = x[X_PA + k]
                snaps[r, SNAP_PB + k] = x[X_PB + k]
                snaps[r, SNAP_S + k] = s[k]
            snaps[r, SNAP_SLEW_TORQUE] = x[X_TS]
            for j in range(NJ):
                snaps[r, SNAP_Q + j] = x[X_Q + j]
            idx[1] = r + 1
        if i == n_steps:
            break
        if rk4:
            _deriv(chain, cyl, hc, hg, hs, cj, sj, x, payload, u_cmd, flags, k1, s, dsdq, v,
                   force, tau, qdd, flow, mm, hb, lo, wr, work, e, zero, rhs)
            for m in range(N_X):
                xt[m] = x[m] + 0.5 * dt * k1[m]
            _deriv(chain, cyl, hc, hg, hs, cj, sj, xt, payload, u_cmd, flags, k2, s, dsdq, v,
                   force, tau, qdd, flow, mm, hb, lo, wr, work, e, zero, rhs)
            for m in range(N_X):
                xt[m] = x[m] + 0.5 * dt * k2[m]
            _deriv(chain, cyl, hc, hg, hs, cj, sj, xt, payload, u_cmd, flags, k3, s, dsdq, v,
                   force, tau, qdd, flow, mm, hb, lo, wr, work, e, zero, rhs)
            for m in range(N_X):
                xt[m] = x[m] + dt * k3[m]
            _deriv(chain, cyl, hc, hg, hs, cj, sj, xt, payload, u_cmd, flags, k4, s, dsdq, v,
                   force, tau, qdd, flow, mm, hb, lo, wr, work, e, zero, rhs)
            for m in range(N_X):
                x[m] += dt / 6.0 * (k1[m] + 2.0 * k2[m] + 2.0 * k3[m] + k4[m])
            for k in range(NC):
                x[X_PA + k] = max(x[X_PA + k], hg[G_PMIN])
                x[X_PB + k] = max(x[X_PB + k], hg[G_PMIN])
            cylinder_kinematics(cyl, x[X_Q:X_Q + NJ], s, dsdq)
        else:
            # symplectic Euler for the mechanics
            for j in range(NJ):
                x[X_QD + j] += dt * qdd[j]
                q_new[j] = x[X_Q + j] + dt * x[X_QD + j]
            cylinder_kinematics(cyl, q_new, s_new, dsdq_new)
            for k in range(NC):
                ca, cb = capacitances(s[k], hc[k, C_A1], hc[k, C_A2], hc[k, C_STROKE],
                                      hc[k, C_V0], hg[G_BOIL], hg[G_BHOSE])
                ca1, cb1 = capacitances(s_new[k], hc[k, C_A1], hc[k, C_A2], hc[k, C_STROKE],
                                        hc[k, C_V0], hg[G_BOIL], hg[G_BHOSE])
                # piston motion: exact closed-chamber law p = p0 − B·ln(Ve/Ve0) (Ve = B·C),
                # which keeps the oil-spring energy exact; then valve/relief flows
                pa = x[X_PA + k] - hg[G_BOIL] * math.log(ca1 / ca)
                pb = x[X_PB + k] - hg[G_BOIL] * math.log(cb1 / cb)
                # flows linearised about the pressure after the displacement (Q − g·Δp)
                qa = flow[4 * k] - flow[4 * k + 2] * (pa - x[X_PA + k])
                qb = flow[4 * k + 1] - flow[4 * k + 3] * (pb - x[X_PB + k])
                x[X_PA + k] = pressure_step(pa, qa, flow[4 * k + 2], ca1, dt, hg[G_PMIN])
                x[X_PB + k] = pressure_step(pb, qb, flow[4 * k + 3], cb1, dt, hg[G_PMIN])
                x[X_U + 1 + k] = spool_step(x[X_U + 1 + k], u_cmd[1 + k], hc[k, C_TAU], dt)
            # slewing drive: torque rate with the updated speed (symplectic pairing)
            w_old = x[X_QD + sj] - dt * qdd[sj]
            dtorque += hs[S_KS] * (w_old - x[X_QD + sj])
            x[X_TS] += dt * dtorque
            x[X_U] = spool_step(x[X_U], u_cmd[0], hs[S_TAU], dt)
            for j in range(NJ):
                x[X_Q + j] = q_new[j]
            for k in range(NC):
                s[k] = s_new[k]
                dsdq[k] = dsdq_new[k]
        if flags[F_LOSSES] > 0.0:
            # the slewing circuit's relief valve caps the drive torque
            x[X_TS] = min(max(x[X_TS], -hs[S_TMAX]), hs[S_TMAX])
