"""``cranetwin ingest --processes N``: N daemon processes on one UDP address, each machine always
served by the same one, a dead one restarted on its socket.

The parent binds the ``SO_REUSEPORT`` group (:func:`~cranetwin.ingest.steering.bind_group`:
socket ``i`` receives the machines with ``wire_id % N == i``), keeps every socket open for its
whole life, and runs child ``i`` (``python -m cranetwin.ingest.child``) on an inherited copy of
socket ``i``. The child is a whole :class:`~cranetwin.ingest.daemon.IngestDaemon` with its own
decoder, writer and database connection — or, with a fleet bus configured, the daemon publishing
to JetStream (:func:`~cranetwin.ingest.bus_serve.serve_to_bus`, docs/BUS.md) with its own NATS
connection; its settings (database and bus URLs included) come as one JSON object on its stdin,
never in argv. The parent reads nothing from the sockets itself.

* **A child dies** (``kill -9``, a crash): nothing acknowledged is lost — a child acks only
  after its commit (on the bus: after the PubAcks). Its socket stays in the group at index ``i``
  (the parent holds it), so the kernel keeps steering the datagrams of its machines
  (``wire_id % N == i``) to it and queues them in the socket's receive buffer; the parent
  restarts the child on the same socket (after 0.2 s; while it keeps dying within 10 s of its
  start, after twice the previous wait, up to 5 s), which reads them. What was queued or in
  flight and not acked is retransmitted by the machines and deduplicated by storage (on the
  bus: by JetStream's duplicate window, then by storage). No other machine moves.
* **Stop**: SIGTERM/SIGINT to the parent is forwarded once to every child (each flushes, acks
  and exits as a single daemon does); a second signal is forwarded too (children give up their
  unwritten batches at once). Children run in their own session, so a terminal's Ctrl-C
  reaches them only through the parent. A child whose parent dies gets SIGTERM
  (``PR_SET_PDEATHSIG``).
* **Changing N** is a restart of the whole group: the program's modulus is N, so with N + 1
  about N/(N+1) of the machines move to another process. That is safe — the protocol state a
  process keeps per machine is only an optimisation (replays are recognised by storage too) —
  but it costs a burst of retransmissions; an added member socket that the program does not
  address would receive nothing. Across hosts, a load balancer with consistent hashing in front
  does the steering (docs/INGEST.md).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import select
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from types import FrameType
from typing import TYPE_CHECKING, Any

from cranetwin.ingest.config import DaemonConfig, IngestConfigError
from cranetwin.ingest.steering import bind_group

if TYPE_CHECKING:
    from cranetwin.bus.subjects import BusConfig
    from cranetwin.storage.shardmap import StoreSpec

__all__ = ["ProcessGroup", "child_spec", "merge_counters"]

log = logging.getLogger("cranetwin.ingest.processes")

RESTART_MIN_S = 0.2
RESTART_MAX_S = 5.0
STABLE_S = 10.0  # a child that ran this long before dying is restarted after RESTART_MIN_S


@dataclass
class _Child:
    index: int
    fd: int
    proc: subprocess.Popen[bytes] | None = None
    info: dict[str, Any] = field(default_factory=dict)
    started: float = 0.0
    delay_s: float = RESTART_MIN_S / 2  # doubled before each restart after a short life
    due: float = 0.0  # monotonic time of the next (re)start while it is down
    final: dict[str, Any] = field(default_factory=dict)


def child_spec(db_url: str | StoreSpec, config: DaemonConfig, index: int, fd: int, *,
               live_url: str | None, busy_timeout_s: float, log_level: str,
               bus: BusConfig | None = None) -> dict[str, Any]:
    """The JSON object a child reads on stdin: its settings and the descriptor of its socket.

    The metrics endpoint of child ``i`` is ``metrics_port + i`` (port 0: each any free port).
    ``bus`` (the fleet bus, or None: write to the database) travels as its fields.
    """
    cfg = dataclasses.asdict(config)
    limits = cfg.pop("limits")
    cfg.pop("socket_fd")
    if config.metrics_host is not None and config.metrics_port:
        cfg["metrics_port"] = config.metrics_port + index
    db = db_url if isinstance(db_url, str) else db_url.to_json()
    return {"db_url": db, "config": cfg, "limits": limits, "index": index, "fd": fd,
            "live_url": live_url, "busy_timeout_s": busy_timeout_s, "log_level": log_level,
            "parent_pid": os.getpid(),
            "bus": dataclasses.asdict(bus) if bus is not None else None}


def merge_counters(finals: list[dict[str, Any]]) -> dict[str, Any]:
    """Sum of the children's final counters (numbers summed, ``dropped`` summed per reason)."""
    out: dict[str, Any] = {}
    for f in finals:
        for k, v in f.items():
            if k in ("event", "index", "pid", "time_unix_s", "uptime_s"):
                continue
            if isinstance(v, dict):
                d = out.setdefault(k, {})
                for r, n in v.items():
                    d[r] = d.get(r, 0) + n
            elif isinstance(v, int | float) and not isinstance(v, bool):
                out[k] = out.get(k, 0) + v
    return out


