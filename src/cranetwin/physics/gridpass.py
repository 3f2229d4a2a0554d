"""The replay's model-step stage fused into one compiled loop (paper Sect. 2, Eq. 1–4).

At every grid instant (1 kHz for 100 Hz samples) the twin evaluates the natural splines of the
smoothed channels, solves the inverse kinematics of the cylinders (rod position → joint angle,
moment arm ds/dq and d²s/dq²; the chain rule gives qd and qdd), the cylinder forces of Eq. 1–2,
the actuator joint loads F·ds/dq, the inverse dynamics (RNEA) with the payload, the
forward-dynamics acceleration correction of Eq. 3/4 (M_DD·Δqdd_D = residual_D) and the joint
reaction wrenches. Done as separate vectorised calls this costs a dozen temporaries of
n × (up to 24) doubles per chunk and a pass over memory for each; here each instant is computed
start to finish in registers and written once to the output arrays.

:func:`grid_pass` is written once, as plain Python, and compiled twice:

* here, with the generic RNEA (:func:`cranetwin.physics.kernels.rnea_into`), as
  :data:`grid_pass_generic` — the fallback;
* into the machine's generated module (:mod:`cranetwin.physics.codegen`), where the calls
  of ``rnea_row``/``rnea_lin_row`` are replaced by the RNEA specialised to that machine,
  inlined (``codegen.inline_rnea``). Its
  source is copied there (:func:`template_source`) so that numba's on-disk cache is keyed by the
  generated file and never mixes machines.

The inputs are prepared by :class:`cranetwin.twin.replay.TwinStream`; every quantity has the
meaning it has there (the tests compare the two paths).
"""

from __future__ import annotations

import inspect
import logging
import math
import textwrap
from collections.abc import Callable
from typing import Any

import numpy as np
from numba import njit

from cranetwin.physics.actuator import eq1_cylinder_force, eq2_friction
from cranetwin.physics.chain import CYL_BLOCK, ChainParams
from cranetwin.physics.kernels import _chol_solve, cylinder_motion, rnea_into
from cranetwin.physics.kernels import mass_matrix_batch as K_mass_matrix_batch

IMPORTS = ("import numpy as np\n"
           "from cranetwin.physics.chain import CYL_BLOCK\n"
           "from cranetwin.physics.gridpass import chol_solve_inline, derivative_group\n"
           "from cranetwin.physics.gridpass import joint_motion\n"
           "from cranetwin.physics.actuator import eq1_cylinder_force, eq2_friction")
"""Imports the copied :func:`grid_pass` needs in the generated module (besides ``math`` and
``njit``, which it has)."""

_log = logging.getLogger(__name__)

# Layout of the quantity table ``src``/``der`` (nc cylinders):
#   [0, nc) rod positions s [m]; [nc, 2nc) rod velocities [m/s]; [2nc, 3nc) rod accelerations
#   [m/s²]; 3nc slew angle θ0 [rad]; 3nc+1 its rate; 3nc+2 its acceleration;
#   [3nc+3, 4nc+3) pA [Pa]; [4nc+3, 5nc+3) pB [Pa]; 5nc+3 net slewing torque [N·m].
# src[i] is the spline column a quantity comes from (−1: absent, 0), der[i] the derivative
# order of that column's spline (0, 1 or 2).


def n_quantities(n_cylinders: int) -> int:
    """Length of the ``src``/``der`` table for ``n_cylinders`` cylinders."""
    return 5 * n_cylinders + 4


@njit(cache=True)
def rnea_row(chain, q, qd, qdd, pl_kg, k, tau, wrench, work):  # type: ignore[no-untyped-def]
    """Generic RNEA of row k (tau and wrench) for the generic build of :func:`grid_pass`; the
    generated build has the RNEA inlined at the call's marker instead."""
    rnea_into(chain, q[k], qd[k], qdd[k], pl_kg, 1.0, tau[k], wrench[k], work)


