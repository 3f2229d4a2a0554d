"""Query parameters shared by the routes: the ``from``/``to`` range as a typed dependency."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Query

from cranetwin.service.timerange import TimeRange

AFTER_FROM = ("must be after `from`: a range with `to` ≤ `from` is answered 422 (JSON Schema "
              "cannot relate two parameters, so the schema alone does not say it)")
"""The rule of every ``from``/``to`` pair, in each ``to`` parameter's description."""

TIME_DESCRIPTION = ("ISO 8601 with zone (`2026-11-23T10:42:00Z`; no zone = UTC) or epoch seconds "
                    "(`1795430520.5`) [s]")


def time_range(
    from_: Annotated[str, Query(alias="from", description=f"Start of the range: {TIME_DESCRIPTION}",
                                examples=["2026-11-23T10:42:00Z"], max_length=64)],
    to: Annotated[str, Query(description=f"End of the range (exclusive): {TIME_DESCRIPTION}; "
                             f"{AFTER_FROM}",
                             examples=["2026-11-23T10:43:00Z"], max_length=64)],
) -> TimeRange:
    """Dependency: the ``from``/``to`` query parameters as a validated :class:`TimeRange`."""
    return TimeRange.parse(from_, to)


RangeDep = Annotated[TimeRange, Depends(time_range)]
