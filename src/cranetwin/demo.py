"""The one-command demo: ingest daemon, API service and a simulated fleet, stopped by one Ctrl-C.

:class:`FleetDemo` runs each part as a child process of the ``cranetwin`` command (the same
commands a deployment runs, see ``docker-compose.yml``):

1. ``cranetwin ingest`` — the UDP daemon writing to the embedded SQLite database;
2. ``cranetwin serve --no-worker`` — the HTTP API, live websocket and web UI on the same database;
   ``cranetwin worker`` — the twin worker, its own process as in a deployment: its numba replays
   (a second of CPU per machine-minute) never compete with the API's requests for the
   interpreter, a crash of one leaves the other running, and the demo exercises the same
   two-process path (progress marks in the database) that production runs;
3. an admin key (to register machines) and a fleet key (printed beside the URL, to sign in once
   in the browser: the page keeps a session cookie, no key travels in a URL; fleet so that the
   Report button works) via ``cranetwin keys create``; machines registered with
   ``POST /api/v1/machines``;
4. one ``cranetwin send`` per crane, streaming the simulator's ``log-loading`` work cycles with its
   own log mass (a scenario file per crane) over UDP, in real time, simulated continuously (a
   simulator session advanced as the sender needs samples: no replayed loop that jumps the crane
   back to its first pose).

Start-up is guarded: a lock file in the demo's directory (and one beside an SQLite database)
refuses a second demo over a running one, the API and UDP ports are probed before anything
starts, and nothing an earlier run left is deleted — an existing demo database is continued
(its cranes stream again with the secrets kept in the demo's directory), an old send journal
that cannot belong to a newly registered crane is moved aside. The wait for the API follows its
progress (process started, port open, ``/healthz``) and says what it waits for.

With ``attach=True`` only steps 3–4 run, against a service and daemon started elsewhere (the
``fleet`` service of docker-compose). Children run in their own sessions so that the terminal's
Ctrl-C reaches only this process, which then stops them in order: senders (they flush), then the
daemon (it flushes its queue), then the worker (it finishes its window), then the API.

Where the children's logs go is the ``demo_logs`` setting (``CRANETWIN_DEMO_LOGS``).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Sequence
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
        payloads_kg: Log mass per crane [kg] (cycled when there are more cranes), within the
            PATU 655's rated load at the scenario's reach (≥ 550 kg at 3.8–4.1 m) also with the
            scenario's ± 15 % per log: the demo raises no overload warnings of its own.
        db_url: Database of the daemon and the service (embedded SQLite by default; None =
            ``CRANETWIN_DATABASE_URL``). An existing database is continued, never deleted.
        host: Bind address of the API.
        port: TCP port of the API.
        udp_port: UDP port of the ingest daemon.
        speed: Simulation speed (1 = real time).
        attach: Only register machines and stream (service and daemon run elsewhere).
        api_url: API base URL when attached (default ``http://host:port``).
        ingest_addr: ``host:port`` of the daemon when attached.
        public_url: Base URL printed for the browser (default: the API URL).
        model: Machine model of the cranes.
        scenario_s: Simulated work per crane [s], continuous (the cranes hold still after it).
        start_timeout_s: Longest wait for the API to answer ``/healthz`` [s] (a first start
            compiles numba kernels and migrates the database; the wait reports its progress).
        batch: Samples per datagram (5 at 100 Hz: 20 datagrams/s, so the live view gets 20
            frames/s; the sender's default of 50 saves bytes but adds 0.5 s of latency).
    """

    machines: int = 3
    payloads_kg: Sequence[float] = (250.0, 320.0, 200.0, 280.0, 150.0)
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
    scenario_s: float = 86400.0
    start_timeout_s: float = 600.0
    batch: int = 5
    extra_env: dict[str, str] = field(default_factory=dict)

    @property
    def api(self) -> str:
        return self.api_url or f"http://{self.host}:{self.port}"

    @property
    def ingest(self) -> str:
        return self.ingest_addr or f"127.0.0.1:{self.udp_port}"