@njit(cache=True)
def rnea_lin_row(chain, q, acc, pl_kg, k, wrench, work, zero, tau_tmp, w_tmp):  # type: ignore[no-untyped-def]
    """Adds to ``wrench[k]`` the part of the RNEA wrenches linear in the accelerations (qd = 0,
    no gravity) at accelerations ``acc[k]``: RNEA is affine in qdd, so a wrench at qdd + Δ is
    the wrench at qdd plus this at Δ (generic build; the generated one is inlined)."""
    rnea_into(chain, q[k], zero, acc[k], pl_kg, 0.0, tau_tmp, w_tmp, work)
    for i in range(w_tmp.shape[0]):
        for j in range(6):
            wrench[k, i, j] += w_tmp[i, j]


@njit(cache=True)
def derivative_group(src, der, order):  # type: ignore[no-untyped-def]
    """Rows (quantity, spline column) of the quantities taken from a spline's derivative of
    ``order`` (module comment on the ``src``/``der`` table)."""
    n = 0
    for m in range(src.shape[0]):
        if src[m] >= 0 and der[m] == order:
            n += 1
    out = np.empty((n, 2), dtype=np.uint64)  # unsigned: no negative-index wraparound code
    n = 0
    for m in range(src.shape[0]):
        if src[m] >= 0 and der[m] == order:
            out[n, 0] = m
            out[n, 1] = src[m]
            n += 1
    return out


@njit(cache=True)
def spline_points(coef, i_first, n_out, r, h0, h_last, src, der, out):  # type: ignore[no-untyped-def]
    """Spline quantities at rows g = 0 … n_out−1: knot interval i_first + g // r at offset
    h0·(g % r)/r; a row past the last interval is the end knot (last interval at h_last).

    Args:
        coef: Spline pieces (n_int, 4, k): y_i, b_i, c_i, d_i per column.
        src, der: Column and derivative order per quantity (module comment); src < 0 gives 0.
        out: (n_out, len(src)).
    """
    n_int = coef.shape[0]
    nq = src.shape[0]
    for g in range(n_out):
        i = i_first + g // r
        dx = h0 * (g % r) / r
        if i >= n_int:
            i = n_int - 1
            dx = h_last
        for m in range(nq):
            c = src[m]
            if c < 0:
                out[g, m] = 0.0
                continue
            a0 = coef[i, 0, c]
            b = coef[i, 1, c]
            c2 = coef[i, 2, c]
            d = coef[i, 3, c]
            nu = der[m]
            if nu == 0:
                out[g, m] = a0 + dx * (b + dx * (c2 + dx * d))
            elif nu == 1:
                out[g, m] = b + dx * (2.0 * c2 + 3.0 * d * dx)
            else:
                out[g, m] = 2.0 * c2 + 6.0 * d * dx


chol_solve_inline = njit(cache=True, inline="always")(_chol_solve.py_func)
""":func:`cranetwin.physics.kernels._chol_solve`, inlined where it is called (no call, no
reference counting of its array arguments in the per-instant loop)."""


KIN_TABLE_NODES = 2049
"""Nodes of the rod-position tables (:func:`kinematics_table`) over each cylinder's stroke:
cells of stroke/2048 (≈ 0.3 mm on the PATU 655)."""


