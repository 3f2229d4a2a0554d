"""Linkages between a cylinder and the joint it drives: one module per kind, one dispatch.

Every kind module gives, for the parameters of one cylinder block (``cyl`` array, block offset
``o``; layout in :mod:`cranetwin.physics.layout`):

* ``state(cyl, o, q)`` -> (s, s′, s″): rod position [m] and its first two derivatives with
  respect to the joint position (s′ = ds/dq is the moment arm) [m/rad, m/rad²];
* ``motion(cyl, o, s)`` -> (q, s′, s″): the inverse and the same derivatives at once;
* ``inverse(cyl, o, s)`` -> q;
* ``matches(joint, cyl)`` and ``fill(block, joint, cyl, base)``: which machine parts it
  describes, and its fields of the block (Python, run once per machine).

All three numeric functions return NaN where the geometry cannot assemble. Kinds:
:mod:`.revolute` (a cylinder directly on a revolute joint, law of cosines), :mod:`.prismatic`
(a cylinder pinned to both bodies of a prismatic joint), :mod:`.linear` (a cylinder acting
along a prismatic joint, s = s0 + q: a telescope) and :mod:`.four_bar` (through a four-bar
linkage).

Adding a kind: its module, an entry in :data:`KINDS` and a branch in each of the four
dispatchers below (numba compiles calls, not look-ups), plus its description in the model
schema (``cranetwin.model.schema.Linkage``). ``tests/test_physics_linear.py`` fails for a
kind in :data:`KINDS` that a dispatcher does not reach.
"""

from __future__ import annotations

import math
from types import ModuleType

import numpy as np
import numpy.typing as npt
from numba import njit

from cranetwin.errors import ModelError
from cranetwin.model import Cylinder, Joint
from cranetwin.physics.layout import C_KIND
from cranetwin.physics.linkage import four_bar, linear, prismatic, revolute

F64 = npt.NDArray[np.float64]

KINDS: tuple[ModuleType, ...] = (four_bar, linear, revolute, prismatic)
"""The kinds, tried in this order by :func:`kind_of` (a cylinder that declares its linkage is
claimed by that kind before the direct kinds look at it)."""


def kind_of(joint: Joint, cyl: Cylinder) -> ModuleType:
    """The kind module that describes ``cyl`` driving ``joint``.

    Raises:
        ModelError: no kind matches.
    """
    for kind in KINDS:
        if kind.matches(joint, cyl):
            return kind
    raise ModelError(f"cylinder {cyl.name!r}: no linkage kind drives a {joint.kind} joint so")


@njit(cache=True, nogil=True)
def state(cyl, o, q):  # type: ignore[no-untyped-def]
    """(s, s′, s″) of the cylinder block at offset o at joint position q (module docstring)."""
    kind = int(cyl[o + C_KIND])
    if kind == revolute.KIND:
        return revolute.state(cyl, o, q)
    if kind == prismatic.KIND:
        return prismatic.state(cyl, o, q)
    if kind == four_bar.KIND:
        return four_bar.state(cyl, o, q)
    if kind == linear.KIND:
        return linear.state(cyl, o, q)
    return math.nan, math.nan, math.nan


@njit(cache=True, nogil=True)
def motion(cyl, o, s):  # type: ignore[no-untyped-def]
    """(q, s′, s″) of the cylinder block at offset o at rod position s."""
    kind = int(cyl[o + C_KIND])
    if kind == revolute.KIND:
        return revolute.motion(cyl, o, s)
    if kind == prismatic.KIND:
        return prismatic.motion(cyl, o, s)
    if kind == four_bar.KIND:
        return four_bar.motion(cyl, o, s)
    if kind == linear.KIND:
        return linear.motion(cyl, o, s)
    return math.nan, math.nan, math.nan


@njit(cache=True, nogil=True)
def inverse(cyl, o, s):  # type: ignore[no-untyped-def]
    """Joint position of the cylinder block at offset o at rod position s."""
    kind = int(cyl[o + C_KIND])
    if kind == revolute.KIND:
        return revolute.inverse(cyl, o, s)
    if kind == prismatic.KIND:
        return prismatic.inverse(cyl, o, s)
    if kind == four_bar.KIND:
        return four_bar.inverse(cyl, o, s)
    if kind == linear.KIND:
        return linear.inverse(cyl, o, s)
    return math.nan


@njit(cache=True, nogil=True)
def branch_signs(cyl, o, q):  # type: ignore[no-untyped-def]
    """Signs that identify the inverse branches at joint position q: (σ, σ_E, σ_F) (the
    direct kinds' σ; the four-bar's two circle intersections)."""
    kind = int(cyl[o + C_KIND])
    if kind == revolute.KIND:
        return revolute.branch(cyl, o, q), 1.0, 1.0
    if kind == prismatic.KIND:
        return prismatic.branch(cyl, o, q), 1.0, 1.0
    if kind == linear.KIND:
        return linear.branch(cyl, o, q), 1.0, 1.0
    se, sf = four_bar.branches(cyl, o, q)
    if math.isnan(se):
        return math.nan, math.nan, math.nan
    return 1.0, se, sf


__all__ = ["KINDS", "branch_signs", "four_bar", "inverse", "kind_of", "linear", "motion",
           "prismatic", "revolute", "state"]
