"""From raw chunks to checked, quantised :class:`~cranetwin.samples.SampleBlock` s.

Per chunk: time → ns since the epoch; values → the channel's unit (and pin-to-pin length →
stroke); rows refused with row, column and reason (unparseable, time not increasing, value
outside the channel's range — never clipped); quantisation to each channel's resolution
(:func:`cranetwin.codec.quantise`); runs of regularly spaced samples cut into blocks.

Runs: consecutive accepted samples whose spacing stays within ``period · (1 ± jitter)`` form
one run; a gap or an irregular spacing starts the next. A run is cut into blocks of at most
``block_samples``; each block's ``t0_ns`` is its first sample's time and its ``period_ns`` the
nominal period (or, where the clock drifts beyond the jitter over the block, the block's mean
spacing). Block identity is deterministic: ``seq`` counts blocks in file order and ``epoch``
is a hash of the file's bytes, the mapping and the machine, so importing the same file twice
stores it once.
"""

from __future__ import annotations

import bisect
import hashlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from cranetwin.codec import QuantiseError, dequantise, quantise
from cranetwin.importer.mapping import ChannelMap, ImportFileError, Mapping
from cranetwin.importer.readers import Chunk, Refusal
from cranetwin.model import Machine
from cranetwin.model.positions import rod_position_problem
from cranetwin.samples import SampleBlock

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
B = npt.NDArray[np.bool_]

BLOCK_SAMPLES = 6000
MAX_BLOCK_SPAN_NS = 6 * 3600 * 10**9  # storage's limit per block
KEEP_REFUSALS = 50
"""Share of the stroke a rod position may lie outside [0, stroke] before it is refused."""


def file_epoch(path: Path, mapping: Mapping, machine_id: str, block_samples: int) -> int:
    """The import's sender epoch: a hash of the file's bytes, the mapping and the machine id
    (1 … 2**63 − 1), so the same import always yields the same block identities."""
    h = hashlib.sha256()
    with path.open("rb") as fh:
        while chunk := fh.read(1 << 22):
            h.update(chunk)
    h.update(mapping.identity())
    h.update(f"\0{machine_id}\0{block_samples}".encode())
    return int.from_bytes(h.digest()[:8], "big") & (2**63 - 1) or 1


@dataclass
class ImportReport:
    """What an import read, accepted and refused.

    Attributes:
        rows_read: Data rows in the file.
        rows_accepted: Rows that became samples.
        refused: Refused rows counted per (column, kind of reason).
        first_refusals: The first refusals in file order (at most 50), each with row and column.
        runs: Regular runs (a gap or irregular spacing starts a new one).
        blocks: Blocks made.
        channels: Channels imported, machine order.
        absent: Optional channels the file does not have.
        period_ns: Nominal sample period [ns].
        max_time_shift_ns: Largest distance of a sample's time from its block's grid [ns].
        t_first_ns: First accepted sample time [ns since the epoch], or None.
        t_last_ns: Last accepted sample time [ns], or None.
        payload_rows: Rows with a known payload accepted (the mapping's ``[payload]`` column).
        payload_refused: Payload values refused (negative or above the largest accepted; the
            rows' samples are kept, the payload is not known there).
        payload_zeroed: Payload values below zero within the tolerance, read as 0 kg.
    """

    rows_read: int = 0
    rows_accepted: int = 0
    refused: Counter[tuple[str, str]] = field(default_factory=Counter)
    first_refusals: list[Refusal] = field(default_factory=list)
    runs: int = 0
    blocks: int = 0
    channels: tuple[str, ...] = ()
    absent: tuple[str, ...] = ()
    period_ns: int = 0
    max_time_shift_ns: int = 0
    t_first_ns: int | None = None
    t_last_ns: int | None = None
    payload_rows: int = 0
    payload_refused: int = 0
    payload_zeroed: int = 0

    @property
    def rows_refused(self) -> int:
        return self.rows_read - self.rows_accepted

    def refuse(self, refusals: list[Refusal], kind: str) -> None:
        for r in refusals:
            self.refused[(r.column, kind)] += 1
            if len(self.first_refusals) < KEEP_REFUSALS:
                self.first_refusals.append(r)

    def summary(self) -> str:
        """Several lines: counts, then the refusals by column and kind, then the first ones."""
        out = [f"{self.rows_read} rows read, {self.rows_accepted} accepted, "
               f"{self.rows_refused} refused; {self.runs} regular run(s) in {self.blocks} "
               f"block(s), period {self.period_ns / 1e6:g} ms"]
        if self.absent:
            out.append(f"optional channel(s) not in the file: {', '.join(self.absent)}")
        if self.payload_rows or self.payload_refused:
            out.append(f"known payload: {self.payload_rows} row(s) accepted, "
                       f"{self.payload_refused} value(s) refused (not known there)"
                       + (f", {self.payload_zeroed} below zero within the tolerance read as "
                          "0 kg" if self.payload_zeroed else ""))
        for (col, kind), k in sorted(self.refused.items()):
            out.append(f"  refused {k} row(s): column {col!r}: {kind}")
        if self.first_refusals:
            out.append("first refused rows:")
            out += [f"  {r}" for r in sorted(self.first_refusals, key=lambda r: r.row)[:20]]
        return "\n".join(out)


