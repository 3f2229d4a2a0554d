"""Data of one machine over a time range: samples, twin replay, load history, events, find."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, Query, Request
from fastapi.responses import Response, StreamingResponse

from cranetwin.api.deps import CurrentKey, FleetKey, MachineDep, ServicesDep
from cranetwin.api.errors import PROBLEM_RESPONSES
from cranetwin.api.limits import run_heavy, stream_heavy
from cranetwin.api.params import RangeDep
from cranetwin.api.schemas import EventOut, FindOut, HistoryOut, SamplesPage, TwinOut

JSON = "application/json"

router = APIRouter(prefix="/api/v1/machines/{machine_id}", tags=["data"],
                   responses=PROBLEM_RESPONSES)


@router.get("/samples", response_model=SamplesPage, summary="Raw samples (paginated)")
def get_samples(
    key: CurrentKey, machine: MachineDep, services: ServicesDep, rng: RangeDep,
    limit: Annotated[int, Query(ge=1, le=100_000, description="samples per page (at most "
                                "CRANETWIN_MAX_SAMPLES_LIMIT, 10000)")] = 1000,
    cursor: Annotated[str | None, Query(max_length=64, description="next_cursor of the "
                                        "previous page")] = None,
) -> SamplesPage:
    """Stored samples in [from, to), oldest first, ``limit`` per page; follow ``next_cursor``."""
    page = services.fleet.samples_page(machine, rng, limit, cursor)
    return SamplesPage(channels=page.channels, t=page.t, values=page.values,
                       next_cursor=page.next_cursor)


@router.get("/twin", response_model=TwinOut, summary="Twin replay of a window")
async def get_twin(
    key: CurrentKey, machine: MachineDep, services: ServicesDep, rng: RangeDep,
    rate_hz: Annotated[float, Query(gt=0, le=1000, description="output rate [Hz]",
                                    examples=[50])] = 50.0,
) -> Response:
    """Joint coordinates, body poses, tip path, cylinder pins and forces (Eq. 1–2), joint
    torques and reaction wrenches (inverse dynamics), payload estimate — for [from, to) at
    ``rate_hz``. At most CRANETWIN_MAX_TWIN_RANGE_S (120 s) and 12000 output samples per call;
    results of windows that end before the newest stored data are cached per (machine,
    known-payload version, late-data version, window, rate): a payload stored or deleted, late
    samples stored into a past window, data dropped by retention are replayed at the next call.
    A heavy request (rate limit and heavy threads:
    docs/API.md "Service limits")."""
    from cranetwin.service import heavyproc

    fleet = services.fleet
    cache_key = fleet.twin_key(machine, rng, rate_hz)
    if cache_key is not None:
        cached = fleet.twin_cache.get(cache_key)
        if cached is not None:
            return Response(cached, media_type=JSON)
    body = await run_heavy(services, key, fleet.twin_body, machine, rng, rate_hz,
                           process_fn=heavyproc.twin_body)
    if cache_key is not None:
        fleet.twin_cache.put(cache_key, body)
    return Response(body, media_type=JSON)


@router.get("/history", response_model=HistoryOut, summary="Load history (min/max/mean)")
def get_history(
    key: CurrentKey, machine: MachineDep, services: ServicesDep, rng: RangeDep,
    channels: Annotated[str, Query(max_length=2000, description="comma-separated channel "
                                   "names: raw (`lift_pA`) or derived (`force:lift`, `payload`, "
                                   "`moment:theta1`, `working`)",
                                   examples=["lift_pA,force:lift,payload"])],
    max_points: Annotated[int, Query(ge=1, le=100_000, description="most buckets per channel "
                                     "(≤ CRANETWIN_MAX_HISTORY_POINTS, 10000)")] = 2000,
) -> Response:
    """Min/max/mean per bucket from the stored per-interval summaries (never from raw samples);
    buckets are whole summary intervals, at most ``max_points`` of them per channel."""
    return Response(services.fleet.history(machine, rng, channels, max_points), media_type=JSON)


@router.get("/events", response_model=list[EventOut], summary="Events in a range (paged)",
            responses={200: {"headers": {"Link": {
                "description": 'next page: `<url>; rel="next"` (absent on the last)',
                "schema": {"type": "string"}}}}})
def get_events(
    key: CurrentKey, machine: MachineDep, services: ServicesDep, rng: RangeDep,
    request: Request, response: Response,
    severity: Annotated[str | None, Query(max_length=100, description="keep these "
                                          "severities, comma-separated: info, warning, "
                                          "critical", examples=["critical"])] = None,
    kind: Annotated[str | None, Query(max_length=1000, description="keep these kinds, "
                                      "comma-separated", examples=["overload"])] = None,
    limit: Annotated[int, Query(ge=1, le=10_000, description="events per page")] = 1000,
    cursor: Annotated[str | None, Query(max_length=64, description="continue after the "
                                        "previous page (from its `Link: rel=next`)")] = None,
) -> list[EventOut]:
    """Stored events (overload, end-stop impact, over-pressure, …) in [from, to), oldest first,
    filtered by severity and kind, ``limit`` per page; the ``Link`` header names the next."""
    from cranetwin.service.events import readable_message
    from cranetwin.service.queries import events_page

    def names(text: str | None) -> list[str] | None:
        return None if text is None else [n.strip() for n in text.split(",") if n.strip()]

    page = events_page(services.backend, machine.machine_id, rng, kinds=names(kind),
                       severities=names(severity), limit=limit, cursor=cursor)
    if page.next_cursor is not None:
        nxt = request.url.remove_query_params(["cursor", "key"]).include_query_params(
            cursor=page.next_cursor)
        response.headers["Link"] = f'<{nxt}>; rel="next"'
    return [EventOut(**{**e, "message": readable_message(e["kind"], e.get("evidence") or {},
                                                        str(e.get("message", "")))})
            for e in page.events]


@router.get("/export", summary="Export raw or derived series as CSV or Parquet (fleet)",
            responses={200: {"content": {"text/csv": {}, "application/vnd.apache.parquet": {}},
                             "description": "the series as a file, streamed"}},
            response_class=StreamingResponse)
async def export_series(
    key: FleetKey, machine: MachineDep, services: ServicesDep, rng: RangeDep,
    series: Annotated[Literal["raw", "forces", "joint_loads", "payload", "cycles", "events"],
                      Query(description="raw samples, twin series (cylinder forces, joint "
                                        "loads, payload), work cycles or events")] = "raw",
    format: Annotated[Literal["csv", "parquet"], Query(description="file format")] = "csv",
) -> StreamingResponse:
    """Any range of one series as CSV or Parquet, produced chunk by chunk while it is sent
    (never the whole range in memory), on a heavy thread. Columns: docs/API.md "Export"."""
    from cranetwin.service.export import Export
    from cranetwin.service.export import export_series as run

    def start() -> Export:
        return run(services.fleet, machine, rng, series, format)

    exp, body = await stream_heavy(services, key, start, lambda e: e.body)
    return StreamingResponse(body, media_type=exp.media_type, headers={
        "Content-Disposition": f'attachment; filename="{exp.filename}"'})


@router.get("/find", response_model=FindOut, summary="Find the moment a condition held")
def find_moment(
    key: CurrentKey, machine: MachineDep, services: ServicesDep, rng: RangeDep,
    channel: Annotated[str, Query(max_length=100, description="raw or derived channel",
                                  examples=["force:lift"])],
    op: Annotated[Literal["gt", "lt"], Query(description="gt: value above; lt: below")],
    value: Annotated[float, Query(description="threshold in the channel's unit",
                                  examples=[60000.0], allow_inf_nan=False)],
    which: Annotated[Literal["first", "last"], Query(description="earliest or latest")] = "first",
) -> FindOut:
    """When ``channel`` first (last) went above (``gt``) or below (``lt``) ``value`` in
    [from, to): from the summaries, refined to the exact sample for raw channels."""
    hit = services.fleet.find(machine, rng, channel, op, value, which)
    return FindOut(t=hit.t, value=hit.value)


@router.get("/analytics", summary="Load spectrum, damage, duty class, productivity (fleet)",
            response_model=dict[str, Any])
async def get_analytics(key: FleetKey, machine: MachineDep, services: ServicesDep,
                        rng: RangeDep) -> dict[str, Any]:
    """Analytics of [from, to) from the derived history: load spectrum, Miner damage, duty
    class and productivity (a heavy request)."""
    return await run_heavy(services, key, services.fleet.analytics, machine, rng)


@router.get("/report", summary="Report download (fleet)",
            responses={200: {"content": {"application/pdf": {}, "application/zip": {},
                                         "text/csv": {}, "text/html": {}},
                             "description": "the report file (csv: a zip of CSV tables; "
                                            "a single CSV when the range holds no samples)"}},
            response_class=Response)
async def get_report(
    key: FleetKey, machine: MachineDep, services: ServicesDep, rng: RangeDep,
    format: Annotated[Literal["pdf", "csv", "html"], Query(description="file format")] = "pdf",
) -> Response:
    """The maintenance report of [from, to) (cranetwin.reports): load spectra, damage and
    remaining life, duty class, events, productivity — as PDF, HTML or a zip of CSV tables."""
    from cranetwin.reports import render

    rep = await run_heavy(services, key, services.fleet.report, machine, rng, format, render)
    return Response(rep.body, media_type=rep.media_type,
                    headers={"Content-Disposition": f'attachment; filename="{rep.filename}"'})