@njit(cache=True, error_model="numpy")
def kinematics_table(cyl, stroke, n_nodes, table):  # type: ignore[no-untyped-def]
    """Quintic pieces of each cylinder's inverse kinematics q(s) over its stroke.

    At ``n_nodes`` equally spaced rod positions the exact inverse (:func:`cylinder_motion`)
    gives q, dq/ds = 1/s′ and d²q/ds² = −s″/s′³; on each cell the quintic Hermite polynomial
    through those six numbers is stored as coefficients of u = (s − s_i)/h, so that
    ``table[k, i] @ (1, u, …, u⁵)`` is q. Its error is of order h⁶·q⁽⁶⁾ for q and h⁴·q⁽⁶⁾ for
    d²q/ds²: with 2048 cells, below 1e-12 relative on the PATU 655 (tested against the exact
    inverse), at a seventh of its cost per instant.

    Args:
        cyl: Flat cylinder parameters; stroke (nc,) [m]; table: output (nc, n_nodes − 1, 6).

    Returns:
        (nc,) booleans: the table of that cylinder is usable (the geometry produces every node,
        and q has no jump); where False, the grid pass uses the exact inverse.
    """
    nc = stroke.shape[0]
    ok = np.ones(nc, dtype=np.bool_)
    q = np.empty(n_nodes)
    q1 = np.empty(n_nodes)
    q2 = np.empty(n_nodes)
    for k in range(nc):
        h = stroke[k] / (n_nodes - 1)
        for i in range(n_nodes):
            qi, d1, d2 = cylinder_motion(cyl, k, min(i * h, stroke[k]))
            q[i] = qi
            q1[i] = 1.0 / d1
            q2[i] = -d2 / (d1 * d1 * d1)
            if not (math.isfinite(qi) and math.isfinite(q1[i]) and math.isfinite(q2[i])):
                ok[k] = False
        for i in range(n_nodes - 1):
            p0 = q[i]
            dp = q[i + 1] - p0
            if abs(dp) > 0.1:  # a wrap or a branch change inside the stroke
                ok[k] = False
            m0 = q1[i] * h
            m1 = q1[i + 1] * h
            c0 = q2[i] * h * h
            c1 = q2[i + 1] * h * h
            table[k, i, 0] = p0
            table[k, i, 1] = m0
            table[k, i, 2] = 0.5 * c0
            table[k, i, 3] = 10.0 * dp - 6.0 * m0 - 4.0 * m1 - 1.5 * c0 + 0.5 * c1
            table[k, i, 4] = -15.0 * dp + 8.0 * m0 + 7.0 * m1 + 1.5 * c0 - c1
            table[k, i, 5] = 6.0 * dp - 3.0 * m0 - 3.0 * m1 - 0.5 * c0 + 0.5 * c1
    return ok


@njit(cache=True, inline="always")
def table_inverse(table, k, cells_per_m, s):  # type: ignore[no-untyped-def]
    """(q, dq/ds, d²q/ds²) of cylinder k at rod position s in [0, stroke] from its table
    (``cells_per_m`` = cells / stroke [1/m]): the inverse map and its derivatives, so that the
    chain rule needs no division (qd = q′·v, qdd = q′·a + q″·v²; the moment arm ds/dq is 1/q′).
    :func:`cylinder_motion` returns the forward derivatives instead: q′ = 1/s′, q″ = −s″/s′³."""
    n_cells = table.shape[1]
    x = s * cells_per_m
    i = int(x)
    if i >= n_cells:
        i = n_cells - 1
    u = x - i
    iu = np.uint64(i)  # s ≥ 0: as an unsigned index, no negative-index wraparound code
    c0 = table[k, iu, 0]
    c1 = table[k, iu, 1]
    c2 = table[k, iu, 2]
    c3 = table[k, iu, 3]
    c4 = table[k, iu, 4]
    c5 = table[k, iu, 5]
    # Estrin's scheme (u², u⁴ and the pairs in parallel): a third of Horner's dependency
    # chain, which sits on the per-instant critical path (rod position → angle → dynamics)
    u2 = u * u
    u4 = u2 * u2
    qv = (c0 + u * c1) + u2 * (c2 + u * c3) + u4 * (c4 + u * c5)
    g1 = ((c1 + u * (2.0 * c2)) + u2 * (3.0 * c3 + u * (4.0 * c4)) + u4 * (5.0 * c5)) * cells_per_m
    g2 = (((2.0 * c2) + u * (6.0 * c3)) + u2 * ((12.0 * c4) + u * (20.0 * c5))) * (
        cells_per_m * cells_per_m)
    return qv, g1, g2


@njit(cache=True, inline="always")
def inverse_motion(table, table_ok, cyl, k, cells_per_m, s):  # type: ignore[no-untyped-def]
    """(q, dq/ds, d²q/ds²) of cylinder k at rod position s: from its table where usable
    (:func:`table_inverse`), else from the exact inverse (:func:`cylinder_motion`)."""
    if table_ok[k]:
        return table_inverse(table, k, cells_per_m, s)
    qj, d1, d2 = cylinder_motion(cyl, k, s)
    g1 = 1.0 / d1
    return qj, g1, -d2 * g1 * g1 * g1


