"""Read a user's file in chunks of rows: CSV (pyarrow's parser, numpy's where it cannot),
Parquet (pyarrow) and ASAM MDF4 (asammdf, :mod:`.mdf`).

Each reader yields :class:`Chunk` s: the raw time column, the raw value columns the mapping
needs (float64, NaN = missing) and the rows it could not parse, with row, column and reason.
Memory is one chunk at a time. Conversion, checks and runs are :mod:`.pipeline`'s.
"""

from __future__ import annotations

import csv
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from cranetwin.errors import MissingExtraError
from cranetwin.importer.mapping import ImportFileError

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
TimeKind = Literal["float", "int", "str"]
Format = Literal["csv", "parquet", "mdf"]

CSV_CHUNK_BYTES = 8 << 20
PARQUET_BATCH_ROWS = 1 << 17


@dataclass(frozen=True)
class Refusal:
    """One value or row that was not imported.

    Attributes:
        row: Data row, 1-based (the first row after a CSV header is 1; Parquet/MDF record
            index + 1).
        column: Column (or ``(row)`` for the whole row, ``(time)`` context in the name).
        reason: Why, in one line.
        line: CSV only: the line number in the file (1-based), else None.
    """

    row: int
    column: str
    reason: str
    line: int | None = None

    def __str__(self) -> str:
        where = f"row {self.row}" + (f" (line {self.line})" if self.line is not None else "")
        return f"{where}, column {self.column!r}: {self.reason}"


@dataclass
class Chunk:
    """Consecutive rows of a file.

    Attributes:
        first_row: 1-based data row number of the chunk's first row.
        time: The raw time column, shape (n,): float64, int64 or str.
        columns: Raw values per needed column, shape (n,) each [file units]; NaN = missing.
        bad: Shape (n,), True where the row could not be parsed (see ``refusals``).
        refusals: Why each bad row was refused.
        lines: CSV: file line number per row, shape (n,); else None.
        done: Progress units done after this chunk (bytes or rows).
        total: Progress units of the whole file.
    """

    first_row: int
    time: npt.NDArray[Any]
    columns: dict[str, F64]
    bad: npt.NDArray[np.bool_]
    refusals: list[Refusal] = field(default_factory=list)
    lines: I64 | None = None
    done: int = 0
    total: int = 0

    @property
    def n(self) -> int:
        return int(self.bad.shape[0])


def detect_format(path: Path) -> Format:
    """The file's format from its suffix (``.csv``/``.txt``/``.tsv``, ``.parquet``/``.pq``,
    ``.mf4``/``.mdf``)."""
    suf = path.suffix.lower()
    if suf in (".csv", ".txt", ".tsv"):
        return "csv"
    if suf in (".parquet", ".pq"):
        return "parquet"
    if suf in (".mf4", ".mdf"):
        return "mdf"
    raise ImportFileError(f"{path}: unknown file type {suf!r}; expected .csv, .parquet or .mf4")


def _pick_time(names: list[str], time_column: str | None, path: Path) -> str:
    if time_column is not None:
        if time_column not in names:
            raise ImportFileError(f"{path}: no time column {time_column!r}; columns: "
                                  f"{', '.join(names)}")
        return time_column
    for cand in ("t_s", "time"):
        if cand in names:
            return cand
    raise ImportFileError(f"{path}: no time column (looked for 't_s' and 'time'); name it in "
                          f"the mapping's [time] column; columns: {', '.join(names)}")


def _missing_columns(needed: list[str], names: list[str], path: Path) -> None:
    miss = [c for c in needed if c not in names]
    if miss:
        raise ImportFileError(f"{path}: no column(s) {', '.join(map(repr, miss))}; the file has: "
                              f"{', '.join(names)}")


# -- CSV --------------------------------------------------------------------------------------

_EMPTY = re.compile(r"(^|{d})(?=[ \t]*(?:{d}|\r?$))", re.MULTILINE)


def _fill_empty(text: str, delim: str) -> str:
    """Empty fields → ``nan`` (a dropout), so numpy parses them."""
    d = re.escape(delim)
    return re.sub(_EMPTY.pattern.format(d=d), r"\1nan", text, flags=re.MULTILINE)


def csv_header(path: Path, delimiter: str) -> tuple[list[str], int, int]:
    """Column names, the header's line number (1-based) and the byte offset after it."""
    with path.open("rb") as fh:
        line_no = 0
        for raw in fh:
            line_no += 1
            text = raw.decode("utf-8-sig" if line_no == 1 else "utf-8", errors="replace")
            if text.startswith("#") or not text.strip():
                continue
            names = [c.strip() for c in next(csv.reader([text.rstrip("\r\n")],
                                                        delimiter=delimiter))]
            return names, line_no, fh.tell()
    raise ImportFileError(f"{path}: no header row (the first line that is not a # comment)")


