"""Inverse kinematics of the cylinders by table: rod position s -> joint angle q, q′ = dq/ds
and q″ = d²q/ds², for the twin's per-instant loops.

The exact inverse (:func:`cranetwin.physics.kernels.cylinder_motion`: the linkage's closed
form or circle intersections, then s′ and s″ by differentiation) costs about seven times a
table look-up. On each of ``KIN_TABLE_NODES − 1`` equal cells of a cylinder's stroke, the
quintic Hermite polynomial through q, q′, q″ at both ends is stored as coefficients of
u = (s − s_i)/h, shape (n_cylinders, cells, 6). Its error is of order h⁶·q⁽⁶⁾ for q and
h⁴·q⁽⁶⁾ for q″: with 2048 cells below 1e-12 relative on the PATU 655 (tested against the exact
inverse). A cylinder whose table is not usable (a node the geometry cannot produce, or a jump
of q inside the stroke) uses the exact inverse.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from cranetwin.physics.chain import CYL_BLOCK
from cranetwin.physics.kernels import cylinder_motion

KIN_TABLE_NODES = 2049
"""Nodes of the rod-position tables (:func:`kinematics_table`) over each cylinder's stroke:
cells of stroke/2048 (≈ 0.3 mm on the PATU 655)."""


@njit(cache=True, nogil=True, error_model="numpy")
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


@njit(cache=True, nogil=True, inline="always")
def table_inverse(table, k, cells_per_m, s):  # type: ignore[no-untyped-def]
    """(q, dq/ds, d²q/ds²) of cylinder k at rod position s in [0, stroke] from its table
    (``cells_per_m`` = cells / stroke [1/m]): the inverse map and its derivatives, so that the
    chain rule needs no division (qd = q′·v, qdd = q′·a + q″·v²; the moment arm ds/dq is 1/q′).
    :func:`cylinder_motion` returns the forward derivatives instead: q′ = 1/s′, q″ = −s″/s′³."""
    n_cells = table.shape[1]
    x = s * cells_per_m
    i = min(int(x), n_cells - 1)
    u = x - i
    c = table[k, i]
    qv = c[0] + u * (c[1] + u * (c[2] + u * (c[3] + u * (c[4] + u * c[5]))))
    g1 = (c[1] + u * (2.0 * c[2] + u * (3.0 * c[3] + u * (4.0 * c[4] + u * 5.0 * c[5])))) * (
        cells_per_m)
    g2 = (2.0 * c[2] + u * (6.0 * c[3] + u * (12.0 * c[4] + u * 20.0 * c[5]))) * (
        cells_per_m * cells_per_m)
    return qv, g1, g2


@njit(cache=True, nogil=True, inline="always")
def inverse_motion(table, table_ok, cyl, k, cells_per_m, s):  # type: ignore[no-untyped-def]
    """(q, dq/ds, d²q/ds²) of cylinder k at rod position s: from its table where usable
    (:func:`table_inverse`), else from the exact inverse (:func:`cylinder_motion`)."""
    if table_ok[k]:
        return table_inverse(table, k, cells_per_m, s)
    qj, d1, d2 = cylinder_motion(cyl, k, s)
    g1 = 1.0 / d1
    return qj, g1, -d2 * g1 * g1 * g1


@njit(cache=True, nogil=True, inline="always")
def joint_motion(table, table_ok, cyl, k, cells_per_m, s, v, a):  # type: ignore[no-untyped-def]
    """Cylinder k's joint at rod position s [m], velocity v [m/s], acceleration a [m/s²]:
    (q, qd, qdd, moment arm ds/dq) by the chain rule through :func:`inverse_motion`
    (qd = q′·v, qdd = q′·a + q″·v², ds/dq = 1/q′)."""
    qj, g1, g2 = inverse_motion(table, table_ok, cyl, k, cells_per_m, s)
    return qj, g1 * v, g1 * a + g2 * v * v, 1.0 / g1


@njit(cache=True, nogil=True, error_model="numpy")
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
