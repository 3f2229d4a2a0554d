"""Coarse quantisation in the data: recognise the lattice, reconstruct the signal behind it.

A quantised channel reports ``o + k·h`` (offset o, step h, integer k): between level changes it
holds still, and its error, up to ±h/2, is systematic wherever the signal is slow (a 25 bar
staircase on a slowly rising pressure is 25 bar wrong just before each step). Smoothing cannot
remove it: the staircase shows no noise in its higher differences. The data give it away,
though: their values lie on a lattice.

**Detection** (:func:`detect_lattice`). Continuous (noisy) data almost never repeat a value, so
the first test is repetition: at most half as many distinct values as finite samples. The
distinct values, merged where they differ by no more than the float tolerance
``tol = REL_TOL · max|y|``, are then fitted by ``o + k·h`` with h their smallest gap (a signal
that moves between levels visits neighbouring ones) and k = round((level − o)/h); every sample
must lie within ``tol`` of the fitted lattice, h must be at least ``MIN_STEP_TOLS``
tolerances (so that a level lands on the lattice by accident with probability
≤ 2/``MIN_STEP_TOLS``) and the lattice may span no more cells than there are samples. A single
level gives no step.

**Reconstruction** (:func:`reconstruct`). Where the level changes between samples i−1 and i the
signal crossed the boundary between the two cells, (q_{i−1} + q_i)/2, at about t = i − ½: its
value there is known far better than ±h/2. The reconstruction is the piecewise-linear signal
through those crossings that stays in every sample's cell [q − h/2, q + h/2]:

* a level held between crossings in one direction (a passage): linear from crossing to crossing;
* a level entered and left on the same side (a turning point): through the cell centre q at the
  middle of the run;
* a level held longer than 2·``reach`` samples (a rest): from each crossing to the cell centre
  within ``reach`` samples, the centre in between (where the signal rests in the cell is not
  known; the centre halves the worst error);
* at the ends of the data (or of a block): the cell centre at the first and last sample.

The result is clipped to the cells (a jump over several levels between two samples could
otherwise leave one). The value at a sample depends only on the samples within 2·``reach`` of
it, so a block with that much context on each side gives the same values as the whole record
(the stream equals the batch at every seam). Cost: one pass over the run boundaries and one
``np.interp``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from cranetwin.errors import SignalError
from cranetwin.signal.window import DEFAULT_WINDOWS

F64 = npt.NDArray[np.float64]

REL_TOL = 2.0**-22
"""Relative tolerance of a lattice level [share of max|y|]: two ulps of float32, so that values
a logger stored in single precision still lie on their lattice (float64 rounding is 2^-52)."""
MIN_STEP_TOLS = 1000.0
"""A detected step is at least this many tolerances: a continuous value falls within ±tol of a
lattice point by accident with probability 2·tol/h ≤ 0.2 %."""
MIN_SAMPLES = 8
"""Fewer finite samples than this give no verdict (too few to show repetition)."""
_MAX_LEVELS = 2 * (int(2.0 / (MIN_STEP_TOLS * REL_TOL)) + 1)
"""More merged levels than any lattice :func:`detect_lattice` accepts can show: its cells span
at most 2·max|y| / (MIN_STEP_TOLS·tol) + 1, and samples within ±tol of one lattice point
merge into at most two levels."""
REACH = max(DEFAULT_WINDOWS) // 2
"""Default reach of :func:`reconstruct` [samples]: a level held longer than the longest
smoothing window (2·REACH + 1) is taken as a rest; shorter ones as passages or turning points,
which the smoothing windows would span anyway."""
CONTEXT = 2 * REACH
"""Samples of context on each side with which a block's reconstruction (default reach) equals
the whole record's at the block's samples (:func:`reconstruct`)."""


class Lattice(NamedTuple):
    """The lattice ``offset + k·step`` a channel's values lie on.

    Attributes:
        step: h [channel unit], > 0.
        offset: o [channel unit]: a level (the smallest value seen).
        levels: Distinct levels seen.
    """

    step: float
    offset: float
    levels: int


def detect_lattice(y: npt.ArrayLike) -> Lattice | None:
    """The lattice the finite values of ``y`` lie on, or None (module docstring).

    Args:
        y: Samples, shape (n,) [any unit]; NaN and ±inf are ignored.

    Returns:
        The :class:`Lattice`, or None when the values are not on a lattice: too few samples,
        one level only, too little repetition for a lattice, or levels off the lattice.
    """
    a = np.asarray(y, dtype=np.float64)
    if a.ndim != 1:
        raise SignalError(f"lattice detection needs a 1-D array, got shape {a.shape}")
    x = a[np.isfinite(a)]
    if x.shape[0] < MIN_SAMPLES:
        return None
    scale = float(np.max(np.abs(x)))
    tol = REL_TOL * scale
    sub_n = 2 * _MAX_LEVELS
    if x.shape[0] > 2 * sub_n:  # cheap exact rejection of continuous data: no subset of a
        sub = np.sort(x[:: x.shape[0] // sub_n])  # lattice holds more levels than it has
        if np.count_nonzero(np.diff(sub) > tol) >= _MAX_LEVELS:
            return None
    u = np.unique(x)
    levels = u[np.concatenate(([True], np.diff(u) > tol))]
    nl = levels.shape[0]
    if nl < 2 or 2 * nl > x.shape[0]:
        return None
    h0 = float(np.min(np.diff(levels)))
    if not h0 >= MIN_STEP_TOLS * tol:
        return None
    k = np.rint((levels - levels[0]) / h0)
    if k[-1] + 1 > x.shape[0]:
        return None
    # least-squares step and offset over every level (k known): exact lattices refit to h0
    km = float(k.mean())
    dk = k - km
    h = float(dk @ (levels - levels.mean()) / (dk @ dk))
    o = float(levels.mean() - h * km)
    # every sample, not only the merged levels: a dense continuum would merge into one level
    if not np.all(np.abs(x - (o + np.rint((x - o) / h) * h)) <= tol):
        return None
    return Lattice(h, float(levels[0]), int(nl))


FLAT_MIN_SAMPLES = 100
"""Fewer finite samples than this are not called flat by :func:`single_level`."""


def single_level(y: npt.ArrayLike) -> bool:
    """True when at least :data:`FLAT_MIN_SAMPLES` finite values of ``y`` (shape (n,), any
    unit) all lie within ``REL_TOL · max|y|`` of one value: a reading that never changed. It
    shows none of the quantity's variation and no lattice (:func:`detect_lattice` needs two
    levels), so its error is not bounded by anything seen in the data: a stuck sensor, or a
    quantisation step coarser than all the variation."""
    a = np.asarray(y, dtype=np.float64)
    x = a[np.isfinite(a)]
    if x.shape[0] < FLAT_MIN_SAMPLES:
        return False
    lo, hi = float(x.min()), float(x.max())
    return hi - lo <= REL_TOL * max(abs(lo), abs(hi))


def reconstruct(y: F64, step: float, reach: int = REACH) -> F64:
    """The piecewise-linear signal through the level crossings of quantised samples, inside
    every sample's cell (module docstring).

    Args:
        y: Quantised samples, shape (n,) [channel unit]; NaN stays NaN (the finite samples
            are taken as consecutive). A level change is a difference of more than step/2.
        step: Their lattice's step h (:attr:`Lattice.step`) [channel unit], > 0.
        reach: Samples over which a level held longer than 2·reach returns from its crossings
            to the cell centre (≥ 1). The value at a sample depends on the samples within
            2·reach of it.

    Returns:
        Reconstructed samples, shape (n,), each within ±step/2 of its sample.
    """
    if not step > 0:
        raise SignalError(f"step must be > 0, got {step}")
    if reach < 1:
        raise SignalError(f"reach must be >= 1 sample, got {reach}")
    a = np.asarray(y, dtype=np.float64)
    out = a.copy()
    fin = np.isfinite(a)
    x = a[fin]
    m = x.shape[0]
    if m == 0:
        return out
    h = float(step)
    starts = np.flatnonzero(np.concatenate(([True], np.abs(np.diff(x)) > 0.5 * h)))
    ends = np.concatenate((starts[1:] - 1, [m - 1]))
    v = x[starts]  # the runs' cell centres
    nr = starts.shape[0]
    length = ends - starts + 1
    closed_l = np.arange(nr) > 0
    closed_r = np.arange(nr) < nr - 1
    rest = length > 2 * reach
    rise_in = np.zeros(nr)
    rise_in[1:] = np.sign(v[1:] - v[:-1])
    rise_out = np.zeros(nr)
    rise_out[:-1] = np.sign(v[1:] - v[:-1])
    turn = closed_l & closed_r & ~rest & (rise_in * rise_out < 0)
    groups = (
        (starts[1:] - 0.5, 0.5 * (v[:-1] + v[1:])),                    # crossings
        (starts[~closed_l], v[~closed_l]),                             # data start
        (ends[~closed_r], v[~closed_r]),                               # data end
        (starts[closed_l & rest] + reach - 0.5, v[closed_l & rest]),   # rest: to the centre
        (ends[closed_r & rest] - reach + 0.5, v[closed_r & rest]),     # and back out of it
        (0.5 * (starts[turn] + ends[turn]), v[turn]),                  # turning points
    )
    t_a = np.concatenate([g[0] for g in groups]).astype(np.float64)
    v_a = np.concatenate([g[1] for g in groups])
    order = np.argsort(t_a, kind="stable")
    r = np.interp(np.arange(m, dtype=np.float64), t_a[order], v_a[order])
    np.clip(r, x - 0.5 * h, x + 0.5 * h, out=r)
    out[fin] = r
    return out


def reconstruct_columns(rows: F64, steps: Sequence[float]) -> F64:
    """Rows of several channels with every quantised one reconstructed (:func:`reconstruct`,
    default reach): what the replay smooths, and what the model-based force's raw pressures
    are.

    Args:
        rows: Samples, shape (n, c) [channel units].
        steps: Per column its detected step (c,) [channel unit]; 0: not quantised.

    Returns:
        A copy of ``rows`` with column j reconstructed where steps[j] > 0; ``rows`` itself
        when no column is.
    """
    quantised = [j for j, h in enumerate(steps) if h > 0]
    if not quantised:
        return rows
    out = rows.copy()
    for j in quantised:
        out[:, j] = reconstruct(rows[:, j], steps[j])
    return out
