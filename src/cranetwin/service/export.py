"""Export of raw and derived series of one machine as CSV or Parquet, streamed chunk by chunk.

Series (columns in order; times [s since the Unix epoch] unless named ``_ns``):

==============  ===============================================================================
``raw``         ``t_ns`` (int64, the stored sample time [ns], exact), ``t_s``, then one column per
                channel of the machine description in its units (Pa, m, N·m, rad); empty (CSV)
                or null (Parquet) where a sample is missing. The stored samples exactly:
                :func:`cranetwin.storage.bulkread.read_samples_bulk` (what ``read_samples``
                returns, decoded a chunk of blocks at a time).
``forces``      ``t_s``, ``force.<cyl>`` [N]: cylinder forces (paper Eq. 1–2) of the twin.
``joint_loads`` ``t_s``, ``torque_id.<joint>`` [N·m or N], ``wrench.<joint>.fx|fy|fz`` [N] and
                ``.mx|my|mz`` [N·m] (inverse dynamics, child body frame).
``payload``     ``t_s``, ``payload_kg``, ``payload_std_kg`` [kg].
``cycles``      one row per work cycle of the analytics (the reports' cycles): ``t_grab``,
                ``t_release``, ``duration_s``, ``payload_kg``, ``load_ratio``, ``lift``,
                ``swing``, ``reach_max_m``.
``events``      ``t_s``, ``kind``, ``severity``, ``message``, ``evidence`` (JSON text).
==============  ===============================================================================

The twin series (``forces``, ``joint_loads``, ``payload``) are replayed minute by minute the
way the twin worker replays a minute (the minute with ``margin_s`` of samples either side, the
replay's values inside the minute kept; :mod:`cranetwin.importer.replay` names the columns), at
the data's sample rate; minutes without samples are skipped with one index probe.

Memory stays bounded by one chunk (``chunk_samples`` raw samples, one minute of replay): the
body is produced by an iterator of ``bytes`` that a caller streams (the API's
``StreamingResponse``, the CLI's file). Parquet output is one row group per chunk.
"""

from __future__ import annotations

import io
import json
import math
import queue
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from cranetwin.errors import CraneTwinError, MissingExtraError
from cranetwin.model import Machine
from cranetwin.service.errors import InvalidRequestError
from cranetwin.service.replayer import Replayer, sample_rate_hz
from cranetwin.service.timerange import TimeRange

if TYPE_CHECKING:
    from cranetwin.service.backend import MachineRecord
    from cranetwin.service.fleet import FleetService

SERIES = ("raw", "forces", "joint_loads", "payload", "cycles", "events")
FORMATS = ("csv", "parquet")
MEDIA_TYPES = {"csv": "text/csv", "parquet": "application/vnd.apache.parquet"}
CHUNK_SAMPLES = 100_000
"""Raw samples per chunk (about 10 MB of arrays for a dozen channels)."""
MINUTE_S = 60.0

Columns = dict[str, npt.NDArray[Any]]


def _pa() -> Any:
    try:
        import pyarrow as pa
    except ImportError as exc:
        raise MissingExtraError("import", "CSV and Parquet export") from exc
    return pa


def _pa_module(name: str) -> Any:
    """``pyarrow.csv`` or ``pyarrow.parquet``; MissingExtraError without the extra."""
    try:
        if name == "csv":
            import pyarrow.csv as mod
        else:
            import pyarrow.parquet as mod
    except ImportError as exc:
        raise MissingExtraError("import", "CSV and Parquet export") from exc
    return mod


def check(series: str, fmt: str) -> None:
    """Refuse an unknown series or format before any work starts.

    Raises:
        InvalidRequestError: Unknown series or format.
        MissingExtraError: pyarrow is not installed (extra ``import``).
    """
    if series not in SERIES:
        raise InvalidRequestError("Unknown series", f"series={series!r}: expected one of "
                                  f"{', '.join(SERIES)}")
    if fmt not in FORMATS:
        raise InvalidRequestError("Unknown format", f"format={fmt!r}: expected csv or parquet")
    _pa()


def schema(series: str, machine: Machine) -> Any:
    """The pyarrow schema of ``series`` for ``machine`` (columns as in the module docstring)."""
    pa = _pa()
    f64 = pa.float64()
    if series == "raw":
        return pa.schema([("t_ns", pa.int64()), ("t_s", f64)]
                         + [(c.name, f64) for c in machine.channels])
    if series == "cycles":
        return pa.schema([("t_grab", f64), ("t_release", f64), ("duration_s", f64),
                          ("payload_kg", f64), ("load_ratio", f64), ("lift", pa.bool_()),
                          ("swing", pa.bool_()), ("reach_max_m", f64)])
    if series == "events":
        s = pa.string()
        return pa.schema([("t_s", f64), ("kind", s), ("severity", s), ("message", s),
                          ("evidence", s)])
    return pa.schema([(n, f64) for n in twin_columns(series, machine)])