def demo_dir(port: int) -> Path:
    """The demo's default directory (logs, lock, scenario and secret files) for an API on
    ``port``: ``$TMPDIR/cranetwin-demo-<uid>-<port>``, so demos on other ports do not meet."""
    return Path(tempfile.gettempdir()) / f"cranetwin-demo-{os.getuid()}-{port}"


def port_in_use(host: str, port: int, kind: int = socket.SOCK_STREAM) -> bool:
    """Whether binding ``host:port`` (TCP, or UDP with ``kind=SOCK_DGRAM``) fails because it is
    taken (a TCP port in TIME_WAIT counts as free)."""
    with socket.socket(socket.AF_INET, kind) as s:
        if kind == socket.SOCK_STREAM:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError:
            return True
    return False


class DemoLock:
    """An exclusive ``flock`` on a file holding the owner's pid and URL. The kernel releases it
    when the process ends, however it ends, so a crashed demo leaves no stale lock."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._fd: int | None = None

    def acquire(self, what: str) -> None:
        """Take the lock, or raise :class:`DemoError` naming the running demo."""
        self.path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            try:
                owner = self.path.read_text("utf-8").strip()
            except OSError:
                owner = ""
            owner = owner or f"lock {self.path}"
            raise DemoError(f"a demo is already running on {what} ({owner}). "
                            "Stop it first (Ctrl-C in its terminal), or start another one with "
                            "other --port, --udp-port and --db.") from None
        self._fd = fd

    def write(self, text: str) -> None:
        if self._fd is not None:
            os.ftruncate(self._fd, 0)
            os.pwrite(self._fd, text.encode(), 0)

    def release(self) -> None:
        if self._fd is not None:
            with contextlib.suppress(OSError):
                self.path.unlink()
            os.close(self._fd)
            self._fd = None


def cranetwin_command() -> list[str]:
    """argv prefix that runs the ``cranetwin`` CLI with this interpreter."""
    return [sys.executable, "-c", "from cranetwin.cli import main; main()"]


def demo_location(i: int) -> tuple[float, float]:
    """GPS position of the demo's ``i``-th crane (0-based): latitude, longitude [deg], a few
    km apart near Joensuu. The crane is registered there and its sender reports it."""
    return 62.60 + 0.01 * i, 29.76 + 0.02 * i


def demo_scenario(payload_kg: float, seed: int, duration_s: float) -> Any:
    """The scenario a demo crane streams: ``log-loading`` cycles with logs of ``payload_kg``
    (± 15 % per log) for ``duration_s``, simulated continuously by its sender."""
    from cranetwin.sim.scenario import log_loading

    return log_loading(duration_s=duration_s, payload_kg=payload_kg, seed=seed)


class FleetDemo:
    """Start, watch and stop the demo's processes. Use :meth:`run` or start/stop yourself."""

    def __init__(self, config: DemoConfig,
                 progress: Callable[[str], None] | None = None) -> None:
        self.config = config
        self.children: list[tuple[str, subprocess.Popen[bytes]]] = []
        self.browser_key: str | None = None
        self.machine_ids: list[str] = []
        self.progress = progress or log.info
        from cranetwin.settings import Settings, load_settings

        logs = load_settings(Settings).demo_logs
        self.logdir = logs if logs is not None else demo_dir(config.port)
        self._locks: list[DemoLock] = []

    # --- processes ---------------------------------------------------------------------------
    def _spawn(self, name: str, args: list[str],
               defaults: dict[str, str] | None = None) -> subprocess.Popen[bytes]:
        """Start ``cranetwin <args>``; ``defaults``: environment variables it gets unless the
        environment (or the config's ``extra_env``) sets them."""
        self.logdir.mkdir(mode=0o700, parents=True, exist_ok=True)
        out = open(self.logdir / f"{name}.log", "ab")  # noqa: SIM115 - closed with the child
        env = {**(defaults or {}), **os.environ, **self.config.extra_env}
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

    def _health(self) -> tuple[bool, str]:
        """(healthy, what the API is doing as far as one probe can tell)."""
        try:
            with urllib.request.urlopen(self.config.api + "/healthz", timeout=2) as resp:
                if resp.status == 200:
                    return True, "healthy"
                return False, f"/healthz answers HTTP {resp.status}"
        except urllib.error.HTTPError as exc:
            return False, f"/healthz answers HTTP {exc.code}"
        except (urllib.error.URLError, OSError) as exc:
            reason = getattr(exc, "reason", exc)
            if isinstance(reason, ConnectionRefusedError):
                return False, ("its port is not open yet (the process is importing, compiling "
                               "or migrating the database)")
            if isinstance(reason, TimeoutError | socket.timeout):
                return False, "its port is open but /healthz does not answer yet (starting up)"
            return False, f"no answer yet ({reason})"

    def wait_healthy(self, timeout_s: float | None = None) -> None:
        """Wait until ``/healthz`` answers 200, reporting each change of what is waited for
        (and every 15 s the API log's last line) through :attr:`progress`.

        Raises:
            DemoError: a child died, or ``timeout_s`` (default ``start_timeout_s``) passed.
        """
        timeout_s = self.config.start_timeout_s if timeout_s is None else timeout_s
        t0 = time.monotonic()
        last, next_note = "", t0 + 15.0
        while True:
            ok, state = self._health()
            if ok:
                self.progress(f"the API answers at {self.config.api} "
                              f"({time.monotonic() - t0:.1f} s)")
                return
            if not self.config.attach:
                self._check_children()
            now = time.monotonic()
            if state != last:
                self.progress(f"waiting for the API at {self.config.api}: {state}")
                last = state
            elif now >= next_note:
                tail = "" if self.config.attach else self._log_tail("api", 1).strip()
                self.progress(f"still waiting for the API ({now - t0:.0f} s of at most "
                              f"{timeout_s:.0f} s): {state}" + (f"; its log: {tail}" if tail
                                                                 else ""))
                next_note = now + 15.0
            if now - t0 > timeout_s:
                where = "" if self.config.attach else (
                    f"; its log ({self.logdir / 'api.log'}) ends:\n{self._log_tail('api')}")
                raise DemoError(f"the API at {self.config.api} did not become healthy in "
                                f"{timeout_s:.0f} s (--start-timeout): {state}{where}")
            time.sleep(0.2)

    def preflight(self) -> None:
        """Refuse to start over a running demo or on a taken port (before anything starts).

        Raises:
            DemoError: the demo's lock is held, or a port is in use.
        """
        c = self.config
        lock = DemoLock(self.logdir / "demo.lock")
        lock.acquire(f"the directory {self.logdir}")
        self._locks.append(lock)
        db = self._sqlite_path()
        if db is not None:
            dblock = DemoLock(Path(f"{db}.demo-lock"))
            dblock.acquire(f"the database {db}")
            self._locks.append(dblock)
        if port_in_use(c.host, c.port):
            raise DemoError(f"TCP port {c.port} on {c.host} is in use (another demo or "
                            f"program?); choose another with --port")
        if port_in_use("127.0.0.1", c.udp_port, socket.SOCK_DGRAM):
            raise DemoError(f"UDP port {c.udp_port} is in use (another demo's ingest daemon?); "
                            "choose another with --udp-port")
        for lk in self._locks:
            lk.write(f"pid {os.getpid()}, API {c.api}, UDP {c.ingest}\n")

    # --- the demo ----------------------------------------------------------------------------
    def start(self) -> str:
        """Start everything; returns the URL to open (the key to sign in with is
        :attr:`browser_key`)."""
        c = self.config
        db = ["--db", c.db_url] if c.db_url else []
        if not c.attach:
            self.preflight()
            db_path = self._sqlite_path()
            if db_path is not None and db_path.exists():
                self.progress(f"continuing the existing demo database {db_path} (delete it "
                              "for a fresh start)")
            self._migrate()
            # its Prometheus endpoint on a free port: the default 9105 may be taken
            self._spawn("ingest", ["ingest", "--bind", c.ingest, "--metrics-bind", "127.0.0.1:0",
                                   *db])
            # one local user: replays on the API's threads, no replay process to start beside
            # the three of the demo (fairness between keys is for shared servers)
            self._spawn("api", ["serve", "--host", c.host, "--port", str(c.port), "--no-worker",
                                *db], defaults={"CRANETWIN_HEAVY_PROCESSES": "0"})
            self._spawn("worker", ["worker", "--metrics-bind", "0", *db])
        self.wait_healthy()
        admin = self._create_key("admin", "fleet demo")
        self.browser_key = self._create_key("fleet", "fleet demo browser")
        existing = {m["machine_id"]: m for m in self._request("GET", "/api/v1/machines",
                                                              admin)}
        k = 0
        for i in range(c.machines):
            k += 1
            mid = f"crane-{k}"
            payload = float(c.payloads_kg[i % len(c.payloads_kg)])
            lat, lon = demo_location(i)
            secret = self.logdir / f"secret-{mid}"
            wire_file = self.logdir / f"wire-{mid}"
            if mid in existing and secret.exists() and wire_file.exists():
                # a continued demo: this crane's secret and wire id are in the demo's directory
                wire_id = int(wire_file.read_text("utf-8"))
                self.progress(f"{mid}: continuing (registered by an earlier run)")
            else:
                # a machine's secret is shown only once: on a database that already has crane-k
                # without its secret here (a restarted docker-compose fleet) use the next free id
                while mid in existing:
                    k += 1
                    mid = f"crane-{k}"
                created = self._request("POST", "/api/v1/machines", admin, {
                    "machine_id": mid, "model": c.model,
                    "name": f"Crane {k} ({payload:.0f} kg logs)",
                    "location": {"lat": lat, "lon": lon}})
                wire_id = int(created["wire_id"])
                secret = self._secret_file(mid, created)
                wire_file.write_text(str(wire_id), "utf-8")
                self._set_journal_aside(mid)
            scenario = self._scenario_file(mid, payload, seed=i + 1)
            self._spawn(f"send-{mid}", ["send", "--machine", mid,
                                        "--journal", str(self._journal_root()),
                                        "--wire-id", str(wire_id), "--key-file", str(secret),
                                        "--scenario", str(scenario), "--host", c.ingest,
                                        "--speed", f"{c.speed}", "--seed", str(i + 1),
                                        "--batch", str(c.batch),
                                        # status datagrams report where it was registered
                                        "--position", f"{lat!r},{lon!r}"])
            self.machine_ids.append(mid)
        public = c.public_url or c.api
        url = f"{public}/"
        try:
            READY_FILE.write_text(url)  # never the key: /tmp is readable by every user
        except OSError:
            pass
        return url

    def _scenario_file(self, mid: str, payload_kg: float, seed: int) -> Path:
        """The ``log-loading`` cycles with logs of ``payload_kg`` as a scenario file."""
        scenario = demo_scenario(payload_kg, seed, self.config.scenario_s)
        path = self.logdir / f"scenario-{mid}.json"
        self.logdir.mkdir(mode=0o700, parents=True, exist_ok=True)
        path.write_text(scenario.model_dump_json(), "utf-8")
        return path

    def _journal_root(self) -> Path:
        root = self.logdir / "journal"
        root.mkdir(mode=0o700, parents=True, exist_ok=True)
        return root

    def _set_journal_aside(self, mid: str) -> None:
        """Move an earlier demo's journal of ``mid`` aside (never deleted): the machine was just
        registered with a new secret, so what an old journal holds could never be acknowledged
        (its tags are under the old secret)."""
        old = self._journal_root() / mid
        if old.exists():
            aside = old.with_name(f"{mid}.old-{time.strftime('%Y%m%dT%H%M%S')}")
            self.progress(f"moving an earlier demo's send journal of {mid} aside to {aside}")
            old.rename(aside)

    def _secret_file(self, mid: str, created: dict[str, Any]) -> Path:
        """The machine's HMAC secret in a private file (never on a command line)."""
        path = self.logdir / f"secret-{mid}"
        path.touch(mode=0o600)
        path.write_text(str(created["secret"]), "utf-8")
        return path

    def _create_key(self, role: str, name: str) -> str:
        """A new API key: in this process when the demo runs its own database (no second
        interpreter start, seconds on a busy machine), else with ``cranetwin keys create``."""
        c = self.config
        if c.attach:
            db = ["--db", c.db_url] if c.db_url else []
            return self._run_cli(["keys", "create", "--role", role, "--name", name, *db])
        from sqlalchemy.exc import SQLAlchemyError
        from sqlalchemy.orm import Session

        from cranetwin.service.keys import new_key
        from cranetwin.settings import Settings, load_settings
        from cranetwin.storage import apikeys
        from cranetwin.storage.engine import make_engine

        engine = make_engine(c.db_url or load_settings(Settings).database_url)
        try:
            key_id, token, digest = new_key()
            with Session(engine) as s, s.begin():
                apikeys.add_key(s, key_id, digest, role, name)
        except (CraneTwinError, SQLAlchemyError) as exc:
            raise DemoError(f"cannot create the demo's {role} key: {exc}") from exc
        finally:
            engine.dispose()
        return token

    def _migrate(self) -> None:
        """Bring the database's schema up to date once, before the daemon, API and worker start:
        on a new database the three would otherwise race to create it (one fails with "table
        alembic_version already exists").

        Raises:
            DemoError: the database cannot be opened or migrated.
        """
        logging.getLogger("alembic").setLevel(logging.WARNING)  # not its plugin list
        from cranetwin.settings import Settings, load_settings
        from cranetwin.storage.engine import display_url, make_engine, migrate

        url = self.config.db_url or load_settings(Settings).database_url
        self.progress(f"preparing the database {display_url(url)}")
        try:
            engine = make_engine(url)
            try:
                migrate(engine)
            finally:
                engine.dispose()
        except CraneTwinError as exc:
            raise DemoError(f"the database {display_url(url)} cannot be prepared: {exc}") from exc

    def _sqlite_path(self) -> Path | None:
        url = self.config.db_url or ""
        if not url.startswith("sqlite:///"):
            return None
        return Path(url.removeprefix("sqlite:///")).absolute()

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
        for lk in self._locks:
            lk.release()
        self._locks.clear()

    def live_machines(self) -> set[str]:
        """The demo's cranes the API lists as ``live`` (empty when it cannot tell)."""
        try:
            listed = self._request("GET", "/api/v1/machines", self.browser_key)
        except (DemoError, OSError, ValueError):
            return set()
        return {m["machine_id"] for m in listed
                if m.get("status") == "live" and m["machine_id"] in self.machine_ids}

    def watch(self, t0: float | None = None) -> None:
        """Block until a child dies (raises :class:`DemoError`) or Ctrl-C; reports through
        :attr:`progress` when each crane first shows as live (seconds since ``t0``, a
        ``time.monotonic()`` value, default now)."""
        t0 = time.monotonic() if t0 is None else t0
        seen: set[str] = set()
        next_poll = 0.0
        while True:
            self._check_children()
            now = time.monotonic()
            if len(seen) < len(self.machine_ids) and now >= next_poll:
                next_poll = now + 1.0
                for mid in sorted(self.live_machines() - seen):
                    seen.add(mid)
                    self.progress(f"{mid} is live ({now - t0:.1f} s after the start)")
            time.sleep(0.5)
