"""Inverse dynamics and the mass matrix of a serial chain, one sample at a time, compiled: the
recursive Newton–Euler algorithm (RNEA) with joint reaction wrenches, the composite-rigid-body
algorithm (CRBA) for M(q), bias forces, and the loops over samples built on them.

Equation of motion (paper Eq. 3–4)::

    M(q)·qdd + C(q, qd)·qd + g(q) = tau

Every function reads the machine from the flat ``chain`` array (:mod:`cranetwin.physics.layout`)
and writes into caller-provided arrays. Conventions: q, qd, qdd shape (n_joints,) [rad or m,
per s, per s²]; payload [kg] is a point mass at the machine's load point (added to the tool mass
lumped in ``chain``); gravity from ``chain``. ``wrench`` rows are [fx, fy, fz, mx, my, mz]: the
spatial force transmitted from the parent to body i across joint i, expressed in the child
body's frame (= joint frame after the joint motion) at the joint origin [N, N·m] — the same
quantity as Pinocchio's ``data.f[i]``. The joint transform is :func:`joint_transform`, once.

Compiled with ``cache=True``, ``fastmath=False`` (results agree with Pinocchio to rounding),
``nogil=True`` (the service runs replays in threads) and no ``parallel``.
:mod:`cranetwin.physics.codegen` traces the same algorithm on symbols to generate
straight-line kernels for one machine.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from cranetwin.physics.layout import (
    GRAVITY_X,
    J_AXIS_X,
    J_FIRST_MOMENT_X,
    J_INERTIA_0,
    J_KIND,
    J_MASS,
    J_ORIGIN_X,
    J_ROT_0,
    LOAD_BODY,
    LOAD_POINT_X,
    N_JOINTS,
    PRISMATIC,
    joint_block,
)

# Recursive Newton–Euler (Luh, Walker & Paul), local frames, serial chain, one sample


@njit(cache=True, nogil=True)
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
    nj = int(chain[N_JOINTS])
    gx = chain[GRAVITY_X] * gravity_scale
    gy = chain[GRAVITY_X + 1] * gravity_scale
    gz = chain[GRAVITY_X + 2] * gravity_scale
    lb = int(chain[LOAD_BODY])
    lx = chain[LOAD_POINT_X]
    ly = chain[LOAD_POINT_X + 1]
    lz = chain[LOAD_POINT_X + 2]
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
        o = joint_block(i)
        kx = chain[o + J_AXIS_X]
        ky = chain[o + J_AXIS_X + 1]
        kz = chain[o + J_AXIS_X + 2]
        prismatic = chain[o + J_KIND] == PRISMATIC
        w_i = work[i]
        joint_transform(chain, i, q[i], w_i)
        r00, r01, r02 = w_i[0], w_i[1], w_i[2]
        r10, r11, r12 = w_i[3], w_i[4], w_i[5]
        r20, r21, r22 = w_i[6], w_i[7], w_i[8]
        px, py, pz = w_i[9], w_i[10], w_i[11]
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
        m = chain[o + J_MASS]
        hx = chain[o + J_FIRST_MOMENT_X]
        hy = chain[o + J_FIRST_MOMENT_X + 1]
        hz = chain[o + J_FIRST_MOMENT_X + 2]
        i00 = chain[o + J_INERTIA_0]
        i01 = chain[o + J_INERTIA_0 + 1]
        i02 = chain[o + J_INERTIA_0 + 2]
        i10 = chain[o + J_INERTIA_0 + 3]
        i11 = chain[o + J_INERTIA_0 + 4]
        i12 = chain[o + J_INERTIA_0 + 5]
        i20 = chain[o + J_INERTIA_0 + 6]
        i21 = chain[o + J_INERTIA_0 + 7]
        i22 = chain[o + J_INERTIA_0 + 8]
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
        o = joint_block(i)
        kx = chain[o + J_AXIS_X]
        ky = chain[o + J_AXIS_X + 1]
        kz = chain[o + J_AXIS_X + 2]
        if chain[o + J_KIND] == PRISMATIC:
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


@njit(cache=True, nogil=True)
def rnea(chain, q, qd, qdd, payload_kg, tau, wrench):  # type: ignore[no-untyped-def]
    """:func:`rnea_into` with gravity on and its own scratch (allocates (nj, 12))."""
    work = np.empty((int(chain[N_JOINTS]), 12))
    rnea_into(chain, q, qd, qdd, payload_kg, 1.0, tau, wrench, work)


@njit(cache=True, nogil=True)
def rnea_batch(chain, q, qd, qdd, payload_kg, tau, wrench):  # type: ignore[no-untyped-def]
    """RNEA over samples: q, qd, qdd (n, nj); payload_kg (n,); tau (n, nj); wrench (n, nj, 6)."""
    nj = int(chain[N_JOINTS])
    work = np.empty((nj, 12))
    for k in range(q.shape[0]):
        rnea_into(chain, q[k], qd[k], qdd[k], payload_kg[k], 1.0, tau[k], wrench[k], work)


@njit(cache=True, nogil=True)
def rnea_tau_batch(chain, q, qd, qdd, payload_kg, tau):  # type: ignore[no-untyped-def]
    """RNEA over samples, joint torques only: tau (n, nj) (wrenches into a reused scratch)."""
    nj = int(chain[N_JOINTS])
    work = np.empty((nj, 12))
    wr = np.empty((nj, 6))
    for k in range(q.shape[0]):
        rnea_into(chain, q[k], qd[k], qdd[k], payload_kg[k], 1.0, tau[k], wr, work)


@njit(cache=True, nogil=True)
def rnea_lin_batch(chain, q, acc, payload_kg, rows, wrench):  # type: ignore[no-untyped-def]
    """Adds to ``wrench`` (n, nj, 6) the part of the RNEA wrenches linear in the accelerations
    (qd = 0, no gravity) at accelerations ``acc`` (n, nj), on the rows where ``rows`` (n,) is
    true: RNEA is affine in qdd, so the wrench at qdd + Δ is the wrench at qdd plus this at Δ."""
    nj = int(chain[N_JOINTS])
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
    nj = int(chain[N_JOINTS])
    work = np.empty((nj, 12))
    wr = np.empty((nj, 6))
    for k in range(q.shape[0]):
        rnea_into(chain, q[k], qd[k], qdd[k], 0.0, 1.0, tau0[k], wr, work)
        rnea_into(chain, q[k], qd[k], qdd[k], 1.0, 1.0, tau1[k], wr, work)


@njit(cache=True, nogil=True, inline="always")
def joint_transform(chain, i, qi, out):  # type: ignore[no-untyped-def]
    """Joint i at position qi [rad or m]: the child frame's rotation R = R0·Rq in the parent
    frame (row-major, out[0:9]; Rq by Rodrigues' formula about the joint axis k,
    Rq = c·I + s·[k]× + (1 − c)·k·kᵀ, identity for a prismatic joint) and its origin
    p = p0 (+ qi·R0·k for a prismatic joint) [m] (out[9:12]). The one numeric form of the
    joint transform: RNEA, CRBA and the body poses call it."""
    o = joint_block(i)
    kx = chain[o + J_AXIS_X]
    ky = chain[o + J_AXIS_X + 1]
    kz = chain[o + J_AXIS_X + 2]
    for r in range(3):
        out[9 + r] = chain[o + J_ORIGIN_X + r]
    if chain[o + J_KIND] == PRISMATIC:
        for r in range(3):
            out[9 + r] += (chain[o + J_ROT_0 + 3 * r] * kx + chain[o + J_ROT_0 + 1 + 3 * r] * ky
                           + chain[o + J_ROT_0 + 2 + 3 * r] * kz) * qi
            for c in range(3):
                out[3 * r + c] = chain[o + J_ROT_0 + 3 * r + c]
    else:
        c_ = math.cos(qi)
        s_ = math.sin(qi)
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
            a0 = chain[o + J_ROT_0 + 3 * r]
            a1 = chain[o + J_ROT_0 + 1 + 3 * r]
            a2 = chain[o + J_ROT_0 + 2 + 3 * r]
            out[3 * r] = a0 * rq00 + a1 * rq10 + a2 * rq20
            out[3 * r + 1] = a0 * rq01 + a1 * rq11 + a2 * rq21
            out[3 * r + 2] = a0 * rq02 + a1 * rq12 + a2 * rq22


@njit(cache=True, nogil=True)
def joint_transforms(chain, q, work):  # type: ignore[no-untyped-def]
    """:func:`joint_transform` of every joint at positions q (nj,) into work (nj, 12)."""
    for i in range(int(chain[N_JOINTS])):
        joint_transform(chain, i, q[i], work[i])


@njit(cache=True, nogil=True)
def body_poses_batch(chain, q, out):  # type: ignore[no-untyped-def]
    """World poses of the chain bodies over samples: q (n, nj) -> out (n, nj, 4, 4), the
    homogeneous transforms body i -> world (body i = child of joint i) [m]."""
    nj = int(chain[N_JOINTS])
    w = np.empty((nj, 12))
    rel = np.zeros((4, 4))
    rel[3, 3] = 1.0
    for k in range(q.shape[0]):
        joint_transforms(chain, q[k], w)
        for i in range(nj):
            for r in range(3):
                for c in range(3):
                    rel[r, c] = w[i, 3 * r + c]
                rel[r, 3] = w[i, 9 + r]
            if i == 0:
                out[k, 0] = rel
            else:
                out[k, i] = out[k, i - 1] @ rel


@njit(cache=True, nogil=True)
def mass_matrix_into(chain, q, payload_kg, out, work, comp):  # type: ignore[no-untyped-def]
    """M(q) by the composite-rigid-body algorithm, into ``out`` (nj, nj).

    Scratch: ``work`` (nj, 12) and ``comp`` (nj, 22) (composite mass, first moment, inertia
    about the origin of each subtree, in its own frame; then 9 temporaries).
    """
    nj = int(chain[N_JOINTS])
    lb = int(chain[LOAD_BODY])
    joint_transforms(chain, q, work)
    for i in range(nj):
        o = joint_block(i)
        for r in range(13):
            comp[i, r] = chain[o + 16 + r]
        if i == lb and payload_kg != 0.0:
            lx = chain[LOAD_POINT_X]
            ly = chain[LOAD_POINT_X + 1]
            lz = chain[LOAD_POINT_X + 2]
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
        o = joint_block(i)
        kx = chain[o + J_AXIS_X]
        ky = chain[o + J_AXIS_X + 1]
        kz = chain[o + J_AXIS_X + 2]
        m = comp[i, 0]
        hx = comp[i, 1]
        hy = comp[i, 2]
        hz = comp[i, 3]
        if chain[o + J_KIND] == PRISMATIC:
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
            oj = joint_block(j)
            if chain[oj + J_KIND] == PRISMATIC:
                val = (chain[oj + J_AXIS_X] * fx + chain[oj + J_AXIS_X + 1] * fy
                       + chain[oj + J_AXIS_X + 2] * fz)
            else:
                val = (chain[oj + J_AXIS_X] * nx + chain[oj + J_AXIS_X + 1] * ny
                       + chain[oj + J_AXIS_X + 2] * nz)
            out[j, i] = val
            out[i, j] = val


@njit(cache=True, nogil=True)
def mass_matrix(chain, q, payload_kg, out):  # type: ignore[no-untyped-def]
    """M(q) of one sample into ``out`` (nj, nj) [kg, kg·m, kg·m²]; symmetric positive definite.

    Composite-rigid-body algorithm; allocates its scratch (use :func:`mass_matrix_into` in a
    hot loop)."""
    nj = int(chain[N_JOINTS])
    mass_matrix_into(chain, q, payload_kg, out, np.empty((nj, 12)), np.empty((nj, 22)))


@njit(cache=True, nogil=True, inline="always")
def mass_matrix_rnea_into(chain, q, payload_kg, out, scratch):  # type: ignore[no-untyped-def]
    """M(q) column by column into ``out`` (nj, nj): column j is RNEA(q, 0, e_j) without
    gravity, then the rounding symmetrised (the exact matrix is symmetric). The simulator's
    forward dynamics uses it (each column is the same RNEA its bias forces use); a slower
    cross-check of :func:`mass_matrix`.

    ``scratch`` = (zero (nj,) all 0, e (nj,), tau (nj,), wr (nj, 6), work (nj, 12)).
    """
    zero, e, tau, wr, work = scratch
    nj = int(chain[N_JOINTS])
    for j in range(nj):
        for i in range(nj):
            e[i] = 0.0
        e[j] = 1.0
        rnea_into(chain, q, zero, e, payload_kg, 0.0, tau, wr, work)
        for i in range(nj):
            out[i, j] = tau[i]
    for i in range(nj):
        for j in range(i + 1, nj):
            m = 0.5 * (out[i, j] + out[j, i])
            out[i, j] = m
            out[j, i] = m


@njit(cache=True, nogil=True)
def mass_matrix_rnea(chain, q, payload_kg, out):  # type: ignore[no-untyped-def]
    """:func:`mass_matrix_rnea_into` allocating its scratch."""
    nj = int(chain[N_JOINTS])
    mass_matrix_rnea_into(chain, q, payload_kg, out,
                          (np.zeros(nj), np.empty(nj), np.empty(nj), np.empty((nj, 6)),
                           np.empty((nj, 12))))


@njit(cache=True, nogil=True)
def bias(chain, q, qd, payload_kg, out):  # type: ignore[no-untyped-def]
    """Bias forces C(q, qd)·qd + g(q) of one sample into ``out`` (nj,) [N·m or N]."""
    nj = int(chain[N_JOINTS])
    zero = np.zeros(nj)
    wr = np.empty((nj, 6))
    work = np.empty((nj, 12))
    rnea_into(chain, q, qd, zero, payload_kg, 1.0, out, wr, work)


@njit(cache=True, nogil=True)
def mass_matrix_batch(chain, q, payload_kg, out):  # type: ignore[no-untyped-def]
    """M(q) over samples: q (n, nj), payload_kg (n,), out (n, nj, nj)."""
    nj = int(chain[N_JOINTS])
    work = np.empty((nj, 12))
    comp = np.empty((nj, 22))
    for k in range(q.shape[0]):
        mass_matrix_into(chain, q[k], payload_kg[k], out[k], work, comp)


@njit(cache=True, nogil=True)
def bias_batch(chain, q, qd, payload_kg, out):  # type: ignore[no-untyped-def]
    """Bias forces over samples: q, qd (n, nj), payload_kg (n,), out (n, nj)."""
    nj = int(chain[N_JOINTS])
    zero = np.zeros(nj)
    wr = np.empty((nj, 6))
    work = np.empty((nj, 12))
    for k in range(q.shape[0]):
        rnea_into(chain, q[k], qd[k], zero, payload_kg[k], 1.0, out[k], wr, work)



@njit(cache=True, nogil=True)
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


@njit(cache=True, nogil=True)
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
    nj = int(chain[N_JOINTS])
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
