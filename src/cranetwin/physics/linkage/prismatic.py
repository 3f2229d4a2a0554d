"""Linkage kind "prismatic": a cylinder pinned between a prismatic joint's parent body (pin C)
and its child body (pin R, at R0 + q·e in the parent frame, e the joint axis there).

With d = R0 − C::

    L² = |d|² + 2(d·e)·q + q²,     L·L′ = d·e + q,     L′² + L·L″ = 1

s = L − closed length; inverse q = −d·e + σ·sqrt((d·e)² − |d|² + L²) on the branch σ chosen
when the machine is compiled. Block fields after
:data:`~cranetwin.physics.layout.C_PARAMS`: ``DE`` (d·e) [m], ``D2`` (|d|²) [m²], ``SIGMA`` (at
the revolute kind's σ offset, so that both read the branch from the same field).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
from numba import njit

from cranetwin.model import Cylinder, Joint
from cranetwin.physics.frames import rpy_matrix
from cranetwin.physics.layout import C_CLOSED, C_PARAMS

F64 = npt.NDArray[np.float64]

KIND = 1
DE, D2, SIGMA = C_PARAMS, C_PARAMS + 1, C_PARAMS + 3


def matches(joint: Joint, cyl: Cylinder) -> bool:
    """This kind drives ``joint`` with ``cyl``: a direct cylinder on a prismatic joint."""
    return cyl.linkage is None and joint.kind == "prismatic"


def fill(block: F64, joint: Joint, cyl: Cylinder, base: F64) -> None:
    """Write the kind's fields into ``block`` (``base`` unused: the pins are taken in the
    parent frame here)."""
    r0 = rpy_matrix(joint.origin_rpy_rad)
    d_vec = (np.asarray(joint.origin_m) + r0 @ np.asarray(cyl.rod_pin_m)
             - np.asarray(cyl.base_pin_m))
    e = r0 @ np.asarray(joint.axis, dtype=np.float64)
    block[DE] = float(d_vec @ e)
    block[D2] = float(d_vec @ d_vec)


@njit(cache=True, nogil=True, inline="always")
def derivatives(de, q, ln):  # type: ignore[no-untyped-def]
    """(L′, L″) from L·L′ = d·e + q and L′² + L·L″ = 1."""
    d1 = (de + q) / ln
    return d1, (1.0 - d1 * d1) / ln


@njit(cache=True, nogil=True)
def state(cyl, o, q):  # type: ignore[no-untyped-def]
    """(s, ds/dq, d²s/dq²) of the block at offset o at joint position q [m]."""
    de = cyl[o + DE]
    l2 = cyl[o + D2] + 2.0 * de * q + q * q
    if l2 <= 0.0:
        return math.nan, math.nan, math.nan
    ln = math.sqrt(l2)
    d1, d2 = derivatives(de, q, ln)
    return ln - cyl[o + C_CLOSED], d1, d2


@njit(cache=True, nogil=True)
def inverse(cyl, o, s):  # type: ignore[no-untyped-def]
    """Joint position [m] at rod position s [m] (NaN if none)."""
    ln = s + cyl[o + C_CLOSED]
    de = cyl[o + DE]
    disc = de * de - cyl[o + D2] + ln * ln
    if disc < 0.0 or ln < 0.0:
        return math.nan
    return -de + cyl[o + SIGMA] * math.sqrt(disc)


@njit(cache=True, nogil=True)
def motion(cyl, o, s):  # type: ignore[no-untyped-def]
    """(q, ds/dq, d²s/dq²) at rod position s [m]; NaN where no position gives s."""
    ln = s + cyl[o + C_CLOSED]
    if ln <= 0.0:
        return math.nan, math.nan, math.nan
    q = inverse(cyl, o, s)
    if not math.isfinite(q):
        return math.nan, math.nan, math.nan
    d1, d2 = derivatives(cyl[o + DE], q, ln)
    return q, d1, d2


@njit(cache=True, nogil=True)
def branch(cyl, o, q):  # type: ignore[no-untyped-def]
    """The inverse branch σ = sign(d·e + q) at joint position q."""
    return np.sign(cyl[o + DE] + q)
