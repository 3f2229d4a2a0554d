"""The replay's grid stage: every output quantity at the grid instants of one chunk.

At every grid instant (e.g. 1 kHz for 100 Hz samples) the twin evaluates the natural splines
of the smoothed channels, the inverse kinematics of the cylinders (rod position → joint angle
q, moment arm ds/dq; the chain rule gives qd and qdd), the cylinder forces of Eq. 1–2, the
actuator joint loads tau_act = F·ds/dq (and the measured drive torque less its Eq. 2 friction),
the inverse dynamics (RNEA) with the payload, the forward-dynamics acceleration correction of
Eq. 3/4 (M_DD·Δqdd_D = residual_D) and the joint reaction wrenches at the corrected
accelerations. In four steps, each a plain function over the chunk's rows:

1. :func:`state_pass` (compiled): splines, kinematics, Eq. 1–2, actuator loads, payload
   interpolated from the samples;
2. ``kernels.rnea``: inverse dynamics and wrenches (the machine's batch kernel:
   :func:`cranetwin.physics.dynamics.batch_kernels`); then, for the cylinders whose force is
   model-based (:mod:`cranetwin.twin.force_model`), :func:`model_pass`: F = τ_id/(ds/dq) +
   the smoothed pressure residual, and its actuator load;
3. :func:`correction_pass` (compiled): residual tau_act − tau_id and Δqdd;
4. ``kernels.rnea_lin``: the wrenches' part linear in the accelerations at Δqdd, added (RNEA
   is affine in qdd).

Quantity table
--------------
The splines carry the channels; ``src[m]`` is the spline column quantity m comes from (−1:
absent, value 0) and ``der[m]`` the derivative order taken (0, 1 or 2). Quantities are placed
by :class:`Quantities` (nc cylinders, nf free joints, i.e. joints no cylinder drives)::

    s [m], v [m/s], a [m/s²]       nc each       rod position, velocity, acceleration
    free                           3 per free joint: angle [rad], rate, acceleration
    pa, pb [Pa]                    nc each       chamber pressures
    torque [N·m]                   1 per free joint: measured drive torque

A free joint whose angle is absent is held at 0 (the reference pose), a passive joint at its
fixed value (``FreeJoints.hold``); one whose torque is absent has an unknown actuator load
(NaN) and keeps its kinematic acceleration.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import numpy.typing as npt
from numba import njit

from cranetwin.physics.actuator import eq1_cylinder_force, eq2_friction
from cranetwin.physics.dynamics import BatchKernels
from cranetwin.physics.rnea import _chol_solve
from cranetwin.twin.kintable import joint_motion

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
B = npt.NDArray[np.bool_]


class Quantities(NamedTuple):
    """Offsets of the quantity table's blocks (module docstring): quantity ``s + k`` is rod
    k's position, ``free + 3·m + d`` free joint m's angle (d = 0), rate (1), acceleration (2),
    ``torque + m`` its drive torque."""

    s: int
    v: int
    a: int
    free: int
    pa: int
    pb: int
    torque: int
    size: int

    @staticmethod
    def of(n_cylinders: int, n_free: int) -> Quantities:
        nc, nf = n_cylinders, n_free
        return Quantities(s=0, v=nc, a=2 * nc, free=3 * nc, pa=3 * nc + 3 * nf,
                          pb=4 * nc + 3 * nf, torque=5 * nc + 3 * nf, size=5 * nc + 4 * nf)


class Splines(NamedTuple):
    """Natural splines of one chunk and how grid row g maps onto them.

    Attributes:
        coef: Pieces (n_int, 4, n_col): y_i, b_i, c_i, d_i per column.
        i_first: Knot interval of row 0; row g lies in interval i_first + g // r.
        r: Grid rows per sample interval.
        h0: Knot spacing [s]; h_last: the last interval's length [s] (a row past the last
            interval is the end knot).
        src, der: The quantity table (module docstring).
        qi: Its :class:`Quantities`.
    """

    coef: F64
    i_first: int
    r: int
    h0: float
    h_last: float
    src: I64
    der: I64
    qi: Quantities


class Cylinders(NamedTuple):
    """The cylinders' kinematics and Eq. 1–2 parameters.

    Attributes:
        cyl: Flat cylinder parameters (:mod:`cranetwin.physics.chain`).
        table, table_ok: Inverse-kinematics tables (:mod:`cranetwin.twin.kintable`).
        params: ``physics.actuator.cylinder_params`` rows (n_c, 5).
        stroke: (n_c,) [m].
        joint: Joint of each cylinder (n_c,).
        stop_margin: A rod this close to an end of its stroke [m] is in the end stop: its
            joint keeps the kinematic acceleration (the stop takes a force the pressures do
            not show).
    """

    cyl: F64
    table: F64
    table_ok: B
    params: F64
    stroke: F64
    joint: I64
    stop_margin: float


class FreeJoints(NamedTuple):
    """Joints no cylinder drives. ``joint`` (n_f,) their indices; ``friction`` (n_f, 3): Fc
    [N·m], vc [rad/s], b [N·m·s/rad] of each one's drive (Eq. 2); ``hold`` (n_f,) [rad or m]
    added to each one's angle: a passive joint's fixed value (its angle is absent, 0), else 0."""

    joint: I64
    friction: F64
    hold: F64


class SampleState(NamedTuple):
    """What the sample-rate stages found at samples 0, 1, … of the chunk (sample j at row
    j·r), interpolated linearly between samples.

    Attributes:
        mass, std: Payload estimate and its standard error [kg] (ns,).
        mm: Mass matrices with payload max(mass, 0), (ns, nj, nj).
        minv: Inverses of M_DD (ns, n_full, n_full) for D the n_full joints whose loads are
            measured (cylinder joints, free joints with a torque), in joint order.
        minv_ok: (ns,) that inverse exists.
        n_full: Size of that D.
        dynamic: Wrench accelerations from forward dynamics (else kinematic).
    """

    mass: F64
    std: F64
    mm: F64
    minv: F64
    minv_ok: B
    n_full: int
    dynamic: bool


class GridOut(NamedTuple):
    """Outputs at the chunk's n grid rows: q, qd, qdd, tau_act, tau_id, resid (n, nj) [rad or
    m, /s, /s², N·m or N]; rod_s, rod_v, pa, pb, force (n, n_c) [m, m/s, Pa, Pa, N]; wrench
    (n, nj, 6) [N, N·m]; mass, std, pl (n,) [kg] (pl: the payload the dynamics use,
    max(mass, 0), 0 for NaN); gap (n,) rows inside a bridged dropout; known (n, nj) joints
    whose load is measured at that row; qdd2 (n, nj) the correction Δqdd; fix (n,) rows
    that have one; arm (n, n_c) the moment arms ds/dq [m/rad or 1]."""

    q: F64
    qd: F64
    qdd: F64
    rod_s: F64
    rod_v: F64
    pa: F64
    pb: F64
    force: F64
    tau_act: F64
    tau_id: F64
    resid: F64
    wrench: F64
    mass: F64
    std: F64
    pl: F64
    gap: B
    known: B
    qdd2: F64
    fix: B
    arm: F64

    @staticmethod
    def empty(n: int, nj: int, nc: int, gap: B) -> GridOut:
        def e(*shape: int) -> F64:
            return np.empty(shape)

        return GridOut(e(n, nj), e(n, nj), e(n, nj), e(n, nc), e(n, nc), e(n, nc), e(n, nc),
                       e(n, nc), e(n, nj), e(n, nj), e(n, nj), e(n, nj, 6), e(n), e(n), e(n),
                       gap, np.zeros((n, nj), dtype=np.bool_), np.zeros((n, nj)),
                       np.zeros(n, dtype=np.bool_), e(n, nc))


@njit(cache=True, nogil=True, inline="always")
def spline_row(sp, g, val):  # type: ignore[no-untyped-def]
    """Every quantity at grid row g into ``val`` (len(src)); returns the row's sample index
    and its fraction of the sample interval."""
    s0 = g // sp.r
    fr = (g - s0 * sp.r) / sp.r
    i = sp.i_first + s0
    dx = sp.h0 * fr
    n_int = sp.coef.shape[0]
    if i >= n_int:
        i = n_int - 1
        dx = sp.h_last
    for m in range(sp.src.shape[0]):
        c = sp.src[m]
        if c < 0:
            val[m] = 0.0
            continue
        a0 = sp.coef[i, 0, c]
        b = sp.coef[i, 1, c]
        c2 = sp.coef[i, 2, c]
        d = sp.coef[i, 3, c]
        nu = sp.der[m]
        if nu == 0:
            val[m] = a0 + dx * (b + dx * (c2 + dx * d))
        elif nu == 1:
            val[m] = b + dx * (2.0 * c2 + 3.0 * d * dx)
        else:
            val[m] = 2.0 * c2 + 6.0 * d * dx
    return s0, fr


@njit(cache=True, nogil=True)
def spline_points(sp, n_out, out):  # type: ignore[no-untyped-def]
    """Every quantity at rows g = 0 … n_out − 1 into out (n_out, len(src))."""
    for g in range(n_out):
        spline_row(sp, g, out[g])


@njit(cache=True, nogil=True, error_model="numpy")
def state_pass(sp, cy, fj, st, out, pre):  # type: ignore[no-untyped-def]
    """Step 1 at every row of ``out``: splines, cylinder kinematics (rods clipped to their
    strokes), Eq. 1–2, actuator loads, the free joints, the payload.

    Args:
        sp: :class:`Splines`; cy: :class:`Cylinders`; fj: :class:`FreeJoints`;
        st: :class:`SampleState`; out: :class:`GridOut` (written but tau_id, resid, wrench,
            qdd2, fix).
        pre: The cylinder states at the rows of ``out`` when the grid rows are the samples
            and the sample-rate stage computed them (:func:`cranetwin.twin.stages.
            cylinder_states` rows, (n, 5·n_c): the same arithmetic on the same values), else
            shape (0, 5·n_c): computed here.

    Returns:
        Number of rows where a rod position has no joint angle (their q is NaN).
    """
    qi = sp.qi
    nc = cy.stroke.shape[0]
    nf = fj.joint.shape[0]
    ns = st.mass.shape[0]
    val = np.empty(sp.src.shape[0])
    cells_per_m = np.empty(nc)
    for k in range(nc):
        cells_per_m[k] = cy.table.shape[1] / cy.stroke[k]
    bad = 0
    reuse = pre.shape[0] > 0
    for g in range(out.q.shape[0]):
        s0, fr = spline_row(sp, g, val)
        row_bad = False
        for k in range(nc):
            raw = val[qi.s + k]
            s = min(max(raw, 0.0), cy.stroke[k])
            v = val[qi.v + k]
            j = cy.joint[k]
            pa = val[qi.pa + k]
            pb = val[qi.pb + k]
            if reuse:
                qj = pre[g, k]
                qdj = pre[g, nc + k]
                qddj = pre[g, 2 * nc + k]
                arm = pre[g, 3 * nc + k]
                f = pre[g, 4 * nc + k]
            else:
                qj, qdj, qddj, arm = joint_motion(cy.table, cy.table_ok, cy.cyl, k,
                                                  cells_per_m[k], s, v, val[qi.a + k])
                p = cy.params[k]
                f = eq1_cylinder_force(pa, pb, v, p[0], p[1], p[2], p[3], p[4])
            if not math.isfinite(qj):
                row_bad = True
            out.q[g, j] = qj
            out.qd[g, j] = qdj
            out.qdd[g, j] = qddj
            out.rod_s[g, k] = s
            out.rod_v[g, k] = v
            out.pa[g, k] = pa
            out.pb[g, k] = pb
            out.force[g, k] = f
            out.arm[g, k] = arm
            out.tau_act[g, j] = f * arm
            out.known[g, j] = not (raw <= cy.stop_margin or raw >= cy.stroke[k] - cy.stop_margin)
        if row_bad:
            bad += 1
        for m in range(nf):
            j = fj.joint[m]
            out.q[g, j] = val[qi.free + 3 * m] + fj.hold[m]
            w = val[qi.free + 3 * m + 1]
            out.qd[g, j] = w
            out.qdd[g, j] = val[qi.free + 3 * m + 2]
            if sp.src[qi.torque + m] >= 0:
                fr_m = fj.friction[m]
                out.tau_act[g, j] = val[qi.torque + m] - eq2_friction(w, fr_m[0], fr_m[1],
                                                                      fr_m[2])
                out.known[g, j] = True
            else:
                out.tau_act[g, j] = math.nan
                out.known[g, j] = False
        u1 = min(s0 + 1, ns - 1)
        mg = st.mass[s0] + fr * (st.mass[u1] - st.mass[s0])
        out.mass[g] = mg
        out.std[g] = st.std[s0] + fr * (st.std[u1] - st.std[s0])
        out.pl[g] = mg if mg > 0.0 else 0.0  # NaN and negative estimates: no payload
    return bad


@njit(cache=True, nogil=True, error_model="numpy")
def correction_pass(r, st, out):  # type: ignore[no-untyped-def]
    """Step 3 at every row: resid = tau_act − tau_id and, with ``st.dynamic``, the Eq. 3/4
    correction Δqdd_D = M_DD⁻¹·resid_D (D: the row's measured joints with a finite residual;
    none inside a dropout) into ``out.qdd2``, ``out.fix`` marking rows that have one.

    An instant with every measured joint in D uses M_DD⁻¹ interpolated between samples (as
    accurate as interpolating M, an O(h²) approximation of M(q(t)) either way, and a fifth of
    the work); one with fewer (a rod in its end stop) solves with the interpolated M by
    Cholesky. r: grid rows per sample interval.
    """
    nj = out.q.shape[1]
    ns = st.mass.shape[0]
    idx = np.empty(nj, dtype=np.int64)
    y = np.empty(nj)
    dacc = np.empty(nj)
    amat = np.empty((nj, nj))
    for g in range(out.q.shape[0]):
        nd = 0
        for j in range(nj):
            rj = out.tau_act[g, j] - out.tau_id[g, j]
            out.resid[g, j] = rj
            out.qdd2[g, j] = 0.0
            if out.known[g, j] and math.isfinite(rj):
                idx[nd] = j
                y[nd] = rj
                nd += 1
        if not st.dynamic or nd == 0 or out.gap[g]:
            continue
        s0 = g // r
        fr = (g - s0 * r) / r
        u1 = min(s0 + 1, ns - 1)
        if nd == st.n_full and st.minv_ok[s0] and st.minv_ok[u1]:
            for a in range(nd):
                dacc[a] = 0.0
            for b in range(nd):  # M⁻¹ is symmetric: minv[s, b, :] is column b
                yb = y[b]
                for a in range(nd):
                    m0 = st.minv[s0, b, a]
                    dacc[a] += (m0 + fr * (st.minv[u1, b, a] - m0)) * yb
            for a in range(nd):
                out.qdd2[g, idx[a]] = dacc[a]
        else:
            for a in range(nd):
                for b in range(nd):
                    m0 = st.mm[s0, idx[a], idx[b]]
                    amat[a, b] = m0 + fr * (st.mm[u1, idx[a], idx[b]] - m0)
            if not _chol_solve(amat, y, nd):
                continue
            for a in range(nd):
                out.qdd2[g, idx[a]] = y[a]
        out.fix[g] = True


@njit(cache=True, nogil=True, error_model="numpy")
def model_pass(cy, use, corr, out):  # type: ignore[no-untyped-def]
    """Step 2b: the model-based force (:mod:`cranetwin.twin.force_model`) of every cylinder k
    with ``use[k]``: F = τ_id / (ds/dq) at its joint + corr[g, k] (the smoothed residual at
    row g, (n, n_c) [N]), and its actuator load F·ds/dq, at every row where the rod is out of
    its end stop and the quotient is finite (elsewhere Eq. 1–2 of the pressures stay)."""
    for g in range(out.q.shape[0]):
        for k in range(use.shape[0]):
            if not use[k]:
                continue
            j = cy.joint[k]
            a = out.arm[g, k]
            if not out.known[g, j]:
                continue
            f = out.tau_id[g, j] / a + corr[g, k]
            if math.isfinite(f):
                out.force[g, k] = f
                out.tau_act[g, j] = f * a


def grid_pass(sp: Splines, cy: Cylinders, fj: FreeJoints, st: SampleState, out: GridOut,
              kernels: BatchKernels, pre: F64, model: tuple[B, F64] | None = None) -> int:
    """Every grid quantity of a chunk into ``out`` (steps 1–4 of the module docstring);
    ``pre``: as :func:`state_pass`; ``model``: (which cylinders, the smoothed residual at
    every row (n, n_c) [N]) of the model-based forces (:func:`model_pass`, after the inverse
    dynamics and before the residual), or None.

    Returns:
        Number of rows where a rod position has no joint angle (their q is NaN).
    """
    bad = int(state_pass(sp, cy, fj, st, out, pre))
    kernels.rnea(out.q, out.qd, out.qdd, out.pl, out.tau_id, out.wrench)
    if model is not None:
        model_pass(cy, model[0], np.ascontiguousarray(model[1]), out)
    correction_pass(sp.r, st, out)
    if st.dynamic:
        kernels.rnea_lin(out.q, out.qdd2, out.pl, out.fix, out.wrench)
    return bad


@njit(cache=True, nogil=True)
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