def twin_columns(series: str, machine: Machine) -> list[str]:
    """Column names of a twin series (``forces``, ``joint_loads``, ``payload``)."""
    if series == "forces":
        return ["t_s"] + [f"force.{c.name}" for c in machine.cylinders]
    if series == "joint_loads":
        out = ["t_s"] + [f"torque_id.{j.name}" for j in machine.joints]
        for j in machine.joints:
            out += [f"wrench.{j.name}.{k}" for k in ("fx", "fy", "fz", "mx", "my", "mz")]
        return out
    if series == "payload":
        return ["t_s", "payload_kg", "payload_std_kg"]
    raise InvalidRequestError("Unknown series", f"{series!r} is not a twin series")


# -- chunk sources -----------------------------------------------------------------------------
def raw_chunks(backend: Any, machine: Machine, machine_id: str, rng: TimeRange,
               nominal_rate_hz: float, chunk_samples: int = CHUNK_SAMPLES) -> Iterator[Columns]:
    """The stored samples of [from, to) as consecutive chunks of about ``chunk_samples`` rows
    (columns of :func:`schema` ``"raw"``); gaps are skipped with one index probe."""
    from cranetwin.storage.bulkread import read_samples_bulk

    names = [c.name for c in machine.channels]
    span = chunk_samples / nominal_rate_hz
    start = rng.t0_s
    with backend.session(machine_id) as session:
        while start < rng.t1_s:
            nxt = backend.next_sample_time(machine_id, start)
            if nxt is None or nxt >= rng.t1_s:
                return
            start = max(start, nxt)
            end = min(rng.t1_s, start + span)
            s = read_samples_bulk(session, machine_id, start, end)
            session.rollback()  # end the read transaction: no snapshot held between chunks
            if s.period_ns:
                span = max(1.0, chunk_samples * s.period_ns * 1e-9)
            if s.t_s.shape[0]:
                t_ns = s.t_ns if s.t_ns is not None else np.rint(s.t_s * 1e9).astype(np.int64)
                out: Columns = {"t_ns": t_ns, "t_s": s.t_s}
                idx = {c: j for j, c in enumerate(s.channels)}
                nan = np.full(s.t_s.shape[0], np.nan)
                cols = np.asfortranarray(s.values)  # contiguous columns: no copy per column
                for n in names:
                    out[n] = cols[:, idx[n]] if n in idx else nan
                yield out
            start = end


def twin_chunks(backend: Any, replayer: Replayer, machine: Machine, machine_id: str,
                rng: TimeRange, series: str, margin_s: float) -> Iterator[Columns]:
    """A twin series of [from, to), one replayed minute per chunk (see the module docstring)."""
    from cranetwin.importer.replay import result_columns

    names = twin_columns(series, machine)
    a = math.floor(rng.t0_s / MINUTE_S) * MINUTE_S
    theta0 = 0.0
    last_end: float | None = None
    while a < rng.t1_s:
        nxt = backend.next_sample_time(machine_id, a)
        if nxt is None or nxt >= rng.t1_s:
            return
        if nxt >= a + MINUTE_S:
            a = math.floor(nxt / MINUTE_S) * MINUTE_S
            continue
        b = a + MINUTE_S
        samples = backend.read_samples(machine_id, a - margin_s, b + margin_s)
        lo, hi = max(a, rng.t0_s), min(b, rng.t1_s)
        if samples.t_s.shape[0] >= 8:
            try:
                res = replayer.replay(machine_id, machine, samples, sample_rate_hz(samples),
                                      theta0_initial=theta0 if last_end == a else 0.0)
            except CraneTwinError:
                res = None
            if res is not None and res.n:
                keep = (res.t_s >= lo) & (res.t_s < hi)
                if keep.any():
                    cols = result_columns(res, machine)
                    yield {n: cols[n][keep] for n in names}
                    theta0 = float(res.q[keep][-1, 0])
                    last_end = b
        a = b


