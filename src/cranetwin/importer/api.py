"""Import a file: into storage (:func:`import_file`) or into memory (:func:`read_file`)."""

from __future__ import annotations

import queue
import threading
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import numpy.typing as npt

from cranetwin.importer.mapping import ChannelMap, ImportFileError, Mapping, load_mapping
from cranetwin.importer.mdf import mdf_start_s
from cranetwin.importer.payload import payload_at
from cranetwin.importer.pipeline import (
    BLOCK_SAMPLES,
    ImportReport,
    Pipeline,
    file_epoch,
    raw_time_ns,
)
from cranetwin.importer.readers import (
    Chunk,
    TimeKind,
    detect_format,
    file_columns,
    iter_chunks,
)
from cranetwin.model import Machine
from cranetwin.samples import SampleArrays, SampleBlock

if TYPE_CHECKING:
    from cranetwin.storage import Store

F64 = npt.NDArray[np.float64]
Progress = Callable[[int, int], None]
"""Called with (units done, units in all) after each chunk (bytes for CSV, rows otherwise)."""


def _time_kind(mapping: Mapping) -> TimeKind:
    if mapping.time_format == "iso8601":
        return "str"
    if mapping.time_format == "epoch_ns":
        return "int"
    return "float"


def iter_blocks(path: str | Path, machine: Machine, mapping: Mapping | str | Path | None = None,
                machine_id: str | None = None, *, progress: Progress | None = None,
                block_samples: int = BLOCK_SAMPLES) -> tuple[Pipeline, Iterator[SampleBlock]]:
    """The blocks of a file, in file order, made as they are read (bounded memory).

    Args:
        path: CSV, Parquet or MDF4 file.
        machine: The machine the file recorded.
        mapping: A :class:`Mapping`, a mapping TOML file, or None for the default mapping.
        machine_id: Storage id the blocks carry (default: the machine's name).
        progress: See :data:`Progress`.
        block_samples: Most samples per block.

    Returns:
        ``(pipeline, blocks)``: ``pipeline.report`` is complete once ``blocks`` is exhausted.

    Raises:
        ImportFileError: Unreadable file, missing columns, bad mapping, a convention mix-up
            (raised on the first chunk, before any block is made).
        MissingExtraError: Parquet or MDF without the ``import`` extra.
    """
    p = Path(path)
    fmt = detect_format(p)
    m = mapping if isinstance(mapping, Mapping) else load_mapping(mapping, machine)
    if fmt == "csv" and m.delimiter == "," and p.suffix.lower() == ".tsv":
        m = replace(m, delimiter="\t")
    if not p.is_file():
        raise ImportFileError(f"{p}: no such file")
    names = set(file_columns(p, fmt, m.delimiter))
    present, absent, missing = [], [], []
    for cm in m.channels:
        if cm.column in names:
            present.append(cm)
        elif machine.channel(cm.channel).optional:
            absent.append(cm.channel)
        else:
            missing.append(f"{cm.channel} (column {cm.column!r})")
    if missing:
        raise ImportFileError(f"{p}: the file lacks required channel(s) {', '.join(missing)}; "
                              f"map them in the mapping's [channels.NAME] column = \"…\"; the "
                              f"file has: {', '.join(sorted(names))}")
    start_s = m.start_s
    if fmt == "mdf":
        if m.time_format not in ("relative_s",):
            m = replace(m, time_format="relative_s")
        if start_s is None:
            start_s = mdf_start_s(p)
    mid = machine_id or machine.name
    pipe = Pipeline(machine, m, mid, file_epoch(p, m, mid, block_samples), present, start_s,
                    block_samples)
    pipe.report.absent = tuple(absent)
    needed = [cm.column for cm in present]

    def gen() -> Iterator[SampleBlock]:
        for chunk in iter_chunks(p, fmt, needed, m.time_column, _time_kind(m), m.delimiter):
            yield from pipe.feed(chunk)
            if progress is not None:
                progress(chunk.done, chunk.total)
        yield from pipe.finish()

    return pipe, gen()


@dataclass(frozen=True)
class ImportedFile:
    """A file read into memory: its samples (quantised, on each run's grid) and the report.

    Attributes:
        samples: The samples.
        report: What was read, accepted and refused.
        payload_kg: The mapping's known payload column at the sample times [kg], shape (n,)
            (NaN where the file's row nearest in time is over half a period away or empty);
            None when the mapping names no payload column (:mod:`cranetwin.importer.payload`).
    """

    samples: SampleArrays
    report: ImportReport
    payload_kg: npt.NDArray[np.float64] | None = None


