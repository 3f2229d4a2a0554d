"""What the API (and any other front end) asks of the fleet: one object per process holding the
store adapter, the replayer, the replay cache, the live payload estimators and, when asked, the
twin worker.

Each capability returns plain data — dataclasses, dicts of arrays, pre-serialised JSON bytes —
and raises :mod:`cranetwin.service.errors` (or the replay's own errors); nothing here knows HTTP.
Machine status, samples paging, twin windows (cached), history from summaries, "find the
moment", events, analytics and reports, ISO 15143-3 snapshots; the queries that replay nothing
live in :mod:`cranetwin.service.queries`.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import orjson

from cranetwin.errors import CraneTwinError, TwinError
from cranetwin.model import Machine
from cranetwin.service import aemp
from cranetwin.service.backend import Backend, MachineRecord, Progress
from cranetwin.service.cache import LruCache
from cranetwin.service.errors import InvalidRequestError, NotFoundError
from cranetwin.service.live_payload import LivePayload, public_kg
from cranetwin.service.metrics import Metrics
from cranetwin.service.queries import (
    Moment,
    SamplesPage,
    check_channels,
    find_moment,
    samples_page,
)
from cranetwin.service.replayer import Replayer, sample_rate_hz
from cranetwin.service.timerange import TimeRange, iso
from cranetwin.service.views import twin_json
from cranetwin.service.worker import TwinWorker
from cranetwin.settings import Settings

log = logging.getLogger(__name__)

MAX_HISTORY_CHANNELS = 32
MAX_LIST_LIVE_PAYLOADS = 32
"""Live payload estimators the machines list may start (machines without a worker estimate)."""

Status = Literal["live", "idle", "offline"]


TwinKey = tuple[str, int, int, float, float, float]
"""Key of a cached replay (:meth:`FleetService.twin_key`): machine id, known-payload version,
late-data version, window start and end [s], output rate [Hz]."""


@dataclass(frozen=True)
class MachineStatus:
    """A machine as the fleet page shows it.

    Attributes:
        machine_id: Identifier.
        name: Display name.
        model: Machine description name (``"custom"`` for inline TOML).
        status: ``live`` (newest sample younger than ``live_idle_s``), ``idle`` (younger than
            ``live_offline_s``) or ``offline``.
        last_seen_s: Time of the newest stored sample [s], or None.
        payload_kg: Latest payload estimate, ≥ 0 [kg], or None.
        alarms: Critical events of the last 24 h.
        location: (latitude, longitude) [deg], or None.
        data_range: (first, last) stored sample time [s], or None.
    """

    machine_id: str
    name: str
    model: str
    status: Status
    last_seen_s: float | None
    payload_kg: float | None
    alarms: int
    location: tuple[float, float] | None
    data_range: tuple[float, float] | None


RenderReport = Callable[[Any, Machine, str, str, Any], tuple[bytes, str, str]]
"""``(analytics report, machine, format, source label, service schedule) -> (body, media type,
file name)``."""


@dataclass(frozen=True)
class ReportFile:
    """A rendered report: its bytes, media type and file name."""

    body: bytes
    media_type: str
    filename: str


class FleetService:
    """The fleet's data, replayed and summarised (see module docstring).

    Args:
        settings: The settings of the process.
        backend: The store adapter (opened).
        metrics: Where the twin worker counts its windows (a new registry when None).
    """

    def __init__(self, settings: Settings, backend: Backend,
                 metrics: Metrics | None = None) -> None:
        self.settings = settings
        self.backend = backend
        self.metrics = metrics if metrics is not None else Metrics()
        self.twin_cache: LruCache[bytes] = LruCache(settings.twin_cache_entries,
                                                    settings.twin_cache_bytes)
        self.replayer = Replayer(backend.store.read_payload)
        self.worker: TwinWorker | None = None
        self.live_payload: dict[str, LivePayload] = {}
        """Live payload estimators of the machines watched live (created by their follower)."""
        self._worker_task: asyncio.Task[None] | None = None

    @classmethod
    def open(cls, settings: Settings, metrics: Metrics | None = None) -> FleetService:
        """Open the store of the settings (``database_url``, or the shards of
        ``storage_shards``) and build the service."""
        from cranetwin.storage import store_spec

        return cls(settings, Backend.open(store_spec(settings)), metrics)

    async def start(self) -> None:
        """Warm up (:mod:`cranetwin.service.warmup`, before serving: ~0.5 s, and done in the
        background it slowed the first seconds of requests), then start the twin worker in this
        process; each if the settings ask for it (``warm_up``, ``worker_in_process``)."""
        if self.settings.warm_up:
            from cranetwin.service.warmup import run_warm_up

            await asyncio.to_thread(run_warm_up, then=self.warm_machines)
        if self.settings.worker_in_process:
            self.worker = TwinWorker(self.backend, self.settings, self.metrics, self.replayer)
            self._worker_task = asyncio.get_running_loop().create_task(
                self.worker.run_forever(), name="twin-worker")

    def warm_machines(self, limit: int = 4, span_s: float = 30.0) -> int:
        """Replay the newest ``span_s`` of the ``limit`` most recently seen machines once, so
        that their smoothing choice is cached before the first page asks for a short window.

        Returns:
            Machines replayed.
        """
        seen = []
        for rec in self.backend.list_machines():
            dr = self.backend.data_range(rec.machine_id)
            if dr is not None:
                seen.append((dr[1], rec))
        done = 0
        for end, rec in sorted(seen, key=lambda x: -x[0])[:limit]:
            samples = self.backend.read_samples(rec.machine_id, end - span_s, end + 1.0)
            if samples.t_s.shape[0] < 8:
                continue
            try:
                self.replayer.replay(rec.machine_id, self.backend.model_of(rec), samples,
                                     sample_rate_hz(samples))
            except CraneTwinError as exc:
                log.info("warm-up of %s skipped: %s", rec.machine_id, exc)
                continue
            done += 1
        return done

    async def close(self, timeout_s: float = 30.0) -> None:
        """Stop the in-process worker (it finishes the window it is replaying, for at most
        ``timeout_s``; then it is cancelled and that window is done again next time) and close
        the store."""
        if self.worker is not None and self._worker_task is not None:
            self.worker.stop_event.set()
            try:
                await asyncio.wait_for(asyncio.shield(self._worker_task), timeout_s)
            except TimeoutError:
                log.warning("twin worker did not stop in %.0f s; cancelled", timeout_s)
                self._worker_task.cancel()
                await asyncio.gather(self._worker_task, return_exceptions=True)
            except Exception:  # noqa: BLE001 - logged by the worker; shutting down anyway
                log.exception("twin worker failed while stopping")
        self.backend.close()

    def refresh_gauges(self) -> None:
        """Copy cache counters into the metrics."""
        self.metrics.twin_cache_hits.set(self.twin_cache.hits)
        self.metrics.twin_cache_misses.set(self.twin_cache.misses)
        self.metrics.twin_cache_bytes.set(self.twin_cache.nbytes)
        self.metrics.twin_cache_max_bytes.set(self.settings.twin_cache_bytes)
        self.metrics.twin_cache_evictions.set(self.twin_cache.evictions)

    # -- machines ---------------------------------------------------------------------------------
    def _status(self, last_seen: float | None) -> Status:
        if last_seen is None:
            return "offline"
        age = time.time() - last_seen
        if age <= self.settings.live_idle_s:
            return "live"
        return "idle" if age <= self.settings.live_offline_s else "offline"

    def machine_status(self, rec: MachineRecord) -> MachineStatus:
        """Status of a machine from its newest sample, payload from the worker (or a live
        estimate when fresher), alarms of the last 24 h and its stored data range."""
        rng = self.backend.data_range(rec.machine_id)
        last = rng[1] if rng else None
        prog = self.backend.progress(rec.machine_id)
        now = time.time()
        alarms = self.backend.count_events(rec.machine_id, now - 86400.0, now, "critical")
        payload = public_kg(prog.last_payload_kg if prog is not None else None)
        lp = self.live_payload.get(rec.machine_id)
        if payload is None and self._status(last) == "live":
            # streaming, but the worker has no estimate yet (its first window ends 1–2 min
            # after the first sample): keep a live estimate going, shown from the next listing
            if lp is None and len(self.live_payload) < MAX_LIST_LIVE_PAYLOADS:
                lp = self.live_payload[rec.machine_id] = LivePayload(
                    rec.machine_id, self.backend.model_of(rec), self.backend, self.replayer)
            if lp is not None:
                lp.value()  # starts a refresh when one is due
        if lp is not None and lp.kg is not None and lp.t_s is not None and (
                prog is None or lp.t_s > prog.watermark_s):  # watched live: fresher
            payload = public_kg(lp.kg)
        loc = (rec.location[0], rec.location[1]) if rec.location else None
        return MachineStatus(machine_id=rec.machine_id, name=rec.name, model=rec.model,
                             status=self._status(last), last_seen_s=last, payload_kg=payload,
                             alarms=alarms, location=loc, data_range=rng)

    def live_payload_of(self, rec: MachineRecord) -> LivePayload:
        """The live payload estimator of ``rec`` (created on first use)."""
        lp = self.live_payload.get(rec.machine_id)
        if lp is None:
            lp = self.live_payload[rec.machine_id] = LivePayload(
                rec.machine_id, self.backend.model_of(rec), self.backend, self.replayer)
        return lp

    # -- samples ----------------------------------------------------------------------------------
    def samples_page(self, rec: MachineRecord, rng: TimeRange, limit: int,
                     cursor: str | None) -> SamplesPage:
        """One page of raw samples in [from, to) (:func:`cranetwin.service.queries.samples_page`).
        """
        if limit > self.settings.max_samples_limit:
            raise InvalidRequestError("Page too large", f"limit={limit}; at most "
                                      f"{self.settings.max_samples_limit} samples per page")
        return samples_page(self.backend, rec.machine_id, rng, limit, cursor,
                            self.settings.nominal_rate_hz)

    # -- twin -------------------------------------------------------------------------------------
    def twin_window(self, rec: MachineRecord, rng: TimeRange, rate_hz: float) -> bytes:
        """Replay of [from, to) at ``rate_hz`` as JSON bytes (cached: :meth:`twin_key`)."""
        key = self.twin_key(rec, rng, rate_hz)
        body = None if key is None else self.twin_cache.get(key)
        if body is None:
            body = self.twin_body(rec, rng, rate_hz)
            if key is not None:
                self.twin_cache.put(key, body)
        return body

    def twin_key(self, rec: MachineRecord, rng: TimeRange, rate_hz: float) -> TwinKey | None:
        """The replay cache's key of a twin request, after checking its limits: the machine,
        the version of its stored known payload (:mod:`cranetwin.storage.payload_version`),
        its late-data version (:mod:`cranetwin.storage.late_version`), the window and the
        rate; None when the window may still grow (it does not end ``twin_margin_s`` before
        the end of the newest stored block): not cached.

        A replay depends on the known payload and on the blocks stored around the window,
        which any process may change: a payload stored or deleted (an import, ``cranetwin
        payload delete``, another API process) raises the payload version, a block stored
        behind the machine's newest one (late data from a machine that was offline, a
        backfill, blocks committed out of order) and retention raise the late-data version,
        each in the transaction of the change. Both are read with the newest block end in one
        statement, before the replay reads anything (:meth:`Backend.machine`, read for the
        request: no query of its own; a record without them, from a listing, is read again),
        so a result replayed before a change is never found under the key of a request made
        after it (an entry stored under an old version is simply not hit again, and ages out
        of the cache), while blocks appended after the newest (a live machine) leave the keys
        of past windows unchanged.

        Raises:
            InvalidRequestError: Window too long, rate too high, too many output samples.
        """
        s = self.settings
        rng.limit(s.max_twin_range_s, "the twin")
        if rate_hz > s.max_twin_rate_hz:
            raise InvalidRequestError("Rate too high",
                                      f"rate_hz={rate_hz}; at most {s.max_twin_rate_hz}")
        n_out = rng.duration_s * rate_hz
        if n_out > s.max_twin_points:
            raise InvalidRequestError(
                "Too many points", f"{n_out:.0f} output samples requested ({rng.duration_s:g} s "
                f"at {rate_hz:g} Hz); at most {s.max_twin_points} per call")
        if rec.payload_version is None or rec.late_version is None:
            rec = self.backend.machine(rec.machine_id)
        assert rec.payload_version is not None and rec.late_version is not None
        newest = rec.newest_block_s
        if newest is None or rng.t1_s + s.twin_margin_s > newest:
            return None
        return (rec.machine_id, rec.payload_version, rec.late_version, round(rng.t0_s, 6),
                round(rng.t1_s, 6), float(rate_hz))

    def twin_body(self, rec: MachineRecord, rng: TimeRange, rate_hz: float) -> bytes:
        """The replay of a twin request (checked by :meth:`twin_key`) as JSON bytes."""
        return orjson.dumps(self._twin(rec, rng, rate_hz), option=orjson.OPT_SERIALIZE_NUMPY)

    def _twin(self, rec: MachineRecord, rng: TimeRange, rate_hz: float) -> dict[str, Any]:
        machine = self.backend.model_of(rec)
        m = self.settings.twin_margin_s
        samples = self.backend.read_samples(rec.machine_id, rng.t0_s - m, rng.t1_s + m)
        inside = (samples.t_s >= rng.t0_s) & (samples.t_s < rng.t1_s)
        if not inside.any():
            return _empty_twin(machine)
        if samples.t_s.shape[0] < 8:
            raise TwinError(f"only {samples.t_s.shape[0]} samples in and around the window; "
                            "the twin needs at least 8")
        sample_hz = sample_rate_hz(samples)
        grid_hz = sample_hz * max(1, math.ceil(rate_hz / sample_hz - 1e-9))
        res = self.replayer.replay(rec.machine_id, machine, samples, grid_hz)
        return twin_json(machine, res, rng.t0_s, rng.t1_s, rate_hz)

    # -- history / find / events ------------------------------------------------------------
    def history(self, rec: MachineRecord, rng: TimeRange, channels: str,
                max_points: int) -> bytes:
        """Min/max/mean per bucket of each channel, from the stored summaries, as JSON bytes
        ``{"channels": {name: {t, min, max, mean}}}`` serialised straight from the arrays."""
        s = self.settings
        rng.limit(s.max_history_range_s, "load history")
        if max_points > s.max_history_points:
            raise InvalidRequestError("Too many points",
                                      f"max_points={max_points}; at most {s.max_history_points}")
        names = list(dict.fromkeys(c.strip() for c in channels.split(",") if c.strip()))
        if not names:
            raise InvalidRequestError("No channels",
                                      "channels: give one or more names, comma-separated")
        if len(names) > MAX_HISTORY_CHANNELS:
            raise InvalidRequestError(
                "Too many channels",
                f"{len(names)} channels; at most {MAX_HISTORY_CHANNELS} per request")
        check_channels(self.backend.model_of(rec), names)
        data = self.backend.summaries(rec.machine_id, names, rng.t0_s, rng.t1_s, max_points)
        out = {n: {"t": data[n][0], "min": data[n][1], "max": data[n][2], "mean": data[n][3]}
               for n in names}
        return orjson.dumps({"channels": out}, option=orjson.OPT_SERIALIZE_NUMPY)

    def find(self, rec: MachineRecord, rng: TimeRange, channel: str, op: Literal["gt", "lt"],
             value: float, which: Literal["first", "last"]) -> Moment:
        """First/last time ``channel`` op ``value`` held in [from, to)
        (:func:`cranetwin.service.queries.find_moment`)."""
        rng.limit(self.settings.max_history_range_s, "find")
        machine = self.backend.model_of(rec)
        check_channels(machine, [channel])
        return find_moment(self.backend, machine, rec.machine_id, rng, channel, op, value, which)

    def events(self, rec: MachineRecord, rng: TimeRange) -> list[dict[str, Any]]:
        """Stored events in [from, to): ``{t, kind, severity, message, evidence}`` each."""
        rng.limit(self.settings.max_history_range_s, "events")
        return self.backend.events(rec.machine_id, rng.t0_s, rng.t1_s)

    def analytics(self, rec: MachineRecord, rng: TimeRange) -> dict[str, Any]:
        """Analytics of the range: replayed window by window into cranetwin.analytics."""
        from cranetwin.service.analytics import analytics_json, analytics_report

        report = analytics_report(self.backend, self.replayer, self.backend.model_of(rec),
                                  rec.machine_id, rng, self.settings.twin_margin_s,
                                  self.settings.max_analytics_range_s)
        return analytics_json(report, rng)

    def report(self, rec: MachineRecord, rng: TimeRange, fmt: str,
               render_report: RenderReport) -> ReportFile:
        """The maintenance report of the range, rendered by ``render_report`` (the caller passes
        :func:`cranetwin.reports.render`: PDF, HTML or a zip of CSV tables; reports sit above
        this layer); a one-table stub file when the range holds no samples."""
        from cranetwin.service.analytics import analytics_json, analytics_report, render

        machine = self.backend.model_of(rec)
        rep = analytics_report(self.backend, self.replayer, machine, rec.machine_id, rng,
                               self.settings.twin_margin_s, self.settings.max_analytics_range_s)
        if rep is None:
            body, media, name = render(analytics_json(None, rng), fmt, rec.machine_id)
        else:
            from cranetwin.service.schedules import statuses

            source = f"cranetwin API: machine {rec.machine_id}, {iso(rng.t0_s)} – {iso(rng.t1_s)}"
            body, media, name = render_report(rep, machine, fmt, source,
                                              statuses(self.backend, rec.machine_id))
            name = f"{rec.machine_id}-{name}"
        return ReportFile(body, media, name)

    # -- AEMP -------------------------------------------------------------------------------------
    def _figures(self, recs: list[MachineRecord]) -> list[aemp.EquipmentFigures]:
        """AEMP figures of ``recs``: worker counters, duty to date, the reported hour meter,
        install time and identifiers (one metadata query for all)."""
        from cranetwin.service.history import stored_duty
        from cranetwin.storage.aempreads import status_rows

        store = self.backend.store
        status = {k: v for e, ids in store.engines_of(r.machine_id for r in recs)
                  for k, v in status_rows(e, ids).items()}  # one query per shard
        out = []
        for rec in recs:
            p = self.backend.progress(rec.machine_id) or Progress.empty(rec.machine_id)
            duty = stored_duty(store.engine_for(rec.machine_id), rec.machine_id)
            st = status.get(rec.machine_id)
            meta = st.metadata if st is not None else {}
            meter = (st.operating_hours, st.status_s) if st is not None and \
                st.operating_hours is not None and st.status_s is not None else None
            install = meta.get("registered_t_s")
            if install is None:
                dr = self.backend.data_range(rec.machine_id)
                install = dr[0] if dr is not None else None
            loc = None
            if rec.location is not None:
                times = [t for t in (meta.get("location_t_s"), st.status_s if st else None)
                         if t is not None]
                when = max(times) if times else install
                if when is not None:
                    loc = (rec.location[0], rec.location[1], float(when))
            out.append(aemp.EquipmentFigures(
                machine_id=rec.machine_id, name=rec.name, model=rec.model,
                machine=self.backend.model_of(rec), location=loc,
                counters_t_s=p.watermark_s if p.windows else None,
                operating_s=p.operating_s, idle_s=p.idle_s, load_count=p.load_count,
                payload_total_kg=p.payload_total_kg, load_cube_sum=p.load_cube_sum,
                overloads=p.overloads, max_payload_kg=p.max_payload_kg,
                duty=None if duty is None else (duty[0], duty[1]), hour_meter=meter,
                install_t_s=None if install is None else float(install),
                serial_number=meta.get("serial_number"), pin=meta.get("pin"),
                oem_name=str(meta.get("oem_name") or "cranetwin")))
        return out

    def aemp_fleet(self, page: int, base_url: str) -> dict[str, Any]:
        """ISO 15143-3 Fleet page ``page`` (``base_url``: absolute URL of ``…/Fleet``); 404 past
        the last page."""
        recs = self.backend.list_machines()
        n_total = len(recs)
        last = max(1, math.ceil(n_total / aemp.PAGE_SIZE))
        if page > last:
            raise NotFoundError("No such page", f"page {page} requested; the fleet has {last} "
                                f"page(s) of {aemp.PAGE_SIZE}")
        recs = sorted(recs, key=lambda r: r.machine_id)
        recs = recs[(page - 1) * aemp.PAGE_SIZE: page * aemp.PAGE_SIZE]
        return aemp.fleet_page(self._figures(recs), page, n_total, base_url, time.time())

    def aemp_equipment(self, machine_id: str, self_url: str = "") -> dict[str, Any]:
        """ISO 15143-3 snapshot of one machine (``self_url``: its absolute URL)."""
        rec = self.backend.machine(machine_id)
        return aemp.equipment_document(self._figures([rec])[0], self_url, time.time())

    def aemp_series(self, machine_id: str, element: str, rng: TimeRange, page: int,
                    base_url: str) -> dict[str, Any]:
        """ISO 15143-3 time series ``element`` of one machine over [start, end], page ``page``
        (``base_url``: absolute URL without the page number); 404 for an element not served
        or a page past the last."""
        from cranetwin.storage.aempreads import minute_times, times_until

        rec = self.backend.machine(machine_id)
        if element not in aemp.SERIES:
            raise NotFoundError("No such time series", f"{element!r}: served are "
                                f"{', '.join(aemp.SERIES)}")
        engine = self.backend.store.engine_for(machine_id)
        minutes = minute_times(engine, machine_id, rng.t0_s, rng.t1_s)
        before = times_until(engine, machine_id, rng.t0_s)
        offset = 0.0
        fig = self._figures([rec])[0]
        if element == "CumulativeOperatingHours" and fig.hour_meter is not None:
            counted, _ = times_until(engine, machine_id, fig.hour_meter[1])
            offset = fig.hour_meter[0] - counted / 3600.0
        points = aemp.hourly_points(minutes, element, before, offset)
        last = max(1, math.ceil(len(points) / aemp.PAGE_SIZE))
        if page > last:
            raise NotFoundError("No such page", f"page {page} requested; the series has "
                                f"{last} page(s) of {aemp.PAGE_SIZE}")
        return aemp.series_document(element, points, page, base_url, time.time())


def _empty_twin(machine: Machine) -> dict[str, Any]:
    z = np.zeros((0,))
    return {"t": z, "q": np.zeros((0, machine.n_joints)), "tip": np.zeros((0, 3)),
            "poses": {j.child: np.zeros((0, 16)) for j in machine.joints},
            "cylinder_pins": {c.name: np.zeros((0, 6)) for c in machine.cylinders},
            "cylinder_forces": {c.name: z for c in machine.cylinders},
            "utilisation": {c.name: z for c in machine.cylinders},
            "joint_torques": np.zeros((0, machine.n_joints)),
            "wrenches": np.zeros((0, machine.n_joints, 6)),
            "payload": {"t": z, "kg": z, "std_kg": z}}