@njit(cache=True, inline="always")
def joint_motion(table, table_ok, cyl, k, cells_per_m, s, v, a):  # type: ignore[no-untyped-def]
    """Cylinder k's joint at rod position s [m], velocity v [m/s], acceleration a [m/s²]:
    (q, qd, qdd, moment arm ds/dq) by the chain rule through :func:`inverse_motion`
    (qd = q′·v, qdd = q′·a + q″·v², ds/dq = 1/q′)."""
    qj, g1, g2 = inverse_motion(table, table_ok, cyl, k, cells_per_m, s)
    return qj, g1 * v, g1 * a + g2 * v * v, 1.0 / g1


@njit(cache=True)
def dd_inverse_batch(mm, full, minv, ok):  # type: ignore[no-untyped-def]
    """Inverses of the submatrices M_DD (rows and columns ``full``) of mass matrices mm
    (ns, nj, nj) into minv (ns, nd, nd), by Cholesky (M is symmetric positive definite):
    M_DD = L·Lᵀ, then L⁻¹ by forward substitution and M_DD⁻¹ = L⁻ᵀ·L⁻¹ (symmetric, each
    entry computed once). ok[k] False (minv[k] = 0) where M_DD is not finite or not positive
    definite."""
    nd = full.shape[0]
    lo = np.zeros((nd, nd))  # L
    li = np.zeros((nd, nd))  # L⁻¹
    for k in range(mm.shape[0]):
        good = True
        for c in range(nd):
            fc = full[c]
            t = mm[k, fc, fc]
            for p in range(c):
                t -= lo[c, p] * lo[c, p]
            if not t > 0.0 or not math.isfinite(t):
                good = False
                break
            lcc = math.sqrt(t)
            lo[c, c] = lcc
            rc = 1.0 / lcc
            li[c, c] = rc
            for r in range(c + 1, nd):
                t = mm[k, full[r], fc]
                for p in range(c):
                    t -= lo[r, p] * lo[c, p]
                lo[r, c] = t * rc
        ok[k] = good
        if not good:
            for r in range(nd):
                for c in range(nd):
                    minv[k, r, c] = 0.0
            continue
        for i in range(1, nd):
            for j in range(i):
                t = 0.0
                for p in range(j, i):
                    t += lo[i, p] * li[p, j]
                li[i, j] = -t * li[i, i]
        for i in range(nd):
            for j in range(i + 1):
                t = 0.0
                for p in range(i, nd):
                    t += li[p, i] * li[p, j]
                minv[k, i, j] = t
                minv[k, j, i] = t


@njit(cache=True, error_model="numpy")
def table_motion_batch(table, table_ok, cyl, s, v, a, q, qd, qdd, arm):  # type: ignore[no-untyped-def]
    """:func:`cranetwin.physics.kernels.cylinder_motion_batch` through the tables (the exact
    inverse for a cylinder whose table is not usable); s must lie within the strokes."""
    nc = table_ok.shape[0]
    for i in range(s.shape[0]):
        for k in range(nc):
            ji = int(cyl[1 + k * CYL_BLOCK + 1])
            q[i, ji], qd[i, ji], qdd[i, ji], arm[i, k] = joint_motion(
                table, table_ok, cyl, k, table.shape[1] / cyl[1 + k * CYL_BLOCK + 3], s[i, k],
                v[i, k], a[i, k])


