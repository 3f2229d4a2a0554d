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
from cranetwin.importer.payload import PayloadCheck, payload_at, payload_limit_kg
from cranetwin.importer.pipeline import (
    BLOCK_SAMPLES,
    ImportReport,
    Pipeline,
    file_epoch,
    raw_time_ns,
)
from cranetwin.importer.readers import (
    Chunk,
    Refusal,
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
    after :func:`import_file` (same checks, conversion, quantisation and time grid), with the
    mapping's payload column as :func:`import_file` stores it.

    Raises:
        ImportFileError: As :func:`iter_blocks`; also when no row was accepted.
    """
    m = mapping if isinstance(mapping, Mapping) else load_mapping(mapping, machine)
    rows = _file_payload_rows(Path(path), m, machine) if m.payload_column is not None else None
    pipe, blocks = iter_blocks(path, machine, m, machine_id, progress=progress)
    got = _collect(pipe, blocks, str(path))
    if rows is None:
        return got
    _report_payload(pipe.report, rows)
    t_ns = got.samples.t_ns if got.samples.t_ns is not None else np.rint(
        got.samples.t_s * 1e9).astype(np.int64)
    return replace(got, payload_kg=payload_at(t_ns, rows.t_ns, rows.kg, pipe.report.period_ns))


@dataclass(frozen=True)
class PayloadRows:
    """The mapping's payload column as read, checked (:class:`PayloadCheck`) and converted.

    Attributes:
        t_ns: Row times [ns since the epoch], shape (m,) (rows without a usable time dropped).
        kg: Payload per row [kg], shape (m,); NaN = empty or refused.
        negative, high: The refusals (negative; above the largest accepted), with row and
            column.
        check: The check applied.
        zeroed: Values below zero within the tolerance, read as 0 kg.
    """

    t_ns: npt.NDArray[np.int64]
    kg: F64
    negative: list[Refusal]
    high: list[Refusal]
    check: PayloadCheck
    zeroed: int = 0


def _payload_check(m: Mapping, machine: Machine) -> PayloadCheck:
    assert m.payload_column is not None
    return PayloadCheck(m.payload_column, m.payload_unit, m.payload_scale,
                        payload_limit_kg(machine, m.payload_max_kg), m.range_tolerance)


def _file_payload_rows(p: Path, m: Mapping, machine: Machine,
                       progress: Progress | None = None) -> PayloadRows:
    """The mapping's payload column of a file (a pass over the file that reads the time and
    that column only), before any sample is read or stored.

    Raises:
        ImportFileError: The file has no such column.
    """
    assert m.payload_column is not None
    if not p.is_file():
        raise ImportFileError(f"{p}: no such file")
    fmt = detect_format(p)
    delim = "\t" if fmt == "csv" and m.delimiter == "," and p.suffix.lower() == ".tsv" \
        else m.delimiter
    if m.payload_column not in set(file_columns(p, fmt, delim)):
        raise ImportFileError(f"{p}: no payload column {m.payload_column!r} (the mapping's "
                              "[payload] column)")
    start_s = m.start_s
    time_map = m
    if fmt == "mdf":
        time_map = replace(m, time_format="relative_s")
        if start_s is None:
            start_s = mdf_start_s(p)
    check = _payload_check(m, machine)
    ts: list[npt.NDArray[np.int64]] = []
    vs: list[F64] = []
    neg: list[Refusal] = []
    high: list[Refusal] = []
    zeroed = 0
    for chunk in iter_chunks(p, fmt, [m.payload_column], m.time_column, _time_kind(time_map),
                             delim):
        t, tbad = raw_time_ns(chunk.time, time_map, start_s)
        keep = ~(tbad | chunk.bad)
        rows = np.arange(chunk.first_row, chunk.first_row + chunk.n)[keep]
        got = check.apply(chunk.columns[m.payload_column][keep] * m.payload_scale, rows,
                          None if chunk.lines is None else chunk.lines[keep])
        ts.append(t[keep])
        vs.append(got.kg)
        neg += got.negative
        high += got.high
        zeroed += got.zeroed
        if progress is not None:
            progress(chunk.done, chunk.total)
    return PayloadRows(np.concatenate(ts) if ts else np.zeros(0, dtype=np.int64),
                       np.concatenate(vs) if vs else np.zeros(0), neg, high, check, zeroed)


def _report_payload(rep: ImportReport, rows: PayloadRows) -> None:
    """Count the payload column's rows and refusals in the import's report."""
    rep.payload_rows = int(np.isfinite(rows.kg).sum())
    rep.payload_refused = len(rows.negative) + len(rows.high)
    rep.payload_zeroed = rows.zeroed
    rep.refuse(rows.negative, rows.check.negative_kind)
    rep.refuse(rows.high, rows.check.high_kind)


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
    keep = ~tbad
    check = _payload_check(m, machine)
    checked = check.apply(kg[keep], np.arange(1, n + 1)[keep], None)
    kg_ok = checked.kg
    _report_payload(pipe.report, PayloadRows(t[keep], kg_ok, checked.negative, checked.high,
                                             check, checked.zeroed))
    t_ns = got.samples.t_ns if got.samples.t_ns is not None else np.rint(
        got.samples.t_s * 1e9).astype(np.int64)
    return replace(got, payload_kg=payload_at(t_ns, t[keep], kg_ok, pipe.report.period_ns))


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
        samples_stored: Samples of the blocks newly stored.
        payload_runs_stored: Known payload runs newly stored (one per block stored or already
            stored, at its sample times; only with the mapping's ``[payload]`` column).
        payload_runs_duplicate: Payload runs already stored with the same values.
        payload_runs_differing: Payload runs already stored with other values (kept as
            stored: e.g. the same file imported before with another ``[payload]`` unit).
    """

    report: ImportReport
    stored: int = 0
    duplicate: int = 0
    refused: Counter[str] = field(default_factory=Counter)
    refused_detail: str = ""
    epoch: int = 0
    samples_stored: int = 0
    payload_runs_stored: int = 0
    payload_runs_duplicate: int = 0
    payload_runs_differing: int = 0


