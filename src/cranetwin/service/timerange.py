"""Time ranges and time text of the service: epoch seconds in, ISO 8601 UTC out."""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import UTC, datetime

from cranetwin.service.errors import InvalidRequestError

_EPOCH_MIN = 0.0
_EPOCH_MAX = 253402300799.0  # 9999-12-31T23:59:59Z


def parse_time(value: str, name: str) -> float:
    """Seconds since the Unix epoch of an ISO 8601 string or a number.

    Raises:
        InvalidRequestError: ``value`` is neither, not finite, or outside years 1970–9999.
    """
    text = value.strip()
    try:
        t = float(text)
    except ValueError:
        try:
            dt = datetime.fromisoformat(text.replace("Z", "+00:00").replace("z", "+00:00"))
        except ValueError as exc:
            raise InvalidRequestError("Invalid time", f"{name}={value!r}: expected ISO 8601 "
                                      "(2026-11-23T10:42:00Z) or epoch seconds "
                                      "(1795430520.5)") from exc
        if dt.tzinfo is None:
            dt = dt.replace(tzinfo=UTC)
        try:
            t = dt.timestamp()
        except (OverflowError, OSError, ValueError) as exc:
            raise InvalidRequestError("Invalid time", f"{name}={value!r} is out of range") from exc
    if not math.isfinite(t) or not _EPOCH_MIN <= t <= _EPOCH_MAX:
        raise InvalidRequestError("Invalid time", f"{name}={value!r}: expected a finite time "
                                  "between 1970-01-01 and 9999-12-31")
    return t


def iso(t_s: float | None) -> str | None:
    """ISO 8601 UTC text of epoch seconds (millisecond precision), None stays None."""
    if t_s is None:
        return None
    return datetime.fromtimestamp(t_s, UTC).isoformat(timespec="milliseconds").replace(
        "+00:00", "Z")


@dataclass(frozen=True)
class TimeRange:
    """A half-open query range [t0_s, t1_s) in epoch seconds, t1_s > t0_s."""

    t0_s: float
    t1_s: float

    @staticmethod
    def parse(from_: str, to: str) -> TimeRange:
        """The range of two times given as text (:func:`parse_time`).

        Raises:
            InvalidRequestError: A time is invalid, or ``to`` is not after ``from_``.
        """
        t0, t1 = parse_time(from_, "from"), parse_time(to, "to")
        if not t1 > t0:
            raise InvalidRequestError("Invalid range", f"to ({to}) must be after from ({from_})")
        return TimeRange(t0, t1)

    @property
    def duration_s(self) -> float:
        """Length of the range [s]."""
        return self.t1_s - self.t0_s

    def limit(self, max_s: float, what: str) -> TimeRange:
        """This range, or :class:`InvalidRequestError` when longer than ``max_s`` seconds."""
        if self.duration_s > max_s:
            raise InvalidRequestError(
                "Range too long", f"{self.duration_s:.6g} s requested; {what} covers at most "
                f"{max_s:.6g} s per request (split the range)")
        return self