def raw_time_ns(raw: npt.NDArray[Any], mapping: Mapping, start_s: float | None,
             ) -> tuple[I64, B]:
    """Raw time column → int64 ns since the epoch, and a mask of unusable entries."""
    fmt = mapping.time_format
    if raw.dtype.kind == "M":  # typed timestamps (Parquet, datetime64 columns): UTC
        ts = raw.astype("datetime64[ns]")
        return ts.astype(np.int64), np.isnat(ts)
    if raw.dtype.kind == "i" and fmt in ("epoch_ns", "iso8601"):
        return raw.astype(np.int64), np.zeros(raw.shape[0], dtype=bool)
    if fmt == "iso8601":
        return _iso_ns(raw)
    x = raw.astype(np.float64)
    scale = {"epoch_s": 1e9, "epoch_ms": 1e6, "epoch_us": 1e3, "epoch_ns": 1.0,
             "relative_s": 1e9}[fmt]
    ok = np.isfinite(x)
    base = 0
    if fmt == "relative_s":
        if start_s is None:
            raise ImportFileError("relative time needs a start time (time.start)")
        base = round(start_s * 1e9)
    if fmt in ("epoch_s", "relative_s"):  # split whole seconds off: exact to the ns
        whole = np.floor(np.where(ok, x, 0.0))
        t = whole.astype(np.int64) * 10**9 + np.rint((np.where(ok, x, 0.0) - whole) * 1e9
                                                    ).astype(np.int64)
    else:
        t = np.rint(np.where(ok, x, 0.0) * scale).astype(np.int64)
    return t + base, ~ok


def _iso_ns(raw: npt.NDArray[Any]) -> tuple[I64, B]:
    s = np.char.strip(raw.astype(str))
    n = s.shape[0]
    bad = np.zeros(n, dtype=bool)
    if n == 0:
        return np.zeros(0, dtype=np.int64), bad
    for utc in ("Z", "+00:00", "+0000"):  # numpy parses naive times (as UTC) only
        s = np.where(np.char.endswith(s, utc), np.char.replace(s, utc, ""), s)
    zoned = np.char.find(np.char.partition(s, "T")[:, 2], "+") >= 0
    zoned |= np.char.count(np.char.partition(s, "T")[:, 2], "-") > 0
    if not zoned.any():
        try:
            return s.astype("datetime64[ns]").astype(np.int64), bad
        except ValueError:
            pass
    import datetime as dt

    out = np.zeros(n, dtype=np.int64)
    for i, text in enumerate(s.tolist()):
        try:
            d = dt.datetime.fromisoformat(text)
        except ValueError:
            bad[i] = True
            continue
        if d.tzinfo is None:
            d = d.replace(tzinfo=dt.UTC)
        delta = d - dt.datetime(1970, 1, 1, tzinfo=dt.UTC)
        out[i] = (delta.days * 86400 + delta.seconds) * 10**9 + delta.microseconds * 1000
    return out, bad


def estimate_period_ns(t: I64, jitter: float) -> int:
    """Nominal sample period of times ``t`` [ns]: the mean of the spacings within ``jitter`` of
    the median spacing (float epoch seconds carry ≈ 0.24 µs steps, so one spacing is not
    exact), rounded to a whole µs when it is within 10 ppm of one (loggers count µs)."""
    d = np.diff(t)
    if d.size == 0:
        return 0
    med = float(np.median(d))
    regular = d[np.abs(d - med) <= jitter * med]
    p = float(regular.mean()) if regular.size else med
    us = round(p / 1000.0) * 1000.0
    return int(us) if us > 0 and abs(p - us) <= 1e-5 * p else round(p)


