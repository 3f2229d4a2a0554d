"""Live stream: one follower task per watched machine, fanned out to every websocket client.

The follower polls the store for samples newer than the last it saw, ``live_rate_hz`` times a
second, turns the newest into a frame (:class:`~cranetwin.api.views.LiveKinematics`: pose,
cylinder pins and forces, pressures), serialises it once and offers it to every client. Each
client has a queue of one frame: a slow client skips frames instead of slowing the others or
growing memory. The follower starts with the first client of a machine and stops with the last.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from cranetwin.api.views import LiveKinematics
from cranetwin.model import Machine
from cranetwin.samples import SampleArrays

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
        self.after_t = latest if latest is not None else time.time() - 1.0
        self.period_s = period_s
        self.extra = extra
        self.on_frame = on_frame
        self.clients: set[Client] = set()
        self.task: asyncio.Task[None] | None = None
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
            await asyncio.sleep(max(0.0, self.period_s - (time.monotonic() - start)))

    def _publish(self, samples: SampleArrays) -> None:
        if self._kin is None or self._kin.channels != samples.channels:
            self._kin = LiveKinematics(self.machine, samples.channels)
            self._prev = None
        frames = self._kin.frames(samples.t_s[-1:], samples.values[-1:],
                                  samples.values[-2] if samples.t_s.shape[0] > 1 else self._prev)
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
    """The followers of all watched machines."""

    def __init__(self) -> None:
        self.followers: dict[str, Follower] = {}

    @property
    def n_clients(self) -> int:
        """Open client subscriptions."""
        return sum(len(f.clients) for f in self.followers.values())

    def subscribe(self, machine_id: str, make: Callable[[], Follower]) -> Client:
        """A new client of ``machine_id``, starting its follower if needed."""
        f = self.followers.get(machine_id)
        if f is None:
            f = make()
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
