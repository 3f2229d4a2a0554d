"""numba kernels for one sample (and their batch loops): for the simulator and the hot paths.

For the simulator engineer
--------------------------
Build the parameters once, outside your ``@njit`` loop, and pass the two float64 arrays in::

    from cranetwin.physics import actuator as A, compile_chain, kernels as K
    p = compile_chain(machine)            # p.chain, p.cyl: flat float64 arrays
    nj, nc = p.n_joints, p.n_cylinders

    @njit
    def step(chain, cyl, q, qd, u, ...):
        M = np.empty((nj, nj)); b = np.empty(nj)
        K.mass_matrix(chain, q, payload_kg, M)        # M(q) (nj, nj) [kg, kg·m, kg·m²], CRBA
        K.bias(chain, q, qd, payload_kg, b)           # C(q, qd)·qd + g(q), shape (nj,)
        s = np.empty(nc); dsdq = np.empty(nc)
        K.cylinder_kinematics(cyl, q, s, dsdq)        # rod positions [m], ds_k/dq_joint(k)
        F = A.eq1_cylinder_force(pA, pB, v, A1, A2, Fc, vc, b)  # Eq. 1-2 (physics.actuator)
        ...  # tau[joint(k)] += F[k] * dsdq[k];  qdd = solve(M, tau - b)

All kernels write into caller-provided arrays; :func:`rnea`, :func:`mass_matrix` and :func:`bias`
allocate a few tiny scratch arrays per call, while :func:`rnea_into` (scratch ``work`` (nj, 12))
and :func:`mass_matrix_into` (composite-rigid-body algorithm, scratch ``work`` (nj, 12) and
``comp`` (nj, 22); ≈ 0.3 µs for 4 joints, a quarter of nj RNEA passes) take it from the caller::

    K.mass_matrix_into(chain, q, payload_kg, M, work, comp)
    K.rnea_into(chain, q, qd, zeros, payload_kg, 1.0, h, wrench, work)   # h = C·qd + g

Also: :func:`cylinder_state2` (s, ds/dq, d²s/dq² of one cylinder), :func:`cylinder_joint`
(inverse kinematics of one cylinder), :func:`joint_transforms`.

Conventions: q, qd, qdd shape (n_joints,) [rad, m, per s, per s²]; payload [kg] is a point mass
at the machine's load point (added to the tool mass lumped in ``chain``); gravity from ``chain``.
``wrench`` rows are [fx, fy, fz, mx, my, mz]: the spatial force transmitted from the parent
to body i across joint i, expressed in the child body's frame (= joint frame after the joint
motion) at the joint origin [N, N·m] — the same quantity as Pinocchio's ``data.f[i]``.

Compiled with ``cache=True`` (compiled code is cached next to this file), ``fastmath=False``
so results agree with Pinocchio to rounding, and no ``parallel``: one thread per call.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
from numba import njit

from cranetwin.physics import linkage
from cranetwin.physics.layout import C_JOINT, HEADER, JOINT_BLOCK, PRISMATIC, cyl_block

F64 = npt.NDArray[np.float64]

# ----------------------------------------------------------------------------------------------
# Recursive Newton–Euler (Luh, Walker & Paul), local frames, serial chain, one sample


@njit(cache=True)
def rnea_into(chain, q, qd, qdd, payload_kg, gravity_scale, tau, wrench, work):  # type: ignore[no-untyped-def]
    """Inverse dynamics of one sample, written into ``tau`` (nj,) and ``wrench`` (nj, 6).

    Args:
        chain: Flat chain parameters (see :mod:`cranetwin.physics.chain`).
        q, qd, qdd: Joint positions, velocities, accelerations, shape (nj,) [rad or m, /s, /s²].
        payload_kg: Point mass at the load point [kg] (tool mass already in ``chain``).
        gravity_scale: 1.0 for gravity as in the machine, 0.0 to leave it out.
        tau: Output joint torques/forces, shape (nj,) [N·m or N].
        wrench: Output joint reaction wrenches, shape (nj, 6) [N, N·m] (module docstring).
        work: Scratch, shape (nj, 12).
    """
    nj = int(chain[0])
    gx = chain[1] * gravity_scale
    gy = chain[2] * gravity_scale
    gz = chain[3] * gravity_scale
    lb = int(chain[4])
    lx = chain[5]
    ly = chain[6]
    lz = chain[7]
    # state of the parent (world): angular velocity, angular acceleration, origin acceleration
    wx = 0.0
    wy = 0.0
    wz = 0.0
    dwx = 0.0
    dwy = 0.0
    dwz = 0.0
    ax_ = -gx
    ay_ = -gy
    az_ = -gz
    for i in range(nj):
        o = HEADER + i * JOINT_BLOCK
        kx = chain[o + 1]
        ky = chain[o + 2]
        kz = chain[o + 3]
        r00 = chain[o + 4]
        r01 = chain[o + 5]
        r02 = chain[o + 6]
        r10 = chain[o + 7]
        r11 = chain[o + 8]
        r12 = chain[o + 9]
        r20 = chain[o + 10]
        r21 = chain[o + 11]
        r22 = chain[o + 12]
        px = chain[o + 13]
        py = chain[o + 14]
        pz = chain[o + 15]
        prismatic = chain[o] == PRISMATIC
        if prismatic:
            # origin slides along R0·k by q
            px += (r00 * kx + r01 * ky + r02 * kz) * q[i]
            py += (r10 * kx + r11 * ky + r12 * kz) * q[i]
            pz += (r20 * kx + r21 * ky + r22 * kz) * q[i]
        else:
            c = math.cos(q[i])
            s = math.sin(q[i])
            v = 1.0 - c
            # Rodrigues: Rq = c I + s [k]x + v k k^T ; R = R0 Rq
            q00 = c + kx * kx * v
            q01 = kx * ky * v - kz * s
            q02 = kx * kz * v + ky * s
            q10 = ky * kx * v + kz * s
            q11 = c + ky * ky * v
            q12 = ky * kz * v - kx * s
            q20 = kz * kx * v - ky * s
            q21 = kz * ky * v + kx * s
            q22 = c + kz * kz * v
            t00 = r00 * q00 + r01 * q10 + r02 * q20
            t01 = r00 * q01 + r01 * q11 + r02 * q21
            t02 = r00 * q02 + r01 * q12 + r02 * q22
            t10 = r10 * q00 + r11 * q10 + r12 * q20
            t11 = r10 * q01 + r11 * q11 + r12 * q21
            t12 = r10 * q02 + r11 * q12 + r12 * q22
            t20 = r20 * q00 + r21 * q10 + r22 * q20
            t21 = r20 * q01 + r21 * q11 + r22 * q21
            t22 = r20 * q02 + r21 * q12 + r22 * q22
            r00, r01, r02 = t00, t01, t02
            r10, r11, r12 = t10, t11, t12
            r20, r21, r22 = t20, t21, t22
        work[i, 0] = r00
        work[i, 1] = r01
        work[i, 2] = r02
        work[i, 3] = r10
        work[i, 4] = r11
        work[i, 5] = r12
        work[i, 6] = r20
        work[i, 7] = r21
        work[i, 8] = r22
        work[i, 9] = px
        work[i, 10] = py
        work[i, 11] = pz
        # acceleration of the new origin, parent frame: a + dw x p + w x (w x p)
        wpx = wy * pz - wz * py
        wpy = wz * px - wx * pz
        wpz = wx * py - wy * px
        bx = ax_ + (dwy * pz - dwz * py) + (wy * wpz - wz * wpy)
        by = ay_ + (dwz * px - dwx * pz) + (wz * wpx - wx * wpz)
        bz = az_ + (dwx * py - dwy * px) + (wx * wpy - wy * wpx)
        # to the child frame: x_child = R^T x_parent
        nwx = r00 * wx + r10 * wy + r20 * wz
        nwy = r01 * wx + r11 * wy + r21 * wz
        nwz = r02 * wx + r12 * wy + r22 * wz
        ndx = r00 * dwx + r10 * dwy + r20 * dwz
        ndy = r01 * dwx + r11 * dwy + r21 * dwz
        ndz = r02 * dwx + r12 * dwy + r22 * dwz
        nax = r00 * bx + r10 * by + r20 * bz
        nay = r01 * bx + r11 * by + r21 * bz
        naz = r02 * bx + r12 * by + r22 * bz
        vd = qd[i]
        ad = qdd[i]
        if prismatic:
            # a += k qdd + 2 w x (k qd)
            nax += kx * ad + 2.0 * (nwy * kz - nwz * ky) * vd
            nay += ky * ad + 2.0 * (nwz * kx - nwx * kz) * vd
            naz += kz * ad + 2.0 * (nwx * ky - nwy * kx) * vd
        else:
            # dw += k qdd + w_parent x (k qd); w += k qd
            ndx += kx * ad + (nwy * kz - nwz * ky) * vd
            ndy += ky * ad + (nwz * kx - nwx * kz) * vd
            ndz += kz * ad + (nwx * ky - nwy * kx) * vd
            nwx += kx * vd
            nwy += ky * vd
            nwz += kz * vd
        wx, wy, wz = nwx, nwy, nwz
        dwx, dwy, dwz = ndx, ndy, ndz
        ax_, ay_, az_ = nax, nay, naz
        # body wrench at the origin: f = m a + dw x h + w x (w x h);
        # n = Io dw + w x (Io w) + h x a   (h = m c, Io inertia about the origin)
        m = chain[o + 16]
        hx = chain[o + 17]
        hy = chain[o + 18]
        hz = chain[o + 19]
        i00 = chain[o + 20]
        i01 = chain[o + 21]
        i02 = chain[o + 22]
        i10 = chain[o + 23]
        i11 = chain[o + 24]
        i12 = chain[o + 25]
        i20 = chain[o + 26]
        i21 = chain[o + 27]
        i22 = chain[o + 28]
        whx = wy * hz - wz * hy
        why = wz * hx - wx * hz
        whz = wx * hy - wy * hx
        fx = m * ax_ + (dwy * hz - dwz * hy) + (wy * whz - wz * why)
        fy = m * ay_ + (dwz * hx - dwx * hz) + (wz * whx - wx * whz)
        fz = m * az_ + (dwx * hy - dwy * hx) + (wx * why - wy * whx)
        iwx = i00 * wx + i01 * wy + i02 * wz
        iwy = i10 * wx + i11 * wy + i12 * wz
        iwz = i20 * wx + i21 * wy + i22 * wz
        nx = (i00 * dwx + i01 * dwy + i02 * dwz) + (wy * iwz - wz * iwy) + (hy * az_ - hz * ay_)
        ny = (i10 * dwx + i11 * dwy + i12 * dwz) + (wz * iwx - wx * iwz) + (hz * ax_ - hx * az_)
        nz = (i20 * dwx + i21 * dwy + i22 * dwz) + (wx * iwy - wy * iwx) + (hx * ay_ - hy * ax_)
        if i == lb and payload_kg != 0.0:
            # payload point mass at the load point r: f_p = m_p (a + dw x r + w x (w x r))
            wrx = wy * lz - wz * ly
            wry = wz * lx - wx * lz
            wrz = wx * ly - wy * lx
            fpx = payload_kg * (ax_ + (dwy * lz - dwz * ly) + (wy * wrz - wz * wry))
            fpy = payload_kg * (ay_ + (dwz * lx - dwx * lz) + (wz * wrx - wx * wrz))
            fpz = payload_kg * (az_ + (dwx * ly - dwy * lx) + (wx * wry - wy * wrx))
            fx += fpx
            fy += fpy
            fz += fpz
            nx += ly * fpz - lz * fpy
            ny += lz * fpx - lx * fpz
            nz += lx * fpy - ly * fpx
        wrench[i, 0] = fx
        wrench[i, 1] = fy
        wrench[i, 2] = fz
        wrench[i, 3] = nx
        wrench[i, 4] = ny
        wrench[i, 5] = nz
    # backward pass: add each child's wrench, carried to the parent's frame and origin
    for i in range(nj - 1, -1, -1):
        o = HEADER + i * JOINT_BLOCK
        kx = chain[o + 1]
        ky = chain[o + 2]
        kz = chain[o + 3]
        if chain[o] == PRISMATIC:
            tau[i] = kx * wrench[i, 0] + ky * wrench[i, 1] + kz * wrench[i, 2]
        else:
            tau[i] = kx * wrench[i, 3] + ky * wrench[i, 4] + kz * wrench[i, 5]
        if i > 0:
            r00 = work[i, 0]
            r01 = work[i, 1]
            r02 = work[i, 2]
            r10 = work[i, 3]
            r11 = work[i, 4]
            r12 = work[i, 5]
            r20 = work[i, 6]
            r21 = work[i, 7]
            r22 = work[i, 8]
            px = work[i, 9]
            py = work[i, 10]
            pz = work[i, 11]
            f0 = wrench[i, 0]
            f1 = wrench[i, 1]
            f2 = wrench[i, 2]
            n0 = wrench[i, 3]
            n1 = wrench[i, 4]
            n2 = wrench[i, 5]
            fx = r00 * f0 + r01 * f1 + r02 * f2
            fy = r10 * f0 + r11 * f1 + r12 * f2
            fz = r20 * f0 + r21 * f1 + r22 * f2
            wrench[i - 1, 0] += fx
            wrench[i - 1, 1] += fy
            wrench[i - 1, 2] += fz
            wrench[i - 1, 3] += r00 * n0 + r01 * n1 + r02 * n2 + (py * fz - pz * fy)
            wrench[i - 1, 4] += r10 * n0 + r11 * n1 + r12 * n2 + (pz * fx - px * fz)
            wrench[i - 1, 5] += r20 * n0 + r21 * n1 + r22 * n2 + (px * fy - py * fx)


@njit(cache=True)
def rnea(chain, q, qd, qdd, payload_kg, tau, wrench):  # type: ignore[no-untyped-def]
    """:func:`rnea_into` with gravity on and its own scratch (allocates (nj, 12))."""
    work = np.empty((int(chain[0]), 12))
    rnea_into(chain, q, qd, qdd, payload_kg, 1.0, tau, wrench, work)


@njit(cache=True)
def rnea_batch(chain, q, qd, qdd, payload_kg, tau, wrench):  # type: ignore[no-untyped-def]
    """RNEA over samples: q, qd, qdd (n, nj); payload_kg (n,); tau (n, nj); wrench (n, nj, 6)."""
    nj = int(chain[0])
    work = np.empty((nj, 12))
    for k in range(q.shape[0]):
        rnea_into(chain, q[k], qd[k], qdd[k], payload_kg[k], 1.0, tau[k], wrench[k], work)


@njit(cache=True)
def rnea_tau_batch(chain, q, qd, qdd, payload_kg, tau):  # type: ignore[no-untyped-def]
    """RNEA over samples, joint torques only: tau (n, nj) (wrenches into a reused scratch)."""
    nj = int(chain[0])
    work = np.empty((nj, 12))
    wr = np.empty((nj, 6))
    for k in range(q.shape[0]):
        rnea_into(chain, q[k], qd[k], qdd[k], payload_kg[k], 1.0, tau[k], wr, work)


@njit(cache=True, nogil=True)
def rnea_lin_batch(chain, q, acc, payload_kg, rows, wrench):  # type: ignore[no-untyped-def]
    """Adds to ``wrench`` (n, nj, 6) the part of the RNEA wrenches linear in the accelerations
    (qd = 0, no gravity) at accelerations ``acc`` (n, nj), on the rows where ``rows`` (n,) is
    true: RNEA is affine in qdd, so the wrench at qdd + Δ is the wrench at qdd plus this at Δ."""
    nj = int(chain[0])
    work = np.empty((nj, 12))
    zero = np.zeros(nj)
    tt = np.empty(nj)
    wt = np.empty((nj, 6))
    for k in range(q.shape[0]):
        if not rows[k]:
            continue
        rnea_into(chain, q[k], zero, acc[k], payload_kg[k], 0.0, tt, wt, work)
        for i in range(nj):
            for j in range(6):
                wrench[k, i, j] += wt[i, j]


@njit(cache=True, nogil=True)
def rnea_payload_batch(chain, q, qd, qdd, tau0, tau1):  # type: ignore[no-untyped-def]
    """Joint loads (n, nj) at the same motion without payload (tau0) and with 1 kg at the load
    point (tau1): tau1 − tau0 is the load per kg of payload (the payload regression)."""
    nj = int(chain[0])
    work = np.empty((nj, 12))
    wr = np.empty((nj, 6))
    for k in range(q.shape[0]):
        rnea_into(chain, q[k], qd[k], qdd[k], 0.0, 1.0, tau0[k], wr, work)
        rnea_into(chain, q[k], qd[k], qdd[k], 1.0, 1.0, tau1[k], wr, work)


@njit(cache=True)
def joint_transforms(chain, q, work):  # type: ignore[no-untyped-def]
    """Parent-from-child rotation R (row-major, work[i, 0:9]) and child origin p in the parent
    frame (work[i, 9:12]) of every joint at positions q (nj,)."""
    nj = int(chain[0])
    for i in range(nj):
        o = HEADER + i * JOINT_BLOCK
        kx = chain[o + 1]
        ky = chain[o + 2]
        kz = chain[o + 3]
        for r in range(3):
            work[i, 9 + r] = chain[o + 13 + r]
        if chain[o] == PRISMATIC:
            for r in range(3):
                work[i, 9 + r] += (chain[o + 4 + 3 * r] * kx + chain[o + 5 + 3 * r] * ky
                                   + chain[o + 6 + 3 * r] * kz) * q[i]
                for c in range(3):
                    work[i, 3 * r + c] = chain[o + 4 + 3 * r + c]
        else:
            c_ = math.cos(q[i])
            s_ = math.sin(q[i])
            v = 1.0 - c_
            rq00 = c_ + kx * kx * v
            rq01 = kx * ky * v - kz * s_
            rq02 = kx * kz * v + ky * s_
            rq10 = ky * kx * v + kz * s_
            rq11 = c_ + ky * ky * v
            rq12 = ky * kz * v - kx * s_
            rq20 = kz * kx * v - ky * s_
            rq21 = kz * ky * v + kx * s_
            rq22 = c_ + kz * kz * v
            for r in range(3):
                a0 = chain[o + 4 + 3 * r]
                a1 = chain[o + 5 + 3 * r]
                a2 = chain[o + 6 + 3 * r]
                work[i, 3 * r] = a0 * rq00 + a1 * rq10 + a2 * rq20
                work[i, 3 * r + 1] = a0 * rq01 + a1 * rq11 + a2 * rq21
                work[i, 3 * r + 2] = a0 * rq02 + a1 * rq12 + a2 * rq22


@njit(cache=True)
def mass_matrix_into(chain, q, payload_kg, out, work, comp):  # type: ignore[no-untyped-def]
    """M(q) by the composite-rigid-body algorithm, into ``out`` (nj, nj).

    Scratch: ``work`` (nj, 12) and ``comp`` (nj, 22) (composite mass, first moment, inertia
    about the origin of each subtree, in its own frame; then 9 temporaries).
    """
    nj = int(chain[0])
    lb = int(chain[4])
    joint_transforms(chain, q, work)
    for i in range(nj):
        o = HEADER + i * JOINT_BLOCK
        for r in range(13):
            comp[i, r] = chain[o + 16 + r]
        if i == lb and payload_kg != 0.0:
            lx = chain[5]
            ly = chain[6]
            lz = chain[7]
            rr = lx * lx + ly * ly + lz * lz
            comp[i, 0] += payload_kg
            comp[i, 1] += payload_kg * lx
            comp[i, 2] += payload_kg * ly
            comp[i, 3] += payload_kg * lz
            comp[i, 4] += payload_kg * (rr - lx * lx)
            comp[i, 5] -= payload_kg * lx * ly
            comp[i, 6] -= payload_kg * lx * lz
            comp[i, 7] -= payload_kg * ly * lx
            comp[i, 8] += payload_kg * (rr - ly * ly)
            comp[i, 9] -= payload_kg * ly * lz
            comp[i, 10] -= payload_kg * lz * lx
            comp[i, 11] -= payload_kg * lz * ly
            comp[i, 12] += payload_kg * (rr - lz * lz)
    # composite inertias, tip to base: carry subtree i into frame i − 1
    for i in range(nj - 1, 0, -1):
        m = comp[i, 0]
        px = work[i, 9]
        py = work[i, 10]
        pz = work[i, 11]
        # h' = R h
        hx = work[i, 0] * comp[i, 1] + work[i, 1] * comp[i, 2] + work[i, 2] * comp[i, 3]
        hy = work[i, 3] * comp[i, 1] + work[i, 4] * comp[i, 2] + work[i, 5] * comp[i, 3]
        hz = work[i, 6] * comp[i, 1] + work[i, 7] * comp[i, 2] + work[i, 8] * comp[i, 3]
        comp[i - 1, 0] += m
        comp[i - 1, 1] += hx + m * px
        comp[i - 1, 2] += hy + m * py
        comp[i - 1, 3] += hz + m * pz
        # J' = R J R^T + m(|p|² I − p p^T) + 2(p·h')I − p h'^T − h' p^T ; T = J R^T first
        for a in range(3):
            j0 = comp[i, 4 + 3 * a]
            j1 = comp[i, 5 + 3 * a]
            j2 = comp[i, 6 + 3 * a]
            for c in range(3):
                comp[i, 13 + 3 * a + c] = (j0 * work[i, 3 * c] + j1 * work[i, 3 * c + 1]
                                           + j2 * work[i, 3 * c + 2])
        pp = px * px + py * py + pz * pz
        ph2 = 2.0 * (px * hx + py * hy + pz * hz)
        for r in range(3):
            r0 = work[i, 3 * r]
            r1 = work[i, 3 * r + 1]
            r2 = work[i, 3 * r + 2]
            pr = px if r == 0 else (py if r == 1 else pz)
            hr = hx if r == 0 else (hy if r == 1 else hz)
            for c in range(3):
                pc = px if c == 0 else (py if c == 1 else pz)
                hc = hx if c == 0 else (hy if c == 1 else hz)
                val = (r0 * comp[i, 13 + c] + r1 * comp[i, 16 + c] + r2 * comp[i, 19 + c]
                       - m * pr * pc - pr * hc - hr * pc)
                if r == c:
                    val += m * pp + ph2
                comp[i - 1, 4 + 3 * r + c] += val
    # columns: force of a unit motion of joint i on subtree i, carried to the base
    for i in range(nj):
        o = HEADER + i * JOINT_BLOCK
        kx = chain[o + 1]
        ky = chain[o + 2]
        kz = chain[o + 3]
        m = comp[i, 0]
        hx = comp[i, 1]
        hy = comp[i, 2]
        hz = comp[i, 3]
        if chain[o] == PRISMATIC:
            # S = (0, k): f = m k, n = h x k
            fx = m * kx
            fy = m * ky
            fz = m * kz
            nx = hy * kz - hz * ky
            ny = hz * kx - hx * kz
            nz = hx * ky - hy * kx
            out[i, i] = kx * fx + ky * fy + kz * fz
        else:
            # S = (k, 0): f = k x h, n = J k
            fx = ky * hz - kz * hy
            fy = kz * hx - kx * hz
            fz = kx * hy - ky * hx
            nx = comp[i, 4] * kx + comp[i, 5] * ky + comp[i, 6] * kz
            ny = comp[i, 7] * kx + comp[i, 8] * ky + comp[i, 9] * kz
            nz = comp[i, 10] * kx + comp[i, 11] * ky + comp[i, 12] * kz
            out[i, i] = kx * nx + ky * ny + kz * nz
        for j in range(i - 1, -1, -1):
            # carry (f, n) from frame j + 1 to frame j
            w = j + 1
            gx = work[w, 0] * fx + work[w, 1] * fy + work[w, 2] * fz
            gy = work[w, 3] * fx + work[w, 4] * fy + work[w, 5] * fz
            gz = work[w, 6] * fx + work[w, 7] * fy + work[w, 8] * fz
            px = work[w, 9]
            py = work[w, 10]
            pz = work[w, 11]
            mx = work[w, 0] * nx + work[w, 1] * ny + work[w, 2] * nz + (py * gz - pz * gy)
            my = work[w, 3] * nx + work[w, 4] * ny + work[w, 5] * nz + (pz * gx - px * gz)
            mz = work[w, 6] * nx + work[w, 7] * ny + work[w, 8] * nz + (px * gy - py * gx)
            fx, fy, fz, nx, ny, nz = gx, gy, gz, mx, my, mz
            oj = HEADER + j * JOINT_BLOCK
            if chain[oj] == PRISMATIC:
                val = chain[oj + 1] * fx + chain[oj + 2] * fy + chain[oj + 3] * fz
            else:
                val = chain[oj + 1] * nx + chain[oj + 2] * ny + chain[oj + 3] * nz
            out[j, i] = val
            out[i, j] = val


@njit(cache=True)
def mass_matrix(chain, q, payload_kg, out):  # type: ignore[no-untyped-def]
    """M(q) of one sample into ``out`` (nj, nj) [kg, kg·m, kg·m²]; symmetric positive definite.

    Composite-rigid-body algorithm; allocates its scratch (use :func:`mass_matrix_into` in a
    hot loop)."""
    nj = int(chain[0])
    mass_matrix_into(chain, q, payload_kg, out, np.empty((nj, 12)), np.empty((nj, 22)))


@njit(cache=True)
def mass_matrix_rnea(chain, q, payload_kg, out):  # type: ignore[no-untyped-def]
    """M(q) column by column, RNEA(q, 0, e_j) without gravity: a slower cross-check of
    :func:`mass_matrix`."""
    nj = int(chain[0])
    zero = np.zeros(nj)
    e = np.empty(nj)
    tau = np.empty(nj)
    wr = np.empty((nj, 6))
    work = np.empty((nj, 12))
    for j in range(nj):
        for i in range(nj):
            e[i] = 0.0
        e[j] = 1.0
        rnea_into(chain, q, zero, e, payload_kg, 0.0, tau, wr, work)
        for i in range(nj):
            out[i, j] = tau[i]
    # symmetrise the rounding (the exact matrix is symmetric)
    for i in range(nj):
        for j in range(i + 1, nj):
            m = 0.5 * (out[i, j] + out[j, i])
            out[i, j] = m
            out[j, i] = m


@njit(cache=True)
def bias(chain, q, qd, payload_kg, out):  # type: ignore[no-untyped-def]
    """Bias forces C(q, qd)·qd + g(q) of one sample into ``out`` (nj,) [N·m or N]."""
    nj = int(chain[0])
    zero = np.zeros(nj)
    wr = np.empty((nj, 6))
    work = np.empty((nj, 12))
    rnea_into(chain, q, qd, zero, payload_kg, 1.0, out, wr, work)


@njit(cache=True)
def mass_matrix_batch(chain, q, payload_kg, out):  # type: ignore[no-untyped-def]
    """M(q) over samples: q (n, nj), payload_kg (n,), out (n, nj, nj)."""
    nj = int(chain[0])
    work = np.empty((nj, 12))
    comp = np.empty((nj, 22))
    for k in range(q.shape[0]):
        mass_matrix_into(chain, q[k], payload_kg[k], out[k], work, comp)


@njit(cache=True)
def bias_batch(chain, q, qd, payload_kg, out):  # type: ignore[no-untyped-def]
    """Bias forces over samples: q, qd (n, nj), payload_kg (n,), out (n, nj)."""
    nj = int(chain[0])
    zero = np.zeros(nj)
    wr = np.empty((nj, 6))
    work = np.empty((nj, 12))
    for k in range(q.shape[0]):
        rnea_into(chain, q[k], qd[k], zero, payload_kg[k], 1.0, out[k], wr, work)


# ----------------------------------------------------------------------------------------------
# Cylinder kinematics: loops over the cylinders and samples; each linkage kind's formulas live in
# its module of cranetwin.physics.linkage


@njit(cache=True, nogil=True)
def four_bar_points(cyl, k, q):  # type: ignore[no-untyped-def]
    """Rod end E and coupler pin F of four-bar cylinder ``k`` at joint angle q, in the joint
    plane (2-D). Returns (Ex, Ey, Fx, Fy, ok); ok False when the linkage cannot assemble."""
    return linkage.four_bar.points(cyl, cyl_block(k), q)


@njit(cache=True, nogil=True)
def cylinder_state(cyl, k, q):  # type: ignore[no-untyped-def]
    """Rod position s [m] and moment arm ds/dq [m/rad or m/m] of cylinder ``k`` at the
    position ``q`` [rad or m] of the joint it drives. NaN when the geometry cannot assemble."""
    s, d1, _ = linkage.state(cyl, cyl_block(k), q)
    return s, d1


@njit(cache=True, nogil=True)
def cylinder_state2(cyl, k, q):  # type: ignore[no-untyped-def]
    """(s, ds/dq, d²s/dq²) of cylinder ``k`` at the position q of its joint [m, m/rad,
    m/rad²] (:func:`cranetwin.physics.linkage.state`)."""
    return linkage.state(cyl, cyl_block(k), q)


@njit(cache=True, nogil=True)
def cylinder_kinematics2_batch(cyl, q, s_out, d1_out, d2_out):  # type: ignore[no-untyped-def]
    """s, ds/dq, d²s/dq² of every cylinder over samples: q (n, nj), outputs (n, nc)."""
    nc = int(cyl[0])
    for i in range(q.shape[0]):
        for k in range(nc):
            o = cyl_block(k)
            s, d1, d2 = linkage.state(cyl, o, q[i, int(cyl[o + C_JOINT])])
            s_out[i, k] = s
            d1_out[i, k] = d1
            d2_out[i, k] = d2


@njit(cache=True, nogil=True)
def cylinder_kinematics(cyl, q, s_out, dsdq_out):  # type: ignore[no-untyped-def]
    """Rod positions s (nc,) [m] and moment arms ds_k/dq_joint(k) (nc,) for joint positions q."""
    nc = int(cyl[0])
    for k in range(nc):
        o = cyl_block(k)
        s, d, _ = linkage.state(cyl, o, q[int(cyl[o + C_JOINT])])
        s_out[k] = s
        dsdq_out[k] = d


@njit(cache=True, nogil=True)
def cylinder_kinematics_batch(cyl, q, s_out, dsdq_out):  # type: ignore[no-untyped-def]
    """:func:`cylinder_kinematics` over samples: q (n, nj), s_out and dsdq_out (n, nc)."""
    for i in range(q.shape[0]):
        cylinder_kinematics(cyl, q[i], s_out[i], dsdq_out[i])


@njit(cache=True, nogil=True)
def cylinder_joint(cyl, k, s):  # type: ignore[no-untyped-def]
    """Inverse of :func:`cylinder_state`: the joint position [rad or m] for rod position s [m],
    on the branch chosen at compile time (:func:`cranetwin.physics.chain.choose_inverse_branches`).
    NaN if none."""
    return linkage.inverse(cyl, cyl_block(k), s)


@njit(cache=True, nogil=True)
def cylinder_joint_batch(cyl, k, s, out):  # type: ignore[no-untyped-def]
    """:func:`cylinder_joint` over samples: s (n,) -> out (n,)."""
    for i in range(s.shape[0]):
        out[i] = linkage.inverse(cyl, cyl_block(k), s[i])


@njit(cache=True, nogil=True)
def branch_signs(cyl, k, q):  # type: ignore[no-untyped-def]
    """Signs that identify the inverse branch at joint position q: (sigma, sigma_E, sigma_F)
    (:func:`cranetwin.physics.linkage.branch_signs`)."""
    return linkage.branch_signs(cyl, cyl_block(k), q)


@njit(cache=True, nogil=True)
def four_bar_points_batch(cyl, k, q, out):  # type: ignore[no-untyped-def]
    """:func:`four_bar_points` over samples: q (n,) -> out (n, 4) = (Ex, Ey, Fx, Fy), NaN if
    the linkage cannot assemble."""
    for i in range(q.shape[0]):
        ex, ey, fx, fy, _ = linkage.four_bar.points(cyl, cyl_block(k), q[i])
        out[i, 0] = ex
        out[i, 1] = ey
        out[i, 2] = fx
        out[i, 3] = fy


@njit(cache=True, nogil=True, error_model="numpy")
def cylinder_motion(cyl, k, s):  # type: ignore[no-untyped-def]
    """(q, ds/dq, d²s/dq²) of cylinder ``k`` at rod position s [m]: the inverse kinematics and
    the forward map's derivatives at once (:func:`cranetwin.physics.linkage.motion`)."""
    return linkage.motion(cyl, cyl_block(k), s)


