"""The mapping of a user's file onto a machine's channels (``--mapping MAP.toml``).

A mapping names, per channel of the machine description, the file's column, its unit and (for
rod positions) its convention; and how the file states time. Everything is optional: a channel
left out is read from a column of the channel's own name, in the channel's unit, as stroke
position; the time from a column ``t_s`` (or ``time``) in epoch seconds. See docs/IMPORT.md::

    [time]
    column = "timestamp"            # default "t_s", else "time"
    format = "iso8601"              # epoch_s | epoch_ms | epoch_us | epoch_ns | iso8601 |
                                    # relative_s (then `start`)
    start = "2026-03-02T06:00:00Z"  # epoch s or ISO 8601; only for relative_s
    period_s = 0.01                 # nominal sample period; default: median spacing
    jitter = 0.25                   # share of the period a spacing may deviate: beyond, a new run

    [csv]
    delimiter = ","

    [channels.lift_pA]
    column = "boom_pA"
    unit = "bar"                    # bar | MPa | kPa | Pa | psi; mm | cm | m | in; deg | rad; …

    [channels.lift_s]
    column = "boom_len"
    unit = "mm"
    convention = "pin_to_pin"       # or "stroke" (default)
    offset = 820.0                  # pin-to-pin length at zero stroke, in `unit`
                                    # (default: the cylinder's closed_length_m)

    [checks]
    range_tolerance = 0.0           # share of a channel's full range allowed beyond min/max

    [payload]                       # a known payload as a time series (not a sensor channel)
    column = "hook_load"
    unit = "kg"                     # kg | t
    max = 5000.0                    # largest accepted payload, in `unit` (default: 3 × the
                                    # machine's largest rated payload; none without a chart)
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import math
import tomllib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

from cranetwin.errors import CraneTwinError
from cranetwin.model import Machine


class ImportFileError(CraneTwinError):
    """A file cannot be imported as asked (unreadable, bad mapping, wrong convention); the
    message says what and where. Nothing of the file is stored when this is raised."""


TimeFormat = Literal["epoch_s", "epoch_ms", "epoch_us", "epoch_ns", "iso8601", "relative_s"]
TIME_FORMATS: tuple[str, ...] = ("epoch_s", "epoch_ms", "epoch_us", "epoch_ns", "iso8601",
                                 "relative_s")
Convention = Literal["stroke", "pin_to_pin"]

# unit → (dimension, factor to SI)
UNITS: dict[str, tuple[str, float]] = {
    "Pa": ("pressure", 1.0), "kPa": ("pressure", 1e3), "MPa": ("pressure", 1e6),
    "bar": ("pressure", 1e5), "mbar": ("pressure", 1e2), "psi": ("pressure", 6894.757293168361),
    "m": ("length", 1.0), "cm": ("length", 1e-2), "mm": ("length", 1e-3),
    "in": ("length", 0.0254),
    "rad": ("angle", 1.0), "deg": ("angle", math.pi / 180.0),
    "N*m": ("torque", 1.0), "N·m": ("torque", 1.0), "Nm": ("torque", 1.0),
    "kN*m": ("torque", 1e3), "kNm": ("torque", 1e3),
    "N": ("force", 1.0), "kN": ("force", 1e3),
    "kg": ("mass", 1.0), "t": ("mass", 1e3),
}


def unit_factor(from_unit: str, to_unit: str, where: str) -> float:
    """Factor that turns a value in ``from_unit`` into ``to_unit``.

    Raises:
        ImportFileError: An unknown unit, or units of different quantities.
    """
    if from_unit == to_unit:
        return 1.0
    a, b = UNITS.get(from_unit), UNITS.get(to_unit)
    if a is None or b is None:
        bad = from_unit if a is None else to_unit
        raise ImportFileError(f"{where}: unknown unit {bad!r}; known: {', '.join(UNITS)}")
    if a[0] != b[0]:
        raise ImportFileError(f"{where}: unit {from_unit!r} is a {a[0]}, the channel is in "
                              f"{to_unit!r} (a {b[0]})")
    return a[1] / b[1]


@dataclass(frozen=True)
class ChannelMap:
    """How one machine channel is read from the file.

    Attributes:
        channel: Channel name in the machine description.
        column: Column (CSV header, Parquet field, MDF channel name) in the file.
        unit: Unit of the column's values.
        convention: ``stroke`` (rod position s) or ``pin_to_pin`` (length L; s = L − offset).
        offset: Pin-to-pin length at zero stroke [``unit``]; None = the cylinder's
            ``closed_length_m``.
        scale: Factor from ``unit`` to the channel's unit (derived).
        shift: Added after scaling, in the channel's unit (derived: −offset for pin-to-pin).
    """

    channel: str
    column: str
    unit: str
    convention: Convention = "stroke"
    offset: float | None = None
    scale: float = 1.0
    shift: float = 0.0


@dataclass(frozen=True)
class Mapping:
    """A parsed mapping, resolved against one machine (see the module docstring).

    Attributes:
        channels: One entry per machine channel read from the file, machine order.
        time_column: The time column (None: ``t_s`` or ``time``, whichever the file has; MDF
            files use their master channel).
        time_format: See :data:`TIME_FORMATS`.
        start_s: Epoch time of relative time 0 [s] (``relative_s``).
        period_s: Nominal sample period [s], or None to take the median spacing.
        jitter: Share of the period one spacing may deviate before a new run starts.
        delimiter: CSV field separator.
        range_tolerance: Share of each channel's full range accepted beyond [min, max].
        payload_column: Column of a known payload [``payload_unit``] (None: none).
        payload_unit: Unit of that column (kg or t).
        payload_scale: Factor from ``payload_unit`` to kg (derived).
        payload_max_kg: Largest accepted payload [kg] as the mapping gives it (None: the
            default, :func:`cranetwin.importer.payload.payload_limit_kg`).
        source: Where the mapping came from (file path or ``<default>``).
        text: Canonical JSON of what the mapping said (part of the import's identity).
    """

    channels: tuple[ChannelMap, ...]
    time_column: str | None = None
    time_format: TimeFormat = "epoch_s"
    start_s: float | None = None
    period_s: float | None = None
    jitter: float = 0.25
    delimiter: str = ","
    range_tolerance: float = 0.0
    payload_column: str | None = None
    payload_unit: str = "kg"
    payload_scale: float = 1.0
    payload_max_kg: float | None = None
    source: str = "<default>"
    text: str = "{}"
    extra: dict[str, Any] = field(default_factory=dict)

    def identity(self) -> bytes:
        """Bytes that change whenever the mapping would change what is stored."""
        skip = ("source", "text", "extra", "payload_column", "payload_unit", "payload_scale",
                "payload_max_kg")
        d = {k: v for k, v in asdict(self).items() if k not in skip}  # the payload: not stored
        return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).digest()


def parse_time_text(text: str | float | int, where: str) -> float:
    """Epoch seconds from a number or ISO 8601 text (naive times are UTC)."""
    if isinstance(text, int | float):
        return float(text)
    try:
        return float(text)
    except ValueError:
        pass
    try:
        t = dt.datetime.fromisoformat(text)
    except ValueError as exc:
        raise ImportFileError(f"{where}: {text!r} is neither epoch seconds nor ISO 8601") from exc
    if t.tzinfo is None:
        t = t.replace(tzinfo=dt.UTC)
    return t.timestamp()


_TOP = {"time", "csv", "channels", "checks", "payload"}
_TIME = {"column", "format", "start", "period_s", "jitter"}
_CHAN = {"column", "unit", "convention", "offset"}


def _check_keys(d: dict[str, Any], allowed: set[str], where: str) -> None:
    extra = sorted(set(d) - allowed)
    if extra:
        raise ImportFileError(f"{where}: unknown key(s) {extra}; expected some of "
                              f"{sorted(allowed)}")


def load_mapping(source: str | Path | None, machine: Machine) -> Mapping:
    """Read a mapping TOML file (or the default mapping when None) for ``machine``.

    Raises:
        ImportFileError: Unreadable file, unknown keys, channels or units, bad values.
    """
    if source is None:
        return mapping_from_dict({}, machine)
    p = Path(source)
    try:
        data = tomllib.loads(p.read_text("utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise ImportFileError(f"{p}: cannot read the mapping: {exc}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ImportFileError(f"{p}: TOML syntax error: {exc}") from exc
    return mapping_from_dict(data, machine, str(p))


def mapping_from_dict(data: dict[str, Any], machine: Machine,
                      source: str = "<dict>") -> Mapping:
    """Validate a parsed mapping against ``machine`` (every problem names its key)."""
    _check_keys(data, _TOP, source)
    tm = dict(data.get("time", {}))
    _check_keys(tm, _TIME, f"{source}: [time]")
    fmt = str(tm.get("format", "epoch_s"))
    if fmt not in TIME_FORMATS:
        raise ImportFileError(f"{source}: time.format {fmt!r}; expected one of "
                              f"{', '.join(TIME_FORMATS)}")
    start = tm.get("start")
    start_s = None if start is None else parse_time_text(start, f"{source}: time.start")
    if fmt == "relative_s" and start_s is None:
        raise ImportFileError(f"{source}: time.format = \"relative_s\" needs time.start "
                              "(epoch seconds or ISO 8601 of relative time 0)")
    period = tm.get("period_s")
    if period is not None and not (isinstance(period, int | float) and period > 0):
        raise ImportFileError(f"{source}: time.period_s must be a number > 0, got {period!r}")
    jitter = tm.get("jitter", 0.25)
    if not (isinstance(jitter, int | float) and 0 < jitter < 0.5):
        raise ImportFileError(f"{source}: time.jitter must be in (0, 0.5), got {jitter!r}")
    csv_ = dict(data.get("csv", {}))
    _check_keys(csv_, {"delimiter"}, f"{source}: [csv]")
    delim = str(csv_.get("delimiter", ","))
    if len(delim) != 1:
        raise ImportFileError(f"{source}: csv.delimiter must be one character, got {delim!r}")
    checks = dict(data.get("checks", {}))
    _check_keys(checks, {"range_tolerance"}, f"{source}: [checks]")
    rtol = checks.get("range_tolerance", 0.0)
    if not (isinstance(rtol, int | float) and rtol >= 0):
        raise ImportFileError(f"{source}: checks.range_tolerance must be ≥ 0, got {rtol!r}")

    pay = dict(data.get("payload", {}))
    _check_keys(pay, {"column", "unit", "max"}, f"{source}: [payload]")
    pay_col = pay.get("column")
    if pay and not (isinstance(pay_col, str) and pay_col):
        raise ImportFileError(f"{source}: payload.column must name the file's payload column, "
                              f"got {pay_col!r}")
    pay_unit = str(pay.get("unit", "kg"))
    pay_scale = unit_factor(pay_unit, "kg", f"{source}: payload.unit")
    pay_max = pay.get("max")
    if pay_max is not None and not (isinstance(pay_max, int | float) and pay_max > 0
                                    and math.isfinite(pay_max)):
        raise ImportFileError(f"{source}: payload.max must be a number > 0 (in payload.unit), "
                              f"got {pay_max!r}")

    given = dict(data.get("channels", {}))
    known = {c.name: c for c in machine.channels}
    unknown = sorted(set(given) - set(known))
    if unknown:
        raise ImportFileError(f"{source}: [channels.{unknown[0]}]: machine {machine.name!r} has "
                              f"no channel {unknown[0]!r}; its channels: {', '.join(known)}")
    cyl = {c.name: c for c in machine.cylinders}
    maps: list[ChannelMap] = []
    for ch in machine.channels:
        spec = dict(given.get(ch.name, {}))
        where = f"{source}: channels.{ch.name}"
        _check_keys(spec, _CHAN, where)
        unit = str(spec.get("unit", ch.unit))
        scale = unit_factor(unit, ch.unit, f"{where}.unit")
        conv = str(spec.get("convention", "stroke"))
        if conv not in ("stroke", "pin_to_pin"):
            raise ImportFileError(f"{where}.convention: {conv!r}; expected \"stroke\" or "
                                  "\"pin_to_pin\"")
        offset = spec.get("offset")
        shift = 0.0
        if conv == "pin_to_pin":
            if ch.quantity != "position" or ch.source not in cyl:
                raise ImportFileError(f"{where}.convention: pin_to_pin applies to cylinder "
                                      f"position channels; {ch.name} is a {ch.quantity}")
            if offset is None:
                shift = -cyl[ch.source].closed_length_m * unit_factor("m", ch.unit, where)
            elif isinstance(offset, int | float):
                shift = -float(offset) * scale
            else:
                raise ImportFileError(f"{where}.offset must be a number, got {offset!r}")
        elif offset is not None:
            raise ImportFileError(f"{where}.offset is for convention = \"pin_to_pin\"")
        maps.append(ChannelMap(ch.name, str(spec.get("column", ch.name)), unit,
                               conv,  # type: ignore[arg-type]
                               None if offset is None else float(offset), scale, shift))
    return Mapping(
        channels=tuple(maps), time_column=None if tm.get("column") is None else str(tm["column"]),
        time_format=fmt,  # type: ignore[arg-type]
        start_s=start_s, period_s=None if period is None else float(period),
        jitter=float(jitter), delimiter=delim, range_tolerance=float(rtol),
        payload_column=None if pay_col is None else str(pay_col), payload_unit=pay_unit,
        payload_scale=pay_scale,
        payload_max_kg=None if pay_max is None else float(pay_max) * pay_scale, source=source,
        text=json.dumps(data, sort_keys=True, default=str))