def grid_pass(chain, coef, i_first, r, h0, h_last, src, der,  # type: ignore[no-untyped-def]
              cyl, table, table_ok, fpar, stroke, stop_margin, slew_joint, drive, has_drive,
              has_theta,
              mk, sk, mm, minv, minv_ok, n_full, dynamic, gap,
              q, qd, qdd, rod_s, rod_v, pa, pb, force, tau_act, tau_id, resid, wrench,
              mass, std, qdd2, work):
    """Every model-step quantity of the replay at rows g = 0 … n−1 (n = q.shape[0]).

    Args:
        chain: Flat chain parameters (the generic RNEA reads them; the generated one ignores).
        coef, i_first, r, h0, h_last, src, der: Splines and the quantity table, as
            :func:`spline_points`.
        cyl: Flat cylinder parameters; table, table_ok: :func:`kinematics_table` and its
            result (the exact inverse where not ok); fpar (nc, 5): A1 [m²], A2 [m²], Fc [N],
            vc [m/s], b [N·s/m] of Eq. 2; stroke (nc,) [m]; stop_margin [m]: a rod this close
            to an end of its stroke is in the end stop (its joint keeps the kinematic
            acceleration).
        slew_joint: Index of the torque-driven slew joint, −1 if none. drive: (Fc, vc, b) of
            its friction. has_drive: the net slewing torque is measured. has_theta: the slew
            angle (θ0 quantities) is known.
        mk, sk: Payload estimate and its standard error at samples 0, 1, … (sample j at row
            j·r) [kg]; mm: mass matrices there (ns, nj, nj), with the payload max(mk, 0);
            minv (ns, n_full, n_full): inverses of M_DD there for D the n_full joints whose
            loads are measured (cylinder joints, the slew if its torque is sent), in joint
            order; minv_ok (ns,): that inverse exists. An instant with all of D usable uses
            the inverse interpolated between samples (as accurate as interpolating M, an
            O(h²) approximation of M(q(t)) either way, and a fifth of the work); one with
            fewer (a rod in its end stop) solves with the interpolated M by Cholesky.
        dynamic: wrench accelerations from forward dynamics (True) or kinematic (False).
        gap: (n,) rows inside a bridged dropout (no dynamic correction there).
        q … std: outputs, (n, nj) / (n, nc) / (n, nj, 6) / (n,).
        qdd2: scratch (n, nj), the correction Δqdd; work: scratch (nj, 12) for the generic
            RNEA.

    Returns:
        Number of rows where a rod position has no joint angle (the geometry cannot produce
        it); their q is NaN.
    """
    n = q.shape[0]
    nj = q.shape[1]
    nc = stroke.shape[0]
    n_int = coef.shape[0]
    nq = src.shape[0]
    ns = mk.shape[0]
    val = np.zeros(nq)
    # quantities grouped by derivative order (no branch per quantity and instant)
    g0 = derivative_group(src, der, 0)
    g1 = derivative_group(src, der, 1)
    g2 = derivative_group(src, der, 2)
    n0 = g0.shape[0]
    n1 = g1.shape[0]
    n2 = g2.shape[0]
    # indices that are never negative are unsigned: numba emits negative-index wraparound
    # code for every signed array index, ≈ 40 % of the instructions of the spline loops
    idx = np.empty(nj, dtype=np.uint64)
    amat = np.empty((nj, nj))
    y = np.empty(nj)
    dacc = np.empty(nj)
    known = np.zeros(nj, dtype=np.bool_)
    zr = np.zeros(nj)  # scratch of the generic build's linear pass
    tt = np.empty(nj)
    wt = np.empty((nj, 6))
    inv_r = 1.0 / r
    cj = np.empty(nc, dtype=np.uint64)
    sj = np.uint64(slew_joint if slew_joint >= 0 else 0)
    cells_per_m = np.empty(nc)
    driven = np.zeros(nj, dtype=np.bool_)
    for k in range(nc):
        cj[k] = int(cyl[1 + k * CYL_BLOCK + 1])
        driven[cj[k]] = True
        cells_per_m[k] = table.shape[1] / stroke[k]
    free = np.empty(nj, dtype=np.uint64)  # joints no cylinder drives
    n_free = 0
    for j in range(nj):
        if not driven[j]:
            free[n_free] = j
            n_free += 1
    bad = 0
    for g in range(n):
        # -- splines ------------------------------------------------------------------------
        s0 = g // r  # sample index (payload, mass matrices) and knot interval
        jr = g - s0 * r
        fr = jr * inv_r
        i = i_first + s0
        dx = h0 * fr
        if i >= n_int:
            i = n_int - 1
            dx = h_last
        iu = np.uint64(i)
        for m in range(n0):
            c = g0[m, 1]
            val[g0[m, 0]] = coef[iu, 0, c] + dx * (coef[iu, 1, c] + dx * (
                coef[iu, 2, c] + dx * coef[iu, 3, c]))
        for m in range(n1):
            c = g1[m, 1]
            val[g1[m, 0]] = coef[iu, 1, c] + dx * (2.0 * coef[iu, 2, c]
                                                   + 3.0 * dx * coef[iu, 3, c])
        for m in range(n2):
            c = g2[m, 1]
            val[g2[m, 0]] = 2.0 * coef[iu, 2, c] + 6.0 * dx * coef[iu, 3, c]
        # -- kinematics, Eq. 1–2, actuator loads --------------------------------------------
        for m in range(n_free):  # the cylinder joints are all written below
            j = free[m]
            q[g, j] = 0.0
            qd[g, j] = 0.0
            qdd[g, j] = 0.0
            tau_act[g, j] = 0.0
            known[j] = False
        if slew_joint >= 0 and has_theta:
            q[g, sj] = val[3 * nc]
            qd[g, sj] = val[3 * nc + 1]
            qdd[g, sj] = val[3 * nc + 2]
        row_bad = False
        for k in range(nc):
            raw = val[k]
            s = min(max(raw, 0.0), stroke[k])
            v = val[nc + k]
            a = val[2 * nc + k]
            ji = cj[k]
            qj, qdj, qddj, d1 = joint_motion(table, table_ok, cyl, k, cells_per_m[k], s, v, a)
            if not math.isfinite(qj):
                row_bad = True
            q[g, ji] = qj
            qd[g, ji] = qdj
            qdd[g, ji] = qddj
            rod_s[g, k] = s
            rod_v[g, k] = v
            pak = val[3 * nc + 3 + k]
            pbk = val[4 * nc + 3 + k]
            pa[g, k] = pak
            pb[g, k] = pbk
            f = eq1_cylinder_force(pak, pbk, v, fpar[k, 0], fpar[k, 1], fpar[k, 2],
                                   fpar[k, 3], fpar[k, 4])
            force[g, k] = f
            tau_act[g, ji] = f * d1
            # a rod at (or past) an end of its stroke is held by the end stop, a force the
            # pressures do not show: its joint keeps the kinematic acceleration there
            known[ji] = not (raw <= stop_margin or raw >= stroke[k] - stop_margin)
        if row_bad:
            bad += 1
        if slew_joint >= 0:
            if has_drive:
                wd = qd[g, sj]
                tau_act[g, sj] = val[5 * nc + 3] - eq2_friction(wd, drive[0], drive[1],
                                                                drive[2])
                known[sj] = True
            else:
                tau_act[g, sj] = math.nan
        # -- payload, interpolated from the samples -------------------------------------------
        u0 = np.uint64(s0)
        u1 = np.uint64(min(s0 + 1, ns - 1))
        mg = mk[u0] + fr * (mk[u1] - mk[u0])
        mass[g] = mg
        std[g] = sk[u0] + fr * (sk[u1] - sk[u0])
        pl = mg if mg > 0.0 else 0.0  # NaN and negative estimates: no payload
        # -- inverse dynamics, residual, Eq. 3/4 correction, wrenches -------------------------
        pass  # @RNEA_HEAD@
        rnea_row(chain, q, qd, qdd, pl, g, tau_id, wrench, work)  # @RNEA qdd tau_id wrench pl@
        nd = 0
        for j in range(nj):
            rj = tau_act[g, j] - tau_id[g, j]
            resid[g, j] = rj
            qdd2[g, j] = 0.0  # the correction Δqdd
            if known[j] and math.isfinite(rj):
                idx[nd] = j
                y[nd] = rj
                nd += 1
        if not dynamic or nd == 0 or gap[g]:
            continue
        if nd == n_full and minv_ok[u0] and minv_ok[u1]:
            # the usual case, every measured joint in D: M_DD⁻¹ interpolated like M. Column
            # by column (M⁻¹ is symmetric, so minv[s, b, :] is column b): nd independent sums
            # instead of nd chains of nd dependent additions on the critical path
            for a_ in range(nd):
                dacc[a_] = 0.0
            for b_ in range(nd):
                yb = y[b_]
                for a_ in range(nd):
                    m0 = minv[u0, b_, a_]
                    dacc[a_] += (m0 + fr * (minv[u1, b_, a_] - m0)) * yb
            for a_ in range(nd):
                qdd2[g, idx[a_]] = dacc[a_]
        else:
            for a_ in range(nd):
                for b_ in range(nd):
                    m0 = mm[u0, idx[a_], idx[b_]]
                    amat[a_, b_] = m0 + fr * (mm[u1, idx[a_], idx[b_]] - m0)
            if not chol_solve_inline(amat, y, nd):
                continue
            for a_ in range(nd):
                qdd2[g, idx[a_]] = y[a_]
        # the wrenches at the corrected accelerations qdd + Δqdd
        rnea_lin_row(chain, q, qdd2, pl, g, wrench, work, zr, tt, wt)  # @RNEA_LIN qdd2 wrench pl@
    return bad