def read_csv(path: Path, needed: list[str], time_column: str | None, time_kind: TimeKind,
             delimiter: str = ",", chunk_bytes: int = CSV_CHUNK_BYTES,
             engine: Literal["auto", "numpy"] = "auto") -> Iterator[Chunk]:
    """Chunks of a CSV file with a header row (``#`` comment lines and blank lines skipped).

    Each chunk is ``chunk_bytes`` of whole lines. With pyarrow installed (``engine="auto"``) its
    C parser reads a chunk whose every line is one data row (:func:`_csv_arrow`); a chunk it
    does not take as it is — a ``#`` or blank line, a bad or short row, an empty time, a quoted
    line break — goes to numpy's parser (the same chunk, so line numbers stay exact), which
    names every bad row and column (text where a number belongs, too few fields).
    """
    names, header_line, start = csv_header(path, delimiter)
    tcol = _pick_time(names, time_column, path)
    _missing_columns(needed, names, path)
    idx = [names.index(c) for c in needed]
    tidx = names.index(tcol)
    arrow = _csv_arrow_parser(len(names), idx, tidx, time_kind, delimiter) \
        if engine == "auto" else None
    total = path.stat().st_size
    row = 1
    line = header_line + 1
    with path.open("rb") as fh:
        fh.seek(start)
        done = start
        rest = b""
        while True:
            buf = fh.read(chunk_bytes)
            data = rest + buf
            if buf:
                cut = data.rfind(b"\n") + 1
                if cut == 0:
                    rest = data
                    continue
                data, rest = data[:cut], data[cut:]
            else:
                rest = b""
            if not data:
                break
            done += len(data)
            n_lines = data.count(b"\n") + (not data.endswith(b"\n"))
            line_nos = np.arange(line, line + n_lines, dtype=np.int64)
            line += n_lines
            got = arrow(data, n_lines) if arrow is not None else None
            if got is not None:
                t, cols = got
                chunk = Chunk(row, t, dict(zip(needed, cols, strict=True)),
                              np.zeros(n_lines, dtype=bool), [], line_nos, done, total)
            else:
                lines = data.decode("utf-8", errors="replace").split("\n")
                if lines and lines[-1] == "":
                    lines.pop()
                chunk = _csv_chunk(lines, line_nos, row, needed, idx, tcol, tidx, time_kind,
                                   delimiter, done, total)
            if chunk.n:
                yield chunk
            row += chunk.n
            if not buf:
                break


ArrowParse = Callable[[bytes, int], "tuple[npt.NDArray[Any], list[F64]] | None"]


def _csv_arrow_parser(width: int, idx: list[int], tidx: int, time_kind: TimeKind,
                      delim: str) -> ArrowParse | None:
    """pyarrow's CSV parser for chunks of ``width``-field rows, or None without pyarrow.

    The returned function takes a chunk's bytes (whole lines, no header) and its line count,
    and gives (time, value columns) — time shape (n,) float64, int64 or str, values shape (n,)
    float64 each in ``idx`` order, NaN where a cell is empty — or None where the chunk is not
    exactly ``n`` clean rows: then numpy's parser takes it. Only an empty cell is missing
    (``nan``, ``NaN``, ``inf`` parse as numbers, as numpy's parser reads them); anything
    else that is not a number, a row with another field count, an empty time, a ``#`` or
    blank line (they are no rows to pyarrow) or a quoted line break (one row over two lines)
    makes the chunk numpy's.
    """
    try:
        import pyarrow as pa
        import pyarrow.csv as pcsv
    except ImportError:
        return None
    cols = [f"c{i}" for i in range(width)]  # header names may repeat; numpy takes the first
    ttype = {"float": pa.float64(), "int": pa.int64(), "str": pa.string()}[time_kind]
    types = {cols[i]: pa.float64() for i in idx}
    types[cols[tidx]] = ttype
    read = pcsv.ReadOptions(column_names=cols, use_threads=False, block_size=CSV_CHUNK_BYTES * 2)
    parse = pcsv.ParseOptions(delimiter=delim, quote_char='"', ignore_empty_lines=True)
    conv = pcsv.ConvertOptions(column_types=types, null_values=[""], true_values=[],
                               false_values=[], strings_can_be_null=True,
                               quoted_strings_can_be_null=True,
                               include_columns=[cols[tidx], *(cols[i] for i in idx)])
    nan = pa.scalar(float("nan"), pa.float64())

    def parse_chunk(data: bytes, n: int) -> tuple[npt.NDArray[Any], list[F64]] | None:
        if data.startswith((b"#", b"\n", b"\r\n")) or b"\n#" in data or b"\n\n" in data \
                or b"\n\r\n" in data:
            return None
        try:
            table = pcsv.read_csv(pa.py_buffer(data), read_options=read, parse_options=parse,
                                  convert_options=conv)
        except pa.ArrowInvalid:
            return None
        if table.num_rows != n:
            return None
        tarr = table.column(0)
        if tarr.null_count:
            return None
        t: npt.NDArray[Any] = (tarr.to_numpy().astype(str) if time_kind == "str"
                               else np.ascontiguousarray(tarr.to_numpy()))
        out: list[F64] = []
        for j in range(1, table.num_columns):
            arr = table.column(j)
            if arr.null_count:
                arr = arr.fill_null(nan)
            out.append(np.ascontiguousarray(arr.to_numpy(), dtype=np.float64))
        return t, out

    return parse_chunk


