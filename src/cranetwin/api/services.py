"""What the routes hold: the fleet service plus the HTTP side's own parts (keys, live fan-out).

One :class:`Services` per app, opened by the app's lifespan: the
:class:`~cranetwin.service.fleet.FleetService` (data, replays, the in-process twin worker when
the settings ask for it), the :class:`~cranetwin.api.auth.KeyVerifier`, the websocket fan-out
(:class:`~cranetwin.api.live.LiveHub`), the Prometheus metrics, the rate limiter
(:class:`~cranetwin.api.limits.RateLimiter`, None when off) and the pool of heavy work
(:class:`~cranetwin.service.heavy.HeavyPool`). The functions below turn
the service's plain results into the public schemas.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from typing import Any

from cranetwin.api.auth import KeyVerifier
from cranetwin.api.limits import RateLimiter
from cranetwin.api.live import Follower, LiveHub
from cranetwin.api.schemas import DataRange, Location, MachineDetail, MachinePublic
from cranetwin.service.alarms import AlarmService
from cranetwin.service.backend import Backend, MachineRecord
from cranetwin.service.fleet import FleetService, MachineStatus
from cranetwin.service.heavy import HeavyPool
from cranetwin.service.live_payload import public_kg
from cranetwin.service.metrics import Metrics
from cranetwin.service.timerange import iso
from cranetwin.settings import Settings

log = logging.getLogger(__name__)


class Services:
    """Everything the routes need (see module docstring).

    Args:
        settings: The settings of the process.
        fleet: The fleet service (its store opened).
        bus: The ingest daemon's live bus, or None (the live view polls the store).
    """

    def __init__(self, settings: Settings, fleet: FleetService, bus: Any = None) -> None:
        self.settings = settings
        self.fleet = fleet
        self.backend: Backend = fleet.backend
        self.metrics: Metrics = fleet.metrics
        self.keys = KeyVerifier(fleet.backend.key_lookup,
                                session_secret=settings.session_secret)
        self.live = LiveHub(bus)
        self.limiter = RateLimiter.from_settings(settings) if settings.rate_limit else None
        n = settings.replay_processes
        if n:
            from cranetwin.service import heavyproc

            self.heavy = HeavyPool(settings.heavy_workers, settings.heavy_queue,
                                   processes=heavyproc.process_pool(settings), process_count=n,
                                   process_warm=heavyproc.warm if settings.warm_up else int)
        else:
            self.heavy = HeavyPool(settings.heavy_workers, settings.heavy_queue)
        self.alarms = AlarmService(fleet.backend, settings.alarm_offline_s, settings.alarm_gap_s)
        self._alarm_task: asyncio.Task[None] | None = None
        self.webhook: Any = None

    @classmethod
    def open(cls, settings: Settings, bus: Any = None) -> Services:
        """Open the store at ``settings.database_url`` and build the services.

        Args:
            settings: The settings of the process.
            bus: A live bus shared with an in-process ingest daemon, or None to open
                ``settings.live_bus_url`` (if set; else the live view polls the store).
        """
        if bus is None and settings.live_bus_url:
            from cranetwin.storage.live import open_bus

            bus = open_bus(settings.live_bus_url)
        return cls(settings, FleetService.open(settings), bus)

    async def start(self) -> None:
        """Warm up and start the in-process worker, as the settings ask."""
        await self.fleet.start()
        cfg = self.settings
        if cfg.warm_up:  # the replay processes start in the background: serving now
            self.heavy.start_processes()
        if cfg.alarm_webhook_url:
            from cranetwin.service.webhooks import WebhookConfig, WebhookNotifier

            if not cfg.alarm_webhook_secret:
                log.warning("CRANETWIN_ALARM_WEBHOOK_URL is set without "
                            "CRANETWIN_ALARM_WEBHOOK_SECRET: webhook off (its requests are signed)")
            else:
                self.webhook = WebhookNotifier(WebhookConfig(
                    cfg.alarm_webhook_url, cfg.alarm_webhook_secret, cfg.alarm_webhook_retries,
                    cfg.alarm_webhook_backoff_s, cfg.alarm_webhook_timeout_s),
                    self.backend.session)
                await asyncio.to_thread(self.alarms.set_notifier, self.webhook,
                                        cfg.alarm_webhook_severity)
        if self.settings.alarm_check_interval_s > 0:
            self._alarm_task = asyncio.create_task(self._check_alarms())

    async def _check_alarms(self) -> None:
        """Raise machine_offline / data_gap events every ``alarm_check_interval_s``, the first
        one interval after the start (not competing with the first page loads)."""
        while True:
            await asyncio.sleep(self.settings.alarm_check_interval_s)
            try:
                await asyncio.to_thread(self.alarms.check_connectivity)
            except Exception as exc:  # noqa: BLE001 - a failed check must not stop the next
                log.warning("alarm check failed: %s", exc)
            if self.webhook is not None:
                try:  # queues new events in the webhook outbox; never waits for a delivery
                    await asyncio.to_thread(self.alarms.notify_new)
                except Exception as exc:  # noqa: BLE001
                    log.warning("webhook check failed: %s", exc)

    async def close(self) -> None:
        """Stop the live followers, the worker, and close the store."""
        if self._alarm_task is not None:
            self._alarm_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._alarm_task
        if self.webhook is not None:
            await asyncio.to_thread(self.webhook.close)
        await self.live.close()
        await asyncio.to_thread(self.heavy.close)
        await self.fleet.close()

    def refresh_gauges(self) -> None:
        """Copy cache counters and the heavy pool's load into the metrics."""
        self.fleet.refresh_gauges()
        self.metrics.heavy_admitted.set(self.heavy.admitted)

    def follower_factory(self, rec: MachineRecord) -> Any:
        """A zero-argument factory of the live follower of ``rec`` (for :class:`LiveHub`)."""
        machine = self.backend.model_of(rec)
        rng = self.backend.data_range(rec.machine_id)

        def extra() -> dict[str, Any]:
            return {"payload_kg": public_kg(self.fleet.live_payload_of(rec).value())}

        def on_frame(n_clients: int) -> None:
            self.metrics.live_frames.inc(n_clients)

        def make() -> Follower:
            return Follower(rec.machine_id, machine, self.backend.read_after,
                            rng[1] if rng else None, 1.0 / self.settings.live_rate_hz, extra,
                            on_frame)

        return make

    def machine_public(self, rec: MachineRecord) -> MachinePublic:
        """List entry of a machine."""
        return public(self.fleet.machine_status(rec))

    def machine_detail(self, rec: MachineRecord) -> MachineDetail:
        """A machine and its stored data range."""
        return detail(self.fleet.machine_status(rec))


def public(st: MachineStatus) -> MachinePublic:
    """The public list entry of a machine's status."""
    loc = Location(lat=st.location[0], lon=st.location[1]) if st.location else None
    return MachinePublic(machine_id=st.machine_id, name=st.name, model=st.model,
                         status=st.status, last_seen=iso(st.last_seen_s),
                         payload_kg=st.payload_kg, alarms=st.alarms, location=loc)


def detail(st: MachineStatus) -> MachineDetail:
    """The public detail of a machine's status (with its stored data range)."""
    rng = st.data_range
    dr = DataRange.model_validate({"from": iso(rng[0]) if rng else None,
                                   "to": iso(rng[1]) if rng else None})
    return MachineDetail(**public(st).model_dump(), data_range=dr)