class ProcessGroup:
    """N ingest daemon processes sharing ``config.host:config.port`` (see the module doc).

    Args:
        db_url: Database of every child (a URL, or a spec with the shards).
        config: Settings of every child (``socket_fd`` is set per child).
        processes: N, 1 … 64.
        live_url: Live fan-out bus URL for the children, or None.
        bus: The fleet bus the children publish blocks to (docs/BUS.md), or None: they write
            to the database.
        busy_timeout_s: SQLite lock wait of each child [s].
        log_level: Logging level of the children (they log to the parent's stderr).
        start_timeout_s: Longest wait for a child's ``ready`` line [s].
    """

    def __init__(self, db_url: str | StoreSpec, config: DaemonConfig, processes: int, *,
                 live_url: str | None = None, busy_timeout_s: float = 3.0,
                 log_level: str = "INFO", start_timeout_s: float = 60.0,
                 bus: BusConfig | None = None) -> None:
        self.db_url = db_url
        self.config = config
        self.n = processes
        self.live_url = live_url
        self.bus = bus
        self.busy_timeout_s = busy_timeout_s
        self.log_level = log_level
        self.start_timeout_s = start_timeout_s
        self.restarts = 0
        self.address: tuple[str, int] | None = None
        self._socks: list[socket.socket] = []
        self._children: list[_Child] = []
        self._signals = 0
        self._forwarded = 0

    # -- children -----------------------------------------------------------------------------
    def _spawn(self, c: _Child) -> None:
        spec = child_spec(self.db_url, self.config, c.index, c.fd, live_url=self.live_url,
                          busy_timeout_s=self.busy_timeout_s, log_level=self.log_level,
                          bus=self.bus)
        proc = subprocess.Popen([sys.executable, "-m", "cranetwin.ingest.child"],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                pass_fds=[c.fd], start_new_session=True)
        assert proc.stdin is not None
        try:
            proc.stdin.write(json.dumps(spec).encode())
            proc.stdin.close()
        except OSError:
            pass  # it died already: seen by the supervisor
        c.proc, c.info, c.started, c.final = proc, {}, time.monotonic(), {}

    def _await_ready(self, c: _Child) -> None:
        """Read the child's ``ready`` line (bounded).

        Raises:
            IngestConfigError: it exited or did not get ready in time.
        """
        assert c.proc is not None and c.proc.stdout is not None
        end = time.monotonic() + self.start_timeout_s
        buf = b""
        fd = c.proc.stdout.fileno()
        while b"\n" not in buf:
            left = end - time.monotonic()
            ready, _, _ = select.select([fd], [], [], max(0.0, min(left, 0.5)))
            if ready:
                chunk = os.read(fd, 4096)
                buf += chunk
                if chunk:
                    continue
            if c.proc.poll() is not None or left <= 0:
                raise IngestConfigError(
                    f"ingest process {c.index} did not start (exit status {c.proc.poll()}; "
                    "see its log above)")
        c.info = json.loads(buf.split(b"\n", 1)[0])

    def start(self) -> None:
        """Bind the group and start every child; returns once all are listening.

        Raises:
            IngestConfigError: the address cannot be bound, or a child did not start.
        """
        cfg = self.config
        self._socks = bind_group(cfg.host, cfg.port, self.n, cfg.rcvbuf_bytes)
        host, port = self._socks[0].getsockname()[:2]
        self.address = (host, port)
        self._children = [_Child(i, s.fileno()) for i, s in enumerate(self._socks)]
        try:
            for c in self._children:
                self._spawn(c)
            for c in self._children:
                self._await_ready(c)
        except BaseException:
            self._kill_all()
            self.close()
            raise

    def ready_info(self) -> dict[str, Any]:
        """What the ``ready`` line reports: address, parent pid, and per child its index, pid
        and metrics URL."""
        h, p = self.address or (self.config.host, self.config.port)
        return {"udp": f"{h}:{p}" if ":" not in h else f"[{h}]:{p}", "pid": os.getpid(),
                "processes": self.n,
                "children": [{"index": c.index, "pid": c.proc.pid if c.proc else None,
                              "metrics": c.info.get("metrics")} for c in self._children]}

    def supervise_once(self) -> None:
        """Restart every child that exited (on its own socket), with backoff while one keeps
        dying at start."""
        now = time.monotonic()
        for c in self._children:
            if c.proc is not None and c.proc.poll() is not None:
                code = c.proc.returncode
                c.delay_s = (RESTART_MIN_S if now - c.started > STABLE_S
                             else min(RESTART_MAX_S, c.delay_s * 2))
                log.error("ingest process %d (pid %d) exited with status %s; restarting it on "
                          "the same socket in %.1f s", c.index, c.proc.pid, code, c.delay_s)
                with contextlib.suppress(OSError):
                    c.proc.stdout.close()  # type: ignore[union-attr]
                c.proc, c.due = None, now + c.delay_s
            if c.proc is None and now >= c.due:
                self._spawn(c)
                self.restarts += 1
                try:
                    self._await_ready(c)
                    log.warning("ingest process %d restarted (pid %d)", c.index, c.info["pid"])
                except IngestConfigError as exc:
                    log.error("%s; retrying", exc)

    # -- stopping -----------------------------------------------------------------------------
    def _on_signal(self, signum: int, frame: FrameType | None) -> None:
        self._signals += 1

    def _forward(self) -> None:
        while self._forwarded < self._signals:
            self._forwarded += 1
            for c in self._children:
                if c.proc is not None and c.proc.poll() is None:
                    with contextlib.suppress(OSError):
                        c.proc.send_signal(signal.SIGTERM)

    def stop(self, timeout_s: float | None = None) -> dict[str, Any]:
        """SIGTERM every child, wait for them (reacting to further signals), then close the
        sockets. A child still running after ``timeout_s`` (default: its shutdown timeout plus
        30 s) is killed.

        Returns:
            The merged final counters (:func:`merge_counters`), ``processes``, ``restarts``, and
            per child its own under ``children``.
        """
        cfg = self.config
        limit = timeout_s if timeout_s is not None else cfg.shutdown_timeout_s + 30.0
        self._signals = max(self._signals, 1)
        self._forward()
        end = time.monotonic() + limit
        while any(c.proc is not None and c.proc.poll() is None for c in self._children):
            self._forward()
            if time.monotonic() > end:
                log.error("ingest processes still running after %.0f s: killed", limit)
                self._kill_all()
                break
            time.sleep(0.05)
        for c in self._children:
            if c.proc is not None and c.proc.stdout is not None:
                c.final = _last_line(c.proc.stdout.read().decode(errors="replace"), "stopped")
                c.proc.stdout.close()
        self.close()
        finals = [{"index": c.index, **c.final} for c in self._children]
        return {**merge_counters(finals), "processes": self.n, "restarts": self.restarts,
                "children": finals}

    def _kill_all(self) -> None:
        for c in self._children:
            if c.proc is not None and c.proc.poll() is None:
                c.proc.kill()
                c.proc.wait(10)

    def close(self) -> None:
        """Close the parent's copies of the sockets (the group ends with the last copy)."""
        for s in self._socks:
            s.close()
        self._socks = []

    def run(self, on_ready: Callable[[ProcessGroup], None] | None = None,
            backstop_s: float = 5.0) -> dict[str, Any]:
        """Start, supervise until SIGTERM/SIGINT, stop (main thread only).

        The parent sleeps until a signal comes (SIGCHLD when a child exits, SIGTERM/SIGINT) or
        a restart is due — no polling while the children run; ``backstop_s`` is the longest
        sleep [s].

        Returns:
            :meth:`stop`'s counters.

        Raises:
            IngestConfigError: the address cannot be bound, or a child did not start.
        """
        r, w = os.pipe()
        os.set_blocking(r, False)
        os.set_blocking(w, False)
        old = {s: signal.signal(s, self._on_signal) for s in (signal.SIGTERM, signal.SIGINT)}
        old[signal.SIGCHLD] = signal.signal(signal.SIGCHLD, _wake)
        old_fd = signal.set_wakeup_fd(w, warn_on_full_buffer=False)
        try:
            self.start()
            if on_ready is not None:
                on_ready(self)
            while not self._signals:
                self.supervise_once()
                select.select([r], [], [], self._sleep_s(backstop_s))
                with contextlib.suppress(BlockingIOError):
                    os.read(r, 4096)
            return self.stop()
        finally:
            signal.set_wakeup_fd(old_fd)
            for s, h in old.items():
                signal.signal(s, h)
            os.close(r)
            os.close(w)

    def _sleep_s(self, backstop_s: float) -> float:
        """How long the supervisor may sleep: until the next restart is due, at most
        ``backstop_s`` [s]."""
        now = time.monotonic()
        due = [c.due - now for c in self._children if c.proc is None]
        return max(0.0, min([backstop_s, *due]))


def _wake(signum: int, frame: FrameType | None) -> None:
    """SIGCHLD: nothing to do here; the signal's wake-up byte ends the supervisor's sleep."""


def _last_line(text: str, event: str) -> dict[str, Any]:
    for line in reversed(text.splitlines()):
        with contextlib.suppress(ValueError):
            d = json.loads(line)
            if isinstance(d, dict) and d.get("event") == event:
                return {k: v for k, v in d.items() if k != "event"}
    return {}
