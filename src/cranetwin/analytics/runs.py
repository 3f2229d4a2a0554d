"""Runs of a boolean condition that may span the chunks of a history.

A :class:`RunTracker` is fed consecutive chunks ``(t, mask, values)`` and returns the runs (maximal
stretches where ``mask`` holds) once they are closed, with statistics of ``values`` over the run.
A run still open at the end of a chunk is carried over; runs closer than ``merge_gap_s`` are
joined; runs shorter than ``min_duration_s`` are dropped. :meth:`flush` closes what is open (end
of the record). Splitting a history into chunks does not change the runs found.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]
B = npt.NDArray[np.bool_]


@dataclass
class Run:
    """One run of a condition.

    Attributes:
        t_start: Time of the first sample in the run [s].
        t_end: Time of the last sample in the run [s].
        n: Samples in the run.
        first: Values at the first sample, shape (k,).
        last: Values at the last sample, shape (k,).
        vmax: Maxima over the run, shape (k,).
        vmin: Minima over the run, shape (k,).
        vsum: Sums over the run, shape (k,).
        t_peak: Time of the maximum of column 0 [s].
        at_peak: Values at that time, shape (k,).
    """

    t_start: float
    t_end: float
    n: int
    first: F64
    last: F64
    vmax: F64
    vmin: F64
    vsum: F64
    t_peak: float
    at_peak: F64

    @property
    def duration_s(self) -> float:
        """t_end − t_start [s]."""
        return self.t_end - self.t_start

    @property
    def mean(self) -> F64:
        """Means over the run, shape (k,)."""
        return self.vsum / max(self.n, 1)

    def join(self, other: Run) -> Run:
        """This run followed by ``other`` (bridging any gap between them)."""
        peak_other = other.vmax[0] > self.vmax[0]
        return Run(self.t_start, other.t_end, self.n + other.n, self.first, other.last,
                   np.maximum(self.vmax, other.vmax), np.minimum(self.vmin, other.vmin),
                   self.vsum + other.vsum, other.t_peak if peak_other else self.t_peak,
                   other.at_peak if peak_other else self.at_peak)


@dataclass
class Segments:
    """The raw stretches of a condition in one chunk: maximal runs of the mask, split at data
    gaps, before any joining across chunks, merging or minimum duration. Stored per window, they
    let :meth:`RunTracker.feed_segments` find the runs of any sequence of windows exactly.

    Attributes:
        t_first: Time of the chunk's first sample [s].
        t_last: Time of its last sample [s].
        runs: Stretches in time order.
        first_at_start: The first stretch starts at the chunk's first sample.
        last_at_end: The last stretch ends at the chunk's last sample.
    """

    t_first: float
    t_last: float
    runs: list[Run]
    first_at_start: bool
    last_at_end: bool


def segments(t: F64, mask: B, values: Sequence[F64], max_gap_s: float = 0.0) -> Segments | None:
    """Raw stretches of ``mask`` in one chunk (see :class:`Segments`); None for no samples.

    Args:
        t: Times, shape (n,) [s].
        mask: The condition, shape (n,).
        values: Statistics columns, each shape (n,) (column 0 is the one whose peak is timed).
        max_gap_s: A time step longer than this splits a stretch (0: never).
    """
    n = t.shape[0]
    if n == 0:
        return None
    m = np.asarray(mask, dtype=bool)
    runs: list[Run] = []
    first_at_start = last_at_end = False
    if m.any():
        brk = np.zeros(n + 1, dtype=bool)  # brk[i]: a new stretch starts at sample i
        brk[0] = brk[n] = True
        if max_gap_s > 0 and n > 1:
            brk[1:n] = np.diff(t) > max_gap_s
        prev = np.concatenate([[False], m[:-1]])
        nxt = np.concatenate([m[1:], [False]])
        starts = np.flatnonzero(m & (~prev | brk[:n]))
        ends = np.flatnonzero(m & (~nxt | brk[1:])) + 1  # exclusive
        for s, e in zip(starts.tolist(), ends.tolist(), strict=True):
            seg = np.column_stack([v[s:e] for v in values])
            i_pk = int(np.argmax(seg[:, 0]))
            runs.append(Run(float(t[s]), float(t[e - 1]), e - s, seg[0].copy(), seg[-1].copy(),
                            seg.max(axis=0), seg.min(axis=0), seg.sum(axis=0),
                            float(t[s + i_pk]), seg[i_pk].copy()))
        first_at_start = bool(starts[0] == 0)
        last_at_end = bool(ends[-1] == n)
    return Segments(float(t[0]), float(t[-1]), runs, first_at_start, last_at_end)


def concat_segments(a: Segments | None, b: Segments | None,
                    max_gap_s: float = 0.0) -> Segments | None:
    """The segments of chunk ``a`` followed by chunk ``b`` (as :func:`segments` of the joined
    chunk would give): a stretch ending at a's last sample joins one starting at b's first
    sample unless the step between them is over ``max_gap_s``."""
    if a is None:
        return b
    if b is None:
        return a
    runs = list(a.runs)
    rb = list(b.runs)
    gap = max_gap_s > 0 and b.t_first - a.t_last > max_gap_s
    if runs and rb and a.last_at_end and b.first_at_start and not gap:
        runs[-1] = runs[-1].join(rb.pop(0))
    runs += rb
    first_at_start = bool(a.runs) and a.first_at_start
    last_at_end = bool(b.runs) and b.last_at_end
    if not b.runs and a.runs:
        last_at_end = False
    return Segments(a.t_first, b.t_last, runs, first_at_start, last_at_end)


@dataclass
class RunTracker:
    """Finds runs of a condition across chunks.

    Attributes:
        min_duration_s: Runs shorter than this (t_end − t_start) are dropped [s].
        merge_gap_s: Runs separated by less than this are joined [s] (0: never).
        max_gap_s: A time step longer than this (no data: machine off) ends a run [s]
            (0: never).
    """

    min_duration_s: float = 0.0
    merge_gap_s: float = 0.0
    max_gap_s: float = 0.0
    _open: Run | None = field(default=None, init=False)
    _pending: Run | None = field(default=None, init=False)

    def _emit(self, run: Run, out: list[Run]) -> None:
        if self._pending is not None:
            if run.t_start - self._pending.t_end < self.merge_gap_s:
                self._pending = self._pending.join(run)
                return
            if self._pending.duration_s >= self.min_duration_s:
                out.append(self._pending)
        self._pending = run

    def feed(self, t: F64, mask: B, values: Sequence[F64]) -> list[Run]:
        """Fold the next chunk.

        Args:
            t: Times, shape (n,) [s].
            mask: The condition, shape (n,).
            values: k statistics columns, each shape (n,); column 0 is the one whose peak is
                timed. Only the samples inside runs are read.

        Returns:
            Runs closed (and released past the merge gap) by this chunk.
        """
        return self.feed_segments(segments(t, mask, values, self.max_gap_s))

    def feed_segments(self, seg: Segments | None) -> list[Run]:
        """Fold the raw stretches of the next chunk (:func:`segments`); :meth:`feed` is
        ``feed_segments(segments(...))``, so stored segments of consecutive chunks give the same
        runs as the samples."""
        out: list[Run] = []
        if seg is None:
            return out
        runs = seg.runs
        gap_before = (self._open is not None and self.max_gap_s > 0
                      and seg.t_first - self._open.t_end > self.max_gap_s)
        if self._open is not None and (not runs or not seg.first_at_start or gap_before):
            # the open run ended just before this chunk
            self._emit(self._open, out)
            self._open = None
        last = len(runs) - 1
        for i, run in enumerate(runs):
            if i == 0 and seg.first_at_start and self._open is not None:
                run = self._open.join(run)
                self._open = None
            if i == last and seg.last_at_end:
                self._open = run
            else:
                self._emit(run, out)
        if self._pending is not None and self._open is None and \
                seg.t_last - self._pending.t_end >= self.merge_gap_s:
            if self._pending.duration_s >= self.min_duration_s:
                out.append(self._pending)
            self._pending = None
        return out

    def flush(self) -> list[Run]:
        """Close and return whatever is open or pending (end of the record), without mutating."""
        out: list[Run] = []
        pending, opened = self._pending, self._open
        if opened is not None:
            if pending is not None and opened.t_start - pending.t_end < self.merge_gap_s:
                pending = pending.join(opened)
            else:
                if pending is not None and pending.duration_s >= self.min_duration_s:
                    out.append(pending)
                pending = opened
        if pending is not None and pending.duration_s >= self.min_duration_s:
            out.append(pending)
        return out