def read_file(path: str | Path, machine: Machine, mapping: Mapping | str | Path | None = None,
              *, machine_id: str | None = None,
              progress: Progress | None = None) -> ImportedFile:
    """Read a CSV, Parquet or MDF4 file into :class:`SampleArrays` as storage would return it
    after :func:`import_file` (same checks, conversion, quantisation and time grid).

    Raises:
        ImportFileError: As :func:`iter_blocks`; also when no row was accepted.
    """
    m = mapping if isinstance(mapping, Mapping) else load_mapping(mapping, machine)
    pipe, blocks = iter_blocks(path, machine, m, machine_id, progress=progress)
    got = _collect(pipe, blocks, str(path))
    if m.payload_column is None:
        return got
    return replace(got, payload_kg=_file_payload(Path(path), m, got.samples, pipe))


def _file_payload(p: Path, m: Mapping, samples: SampleArrays, pipe: Pipeline) -> F64:
    """The mapping's payload column at the samples' times (a second pass over the file that
    reads the time and that column only)."""
    assert m.payload_column is not None
    fmt = detect_format(p)
    if m.payload_column not in set(file_columns(p, fmt, m.delimiter)):
        raise ImportFileError(f"{p}: no payload column {m.payload_column!r} (the mapping's "
                              "[payload] column)")
    ts: list[npt.NDArray[np.int64]] = []
    vs: list[F64] = []
    time_map = replace(m, time_format="relative_s") if fmt == "mdf" else m
    for chunk in iter_chunks(p, fmt, [m.payload_column], m.time_column, _time_kind(m),
                             m.delimiter):
        t, tbad = raw_time_ns(chunk.time, time_map, pipe.start_s)
        keep = ~(tbad | chunk.bad)
        ts.append(t[keep])
        vs.append(chunk.columns[m.payload_column][keep] * m.payload_scale)
    t_ns = samples.t_ns if samples.t_ns is not None else np.rint(samples.t_s * 1e9).astype(
        np.int64)
    return payload_at(t_ns, np.concatenate(ts), np.concatenate(vs), pipe.report.period_ns)


def _collect(pipe: Pipeline, blocks: Iterable[SampleBlock], what: str) -> ImportedFile:
    ts, vs = [], []
    for b in blocks:
        ts.append(b.times_ns())
        vs.append(b.values)
    if not ts:
        raise ImportFileError(f"{what}: no row was accepted\n{pipe.report.summary()}")
    t_ns = np.concatenate(ts)
    values = np.concatenate(vs)
    uniform = bool(np.all(np.diff(t_ns) == pipe.report.period_ns))
    sa = SampleArrays(pipe.machine_id, t_ns.astype(np.float64) / 1e9, pipe.names, values,
                      period_ns=pipe.report.period_ns if uniform else None, t_ns=t_ns)
    return ImportedFile(sa, pipe.report)


class Columns(Protocol):
    """Named columns: a dict of arrays, a pandas DataFrame, a pyarrow Table's ``to_pydict()``."""

    def __contains__(self, name: object, /) -> bool: ...

    def __getitem__(self, name: str, /) -> Any: ...


def read_columns(columns: Columns, machine: Machine, mapping: Mapping | str | Path | None = None,
                 *, machine_id: str | None = None) -> ImportedFile:
    """:func:`read_file` for columns already in memory (a dict of arrays or a DataFrame): the same
    mapping, conversion, checks, quantisation and runs. A ``datetime64`` time column is taken as
    UTC; numbers as the mapping's ``time.format``.

    Raises:
        ImportFileError: Missing columns, a convention mix-up, no row accepted.
    """
    m = mapping if isinstance(mapping, Mapping) else load_mapping(mapping, machine)
    tcol = m.time_column or next((c for c in ("t_s", "time") if c in columns), None)
    if tcol is None or tcol not in columns:
        raise ImportFileError(f"no time column {tcol or 't_s'!r} in the columns given")
    present: list[ChannelMap] = []
    absent: list[str] = []
    for cm in m.channels:
        if cm.column in columns:
            present.append(cm)
        elif machine.channel(cm.channel).optional:
            absent.append(cm.channel)
        else:
            raise ImportFileError(f"the columns lack required channel {cm.channel} (column "
                                  f"{cm.column!r})")
    raw_t = np.asarray(columns[tcol])
    if raw_t.dtype.kind != "M" and m.time_format == "iso8601":
        raw_t = raw_t.astype(str)
    cols = {cm.column: np.asarray(columns[cm.column], dtype=np.float64) for cm in present}
    n = raw_t.shape[0]
    for c, v in cols.items():
        if v.shape != (n,):
            raise ImportFileError(f"column {c!r} has shape {v.shape}; the time has ({n},)")
    pipe = Pipeline(machine, m, machine_id or machine.name, 1, present, m.start_s)
    pipe.report.absent = tuple(absent)
    chunk = Chunk(1, raw_t, cols, np.zeros(n, dtype=bool), [], None, n, n)
    got = _collect(pipe, [*pipe.feed(chunk), *pipe.finish()], "the columns")
    if m.payload_column is None:
        return got
    if m.payload_column not in columns:
        raise ImportFileError(f"no payload column {m.payload_column!r} (the mapping's [payload] "
                              "column) in the columns given")
    kg = np.asarray(columns[m.payload_column], dtype=np.float64) * m.payload_scale
    t, tbad = raw_time_ns(raw_t, m, pipe.start_s)
    t_ns = got.samples.t_ns if got.samples.t_ns is not None else np.rint(
        got.samples.t_s * 1e9).astype(np.int64)
    return replace(got, payload_kg=payload_at(t_ns, t[~tbad], kg[~tbad],
                                              pipe.report.period_ns))