def import_file(path: str | Path, machine: Machine, store: Store, machine_id: str,
                mapping: Mapping | str | Path | None = None, *, progress: Progress | None = None,
                batch_blocks: int = 32) -> ImportSummary:
    """Import a file into storage through :meth:`Store.write_batch` (the ingest daemon's path).

    Importing the same file with the same mapping again stores nothing new (every block is a
    ``duplicate``). Rows are refused, not clipped (see :class:`ImportReport`).

    With the mapping's ``[payload]`` column, the column is read first (a pass over the time
    and that column; refused values counted in the report), and before each batch of blocks
    the known payload at each block's sample times is stored as one run per block
    (:meth:`Store.write_payload_runs`; values as :func:`read_file` gives them, NaN where not
    known), so a twin worker that sees the blocks finds it; the runs of blocks that storage
    then refuses are deleted again. Importing the file again stores it once, and importing it
    again *with* the column adds the series to samples imported without it (the column is no
    part of the import's identity).

    Args:
        path: CSV, Parquet or MDF4 file.
        machine: The machine description of ``machine_id``.
        store: A :class:`cranetwin.storage.Store`.
        machine_id: The registered machine.
        mapping: A :class:`Mapping`, a TOML file or None (default mapping).
        progress: See :data:`Progress` (with a payload column: both passes, as one).
        batch_blocks: Blocks per transaction.

    Raises:
        ImportFileError: See :func:`iter_blocks`; a payload column the file lacks (nothing
            stored).
        StorageError: The database failed (the batches before stay stored; run it again).
    """
    from cranetwin.storage.payloads import PayloadRun

    m = mapping if isinstance(mapping, Mapping) else load_mapping(mapping, machine)
    rows: PayloadRows | None = None
    first = progress
    if m.payload_column is not None:
        outer = progress
        half = None if outer is None else (lambda d, t: outer(d, 2 * t))
        rows = _file_payload_rows(Path(path), m, machine, progress=half)
        first = None if outer is None else (lambda d, t: outer(t + d, 2 * t))
        order = np.argsort(rows.t_ns, kind="stable")
        rows = replace(rows, t_ns=rows.t_ns[order], kg=rows.kg[order])
    pipe, blocks = iter_blocks(path, machine, m, machine_id, progress=first)
    out = ImportSummary(pipe.report, epoch=pipe.epoch)
    if rows is not None:
        _report_payload(pipe.report, rows)
        own = int(np.median(np.diff(rows.t_ns))) if rows.t_ns.size > 1 else 0

    def payload_runs(blocks: list[SampleBlock]) -> list[PayloadRun]:
        """The known payload of each block (in time order), at its sample times."""
        assert rows is not None
        if not blocks:
            return []
        t = [b.times_ns() for b in blocks]
        reach = max(pipe.period_ns, own, 1) // 2 + 1
        lo = np.searchsorted(rows.t_ns, int(t[0][0]) - reach, side="left")
        hi = np.searchsorted(rows.t_ns, int(t[-1][-1]) + reach, side="right")
        kg = payload_at(np.concatenate(t), rows.t_ns[lo:hi], rows.kg[lo:hi], pipe.period_ns,
                        own_ns=own)
        runs, at = [], 0
        for b in blocks:
            runs.append(PayloadRun(int(b.t0_ns), int(b.period_ns), kg[at:at + b.n]))
            at += b.n
        return runs

    def record(batch: list[SampleBlock]) -> None:
        new_runs: set[int] = set()
        if rows is not None:  # before the blocks: a worker that sees them finds the payload
            got = store.write_payload_runs(machine_id, payload_runs(
                sorted(batch, key=lambda b: int(b.t0_ns))))
            out.payload_runs_stored += got.stored
            out.payload_runs_duplicate += got.duplicate
            out.payload_runs_differing += got.differing
            new_runs.update(got.new_starts)
        res = store.write_batch(batch)
        dropped: list[int] = []
        for b, o in zip(batch, res.outcomes, strict=True):
            if not o.durable and int(b.t0_ns) in new_runs:
                dropped.append(int(b.t0_ns))
            if o.status == "stored":
                out.stored += 1
                out.samples_stored += b.n
            elif o.status == "duplicate":
                out.duplicate += 1
            else:
                out.refused[str(o.reason)] += 1
                if not out.refused_detail:
                    out.refused_detail = f"seq {b.seq}: {o.reason}: {o.detail}"
        if dropped:  # the blocks were refused: so is their payload
            out.payload_runs_stored -= store.delete_payload_runs(machine_id, dropped)

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