def cycle_chunks(report: Any) -> Iterator[Columns]:
    """The work cycles of an analytics report (None: no data) as one chunk."""
    cycles = [] if report is None else list(report.cycles)
    if not cycles:
        return
    g = np.array([c.t_grab for c in cycles])
    r = np.array([c.t_release for c in cycles])
    yield {"t_grab": g, "t_release": r, "duration_s": r - g,
           "payload_kg": np.array([c.payload_kg for c in cycles]),
           "load_ratio": np.array([c.load_ratio for c in cycles]),
           "lift": np.array([bool(c.lift) for c in cycles]),
           "swing": np.array([bool(c.swing) for c in cycles]),
           "reach_max_m": np.array([c.reach_max_m for c in cycles])}


def event_chunks(pages: Iterator[list[dict[str, Any]]]) -> Iterator[Columns]:
    """Event pages (contract dicts ``{t, kind, severity, message, evidence}``) as chunks."""
    for page in pages:
        if page:
            yield {"t_s": np.array([e["t"] for e in page], dtype=np.float64),
                   "kind": np.array([e["kind"] for e in page], dtype=object),
                   "severity": np.array([e["severity"] for e in page], dtype=object),
                   "message": np.array([e["message"] for e in page], dtype=object),
                   "evidence": np.array([json.dumps(e.get("evidence") or {}, sort_keys=True)
                                         for e in page], dtype=object)}


# -- writers -------------------------------------------------------------------------------------
class _Sink(io.RawIOBase):
    """A write-only file whose bytes are taken out after each chunk."""

    def __init__(self) -> None:
        self.parts: list[bytes] = []
        self.pos = 0

    def writable(self) -> bool:
        return True

    def write(self, b: Any) -> int:
        data = bytes(b)
        self.parts.append(data)
        self.pos += len(data)
        return len(data)

    def tell(self) -> int:
        return self.pos

    def take(self) -> bytes:
        out = b"".join(self.parts)
        self.parts.clear()
        return out


CSV_INT_MAX = 1e9
"""Integral float columns whose values are all below this in magnitude are written to CSV as
int64: pyarrow writes such a float as its integer digits (``4560000``, ``-3``; from 1e10 on it
switches to ``1e+10``), and formats an int64 column in about half the time of a float64 one."""


def _integral(x: npt.NDArray[np.float64], nan: npt.NDArray[np.bool_] | None) -> bool:
    """Whether every value of ``x`` (NaN aside) is an integer below :data:`CSV_INT_MAX` in
    magnitude and none is −0.0 (which pyarrow writes ``-0``): its int64 text is its float text."""
    y = x if nan is None else x[~nan]
    return bool(y.size) and bool(np.all(np.abs(y) < CSV_INT_MAX)) \
        and bool(np.array_equal(np.trunc(y), y)) and not bool(np.any(np.signbit(y) & (y == 0)))


_NUMPY_OF = {"int64": np.int64, "double": np.float64}
"""numpy dtypes of the Arrow types built from buffers by :func:`_array`."""


def _array(x: npt.NDArray[Any], typ: Any, nulls: npt.NDArray[np.bool_] | None) -> Any:
    """``x`` (shape (n,)) as an Arrow array of ``typ``, null where ``nulls``: an int64 or
    float64 array wraps the numpy buffer (no copy when ``x`` is contiguous of that dtype);
    ``pa.array`` would also import pandas on its first call (0.3–0.5 s of every CLI run and
    of a server's first export) to ask whether ``x`` is a pandas object."""
    pa = _pa()
    dtype = _NUMPY_OF.get(str(typ))
    if dtype is None:  # bool and text columns (cycles, events: small)
        return pa.array(x, type=typ, mask=nulls)
    data = np.ascontiguousarray(x, dtype=dtype)
    if nulls is None:
        return pa.Array.from_buffers(typ, data.shape[0], [None, pa.py_buffer(data)])
    valid = pa.py_buffer(np.packbits(~nulls, bitorder="little"))
    return pa.Array.from_buffers(typ, data.shape[0], [valid, pa.py_buffer(data)],
                                 null_count=int(np.count_nonzero(nulls)))


def _table(cols: Columns, sch: Any, csv: bool = False) -> Any:
    """The pyarrow table of one chunk (NaN as null). ``csv``: the table to write as CSV —
    integral float columns as int64 (:data:`CSV_INT_MAX`: the same text, written faster;
    sensor channels with a whole-number resolution, such as pressures in Pa, are)."""
    pa = _pa()
    arrays = []
    for field in sch:
        x = cols[field.name]
        nan = np.isnan(x) if x.dtype == np.float64 else None
        if nan is not None and not nan.any():
            nan = None
        if csv and x.dtype == np.float64 and _integral(x, nan):
            k = (x if nan is None else np.where(nan, 0.0, x)).astype(np.int64)
            arrays.append(_array(k, pa.int64(), nan))
        else:
            arrays.append(_array(x, field.type, nan))
    if csv:
        return pa.Table.from_arrays(arrays, names=sch.names)
    return pa.Table.from_arrays(arrays, schema=sch)