def _csv_fast(lines: list[str], idx: list[int], tidx: int, time_kind: TimeKind,
              delim: str) -> tuple[npt.NDArray[Any], F64] | None:
    """numpy's C parser over the lines: (time, values), or None where it cannot parse them."""
    n = len(lines)
    try:
        if time_kind == "float":  # one pass for the time and the values
            both = np.loadtxt(lines, delimiter=delim, usecols=[tidx, *idx], ndmin=2,
                              dtype=np.float64, comments=None, quotechar='"')
            t: npt.NDArray[Any] = both[:, 0].copy()
            vals = both[:, 1:]
        else:
            vals = np.loadtxt(lines, delimiter=delim, usecols=idx, ndmin=2, dtype=np.float64,
                              comments=None, quotechar='"') if idx else np.zeros((n, 0))
            t = np.loadtxt(lines, delimiter=delim, usecols=[tidx], ndmin=1, comments=None,
                           quotechar='"', dtype=str if time_kind == "str" else np.int64)
    except ValueError:
        return None
    if vals.shape[0] != n or t.shape[0] != n:
        return None
    return t, vals


def _csv_chunk(lines: list[str], line_nos: I64, row: int, needed: list[str], idx: list[int],
               tcol: str, tidx: int, time_kind: TimeKind, delim: str, done: int,
               total: int) -> Chunk:
    """Parse one chunk of lines: the fast path first (no scan of the text when it is clean);
    then without blank and ``#`` lines, then with empty fields as ``nan``; else row by row."""
    got = _csv_fast(lines, idx, tidx, time_kind, delim)
    if got is None and any(not ln.strip() or ln.startswith("#") for ln in lines):
        keep = [i for i, ln in enumerate(lines) if ln.strip() and not ln.startswith("#")]
        lines = [lines[i] for i in keep]
        line_nos = line_nos[np.asarray(keep, dtype=np.int64)]
        got = _csv_fast(lines, idx, tidx, time_kind, delim)
    if got is None and lines:
        got = _csv_fast(_fill_empty("\n".join(lines), delim).split("\n"), idx, tidx,
                        time_kind, delim)
    if got is None:
        return _csv_slow(lines, line_nos, row, needed, idx, tcol, tidx, time_kind, delim, done,
                         total)
    t, vals = got
    n = len(lines)
    cols = {c: np.ascontiguousarray(vals[:, j]) for j, c in enumerate(needed)}
    return Chunk(row, t, cols, np.zeros(n, dtype=bool), [], line_nos, done, total)


def _num(text: str) -> float:
    s = text.strip()
    return float("nan") if s == "" else float(s)


def _csv_slow(lines: list[str], line_nos: I64, row: int, needed: list[str], idx: list[int],
              tcol: str, tidx: int, time_kind: TimeKind, delim: str, done: int,
              total: int) -> Chunk:
    """Row-by-row parse of a chunk the fast path rejected: every bad row named."""
    n = len(lines)
    vals = np.full((n, len(needed)), np.nan)
    bad = np.zeros(n, dtype=bool)
    refusals: list[Refusal] = []
    t: list[Any] = []
    width = max([*idx, tidx]) + 1
    tdefault: Any = "" if time_kind == "str" else 0
    for i, fields in enumerate(csv.reader(lines, delimiter=delim)):
        r, ln = row + i, int(line_nos[i])
        if len(fields) < width:
            bad[i] = True
            refusals.append(Refusal(r, "(row)", f"{len(fields)} fields, expected at least "
                                    f"{width}", ln))
            t.append(tdefault)
            continue
        raw_t = fields[tidx].strip()
        try:
            t.append(raw_t if time_kind == "str" else
                     int(raw_t) if time_kind == "int" else float(raw_t))
        except ValueError:
            bad[i] = True
            refusals.append(Refusal(r, tcol, f"{raw_t!r} is not a time", ln))
            t.append(tdefault)
        for j, k in enumerate(idx):
            try:
                vals[i, j] = _num(fields[k])
            except ValueError:
                if not bad[i]:
                    refusals.append(Refusal(r, needed[j], f"{fields[k].strip()!r} is not a "
                                            "number", ln))
                bad[i] = True
    tt: npt.NDArray[Any] = np.asarray(t, dtype=str if time_kind == "str" else
                                      np.int64 if time_kind == "int" else np.float64)
    cols = {c: np.ascontiguousarray(vals[:, j]) for j, c in enumerate(needed)}
    return Chunk(row, tt, cols, bad, refusals, line_nos, done, total)


