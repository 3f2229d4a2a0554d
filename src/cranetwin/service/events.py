"""Events as people read them: quantities in the unit a crane operator uses, with its prefix and
a sensible number of digits ("28.4 kN·m", "212 bar", "0.74 rad/s"), never "2.84e+04 N*m".

:func:`format_quantity` formats one value; :func:`event_message` is the one-line text of an
event from its evidence (kind, component, value, limit, unit). The API rewrites the message of
every event it returns with it (stored events keep their evidence in SI units).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from datetime import UTC, datetime
from typing import Any

_PREFIXED = {"N*m": "N·m", "N·m": "N·m", "Nm": "N·m", "N": "N", "N/s": "N/s", "W": "W"}


def _number(v: float) -> str:
    """3 significant digits (all digits of the integer part from 1000 on), never an exponent."""
    a = abs(v)
    if a >= 1000:
        return f"{v:.0f}"
    if a < 0.001:
        return "0"
    text = f"{v:.3g}"
    return f"{v:.0f}" if "e" in text else text


def format_quantity(value: float, unit: str) -> str:
    """``value`` [``unit``, SI] as text with a fitting prefix or unit.

    N, N·m, N/s and W get k/M prefixes; Pa is shown in bar; kg above a tonne in t; a ratio
    (unit ``""``, ``"1"`` or ``"ratio"``) in %; ``*`` becomes ``·``. Non-finite values are
    ``"–"``.
    """
    if not math.isfinite(value):
        return "–"
    if unit in _PREFIXED:
        base = _PREFIXED[unit]
        a = abs(value)
        for scale, prefix in ((1e6, "M"), (1e3, "k")):
            if a >= scale:
                return f"{_number(value / scale)} {prefix}{base}"
        return f"{_number(value)} {base}"
    if unit == "Pa":
        return f"{_number(value / 1e5)} bar"
    if unit == "kg":
        return f"{_number(value / 1000)} t" if abs(value) >= 1000 else f"{value:.0f} kg"
    if unit in ("", "1", "ratio"):
        return f"{_number(value * 100)} %"
    return f"{_number(value)} {unit.replace('*', '·')}".rstrip()


def format_duration(seconds: float) -> str:
    """A duration [s] as people say it: ``"45 s"``, ``"3 min 20 s"``, ``"2 h 5 min"``,
    ``"3 d 4 h"`` (below 2 min in seconds; whole seconds; the smaller unit left out when 0).
    Non-finite or negative durations are ``"–"``."""
    if not math.isfinite(seconds) or seconds < 0:
        return "–"
    s = int(round(seconds))
    if s < 120:
        return f"{s} s"
    if s < 7200:
        m, r = divmod(s, 60)
        return f"{m} min {r} s" if r else f"{m} min"
    if s < 2 * 86400:
        h, r = divmod(s, 3600)
        return f"{h} h {r // 60} min" if r >= 60 else f"{h} h"
    d, r = divmod(s, 86400)
    return f"{d} d {r // 3600} h" if r >= 3600 else f"{d} d"


def format_time(t: float) -> str:
    """Epoch seconds as ``"2026-12-02 10:54:59 UTC"`` (whole seconds)."""
    return datetime.fromtimestamp(t, UTC).strftime("%Y-%m-%d %H:%M:%S UTC")


def event_message(kind: str, component: str, value: float, limit: float, unit: str) -> str:
    """``"slew overspeed on slew: 0.74 rad/s (limit 0.52 rad/s, 142 %)"``."""
    text = f"{kind.replace('_', ' ')} on {component}: {format_quantity(value, unit)} (limit " \
           f"{format_quantity(limit, unit)}"
    if limit and math.isfinite(value) and math.isfinite(limit):
        text += f", {_number(100 * value / limit)} % of it"
    return text + ")"


def readable_message(kind: str, evidence: Mapping[str, Any], stored: str) -> str:
    """The event's message from its evidence when that holds value, limit and unit (else the
    stored message unchanged)."""
    try:
        value = float(evidence["value"])
        limit = float(evidence["limit"])
        unit = str(evidence["unit"])
    except (KeyError, TypeError, ValueError):
        return stored
    return event_message(kind, str(evidence.get("component", "")) or "machine", value, limit,
                         unit)