def template_source() -> str:
    """Source of :func:`grid_pass` (undecorated) for the generated module."""
    return textwrap.dedent(inspect.getsource(grid_pass))


grid_pass_generic: Callable[..., int] = njit(cache=True, error_model="numpy")(grid_pass)


def kernel_for(params: ChainParams, specialised: bool = True) -> Callable[..., int]:
    """The grid pass for a compiled machine: the one in its generated module (RNEA
    specialised to it), or :data:`grid_pass_generic` if ``specialised`` is off or generation
    fails (generation is an optimisation: it never fails the replay)."""
    if not specialised:
        return grid_pass_generic
    fn = _module_attr(params, "grid_pass")
    return grid_pass_generic if fn is None else fn


def _module_attr(params: ChainParams, name: str) -> Callable[..., Any] | None:
    """``name`` of the machine's generated module (looked up once per compiled machine), or
    None when generation fails (logged)."""
    key = (id(params), name)
    hit = _ATTRS.get(key)
    if hit is not None and hit[0] is params:
        return hit[1]
    fn: Callable[..., Any] | None
    try:
        from cranetwin.physics.codegen import specialised_module

        fn = getattr(specialised_module(params), name)
    except Exception as exc:
        _log.warning("specialised %s unavailable (%s); using the generic code", name, exc)
        fn = None
    _ATTRS[key] = (params, fn)
    return fn


