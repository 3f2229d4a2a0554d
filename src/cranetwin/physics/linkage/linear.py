"""Linkage kind "linear": a cylinder acting directly along a prismatic joint (a telescope, a
directly acting linear actuator), whose rod position is the joint position plus an offset::

    s = s0 + q,     s′ = ds/dq = 1,     s″ = 0,     inverse q = s − s0

(s0 = ``LinearActuator.s0_m``, the rod position at q = 0 [m]). No pin geometry enters: the
cylinder's force acts along the joint axis, so the joint force equals the cylinder force. The
cylinder's pins only draw it. Block field after :data:`~cranetwin.physics.layout.C_PARAMS`:
``S0`` [m].
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
from numba import njit

from cranetwin.errors import ModelError
from cranetwin.model import Cylinder, Joint, LinearActuator
from cranetwin.physics.layout import C_PARAMS

F64 = npt.NDArray[np.float64]

KIND = 3
S0 = C_PARAMS


def matches(joint: Joint, cyl: Cylinder) -> bool:
    """This kind drives ``joint`` with ``cyl``: a cylinder declared ``linkage.kind = "linear"``."""
    return isinstance(cyl.linkage, LinearActuator)


def fill(block: F64, joint: Joint, cyl: Cylinder, base: F64) -> None:
    """Write the kind's field into ``block`` (``base`` unused).

    Raises:
        ModelError: the joint is not prismatic.
    """
    if joint.kind != "prismatic":
        raise ModelError(f"cylinder {cyl.name!r}: a linear actuator needs a prismatic joint, "
                         f"joint {joint.name!r} is {joint.kind}")
    lk = cyl.linkage
    assert isinstance(lk, LinearActuator)
    block[S0] = lk.s0_m


@njit(cache=True, nogil=True)
def state(cyl, o, q):  # type: ignore[no-untyped-def]
    """(s, ds/dq, d²s/dq²) of the block at offset o at joint position q [m]."""
    return cyl[o + S0] + q, 1.0, 0.0


@njit(cache=True, nogil=True)
def inverse(cyl, o, s):  # type: ignore[no-untyped-def]
    """Joint position [m] at rod position s [m] (NaN for a NaN s)."""
    if math.isnan(s):
        return math.nan
    return s - cyl[o + S0]


@njit(cache=True, nogil=True)
def motion(cyl, o, s):  # type: ignore[no-untyped-def]
    """(q, ds/dq, d²s/dq²) at rod position s [m]."""
    if math.isnan(s):
        return math.nan, math.nan, math.nan
    return s - cyl[o + S0], 1.0, 0.0


@njit(cache=True, nogil=True)
def branch(cyl, o, q):  # type: ignore[no-untyped-def]
    """One branch: the inverse is unique."""
    return 1.0