@njit(cache=True, nogil=True, error_model="numpy")
def cylinder_motion_batch(cyl, s, v, a, q, qd, qdd, arm):  # type: ignore[no-untyped-def]
    """Joint motion of the cylinder-driven joints and the moment arms in one pass.

    For every sample i and cylinder k: q_j and (ds/dq, d²s/dq²) at s[i, k]
    (:func:`cylinder_motion`) and the chain rule qd_j = v/s', qdd_j = (a − s''·qd_j²)/s'.
    Fills the columns j of the driven joints in q, qd, qdd (n, nj) and arm (n, nc) = ds/dq;
    leaves the other columns untouched. NaN where the geometry cannot produce s.
    """
    nc = int(cyl[0])
    for i in range(s.shape[0]):
        for k in range(nc):
            o = cyl_block(k)
            ji = int(cyl[o + C_JOINT])
            qj, d1, d2 = linkage.motion(cyl, o, s[i, k])
            w = v[i, k] / d1
            q[i, ji] = qj
            qd[i, ji] = w
            qdd[i, ji] = (a[i, k] - d2 * w * w) / d1
            arm[i, k] = d1


@njit(cache=True)
def _chol_solve(a, y, nd):  # type: ignore[no-untyped-def]
    """Solve a[:nd, :nd]·x = y[:nd] for symmetric positive definite a (overwritten by its
    Cholesky factor), x into y. False if a is not positive definite."""
    for c in range(nd):
        s = a[c, c]
        for p in range(c):
            s -= a[c, p] * a[c, p]
        if s <= 0.0:
            return False
        a[c, c] = math.sqrt(s)
        for r in range(c + 1, nd):
            t = a[r, c]
            for p in range(c):
                t -= a[r, p] * a[c, p]
            a[r, c] = t / a[c, c]
    for r in range(nd):  # L z = y
        t = y[r]
        for p in range(r):
            t -= a[r, p] * y[p]
        y[r] = t / a[r, r]
    for r in range(nd - 1, -1, -1):  # Lᵀ x = z
        t = y[r]
        for p in range(r + 1, nd):
            t -= a[p, r] * y[p]
        y[r] = t / a[r, r]
    return True


