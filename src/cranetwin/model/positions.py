"""Rod positions in the machine description's convention, checked before any replay or import work.

Rod positions must be stroke positions s ∈ [0, stroke] [m]: pin-to-pin lengths or millimetres
fed as strokes would otherwise be clipped to an end of the stroke without a word (every rod at
full stroke, the boom angles constant).
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]

POSITION_TOLERANCE = 0.01
"""Rod positions more than this share of the stroke outside [0, stroke] count as outside."""


class RodProblem(NamedTuple):
    """What is wrong with one cylinder's rod positions: the message and the likely cause."""

    message: str
    likely: Literal["pin_to_pin", "millimetres"] | None


def rod_position_problem(name: str, values_m: F64, stroke_m: float, closed_m: float,
                         min_share: float = 0.5) -> RodProblem | None:
    """Why one cylinder's rod positions cannot be stroke positions, or None.

    More than ``min_share`` of the finite values outside [−tol, stroke + tol] (tol =
    ``POSITION_TOLERANCE`` × stroke) is a convention or unit mix-up, not a few bad samples;
    the message names the likely one (pin-to-pin lengths, millimetres).

    Args:
        name: Channel name (for the message).
        values_m: Rod positions, any shape [m, as given].
        stroke_m: Stroke [m].
        closed_m: Pin-to-pin length at zero stroke [m].
        min_share: Share of values outside the stroke that makes a problem (0 … 1).
    """
    v = values_m[np.isfinite(values_m)]
    if v.size == 0:
        return None
    tol = POSITION_TOLERANCE * stroke_m
    out = (v < -tol) | (v > stroke_m + tol)
    if out.mean() <= min_share:
        return None
    lo, hi = float(v.min()), float(v.max())
    msg = (f"{name}: {int(out.sum())} of {v.size} rod positions lie outside the stroke "
           f"[0, {stroke_m:g}] m (they span {lo:.4g} … {hi:.4g} m)")
    if lo >= closed_m - tol and hi <= closed_m + stroke_m + tol:
        return RodProblem(msg + f": these look like pin-to-pin lengths (closed length "
                          f"{closed_m:g} m, so stroke = length − {closed_m:g} m)", "pin_to_pin")
    if -tol <= lo / 1000 and hi / 1000 <= stroke_m + tol:
        return RodProblem(msg + ": these look like millimetres", "millimetres")
    return RodProblem(msg, None)
