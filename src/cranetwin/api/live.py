"""Live stream: one follower task per watched machine, fanned out to every websocket client.

The follower reads the samples newer than the last it saw — when the ingest daemon's live bus
(:mod:`cranetwin.storage.live`) announces a newly stored block of its machine, or at the latest
every ``1 / live_rate_hz`` s when there is no bus — at most ``live_rate_hz`` times a second,
turns the newest into a frame (:class:`~cranetwin.service.views.LiveKinematics`: pose,
cylinder pins and forces, pressures), serialises it once and offers it to every client. Each
client has a queue of one frame: a slow client skips frames instead of slowing the others or
growing memory. The follower starts with the first client of a machine and stops with the last.
"""

from __future__ import annotations

import asyncio
import json
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from cranetwin.model import Machine
from cranetwin.samples import SampleArrays
from cranetwin.service.views import LiveKinematics

log = logging.getLogger(__name__)

ReadNew = Callable[[str, float], SampleArrays | None]
"""``(machine_id, after_t_s) -> samples with t > after_t_s`` (None if nothing)."""


class Client:
    """One websocket subscriber: a one-slot mailbox of serialised frames."""

    def __init__(self) -> None:
        self.queue: asyncio.Queue[str] = asyncio.Queue(maxsize=1)
        self.dropped = 0

    def offer(self, text: str) -> None:
        """Put the newest frame, replacing one not yet sent."""
        if self.queue.full():
            try:
                self.queue.get_nowait()
                self.dropped += 1
            except asyncio.QueueEmpty:
                pass
        self.queue.put_nowait(text)


class Follower:
    """Follows one machine's stored samples and broadcasts frames to its clients.

    Args:
        machine_id: Machine to follow.
        machine: Its description.
        read_new: Reads samples newer than a time (run in a worker thread).
        latest: Time of the newest stored sample [s] or None (where to start).
        period_s: Poll period [s] (1 / live rate).
        extra: Returns fields added to every frame (e.g. the latest payload estimate).
        on_frame: Called once per broadcast frame (metrics).
    """

    def __init__(self, machine_id: str, machine: Machine, read_new: ReadNew, latest: float | None,
                 period_s: float, extra: Callable[[], dict[str, Any]],
                 on_frame: Callable[[int], None]) -> None:
        self.machine_id = machine_id
        self.machine = machine
        self.read_new = read_new
        self.after_t = latest if latest is not None else 0.0
        self.period_s = period_s
        self.extra = extra
        self.on_frame = on_frame
        self.clients: set[Client] = set()
        self.task: asyncio.Task[None] | None = None
        self.wake = asyncio.Event()
        self.poll_s = period_s
        self._kin: LiveKinematics | None = None
        self._prev: np.ndarray | None = None

    async def run(self) -> None:
        """Poll, compute, broadcast until cancelled."""
        while True:
            start = time.monotonic()
            try:
                samples = await asyncio.to_thread(self.read_new, self.machine_id, self.after_t)
                if samples is not None and samples.t_s.shape[0]:
                    self._publish(samples)
            except asyncio.CancelledError:
                raise
            except Exception:  # keep following: one bad read must not end the stream
                log.exception("live follower of %s failed a poll", self.machine_id)
            # at most one frame per period; then wait for a bus note (or the poll period)
            await asyncio.sleep(max(0.0, self.period_s - (time.monotonic() - start)))
            if self.poll_s > self.period_s:
                try:
                    await asyncio.wait_for(self.wake.wait(), timeout=self.poll_s)
                except TimeoutError:
                    pass
            self.wake.clear()

    def _publish(self, samples: SampleArrays) -> None:
        if self._kin is None or self._kin.channels != samples.channels:
            self._kin = LiveKinematics(self.machine, samples.channels)
            self._prev = None
        if samples.t_s.shape[0] > 1:
            prev, prev_t = samples.values[-2], float(samples.t_s[-2])
        else:  # the newest sample of the previous poll (its time is after_t)
            prev, prev_t = self._prev, self.after_t
        frames = self._kin.frames(samples.t_s[-1:], samples.values[-1:], prev, prev_t)
        self.after_t = float(samples.t_s[-1])
        self._prev = samples.values[-1]
        if not frames:
            return
        frame = frames[-1]
        frame.update(self.extra())
        text = json.dumps(frame, separators=(",", ":"))
        for c in list(self.clients):
            c.offer(text)
        self.on_frame(len(self.clients))


class LiveHub:
    """The followers of all watched machines, woken by the live bus when there is one.

    Args:
        bus: The ingest daemon's live fan-out (``cranetwin.storage.live.LiveBus``) or None to
            poll the store only.
    """

    def __init__(self, bus: Any = None) -> None:
        self.followers: dict[str, Follower] = {}
        self.bus = bus
        self._sub: Any = None
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

    def _listen(self) -> None:
        """Bus thread: wake the follower of each announced machine."""
        sub = self._sub
        while sub is not None and self._sub is sub:
            note = sub.get(timeout=0.5)
            if note is None or self._loop is None:
                continue
            f = self.followers.get(note.machine_id)
            if f is not None:
                self._loop.call_soon_threadsafe(f.wake.set)

    def _start_bus(self) -> None:
        if self.bus is None or self._thread is not None:
            return
        self._loop = asyncio.get_running_loop()
        self._sub = self.bus.subscribe()
        self._thread = threading.Thread(target=self._listen, name="live-bus", daemon=True)
        self._thread.start()

    @property
    def n_clients(self) -> int:
        """Open client subscriptions."""
        return sum(len(f.clients) for f in self.followers.values())

    def subscribe(self, machine_id: str, make: Callable[[], Follower]) -> Client:
        """A new client of ``machine_id``, starting its follower if needed."""
        self._start_bus()
        f = self.followers.get(machine_id)
        if f is None:
            f = make()
            if self.bus is not None:
                f.poll_s = 1.0  # the bus wakes it; poll rarely as a safety net
            self.followers[machine_id] = f
            f.task = asyncio.get_running_loop().create_task(f.run(), name=f"live-{machine_id}")
        client = Client()
        f.clients.add(client)
        return client

    def unsubscribe(self, machine_id: str, client: Client) -> None:
        """Remove ``client``; stop the follower with its last client."""
        f = self.followers.get(machine_id)
        if f is None:
            return
        f.clients.discard(client)
        if not f.clients:
            if f.task is not None:
                f.task.cancel()
            del self.followers[machine_id]

    async def close(self) -> None:
        """Stop every follower."""
        tasks = [f.task for f in self.followers.values() if f.task is not None]
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        self.followers.clear()
        sub, self._sub = self._sub, None
        if sub is not None:
            sub.close()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