def position_problem(name: str, values: F64, stroke_m: float, closed_m: float,
                     unit_factor_m: float) -> str | None:
    """Why the rod positions of one cylinder cannot be stroke positions, or None: the twin's
    check (:func:`cranetwin.model.positions.rod_position_problem`, more than half outside the
    stroke) with what to declare in the mapping.

    Args:
        name: Channel name (for the message).
        values: Rod positions as given, in the channel's unit.
        stroke_m: Stroke [m]; closed_m: pin-to-pin length at zero stroke [m].
        unit_factor_m: Metres per channel unit.
    """
    problem = rod_position_problem(name, values * unit_factor_m, stroke_m, closed_m)
    if problem is None:
        return None
    if problem.likely == "pin_to_pin":
        return problem.message + (f"; declare convention = \"pin_to_pin\" (with offset = the "
                                  f"length at zero stroke) for {name} in the mapping")
    if problem.likely == "millimetres":
        return problem.message + "; declare unit = \"mm\" in the mapping"
    return problem.message + ("; check the unit, the convention (stroke or pin-to-pin) and the "
                              "offset in the mapping")


class _OpenRows:
    """The quantised rows of the open run, kept as the chunks appended them: a block's rows are
    a view of one chunk's arrays, or (a block across two chunks) a copy of that block only,
    never of the whole chunk."""

    def __init__(self) -> None:
        self._parts: list[tuple[I64, B]] = []  # (steps, missing), shape (m, c) each
        self._first: list[int] = []  # row index of each part's first row

    def append(self, k: I64, miss: B) -> None:
        """Add rows after the last; k, miss: shape (m, c)."""
        if k.shape[0]:
            last = self._first[-1] + self._parts[-1][0].shape[0] if self._parts else 0
            self._parts.append((k, miss))
            self._first.append(last)

    def rows(self, i: int, j: int) -> tuple[I64, B]:
        """Rows [i, j) (0 ≤ i < j ≤ rows held): steps and missing, shape (j − i, c)."""
        p = bisect.bisect_right(self._first, i) - 1
        k, miss = self._parts[p]
        a = i - self._first[p]
        if j - self._first[p] <= k.shape[0]:
            return k[a:j - self._first[p]], miss[a:j - self._first[p]]
        ks, ms = [k[a:]], [miss[a:]]
        while self._first[p] + self._parts[p][0].shape[0] < j:
            p += 1
            k, miss = self._parts[p]
            ks.append(k[:j - self._first[p]])
            ms.append(miss[:j - self._first[p]])
        return np.concatenate(ks), np.concatenate(ms)

    def drop(self, i: int) -> None:
        """Forget rows before i; row i becomes row 0."""
        parts, first = self._parts, self._first
        self._parts, self._first = [], []
        for (k, miss), f in zip(parts, first, strict=True):
            if f + k.shape[0] > i:
                a = max(0, i - f)
                self._parts.append((k[a:], miss[a:]))
                self._first.append(f + a - i)


