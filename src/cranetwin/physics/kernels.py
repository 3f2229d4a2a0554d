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

Where things live: RNEA, CRBA and their loops in :mod:`cranetwin.physics.rnea` (re-exported
here); each linkage kind's s, s′, s″ and inverse in :mod:`cranetwin.physics.linkage`; here,
the loops of those over the cylinders and samples. Array layouts: :mod:`cranetwin.physics.layout`.
All compiled with ``cache=True, nogil=True``.
"""

from __future__ import annotations

from numba import njit

from cranetwin.physics import linkage
from cranetwin.physics.layout import C_JOINT, cyl_block
from cranetwin.physics.rnea import (
    _chol_solve,
    accel_correction_batch,
    bias,
    bias_batch,
    body_poses_batch,
    joint_transform,
    joint_transforms,
    mass_matrix,
    mass_matrix_batch,
    mass_matrix_into,
    mass_matrix_rnea,
    rnea,
    rnea_batch,
    rnea_into,
    rnea_lin_batch,
    rnea_payload_batch,
    rnea_tau_batch,
)

__all__ = [
    "_chol_solve", "accel_correction_batch", "bias", "bias_batch", "body_poses_batch",
    "branch_signs", "cylinder_joint", "cylinder_joint_batch", "cylinder_kinematics",
    "cylinder_kinematics2_batch", "cylinder_kinematics_batch", "cylinder_motion",
    "cylinder_motion_batch", "cylinder_state", "cylinder_state2", "four_bar_points",
    "four_bar_points_batch", "joint_transform", "joint_transforms", "mass_matrix",
    "mass_matrix_batch", "mass_matrix_into", "mass_matrix_rnea", "rnea", "rnea_batch",
    "rnea_into", "rnea_lin_batch", "rnea_payload_batch", "rnea_tau_batch",
]


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
