"""Linkage kind "revolute": a cylinder pinned directly between a revolute joint's parent body
(pin C) and its child body (pin R).

With u = q − φ the pin distance obeys the triangle (law of cosines) relation::

    L² = K0 − 2·ρ·cos u                       K0 = |R|² + |C|² − 2(a·C)(a·R),
    L·L′ = ρ·sin u                            ρ·(cos φ, sin φ) = (C·R − (a·C)(a·R), C·(a × R))
    L′² + L·L″ = ρ·cos u

(a the joint axis, C and R in the joint frame), s = L − closed length. Inverse:
u = σ·acos((K0 − L²)/(2ρ)) on the branch σ = ±1 chosen when the machine is compiled.
Block fields after :data:`~cranetwin.physics.layout.C_PARAMS`: ``K0`` [m²], ``RHO`` [m²],
``PHI`` [rad], ``SIGMA``.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
from numba import njit

from cranetwin.model import Cylinder, Joint
from cranetwin.physics.layout import C_CENTRE, C_CLOSED, C_PARAMS

F64 = npt.NDArray[np.float64]

KIND = 0
K0, RHO, PHI, SIGMA = C_PARAMS, C_PARAMS + 1, C_PARAMS + 2, C_PARAMS + 3


def matches(joint: Joint, cyl: Cylinder) -> bool:
    """This kind drives ``joint`` with ``cyl``: a direct cylinder on a revolute joint."""
    return cyl.linkage is None and joint.kind == "revolute"


def fill(block: F64, joint: Joint, cyl: Cylinder, base: F64) -> None:
    """Write the kind's fields into ``block`` (base: the base pin C in the joint frame)."""
    a = np.asarray(joint.axis, dtype=np.float64)
    r = np.asarray(cyl.rod_pin_m, dtype=np.float64)
    ac, ar = float(a @ base), float(a @ r)
    block[K0] = float(r @ r + base @ base) - 2 * ac * ar
    p = float(base @ r) - ac * ar
    qq = float(base @ np.cross(a, r))
    block[RHO] = np.hypot(p, qq)
    block[PHI] = np.arctan2(qq, p)


@njit(cache=True, nogil=True, inline="always")
def derivatives(rho, cos_u, sin_u, ln):  # type: ignore[no-untyped-def]
    """(L′, L″) from L·L′ = ρ·sin u and L′² + L·L″ = ρ·cos u."""
    d1 = rho * sin_u / ln
    return d1, (rho * cos_u - d1 * d1) / ln


@njit(cache=True, nogil=True)
def state(cyl, o, q):  # type: ignore[no-untyped-def]
    """(s, ds/dq, d²s/dq²) of the block at offset o at joint angle q [rad]."""
    rho = cyl[o + RHO]
    u = q - cyl[o + PHI]
    l2 = cyl[o + K0] - 2.0 * rho * math.cos(u)
    if l2 <= 0.0:
        return math.nan, math.nan, math.nan
    ln = math.sqrt(l2)
    d1, d2 = derivatives(rho, math.cos(u), math.sin(u), ln)
    return ln - cyl[o + C_CLOSED], d1, d2


@njit(cache=True, nogil=True)
def _wrap(q, centre):  # type: ignore[no-untyped-def]
    return q + 2.0 * math.pi * math.floor((centre - q) / (2.0 * math.pi) + 0.5)


@njit(cache=True, nogil=True)
def motion(cyl, o, s):  # type: ignore[no-untyped-def]
    """Inverse and derivatives at once: (q, ds/dq, d²s/dq²) at rod position s [m]; NaN where
    no angle gives s."""
    ln = s + cyl[o + C_CLOSED]
    rho = cyl[o + RHO]
    c = (cyl[o + K0] - ln * ln) / (2.0 * rho)
    if c > 1.0 or c < -1.0 or ln <= 0.0:
        return math.nan, math.nan, math.nan
    sign = cyl[o + SIGMA]
    q = _wrap(cyl[o + PHI] + sign * math.acos(c), cyl[o + C_CENTRE])
    d1, d2 = derivatives(rho, c, sign * math.sqrt(1.0 - c * c), ln)
    return q, d1, d2


@njit(cache=True, nogil=True)
def inverse(cyl, o, s):  # type: ignore[no-untyped-def]
    """Joint angle [rad] at rod position s [m] (NaN if none)."""
    ln = s + cyl[o + C_CLOSED]
    c = (cyl[o + K0] - ln * ln) / (2.0 * cyl[o + RHO])
    if c > 1.0 or c < -1.0 or ln < 0.0:
        return math.nan
    return _wrap(cyl[o + PHI] + cyl[o + SIGMA] * math.acos(c), cyl[o + C_CENTRE])


@njit(cache=True, nogil=True)
def branch(cyl, o, q):  # type: ignore[no-untyped-def]
    """The inverse branch σ = sign(sin(q − φ)) at joint angle q."""
    return np.sign(math.sin(q - cyl[o + PHI]))
