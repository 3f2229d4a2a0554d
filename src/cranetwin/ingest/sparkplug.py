"""Sample blocks ↔ Sparkplug B payloads (docs/INGEST.md, "MQTT / Sparkplug B"); pure functions.

A machine publishes one block per ``DDATA`` message on ``spBv1.0/<group>/DDATA/<edge
node>/<machine id>``. Its Sparkplug B payload (the Eclipse Tahu protobuf) carries:

* ``payload.seq``: the Sparkplug sequence number (0‥255, per edge node); decoded, but not
  the block's identity (nothing checks its gaps: identity and order are ``block/seq``'s);
* ``payload.timestamp``: when the message was built [ms since the Unix epoch];
* four ``UInt64`` metrics naming the block as the UDP path does: ``block/epoch`` (the sender's
  epoch, 1 ‥ 2**63 − 1), ``block/seq`` (the block's sequence number in that epoch),
  ``block/t0_ns`` (first sample [ns since the Unix epoch]) and ``block/period_ns`` [ns];
* one ``DoubleArray`` metric per channel of the machine description, named after the channel:
  the block's samples in channel units, IEEE 754 float64 little endian as Sparkplug 3.0 packs
  arrays, NaN for a missing sample. A channel left out (or sent with ``is_null``) is missing;
  only optional channels may be left out.

Why per-channel arrays and not one ``DataSet`` or one metric value per sample: arrays are the
Sparkplug 3.0 form for a run of values of one metric (Tahu's ``array_packer``, Ignition 8.1
array tags); a 100-sample block of the PATU 655 (11 channels) is 9.1 kB as arrays, 13.4 kB as
a DataSet (a protobuf message per cell) and 24 kB as per-sample metric values (32 kB with
names instead of aliases); and a channel decodes with one ``numpy.frombuffer`` instead of a
Python loop per cell. Sparkplug timestamps are milliseconds; the block's own times travel in
nanoseconds in ``block/t0_ns`` and ``block/period_ns`` so a 1 kHz stream keeps its exact clock.

``DBIRTH`` declares the device's metrics with their aliases; a ``DDATA`` may then name a metric
by alias only (:func:`birth_aliases`, :func:`encode_birth`).

Values are quantised to the channel's resolution on decoding (k = round(v / resolution)), so
what storage keeps is what the UDP path would have kept for the same sensor readings.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from cranetwin import codec
from cranetwin.errors import MissingExtraError, ProtocolError
from cranetwin.protocol import Layout, Limits
from cranetwin.samples import SampleBlock

NAMESPACE = "spBv1.0"
EPOCH, SEQ, T0, PERIOD = "block/epoch", "block/seq", "block/t0_ns", "block/period_ns"
BLOCK_METRICS = (EPOCH, SEQ, T0, PERIOD)
REBIRTH = "Node Control/Rebirth"
UINT64, BOOLEAN, DOUBLE_ARRAY = 8, 11, 31
"""Sparkplug B ``DataType`` codes (Tahu ``sparkplug_b.proto``)."""
MAX_SAMPLES = 100_000
"""Most samples one DDATA may carry (storage's block limit is 6 h; this bounds memory)."""
INT63 = 2**63 - 1


class SparkplugError(ProtocolError):
    """A Sparkplug message that cannot become a block (counted by ``reason``, never stored).

    Attributes:
        reason: ``bad_topic``, ``bad_payload``, ``unknown_alias``, ``out_of_range``,
            ``bad_time`` — the counter it is counted under.
    """

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


def pb() -> Any:
    """Tahu's ``sparkplug_b_pb2`` module, or MissingExtraError naming the ``mqtt`` extra."""
    try:
        from tahutils.tahu import sparkplug_b_pb2
    except ImportError as exc:
        raise MissingExtraError("mqtt", "Sparkplug B payloads") from exc
    return sparkplug_b_pb2


@dataclass(frozen=True)
class Topic:
    """A Sparkplug B topic ``spBv1.0/<group>/<type>/<edge node>[/<device>]``."""

    group: str
    kind: str
    edge_node: str
    device: str = ""

    def __str__(self) -> str:
        tail = f"/{self.device}" if self.device else ""
        return f"{NAMESPACE}/{self.group}/{self.kind}/{self.edge_node}{tail}"


def parse_topic(topic: str) -> Topic:
    """The parts of a Sparkplug B topic.

    Raises:
        SparkplugError: not ``spBv1.0/<group>/<type>/<edge node>[/<device>]`` (``bad_topic``).
    """
    parts = topic.split("/")
    if len(parts) not in (4, 5) or parts[0] != NAMESPACE or not all(parts[1:]):
        raise SparkplugError("bad_topic", f"not a Sparkplug B topic: {topic[:200]!r}")
    return Topic(parts[1], parts[2], parts[3], parts[4] if len(parts) == 5 else "")


def encode_ddata(block: SampleBlock, spb_seq: int, timestamp_ms: int,
                 aliases: Mapping[str, int] | None = None) -> bytes:
    """The DDATA payload of ``block`` (see the module docstring).

    Args:
        block: Samples of one machine; ``epoch``, ``seq``, ``t0_ns`` and ``period_ns`` set.
        spb_seq: Sparkplug sequence number of the message (0‥255).
        timestamp_ms: Time the message is built [ms since the Unix epoch].
        aliases: Metric name → alias declared in the DBIRTH; metrics then carry the alias
            only (None: names only).
    """
    p = pb().Payload()
    p.timestamp = timestamp_ms
    p.seq = spb_seq % 256
    names: list[str] = [*BLOCK_METRICS, *block.channels]
    ts = block.t0_ns // 1_000_000
    for name in names:
        m = p.metrics.add()
        if aliases is not None and name in aliases:
            m.alias = aliases[name]
        else:
            m.name = name
        m.timestamp = ts
    ids = (block.epoch, block.seq, block.t0_ns, block.period_ns)
    for m, v in zip(p.metrics[:4], ids, strict=True):
        m.datatype = UINT64
        m.long_value = int(v)
    cols = np.ascontiguousarray(np.asarray(block.values, dtype="<f8").T)
    for m, col in zip(p.metrics[4:], cols, strict=True):
        m.datatype = DOUBLE_ARRAY
        m.bytes_value = col.tobytes()
    return bytes(p.SerializeToString())


def encode_birth(layout: Layout, spb_seq: int, timestamp_ms: int,
                 aliases: Mapping[str, int]) -> bytes:
    """A DBIRTH payload declaring the block metrics and every channel, each with its alias
    from ``aliases`` (name → alias) where given."""
    p = pb().Payload()
    p.timestamp = timestamp_ms
    p.seq = spb_seq % 256
    for name in (*BLOCK_METRICS, *layout.names):
        m = p.metrics.add()
        m.name = name
        if name in aliases:
            m.alias = aliases[name]
        m.timestamp = timestamp_ms
        if name in BLOCK_METRICS:
            m.datatype, m.long_value = UINT64, 0
        else:
            m.datatype, m.bytes_value = DOUBLE_ARRAY, b""
    return bytes(p.SerializeToString())


def encode_rebirth(timestamp_ms: int) -> bytes:
    """The NCMD payload asking an edge node to publish its births again."""
    p = pb().Payload()
    p.timestamp = timestamp_ms
    m = p.metrics.add()
    m.name, m.datatype, m.boolean_value = REBIRTH, BOOLEAN, True
    return bytes(p.SerializeToString())


def _parse(payload: bytes) -> Any:
    try:
        p = pb().Payload()
        p.ParseFromString(payload)
    except MissingExtraError:
        raise
    except Exception as exc:  # protobuf's DecodeError and friends
        raise SparkplugError("bad_payload", f"not a Sparkplug B payload: {exc}") from exc
    return p


def birth_aliases(payload: bytes) -> dict[int, str]:
    """Alias → metric name of the metrics a DBIRTH (or NBIRTH) declares with an alias.

    Raises:
        SparkplugError: not a Sparkplug B payload (``bad_payload``).
    """
    return {int(m.alias): str(m.name) for m in _parse(payload).metrics
            if m.name and m.HasField("alias")}


@dataclass(frozen=True)
class DData:
    """One DDATA as sent: the block's identity and its values, not yet on the sensor grid.

    Attributes:
        values: Shape (n, len(layout.channels)) [channel units], NaN = missing.
        spb_seq: The Sparkplug sequence number of the message (0‥255).
    """

    machine_id: str
    epoch: int
    seq: int
    t0_ns: int
    period_ns: int
    values: npt.NDArray[np.float64]
    spb_seq: int


def parse_ddata(payload: bytes, machine_id: str, layout: Layout,
                aliases: Mapping[int, str] | None = None) -> DData:
    """The identity and values of a DDATA payload, in ``layout``'s column order.

    Args:
        payload: The message body.
        machine_id: The device id of the topic (the machine as registered).
        layout: The machine's channel layout (its description).
        aliases: Alias → name learnt from the device's DBIRTH.

    Raises:
        SparkplugError: ``bad_payload`` (malformed, block metrics missing or of the wrong
            type, arrays of unequal length, a non-optional channel missing, an unknown
            channel), ``unknown_alias`` (an alias no DBIRTH declared: ask for a rebirth).
    """
    p = _parse(payload)
    ids: dict[str, int] = {}
    cols: dict[str, Any] = {}
    for m in p.metrics:
        name = m.name
        if not name and m.HasField("alias"):
            name = (aliases or {}).get(int(m.alias), "")
            if not name:
                raise SparkplugError("unknown_alias", f"metric alias {m.alias} of "
                                     f"{machine_id!r} was not declared in a DBIRTH")
        if name in BLOCK_METRICS:
            if m.datatype not in (UINT64, 4) or m.WhichOneof("value") != "long_value":
                raise SparkplugError("bad_payload", f"metric {name} must be a UInt64 value")
            ids[name] = int(m.long_value)
        elif m.datatype == DOUBLE_ARRAY:
            cols[name] = None if m.is_null else m.bytes_value
    missing = [n for n in BLOCK_METRICS if n not in ids]
    if missing:
        raise SparkplugError("bad_payload", f"DDATA of {machine_id!r} without {missing}")
    unknown = sorted(set(cols) - set(layout.names))
    if unknown:
        raise SparkplugError("bad_payload", f"channels {unknown} are not in the machine "
                             f"description of {machine_id!r}")
    return DData(machine_id, ids[EPOCH], ids[SEQ], ids[T0], ids[PERIOD],
                 _columns(cols, layout, machine_id), int(p.seq))


def on_grid(items: Sequence[DData], layout: Layout) -> list[SampleBlock | SparkplugError]:
    """The blocks of ``items`` (all of ``layout``), quantised to the channel resolutions
    (k = round(v / resolution); :func:`cranetwin.codec.quantise`) in one pass over all of
    them; an item whose values cannot be quantised (infinite, beyond 2**53 steps) gives an
    ``out_of_range`` error in its place."""
    if not items:
        return []
    res = layout.resolutions
    try:
        k, mask = codec.quantise(np.concatenate([d.values for d in items]), res)
    except codec.QuantiseError as exc:
        if len(items) > 1:
            return [r for d in items for r in on_grid([d], layout)]
        return [SparkplugError("out_of_range", f"DDATA of {items[0].machine_id!r}: {exc}")]
    values = codec.dequantise(k, mask if mask.any() else None, res)
    out: list[SampleBlock | SparkplugError] = []
    a = 0
    for d in items:
        b = a + d.values.shape[0]
        out.append(SampleBlock(d.machine_id, d.seq, d.t0_ns, d.period_ns, layout.names, res,
                               values[a:b], epoch=d.epoch, steps=k[a:b]))
        a = b
    return out


def decode_ddata(payload: bytes, machine_id: str, layout: Layout,
                 aliases: Mapping[int, str] | None = None) -> tuple[SampleBlock, int]:
    """The block of a DDATA payload (:func:`parse_ddata`, :func:`on_grid`) and its Sparkplug seq.

    Raises:
        SparkplugError: as :func:`parse_ddata`, or ``out_of_range`` (values that cannot be
            quantised).
    """
    d = parse_ddata(payload, machine_id, layout, aliases)
    block = on_grid([d], layout)[0]
    if isinstance(block, SparkplugError):
        raise block
    return block, d.spb_seq


def _columns(cols: Mapping[str, bytes | None], layout: Layout,
             machine_id: str) -> npt.NDArray[np.float64]:
    lengths = {len(b) for b in cols.values() if b is not None}
    if len(lengths) != 1 or 0 in lengths or next(iter(lengths)) % 8:
        raise SparkplugError("bad_payload", f"DDATA of {machine_id!r}: channel arrays must be "
                             f"non-empty float64 arrays of one length, got byte lengths "
                             f"{sorted(lengths)}")
    n = next(iter(lengths)) // 8
    if n > MAX_SAMPLES:
        raise SparkplugError("bad_payload", f"{n} samples in one DDATA; at most {MAX_SAMPLES}")
    raws: list[bytes] = []
    for ch in layout.channels:
        raw = cols.get(ch.name)
        if raw is None:
            if not ch.optional:
                raise SparkplugError("bad_payload", f"DDATA of {machine_id!r} lacks channel "
                                     f"{ch.name!r}")
            raw = _nan_bytes(n)
        raws.append(raw)
    return np.frombuffer(b"".join(raws), dtype="<f8").reshape(len(raws), n).T.astype(np.float64)


@functools.lru_cache(maxsize=64)
def _nan_bytes(n: int) -> bytes:
    return np.full(n, np.nan, dtype="<f8").tobytes()


@functools.lru_cache(maxsize=256)
def _bounds(layout: Layout, margin: float) -> tuple[npt.NDArray[np.float64],
                                                    npt.NDArray[np.float64]]:
    """Accepted value range per channel: ``[min, max]`` widened by ``margin`` of the span."""
    lo = np.array([c.min for c in layout.channels])
    hi = np.array([c.max for c in layout.channels])
    span = (hi - lo) * margin
    return lo - span, hi + span


def limits_problem(block: SampleBlock, layout: Layout, limits: Limits,
                   now_ns: int) -> SparkplugError | None:
    """Why ``block`` is refused at the edge, or None (:func:`limits_problems` of one)."""
    return limits_problems([block], layout, limits, now_ns)[0]


def limits_problems(blocks: Sequence[SampleBlock], layout: Layout, limits: Limits,
                    now_ns: int) -> list[SparkplugError | None]:
    """Per block of ``layout``, why it is refused at the edge, or None: the checks the UDP
    receiver applies (:class:`~cranetwin.protocol.Limits`: times within ``[now − max_past,
    now + max_future]``, every value within its channel's ``[min, max]`` plus
    ``range_margin`` of the span) and the identity ranges (epoch 1 ‥ 2**63 − 1,
    seq < 2**63, period ≥ 1 ns). The values of all blocks are checked in one pass."""
    if not blocks:
        return []
    lo, hi = _bounds(layout, limits.range_margin)
    v = np.concatenate([b.values for b in blocks])
    bad_rows = ((v < lo) | (v > hi)).any(axis=1)
    starts = np.cumsum([0] + [b.n for b in blocks[:-1]])
    bad_blocks = np.logical_or.reduceat(bad_rows, starts)
    lo_t = max(now_ns - int(limits.max_past_s * 1e9), 0)
    hi_t = now_ns + int(limits.max_future_s * 1e9)
    out: list[SparkplugError | None] = []
    for b, bad in zip(blocks, bad_blocks, strict=True):
        if not (1 <= b.epoch <= INT63 and 0 <= b.seq <= INT63 and b.period_ns >= 1
                and 0 <= b.t0_ns <= INT63):
            out.append(SparkplugError("bad_payload", f"epoch {b.epoch}, seq {b.seq}, period "
                                      f"{b.period_ns} ns or t0 {b.t0_ns} ns out of range"))
        elif b.t0_ns < lo_t or b.t_end_ns > hi_t:
            out.append(SparkplugError(
                "bad_time", f"times {b.t0_ns}…{b.t_end_ns} ns outside [now − "
                f"{limits.max_past_s:g} s, now + {limits.max_future_s:g} s]"))
        elif bad:
            with np.errstate(invalid="ignore"):
                cols = ((b.values < lo) | (b.values > hi)).any(axis=0)
            ch = layout.channels[int(np.flatnonzero(cols)[0])]
            out.append(SparkplugError(
                "out_of_range", f"channel {ch.name!r}: value outside [{ch.min:g}, {ch.max:g}] "
                f"+ {limits.range_margin:.0%} margin"))
        else:
            out.append(None)
    return out


def aliases_for(names: Sequence[str]) -> dict[str, int]:
    """Aliases 1, 2, … for ``names`` in order (what :func:`encode_birth` declares)."""
    return {n: i + 1 for i, n in enumerate(names)}