class _Failed:
    def __init__(self, exc: BaseException) -> None:
        self.exc = exc


_DONE = object()


def prefetched(chunks: Iterator[Columns], depth: int = 2) -> Iterator[Columns]:
    """``chunks`` produced in a thread, ≤ ``depth`` ahead of the consumer: reading and decoding
    the next chunk (numpy, zlib and the database driver release the GIL) overlaps encoding
    this one. Closing the iterator (a client that went away) stops the thread."""
    q: queue.Queue[Any] = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def put(x: Any) -> bool:
        while not stop.is_set():
            try:
                q.put(x, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def run() -> None:
        try:
            for c in chunks:
                if not put(c):
                    return
            put(_DONE)
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer
            put(_Failed(exc))
        finally:
            close = getattr(chunks, "close", None)
            if close is not None:
                close()

    t = threading.Thread(target=run, name="export-prefetch", daemon=True)
    t.start()
    try:
        while True:
            x = q.get()
            if x is _DONE:
                return
            if isinstance(x, _Failed):
                raise x.exc
            yield x
    finally:
        stop.set()
        t.join(timeout=10.0)


def encode(chunks: Iterator[Columns], sch: Any, fmt: str) -> Iterator[bytes]:
    """The bytes of a CSV or Parquet file of ``chunks`` (columns of ``sch``), one piece per
    chunk: CSV with one header line, Parquet with one row group per chunk (a file with the
    schema and no rows when there is no chunk). Floats are written exactly (CSV: the
    shortest text that reads back to the same float64)."""
    if fmt == "csv":
        pacsv = _pa_module("csv")
        header = True
        for cols in chunks:
            buf = io.BytesIO()
            pacsv.write_csv(_table(cols, sch, csv=True), buf,
                            pacsv.WriteOptions(include_header=header))
            header = False
            yield buf.getvalue()
        if header:
            yield (",".join(f'"{n}"' for n in sch.names) + "\n").encode()
        return
    pq = _pa_module("parquet")
    sink = _Sink()
    # no dictionary pages: sensor columns rarely repeat, and dictionary attempts halve the speed
    with pq.ParquetWriter(sink, sch, compression="zstd", compression_level=1,
                          use_dictionary=False) as writer:
        for cols in chunks:
            writer.write_table(_table(cols, sch))
            out = sink.take()
            if out:
                yield out
    yield sink.take()


@dataclass(frozen=True)
class Export:
    """A streamed export: ``body`` yields the file's bytes (consume it once)."""

    filename: str
    media_type: str
    body: Iterator[bytes]


def export(series: str, fmt: str, machine: Machine, machine_id: str, rng: TimeRange,
           chunks: Callable[[], Iterator[Columns]]) -> Export:
    """The :class:`Export` of ``chunks()`` (the chunk source of ``series``), checked first."""
    check(series, fmt)
    sch = schema(series, machine)
    stamp = f"{int(rng.t0_s)}-{int(math.ceil(rng.t1_s))}"
    name = f"{machine_id}-{series}-{stamp}.{fmt}"
    return Export(name, MEDIA_TYPES[fmt], encode(chunks(), sch, fmt))


def export_series(fleet: FleetService, rec: MachineRecord, rng: TimeRange, series: str,
                  fmt: str) -> Export:
    """The export of ``series`` of machine ``rec`` over [from, to) as ``fmt`` (any range: the
    body is produced chunk by chunk while it is sent).

    Raises:
        InvalidRequestError: Unknown series or format.
        MissingExtraError: pyarrow is missing.
    """
    check(series, fmt)
    backend = fleet.backend
    machine = backend.model_of(rec)
    mid = rec.machine_id
    s = fleet.settings

    def chunks() -> Iterator[Columns]:
        if series == "raw":
            return prefetched(raw_chunks(backend, machine, mid, rng, s.nominal_rate_hz,
                                         CHUNK_SAMPLES))
        if series == "cycles":
            from cranetwin.service.analytics import analytics_report

            return cycle_chunks(analytics_report(backend, fleet.replayer, machine, mid, rng,
                                                 s.twin_margin_s, s.max_analytics_range_s))
        if series == "events":
            from cranetwin.service.queries import event_pages

            return event_chunks(event_pages(backend, mid, rng))
        return twin_chunks(backend, fleet.replayer, machine, mid, rng, series,
                           s.twin_margin_s)

    return export(series, fmt, machine, mid, rng, chunks)
