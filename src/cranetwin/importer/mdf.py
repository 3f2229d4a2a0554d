"""ASAM MDF4 files (asammdf): channels of one channel group, or of several groups with
different rates put on one time base (:func:`read_mdf`, docs/IMPORT.md)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from cranetwin.errors import MissingExtraError
from cranetwin.importer.mapping import ImportFileError
from cranetwin.importer.readers import Chunk

F64 = npt.NDArray[np.float64]
MDF_CHUNK_ROWS = 1 << 17


def _asammdf() -> Any:
    try:
        import asammdf
    except ImportError as exc:
        raise MissingExtraError("import", "ASAM MDF files") from exc
    return asammdf


def mdf_start_s(path: Path) -> float:
    """Epoch time of an MDF file's relative time 0 [s] (its header's start time)."""
    mdf = _asammdf().MDF(str(path))
    try:
        return float(mdf.header.start_time.timestamp())
    finally:
        mdf.close()


def _group_rate(mdf: Any, group: int) -> float:
    """Samples per second of a channel group (its record count over its master time span)."""
    cycles = int(mdf.groups[group].channel_group.cycles_nr)
    if cycles < 2:
        return 0.0
    t = np.asarray(mdf.get_master(group), dtype=np.float64)
    span = float(t[-1] - t[0]) if t.size else 0.0
    return (cycles - 1) / span if span > 0 else 0.0


def _mdf_values(sig: Any, path: Path, name: str) -> F64:
    """A signal's samples as float64, invalid ones NaN."""
    samples = np.asarray(sig.samples)
    if samples.dtype.kind not in "fiu":
        raise ImportFileError(f"{path}: MDF channel {name!r} holds {samples.dtype}, not numbers")
    v = samples.astype(np.float64)
    if sig.invalidation_bits is not None:
        v[np.asarray(sig.invalidation_bits, dtype=bool)] = np.nan
    return v


def align_to(base_t: F64, t: F64, v: F64, max_gap_s: float) -> F64:
    """Values ``v`` sampled at times ``t`` (s, increasing) on the times ``base_t``: linear
    interpolation between the two neighbouring samples (``numpy.interp``); NaN before the
    first and after the last sample, where a neighbour is NaN (invalid), and where the two
    neighbours are more than ``max_gap_s`` apart (a dropout of that channel)."""
    out = np.full(base_t.shape, np.nan)
    if t.size == 0:
        return out
    ok = np.isfinite(v)
    inside = (base_t >= t[0]) & (base_t <= t[-1])
    if t.size == 1:
        out[base_t == t[0]] = v[0]
        return out
    out[inside] = np.interp(base_t[inside], t, np.where(ok, v, 0.0))
    hi = np.clip(np.searchsorted(t, base_t, side="left"), 1, t.size - 1)
    lo = hi - 1
    exact = t[hi] == base_t
    lo = np.where(exact, hi, lo)
    bad = ~ok[lo] | ~ok[hi] | ((t[hi] - t[lo]) > max_gap_s)
    out[inside & bad] = np.nan
    return out


def read_mdf(path: Path, needed: list[str],
             chunk_rows: int = MDF_CHUNK_ROWS) -> Iterator[Chunk]:
    """Chunks of an MDF4 file; the time is a master channel's, relative seconds since the
    header's start.

    Channels in one channel group share its master time. Channels in several groups (e.g.
    pressures at 100 Hz, positions at 50 Hz) are put on one time base: the master time of
    the group with the highest sample rate among those holding mapped channels (ties: the
    first group). Each channel of another group is interpolated linearly onto it
    (:func:`align_to`); an instant outside that channel's first … last sample, next to one
    of its invalid samples, or between two of its samples more than 1.5 of its own sample
    periods apart is missing (NaN). The base group is read in chunks; the other groups'
    mapped channels are held in memory whole (one float64 per sample).
    """
    asammdf = _asammdf()
    try:
        mdf = asammdf.MDF(str(path))
    except Exception as exc:  # asammdf raises many kinds on a bad file
        raise ImportFileError(f"{path}: not a readable MDF file: {exc}") from exc
    try:
        where: dict[str, tuple[int, int]] = {}
        for c in needed:
            entries = mdf.channels_db.get(c)
            if not entries:
                names = sorted(k for k in mdf.channels_db if not k.startswith("$"))
                raise ImportFileError(f"{path}: no MDF channel {c!r}; the file has: "
                                      f"{', '.join(names)}")
            where[c] = entries[0]
        groups = sorted({g for g, _ in where.values()})
        g = max(groups, key=lambda k: (_group_rate(mdf, k), -k)) if groups else 0
        others: dict[str, tuple[F64, F64, float]] = {}
        for c, (gi, ci) in where.items():
            if gi == g:
                continue
            sig = mdf.get(c, group=gi, index=ci)
            ts = np.asarray(sig.timestamps, dtype=np.float64)
            step = float(np.median(np.diff(ts))) if ts.size > 1 else 0.0
            others[c] = (ts, _mdf_values(sig, path, c), 1.5 * step)
        total = int(mdf.groups[g].channel_group.cycles_nr)
        row = 1
        for off in range(0, total, chunk_rows):
            cnt = min(chunk_rows, total - off)
            t: F64 = np.asarray(mdf.get_master(g, record_offset=off, record_count=cnt),
                                dtype=np.float64)
            cols: dict[str, F64] = {}
            for c in needed:
                gi, ci = where[c]
                if c in others:
                    ts, vs, gap = others[c]
                    cols[c] = align_to(t, ts, vs, gap)
                else:
                    sig = mdf.get(c, group=gi, index=ci, record_offset=off, record_count=cnt)
                    cols[c] = _mdf_values(sig, path, c)
            n = t.shape[0]
            if n == 0:
                break
            yield Chunk(row, t, cols, np.zeros(n, dtype=bool), [], None, off + cnt, total)
            row += n
    finally:
        mdf.close()


def mdf_columns(path: Path) -> list[str]:
    """Channel names of an MDF file."""
    try:
        mdf = _asammdf().MDF(str(path))
    except MissingExtraError:
        raise
    except Exception as exc:  # asammdf raises many kinds on a bad file
        raise ImportFileError(f"{path}: not a readable MDF file: {exc}") from exc
    try:
        return [k for k in mdf.channels_db if not k.startswith("$")]
    finally:
        mdf.close()


__all__ = ["align_to", "mdf_columns", "mdf_start_s", "read_mdf"]