@njit(cache=True)
def accel_correction_batch(chain, q, payload_kg, resid, use, out):  # type: ignore[no-untyped-def]
    """Δqdd solving M_DD(q)·Δqdd_D = resid_D over samples (D: joints with ``use`` true; the
    others keep Δ = 0), by Cholesky of the symmetric positive definite M_DD.

    Args:
        chain: Chain parameters.
        q: Joint positions (n, nj); payload_kg (n,).
        resid: Joint load residuals (n, nj) [N·m or N]; a non-finite residual on a D joint
            makes that sample's Δ zero.
        use: (nj,) booleans.
        out: Δqdd (n, nj).
    """
    nj = int(chain[0])
    work = np.empty((nj, 12))
    comp = np.empty((nj, 22))
    mm = np.empty((nj, nj))
    idx = np.empty(nj, dtype=np.int64)
    nd = 0
    for j in range(nj):
        if use[j]:
            idx[nd] = j
            nd += 1
    a = np.empty((nd, nd))
    y = np.empty(nd)
    for k in range(q.shape[0]):
        for j in range(nj):
            out[k, j] = 0.0
        ok = True
        for r in range(nd):
            y[r] = resid[k, idx[r]]
            if not np.isfinite(y[r]):
                ok = False
        if not ok or nd == 0:
            continue
        mass_matrix_into(chain, q[k], payload_kg[k], mm, work, comp)
        for r in range(nd):
            for c in range(nd):
                a[r, c] = mm[idx[r], idx[c]]
        if not _chol_solve(a, y, nd):
            continue
        for r in range(nd):
            out[k, idx[r]] = y[r]
