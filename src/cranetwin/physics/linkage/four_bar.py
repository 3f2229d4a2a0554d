"""Linkage kind "four-bar": a cylinder that turns a revolute joint through a four-bar linkage
(e.g. an excavator's bucket), in 2-D coordinates of the plane normal to the joint axis (joint
frame; the axis points out of the plane).

Points: C the cylinder's base pin, D the pivot of the rocker link on the parent body, E the rod
end (rocker end, where the coupler link attaches), F the coupler pin on the child body (F0 at
q = 0, rotated by q about the joint). At joint angle q, E is an intersection of the circles
(D, |DE|) and (F, |EF|), and the pin distance is L = |E − C|, s = L − closed length.
Differentiating the two circle conditions (F′ = (−F_y, F_x), F″ = −F)::

    (E − D)·E′ = 0             (E − F)·(E′ − F′) = 0
    (E − D)·E″ = −|E′|²        (E − F)·(E″ − F″) = −|E′ − F′|²
    L·L′ = (E − C)·E′          L′² + L·L″ = |E′|² + (E − C)·E″

Inverse: E on the circles (C, L) and (D, |DE|), then F on (O, |F0|) and (E, |EF|), q the angle
from F0 to F. Circle intersections take the branches stored in the block. Block fields after
:data:`~cranetwin.physics.layout.C_PARAMS` (2-D points as x, y): ``CX``, ``DX``, ``F0X``,
``DE_LEN``, ``EF_LEN``, ``BRANCH_E`` (forward), ``SIGMA_E``, ``SIGMA_F`` (inverse).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
from numba import njit

from cranetwin.errors import ModelError
from cranetwin.model import Cylinder, FourBar, Joint
from cranetwin.physics.frames import joint_frame_point, plane_basis
from cranetwin.physics.layout import C_CENTRE, C_CLOSED

F64 = npt.NDArray[np.float64]

KIND = 2
CX, DX, F0X, DE_LEN, EF_LEN, BRANCH_E, SIGMA_E, SIGMA_F = 9, 11, 13, 15, 16, 17, 18, 19


def matches(joint: Joint, cyl: Cylinder) -> bool:
    """This kind drives ``joint`` with ``cyl``: a cylinder with a four-bar linkage (revolute
    joint)."""
    return isinstance(cyl.linkage, FourBar)


def fill(block: F64, joint: Joint, cyl: Cylinder, base: F64) -> None:
    """Write the kind's fields into ``block`` (base: the base pin C in the joint frame).

    Raises:
        ModelError: the joint is not revolute.
    """
    if joint.kind != "revolute":
        raise ModelError(f"cylinder {cyl.name!r}: a four-bar linkage needs a revolute joint")
    lk = cyl.linkage
    assert isinstance(lk, FourBar)
    e1, e2 = plane_basis(np.asarray(joint.axis, dtype=np.float64))
    d = joint_frame_point(joint, lk.pivot_m)
    f = np.asarray(lk.coupler_pin_m, dtype=np.float64)  # child frame = joint frame at q = 0
    block[CX:CX + 2] = (base @ e1, base @ e2)
    block[DX:DX + 2] = (d @ e1, d @ e2)
    block[F0X:F0X + 2] = (f @ e1, f @ e2)
    block[DE_LEN] = lk.pivot_link_m
    block[EF_LEN] = lk.coupler_link_m
    block[BRANCH_E] = lk.branch


@njit(cache=True, nogil=True)
def circle_intersection(x1, y1, r1, x2, y2, r2, branch):  # type: ignore[no-untyped-def]
    """Intersection of circles (x1, y1, r1) and (x2, y2, r2); ``branch`` +1 puts the point P on
    the side where cross(c2 − c1, P − c1) > 0. Returns (x, y, ok)."""
    dx = x2 - x1
    dy = y2 - y1
    d = math.sqrt(dx * dx + dy * dy)
    if d == 0.0:
        return math.nan, math.nan, False
    a = (r1 * r1 - r2 * r2 + d * d) / (2.0 * d)
    h2 = r1 * r1 - a * a
    if h2 < 0.0:
        return math.nan, math.nan, False
    h = math.sqrt(h2)
    ux = dx / d
    uy = dy / d
    return x1 + a * ux - branch * h * uy, y1 + a * uy + branch * h * ux, True


@njit(cache=True, nogil=True)
def points(cyl, o, q):  # type: ignore[no-untyped-def]
    """Rod end E and coupler pin F at joint angle q: (Ex, Ey, Fx, Fy, ok); ok False when the
    linkage cannot assemble."""
    c = math.cos(q)
    s = math.sin(q)
    fx = c * cyl[o + F0X] - s * cyl[o + F0X + 1]
    fy = s * cyl[o + F0X] + c * cyl[o + F0X + 1]
    ex, ey, ok = circle_intersection(cyl[o + DX], cyl[o + DX + 1], cyl[o + DE_LEN], fx, fy,
                                     cyl[o + EF_LEN], cyl[o + BRANCH_E])
    return ex, ey, fx, fy, ok


@njit(cache=True, nogil=True)
def derivatives(cyl, o, ex, ey, fx, fy):  # type: ignore[no-untyped-def]
    """(L′, L″) at the assembled points E, F (module docstring); NaN at a dead centre of the
    rocker and coupler (E − D parallel to E − F)."""
    r1x = ex - cyl[o + DX]
    r1y = ey - cyl[o + DX + 1]
    r2x = ex - fx
    r2y = ey - fy
    det = r1x * r2y - r1y * r2x
    if det == 0.0:
        return math.nan, math.nan
    lx = ex - cyl[o + CX]
    ly = ey - cyl[o + CX + 1]
    ln = math.sqrt(lx * lx + ly * ly)
    fdx = -fy  # F′
    fdy = fx
    rhs = r2x * fdx + r2y * fdy
    dex = -r1y * rhs / det  # E′
    dey = r1x * rhs / det
    b1 = -(dex * dex + dey * dey)
    gx = dex - fdx
    gy = dey - fdy
    b2 = -(r2x * fx + r2y * fy) - (gx * gx + gy * gy)
    ddx = (b1 * r2y - r1y * b2) / det  # E″
    ddy = (r1x * b2 - r2x * b1) / det
    d1 = (lx * dex + ly * dey) / ln
    return d1, ((dex * dex + dey * dey) + (lx * ddx + ly * ddy) - d1 * d1) / ln


@njit(cache=True, nogil=True)
def state(cyl, o, q):  # type: ignore[no-untyped-def]
    """(s, ds/dq, d²s/dq²) of the block at offset o at joint angle q [rad]."""
    ex, ey, fx, fy, ok = points(cyl, o, q)
    if not ok:
        return math.nan, math.nan, math.nan
    lx = ex - cyl[o + CX]
    ly = ey - cyl[o + CX + 1]
    ln = math.sqrt(lx * lx + ly * ly)
    d1, d2 = derivatives(cyl, o, ex, ey, fx, fy)
    return ln - cyl[o + C_CLOSED], d1, d2


@njit(cache=True, nogil=True)
def _wrap(q, centre):  # type: ignore[no-untyped-def]
    return q + 2.0 * math.pi * math.floor((centre - q) / (2.0 * math.pi) + 0.5)


@njit(cache=True, nogil=True)
def _inverse_points(cyl, o, ln):  # type: ignore[no-untyped-def]
    """E and F for pin distance ln: (Ex, Ey, Fx, Fy, ok)."""
    ex, ey, ok = circle_intersection(cyl[o + CX], cyl[o + CX + 1], ln, cyl[o + DX],
                                     cyl[o + DX + 1], cyl[o + DE_LEN], cyl[o + SIGMA_E])
    if not ok:
        return math.nan, math.nan, math.nan, math.nan, False
    f0x = cyl[o + F0X]
    f0y = cyl[o + F0X + 1]
    rf = math.sqrt(f0x * f0x + f0y * f0y)
    fx, fy, ok = circle_intersection(0.0, 0.0, rf, ex, ey, cyl[o + EF_LEN], cyl[o + SIGMA_F])
    return ex, ey, fx, fy, ok


@njit(cache=True, nogil=True)
def inverse(cyl, o, s):  # type: ignore[no-untyped-def]
    """Joint angle [rad] at rod position s [m] (NaN if none)."""
    ex, ey, fx, fy, ok = _inverse_points(cyl, o, s + cyl[o + C_CLOSED])
    if not ok:
        return math.nan
    f0x = cyl[o + F0X]
    f0y = cyl[o + F0X + 1]
    return _wrap(math.atan2(fy, fx) - math.atan2(f0y, f0x), cyl[o + C_CENTRE])


@njit(cache=True, nogil=True)
def motion(cyl, o, s):  # type: ignore[no-untyped-def]
    """(q, ds/dq, d²s/dq²) at rod position s [m], the derivatives at the E and F the inverse
    found; NaN where no angle gives s."""
    ln = s + cyl[o + C_CLOSED]
    ex, ey, fx, fy, ok = _inverse_points(cyl, o, ln)
    if not ok or ln <= 0.0:
        return math.nan, math.nan, math.nan
    f0x = cyl[o + F0X]
    f0y = cyl[o + F0X + 1]
    # angle from F0 to F: one atan2 of (F0 × F, F0 · F)
    q = _wrap(math.atan2(f0x * fy - f0y * fx, f0x * fx + f0y * fy), cyl[o + C_CENTRE])
    d1, d2 = derivatives(cyl, o, ex, ey, fx, fy)
    return q, d1, d2


@njit(cache=True, nogil=True)
def branches(cyl, o, q):  # type: ignore[no-untyped-def]
    """Inverse branches (σ_E, σ_F) at joint angle q: side of E from the line C→D and of F
    from the line O→E (NaN where the linkage does not assemble)."""
    ex, ey, fx, fy, ok = points(cyl, o, q)
    if not ok:
        return math.nan, math.nan
    cx = cyl[o + CX]
    cy = cyl[o + CX + 1]
    dx = cyl[o + DX]
    dy = cyl[o + DX + 1]
    se = np.sign((dx - cx) * (ey - cy) - (dy - cy) * (ex - cx))
    return se, np.sign(ex * fy - ey * fx)