_ATTRS: dict[tuple[int, str], tuple[ChainParams, Callable[..., Any] | None]] = {}


def payload_kernel_for(params: ChainParams,
                       rnea_tau: Callable[..., None]) -> Callable[..., None]:
    """``rnea_payload_batch(q, qd, qdd, tau0, tau1)``: joint loads (n, nj) without payload and
    with 1 kg at the load point, at the same motion (the payload regression: tau1 − tau0 is
    the load per kg). The machine's generated one traces both passes together, sharing all but
    the payload's terms; without a generated module, two calls of ``rnea_tau``."""
    fn = _module_attr(params, "rnea_payload_batch")
    if fn is not None:
        return fn

    def two(q: Any, qd: Any, qdd: Any, tau0: Any, tau1: Any) -> None:
        n = q.shape[0]
        rnea_tau(q, qd, qdd, np.zeros(n), tau0)
        rnea_tau(q, qd, qdd, np.ones(n), tau1)

    return two


def mass_matrix_kernel_for(params: ChainParams) -> Callable[..., None]:
    """``mass_matrix_batch(q, payload, mm)`` of the machine's generated module (M from traced
    unit-acceleration RNEA columns, ≈ 5× the generic CRBA's speed, equal to 1e-15), or the
    generic :func:`cranetwin.physics.kernels.mass_matrix_batch` bound to the chain."""
    fn = _module_attr(params, "mass_matrix_batch")
    if fn is not None:
        return fn
    chain = params.chain

    def generic(q: Any, payload: Any, mm: Any) -> None:
        K_mass_matrix_batch(chain, q, payload, mm)

    return generic