@dataclass
class ImportSummary:
    """The outcome of :func:`import_file`.

    Attributes:
        report: What was read, accepted and refused (:class:`ImportReport`).
        stored: Blocks newly stored.
        duplicate: Blocks already stored (the same import ran before).
        refused: Blocks storage refused, per reason (``overlap``: another import or the
            daemon already stored samples in that time range).
        refused_detail: The first refused block's detail line, or "".
        epoch: The import's epoch (its block identity with ``seq``).
    """

    report: ImportReport
    stored: int = 0
    duplicate: int = 0
    refused: Counter[str] = field(default_factory=Counter)
    refused_detail: str = ""
    epoch: int = 0
    samples_stored: int = 0


def import_file(path: str | Path, machine: Machine, store: Store, machine_id: str,
                mapping: Mapping | str | Path | None = None, *, progress: Progress | None = None,
                batch_blocks: int = 32) -> ImportSummary:
    """Import a file into storage through :meth:`Store.write_batch` (the ingest daemon's path).

    Importing the same file with the same mapping again stores nothing new (every block is a
    ``duplicate``). Rows are refused, not clipped (see :class:`ImportReport`).

    Args:
        path: CSV, Parquet or MDF4 file.
        machine: The machine description of ``machine_id``.
        store: A :class:`cranetwin.storage.Store`.
        machine_id: The registered machine.
        mapping: A :class:`Mapping`, a TOML file or None (default mapping).
        progress: See :data:`Progress`.
        batch_blocks: Blocks per transaction.

    Raises:
        ImportFileError: See :func:`iter_blocks`.
        StorageError: The database failed (the batches before stay stored; run it again).
    """
    pipe, blocks = iter_blocks(path, machine, mapping, machine_id, progress=progress)
    out = ImportSummary(pipe.report, epoch=pipe.epoch)

    def record(batch: list[SampleBlock]) -> None:
        res = store.write_batch(batch)
        for b, o in zip(batch, res.outcomes, strict=True):
            if o.status == "stored":
                out.stored += 1
                out.samples_stored += b.n
            elif o.status == "duplicate":
                out.duplicate += 1
            else:
                out.refused[str(o.reason)] += 1
                if not out.refused_detail:
                    out.refused_detail = f"seq {b.seq}: {o.reason}: {o.detail}"

    # one writer thread: reading and converting the next batch overlaps storage's encoding and
    # commit of this one (batches stay in file order; one writer, as storage assumes)
    todo: queue.Queue[list[SampleBlock] | None] = queue.Queue(maxsize=2)
    failed: list[BaseException] = []

    def writer() -> None:
        while (batch := todo.get()) is not None:
            if not failed:
                try:
                    record(batch)
                except BaseException as exc:  # handed to the caller's thread below
                    failed.append(exc)

    th = threading.Thread(target=writer, name="cranetwin-import-writer", daemon=True)
    th.start()
    try:
        batch: list[SampleBlock] = []
        for b in blocks:
            batch.append(b)
            if len(batch) >= batch_blocks:
                todo.put(batch)
                batch = []
                if failed:
                    break
        if batch and not failed:
            todo.put(batch)
    finally:
        todo.put(None)
        th.join()
    if failed:
        raise failed[0]
    return out