# -- Parquet ----------------------------------------------------------------------------------

def _pyarrow() -> Any:
    try:
        import pyarrow as pa
        import pyarrow.compute as pc
        import pyarrow.parquet as pq
    except ImportError as exc:
        raise MissingExtraError("import", "Parquet files") from exc
    return pa, pc, pq


def read_parquet(path: Path, needed: list[str], time_column: str | None, time_kind: TimeKind,
                 batch_rows: int = PARQUET_BATCH_ROWS) -> Iterator[Chunk]:
    """Chunks of a Parquet file (one record batch each). A timestamp-typed time column is
    returned as int64 ns since the epoch (naive timestamps are UTC)."""
    pa, pc, pq = _pyarrow()
    try:
        pf = pq.ParquetFile(path)
    except (OSError, pa.ArrowException) as exc:
        raise ImportFileError(f"{path}: not a readable Parquet file: {exc}") from exc
    names = list(pf.schema_arrow.names)
    tcol = _pick_time(names, time_column, path)
    _missing_columns(needed, names, path)
    total = int(pf.metadata.num_rows)
    row = 1
    nan = pa.scalar(float("nan"), pa.float64())
    for batch in pf.iter_batches(batch_size=batch_rows, columns=[tcol, *needed]):
        n = batch.num_rows
        bad = np.zeros(n, dtype=bool)
        refusals: list[Refusal] = []
        tarr = batch.column(0)
        if pa.types.is_timestamp(tarr.type):
            tcast = pc.cast(tarr, pa.timestamp("ns", tarr.type.tz))
            t: npt.NDArray[Any] = pc.fill_null(tcast.cast(pa.int64()), 0).to_numpy().view(
                "datetime64[ns]")  # UTC: whatever the mapping's time.format says
        elif time_kind == "str":
            t = np.asarray(pc.fill_null(tarr.cast(pa.string()), "").to_numpy(
                zero_copy_only=False), dtype=str)
        else:
            t = (pc.fill_null(tarr, 0) if tarr.null_count else tarr).cast(
                pa.int64() if time_kind == "int" else pa.float64()).to_numpy()
        if tarr.null_count:
            nulls = np.asarray(tarr.is_null().to_numpy(zero_copy_only=False))
            bad |= nulls
            refusals += [Refusal(row + int(i), tcol, "no time (null)")
                         for i in np.flatnonzero(nulls)]
        cols: dict[str, F64] = {}
        for j, c in enumerate(needed):
            arr = batch.column(j + 1)
            if not (pa.types.is_floating(arr.type) or pa.types.is_integer(arr.type)
                    or pa.types.is_decimal(arr.type)):
                raise ImportFileError(f"{path}: column {c!r} is {arr.type}, not numbers")
            arr = arr.cast(pa.float64())
            if arr.null_count:
                arr = pc.fill_null(arr, nan)
            cols[c] = np.ascontiguousarray(arr.to_numpy())
        yield Chunk(row, t, cols, bad, refusals, None, min(row - 1 + n, total), total)
        row += n


def iter_chunks(path: Path, fmt: Format, needed: list[str], time_column: str | None,
                time_kind: TimeKind, delimiter: str) -> Iterator[Chunk]:
    """Chunks of ``path`` in format ``fmt``."""
    if not path.is_file():
        raise ImportFileError(f"{path}: no such file")
    if fmt == "csv":
        return read_csv(path, needed, time_column, time_kind, delimiter)
    if fmt == "parquet":
        return read_parquet(path, needed, time_column, time_kind)
    from cranetwin.importer.mdf import read_mdf

    return read_mdf(path, needed)


def file_columns(path: Path, fmt: Format, delimiter: str) -> list[str]:
    """Column (channel) names of a file, for the optional channels it may lack."""
    if fmt == "csv":
        return csv_header(path, delimiter)[0]
    if fmt == "parquet":
        _, _, pq = _pyarrow()
        try:
            return list(pq.ParquetFile(path).schema_arrow.names)
        except Exception as exc:
            raise ImportFileError(f"{path}: not a readable Parquet file: {exc}") from exc
    from cranetwin.importer.mdf import mdf_columns

    return mdf_columns(path)


__all__ = ["Chunk", "Refusal", "detect_format", "file_columns", "iter_chunks"]