class Pipeline:
    """Turns chunks into blocks for one machine (see the module docstring).

    Args:
        machine: The machine description.
        mapping: The file's mapping (resolved against ``machine``).
        machine_id: Storage id the blocks carry.
        epoch: The import's epoch (:func:`file_epoch`).
        present: Channel names of the mapping that the file has (optional ones may lack).
        start_s: Epoch time of relative time 0 (``relative_s`` files) [s].
        block_samples: Most samples per block.
    """

    def __init__(self, machine: Machine, mapping: Mapping, machine_id: str, epoch: int,
                 present: list[ChannelMap], start_s: float | None = None,
                 block_samples: int = BLOCK_SAMPLES) -> None:
        self.machine = machine
        self.mapping = mapping
        self.machine_id = machine_id
        self.epoch = epoch
        self.maps = present
        self.start_s = start_s if start_s is not None else mapping.start_s
        self.block_samples = block_samples
        chans = [machine.channel(m.channel) for m in present]
        self.names = tuple(m.channel for m in present)
        self.res = np.array([c.resolution for c in chans])
        # a channel whose sensor range is unknown (no min/max) has no range check
        tol = mapping.range_tolerance * np.array([c.full_range or 0.0 for c in chans]) + self.res
        self.lo = np.array([-np.inf if c.min is None else c.min for c in chans]) - tol
        self.hi = np.array([np.inf if c.max is None else c.max for c in chans]) + tol
        self.scale = np.array([m.scale for m in present])
        self.shift = np.array([m.shift for m in present])
        self.report = ImportReport(channels=self.names)
        self.period_ns = 0 if mapping.period_s is None else round(mapping.period_s * 1e9)
        self._last_t: int | None = None
        self._seq = 0
        self._checked = False
        # the open run: samples not yet cut into a block
        self._t = np.zeros(0, dtype=np.int64)
        self._open = _OpenRows()
        self._positions: list[tuple[int, float, float, float]] = []
        cyl = {c.name: c for c in machine.cylinders}
        for j, c in enumerate(chans):
            if c.quantity == "position" and c.source in cyl:
                from cranetwin.importer.mapping import unit_factor

                self._positions.append((j, cyl[c.source].stroke_m, cyl[c.source].closed_length_m,
                                        unit_factor(c.unit, "m", c.name)))

    # -- chunks -------------------------------------------------------------------------------
    def feed(self, chunk: Chunk) -> list[SampleBlock]:
        """Check and convert one chunk; the blocks completed by it."""
        rep = self.report
        n = chunk.n
        rep.rows_read += n
        rep.refuse(chunk.refusals, "not parseable")
        bad = chunk.bad.copy()
        rows = np.arange(chunk.first_row, chunk.first_row + n)
        lines = chunk.lines

        def refusals(mask: B, column: str, why: Any) -> list[Refusal]:
            idx = np.flatnonzero(mask)
            return [Refusal(int(rows[i]), column, why(i),
                            None if lines is None else int(lines[i])) for i in idx]

        t, tbad = raw_time_ns(chunk.time, self.mapping, self.start_s)
        tbad &= ~bad
        if tbad.any():
            rep.refuse(refusals(tbad, self._time_name(), lambda i: f"{chunk.time[i]!r} is not a "
                                f"time ({self.mapping.time_format})"), "not a time")
            bad |= tbad
        v = np.empty((n, len(self.maps)))
        for j, m in enumerate(self.maps):
            np.multiply(chunk.columns[m.column], self.scale[j], out=v[:, j])
        if self.shift.any():  # (adding 0 changes no value's step)
            v += self.shift
        if not self._checked:
            self._check_conventions(v[~bad])
        if not self._within_range(chunk):
            with np.errstate(invalid="ignore"):
                out = (v < self.lo) | (v > self.hi)
            out[bad] = False
        else:
            out = np.zeros(0, dtype=bool)
        if out.any():
            for j, m in enumerate(self.maps):
                if out[:, j].any():
                    ch = self.machine.channel(m.channel)
                    raw = chunk.columns[m.column]
                    kind = (f"outside the channel's range [{ch.min:g}, {ch.max:g}] {ch.unit} "
                            f"({m.channel})")
                    rep.refuse(refusals(out[:, j], m.column, lambda i, raw=raw, j=j, kind=kind:
                                        f"{raw[i]:g} {self.maps[j].unit} is {kind}"), kind)
            bad |= out.any(axis=1)
        # time strictly increasing over the accepted rows (across chunks)
        good = np.flatnonzero(~bad)
        tg = t[good]
        if tg.size:
            prev = np.maximum.accumulate(np.concatenate(
                ([self._last_t if self._last_t is not None else np.iinfo(np.int64).min],
                 tg[:-1])))
            back = tg <= prev
            if back.any():
                mask = np.zeros(n, dtype=bool)
                mask[good[back]] = True
                rep.refuse(refusals(mask, self._time_name(),
                                    lambda i: "time not after the previous accepted row's"),
                           "time not after the previous row's")
                bad |= mask
                good = good[~back]
                tg = tg[~back]
        if tg.size == 0:
            return []
        self._last_t = int(tg[-1])
        try:  # every row accepted (the usual case): no copy of the chunk
            k, miss = quantise(v if good.size == n else v[good], self.res)
        except QuantiseError as exc:
            raise ImportFileError(f"values cannot be quantised: {exc}") from exc
        rep.rows_accepted += int(tg.size)
        if rep.t_first_ns is None:
            rep.t_first_ns = int(tg[0])
        rep.t_last_ns = int(tg[-1])
        if self.period_ns == 0:
            if tg.size < 2:
                self._append(tg, k, miss)
                return []
            self.period_ns = estimate_period_ns(np.concatenate([self._t, tg]),
                                                self.mapping.jitter)
            if self.period_ns <= 0:
                raise ImportFileError("cannot tell the sample period from the times; give "
                                      "time.period_s in the mapping")
        self._append(tg, k, miss)
        return self._cut(final=False)

    def finish(self) -> list[SampleBlock]:
        """The blocks of the last open run."""
        if self.period_ns == 0 and self._t.size:
            self.period_ns = 10**9 if self.mapping.period_s is None else self.period_ns
        out = self._cut(final=True)
        self.report.period_ns = self.period_ns
        return out

    # -- helpers ------------------------------------------------------------------------------
    def _time_name(self) -> str:
        return self.mapping.time_column or "(time)"

    def _within_range(self, chunk: Chunk) -> bool:
        """True when every value of ``chunk`` lies within its channel's accepted range (NaN
        aside), decided from each raw column's extremes without a pass over the converted
        values: ``x · scale + shift`` is monotonic in floating point too, so the extremes map
        to the converted extremes exactly. False: check value by value."""
        for j, m in enumerate(self.maps):
            raw = chunk.columns[m.column]
            if raw.size == 0:
                continue
            ext = np.array([np.fmin.reduce(raw), np.fmax.reduce(raw)]) * self.scale[j]
            ext += self.shift[j]
            with np.errstate(invalid="ignore"):
                if (ext < self.lo[j]).any() or (ext > self.hi[j]).any():
                    return False
        return True

    def _check_conventions(self, v: F64) -> None:
        self._checked = True
        for j, stroke, closed, f_m in self._positions:
            msg = position_problem(self.names[j], v[:, j], stroke, closed, f_m)
            if msg is not None:
                raise ImportFileError(msg)

    def _append(self, t: I64, k: I64, miss: B) -> None:
        self._t = np.concatenate([self._t, t])
        self._open.append(k, miss)

    def _cut(self, final: bool) -> list[SampleBlock]:
        t = self._t
        if t.size == 0:
            return []
        p = self.period_ns
        jit = self.mapping.jitter * p
        d = np.diff(t)
        brk = np.flatnonzero((d < p - jit) | (d > p + jit)) + 1  # run starts
        starts = np.concatenate(([0], brk))
        ends = np.concatenate((brk, [t.size]))
        self.report.runs += int(brk.size)
        max_n = max(1, min(self.block_samples, MAX_BLOCK_SPAN_NS // max(p, 1)))
        blocks: list[SampleBlock] = []
        keep_from = t.size
        for r, (a, b) in enumerate(zip(starts.tolist(), ends.tolist(), strict=True)):
            last_run = r == starts.size - 1
            for i in range(a, b, max_n):
                j = min(b, i + max_n)
                if last_run and not final and j == b:  # open: may continue in the next chunk
                    keep_from = i
                    break
                blocks.append(self._block(i, j))
        if final:
            self.report.runs += 1
        self._t = self._t[keep_from:]
        self._open.drop(keep_from)
        return blocks

    def _block(self, i: int, j: int) -> SampleBlock:
        t = self._t[i:j]
        n = j - i
        p = self.period_ns
        if n >= 2 and abs(int(t[-1]) - (int(t[0]) + (n - 1) * p)) > self.mapping.jitter * p:
            p = round((int(t[-1]) - int(t[0])) / (n - 1))  # a drifting clock: its mean spacing
        grid = int(t[0]) + np.arange(n, dtype=np.int64) * p
        shift = int(np.abs(t - grid).max())
        rep = self.report
        rep.max_time_shift_ns = max(rep.max_time_shift_ns, shift)
        rep.blocks += 1
        k, miss = self._open.rows(i, j)
        k = np.ascontiguousarray(k)
        vals = dequantise(k, miss, self.res)
        blk = SampleBlock(self.machine_id, self._seq, int(t[0]), int(p), self.names,
                          tuple(float(x) for x in self.res), vals, epoch=self.epoch, steps=k)
        self._seq += 1
        return blk
