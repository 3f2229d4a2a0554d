"""The one-command demo: ingest daemon, API service and a simulated fleet, stopped by one Ctrl-C.

:class:`FleetDemo` runs each part as a child process of the ``cranetwin`` command (the same
commands a deployment runs, see ``docker-compose.yml``):

1. ``cranetwin ingest`` — the UDP daemon writing to the embedded SQLite database;
2. ``cranetwin serve --no-worker`` — the HTTP API, live websocket and web UI on the same database;
   ``cranetwin worker`` — the twin worker, its own process as in a deployment: its numba replays
   (a second of CPU per machine-minute) never compete with the API's requests for the
   interpreter, a crash of one leaves the other running, and the demo exercises the same
   two-process path (progress marks in the database) that production runs;
3. an admin key (to register machines) and a viewer key (printed in the URL) via
   ``cranetwin keys create``; machines registered with ``POST /api/v1/machines``;
4. one ``cranetwin send`` per crane, streaming the simulator's ``log-loading`` work cycle with its
   own log mass (a scenario file per crane) over UDP, in real time.

With ``attach=True`` only steps 3–4 run, against a service and daemon started elsewhere (the
``fleet`` service of docker-compose). Children run in their own sessions so that the terminal's
Ctrl-C reaches only this process, which then stops them in order: senders (they flush), then the
daemon (it flushes its queue), then the worker (it finishes its window), then the API.

Where the children's logs go is the ``demo_logs`` setting (``CRANETWIN_DEMO_LOGS``).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cranetwin.errors import CraneTwinError

log = logging.getLogger(__name__)

READY_FILE = Path("/tmp/cranetwin-fleet.ready")
"""Written once the fleet streams (the docker-compose health check looks for it)."""


class DemoError(CraneTwinError):
    """The demo could not start (a port in use, a child process that died, a refused request)."""


@dataclass
class DemoConfig:
    """What the demo runs.

    Attributes:
        machines: Number of simulated cranes.
        payloads_kg: Log mass per crane [kg] (cycled when there are more cranes).
        db_url: Database of the daemon and the service (embedded SQLite by default; None =
            ``CRANETWIN_DATABASE_URL``). A fresh demo starts from an empty database: an existing
            SQLite file of that name is replaced (machine secrets are shown only once).
        host: Bind address of the API.
        port: TCP port of the API.
        udp_port: UDP port of the ingest daemon.
        speed: Simulation speed (1 = real time).
        attach: Only register machines and stream (service and daemon run elsewhere).
        api_url: API base URL when attached (default ``http://host:port``).
        ingest_addr: ``host:port`` of the daemon when attached.
        public_url: Base URL printed for the browser (default: the API URL).
        model: Machine model of the cranes.
        scenario_s: Length of each crane's simulated work cycle [s] (the sender repeats it).
        batch: Samples per datagram (5 at 100 Hz: 20 datagrams/s, so the live view gets 20
            frames/s; the sender's default of 50 saves bytes but adds 0.5 s of latency).
    """

    machines: int = 3
    payloads_kg: Sequence[float] = (250.0, 450.0, 700.0, 350.0, 600.0)
    db_url: str | None = "sqlite:///cranetwin-demo.db"
    host: str = "127.0.0.1"
    port: int = 8000
    udp_port: int = 5005
    speed: float = 1.0
    attach: bool = False
    api_url: str | None = None
    ingest_addr: str | None = None
    public_url: str | None = None
    model: str = "patu655"
    scenario_s: float = 120.0
    batch: int = 5
    extra_env: dict[str, str] = field(default_factory=dict)

    @property
    def api(self) -> str:
        return self.api_url or f"http://{self.host}:{self.port}"

    @property
    def ingest(self) -> str:
        return self.ingest_addr or f"127.0.0.1:{self.udp_port}"


def cranetwin_command() -> list[str]:
    """argv prefix that runs the ``cranetwin`` CLI with this interpreter."""
    return [sys.executable, "-c", "from cranetwin.cli import main; main()"]


def demo_location(i: int) -> tuple[float, float]:
    """GPS position of the demo's ``i``-th crane (0-based): latitude, longitude [deg], a few
    km apart near Joensuu. The crane is registered there and its sender reports it."""
    return 62.60 + 0.01 * i, 29.76 + 0.02 * i


class FleetDemo:
    """Start, watch and stop the demo's processes. Use :meth:`run` or start/stop yourself."""

    def __init__(self, config: DemoConfig) -> None:
        self.config = config
        self.children: list[tuple[str, subprocess.Popen[bytes]]] = []
        self.viewer_key: str | None = None
        self.machine_ids: list[str] = []
        from cranetwin.settings import Settings, load_settings

        logs = load_settings(Settings).demo_logs
        default = Path(tempfile.gettempdir()) / f"cranetwin-demo-{os.getuid()}"
        self.logdir = logs if logs is not None else default

    # --- processes ---------------------------------------------------------------------------
    def _spawn(self, name: str, args: list[str]) -> subprocess.Popen[bytes]:
        self.logdir.mkdir(mode=0o700, parents=True, exist_ok=True)
        out = open(self.logdir / f"{name}.log", "ab")  # noqa: SIM115 - closed with the child
        env = {**os.environ, **self.config.extra_env}
        proc = subprocess.Popen([*cranetwin_command(), *args], stdout=out,
                                stderr=subprocess.STDOUT, env=env, start_new_session=True)
        out.close()
        self.children.append((name, proc))
        log.info("started %s (pid %d): %s", name, proc.pid, " ".join(args))
        return proc

    def _check_children(self) -> None:
        for name, proc in self.children:
            code = proc.poll()
            if code is not None:
                tail = self._log_tail(name)
                raise DemoError(f"{name} exited with status {code}; its log "
                                f"({self.logdir / (name + '.log')}) ends:\n{tail}")

    def _log_tail(self, name: str, lines: int = 15) -> str:
        try:
            text = (self.logdir / f"{name}.log").read_text("utf-8", errors="replace")
        except OSError:
            return "(no log)"
        return "\n".join(text.splitlines()[-lines:])

    def _run_cli(self, args: list[str]) -> str:
        res = subprocess.run([*cranetwin_command(), *args], capture_output=True, text=True,
                             env={**os.environ, **self.config.extra_env}, timeout=120)
        if res.returncode != 0:
            raise DemoError(f"cranetwin {' '.join(args[:2])} failed ({res.returncode}): "
                            f"{res.stderr.strip()[-800:]}")
        return res.stdout.strip()

    # --- HTTP --------------------------------------------------------------------------------
    def _request(self, method: str, path: str, key: str | None = None,
                 body: dict[str, Any] | None = None) -> Any:
        data = json.dumps(body).encode() if body is not None else None
        req = urllib.request.Request(self.config.api + path, data=data, method=method)
        req.add_header("Content-Type", "application/json")
        if key:
            req.add_header("X-API-Key", key)
        try:
            with urllib.request.urlopen(req, timeout=10) as resp:
                return json.loads(resp.read() or b"null")
        except urllib.error.HTTPError as exc:
            detail = exc.read().decode("utf-8", errors="replace")[:500]
            raise DemoError(f"{method} {path}: HTTP {exc.code}: {detail}") from exc

    def wait_healthy(self, timeout_s: float = 60.0) -> None:
        """Wait until ``/healthz`` answers 200."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                with urllib.request.urlopen(self.config.api + "/healthz", timeout=2) as resp:
                    if resp.status == 200:
                        return
            except (urllib.error.URLError, OSError):
                pass
            if not self.config.attach:
                self._check_children()
            if time.monotonic() > deadline:
                raise DemoError(f"the API at {self.config.api} did not become healthy in "
                                f"{timeout_s:.0f} s")
            time.sleep(0.2)

    # --- the demo ----------------------------------------------------------------------------
    def start(self) -> str:
        """Start everything; returns the URL to open (with the viewer key)."""
        c = self.config
        db = ["--db", c.db_url] if c.db_url else []
        if not c.attach:
            self._fresh_sqlite()
            # its Prometheus endpoint on a free port: the default 9105 may be taken
            self._spawn("ingest", ["ingest", "--bind", c.ingest, "--metrics-bind", "127.0.0.1:0",
                                   *db])
            self._spawn("api", ["serve", "--host", c.host, "--port", str(c.port), "--no-worker",
                                *db])
            self._spawn("worker", ["worker", "--metrics-bind", "0", *db])
        self.wait_healthy()
        admin = self._run_cli(["keys", "create", "--role", "admin", "--name", "fleet demo", *db])
        self.viewer_key = self._run_cli(["keys", "create", "--role", "viewer",
                                         "--name", "fleet demo viewer", *db])
        existing = {m["machine_id"] for m in self._request("GET", "/api/v1/machines", admin)}
        k = 0
        for i in range(c.machines):
            # a machine's secret is shown only once: on a database that already has crane-k
            # (a restarted docker-compose fleet) register the next free id instead
            k += 1
            while f"crane-{k}" in existing:
                k += 1
            mid = f"crane-{k}"
            payload = float(c.payloads_kg[i % len(c.payloads_kg)])
            lat, lon = demo_location(i)
            created = self._request("POST", "/api/v1/machines", admin, {
                "machine_id": mid, "model": c.model,
                "name": f"Crane {k} ({payload:.0f} kg logs)",
                "location": {"lat": lat, "lon": lon}})
            scenario = self._scenario_file(mid, payload, seed=i + 1)
            journals = self._fresh_journal(mid)
            self._spawn(f"send-{mid}", ["send", "--machine", mid, "--journal", str(journals),
                                        "--wire-id", str(created["wire_id"]),
                                        "--key-file", str(self._secret_file(mid, created)),
                                        "--scenario", str(scenario), "--host", c.ingest,
                                        "--speed", f"{c.speed}", "--seed", str(i + 1),
                                        "--sim-seconds", f"{c.scenario_s}",
                                        "--batch", str(c.batch),
                                        # status datagrams report where it was registered
                                        "--position", f"{lat!r},{lon!r}"])
            self.machine_ids.append(mid)
        public = c.public_url or c.api
        url = f"{public}/?key={self.viewer_key}"
        try:
            READY_FILE.write_text(url)
        except OSError:
            pass
        return url

    def _scenario_file(self, mid: str, payload_kg: float, seed: int) -> Path:
        """The ``log-loading`` cycle with logs of ``payload_kg`` as a scenario file."""
        from cranetwin.sim.scenario import log_loading

        scenario = log_loading(duration_s=self.config.scenario_s, payload_kg=payload_kg,
                               seed=seed)
        path = self.logdir / f"scenario-{mid}.json"
        self.logdir.mkdir(mode=0o700, parents=True, exist_ok=True)
        path.write_text(scenario.model_dump_json(), "utf-8")
        return path

    def _fresh_journal(self, mid: str) -> Path:
        """The demo's send-journal directory, without a journal of an earlier demo's ``mid``:
        the machine was just registered with a new secret, so what an old journal holds could
        never be acknowledged (its tags are under the old secret)."""
        root = self.logdir / "journal"
        root.mkdir(mode=0o700, parents=True, exist_ok=True)
        old = root / mid
        if old.exists():
            log.info("removing the send journal of an earlier demo's %s", mid)
            shutil.rmtree(old)
        return root

    def _secret_file(self, mid: str, created: dict[str, Any]) -> Path:
        """The machine's HMAC secret in a private file (never on a command line)."""
        path = self.logdir / f"secret-{mid}"
        path.touch(mode=0o600)
        path.write_text(str(created["secret"]), "utf-8")
        return path

    def _fresh_sqlite(self) -> None:
        url = self.config.db_url or ""
        if not url.startswith("sqlite:///"):
            return
        path = Path(url.removeprefix("sqlite:///"))
        for p in (path, Path(f"{path}-wal"), Path(f"{path}-shm")):
            if p.exists():
                log.info("removing the previous demo database %s", p)
                p.unlink()

    def stop(self, timeout_s: float = 15.0) -> None:
        """Stop children in order (senders, daemon, worker, API): SIGINT, then SIGTERM, then
        SIGKILL."""
        order = ([c for c in self.children if c[0].startswith("send-")] +
                 [c for c in self.children if c[0] == "ingest"] +
                 [c for c in self.children if c[0] == "worker"] +
                 [c for c in self.children if c[0] == "api"])
        for name, proc in order:
            if proc.poll() is not None:
                continue
            for sig, wait in ((signal.SIGINT, timeout_s), (signal.SIGTERM, 5.0),
                              (signal.SIGKILL, 5.0)):
                try:
                    proc.send_signal(sig)
                    proc.wait(wait)
                    break
                except subprocess.TimeoutExpired:
                    log.warning("%s did not stop on %s", name, sig.name)
                except ProcessLookupError:
                    break
        self.children.clear()
        try:
            READY_FILE.unlink()
        except OSError:
            pass

    def watch(self) -> None:
        """Block until a child dies (raises :class:`DemoError`) or Ctrl-C."""
        while True:
            self._check_children()
            time.sleep(0.5)
