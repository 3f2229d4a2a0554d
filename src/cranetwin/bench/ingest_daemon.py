"""Running ``cranetwin ingest`` as a child process for benchmarks and tests: start it on a port
and wait for its ready line (bounded), scrape its counters, stop or kill it, read its CPU time.
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["DaemonProcess", "cpu_seconds", "free_udp_port", "start_daemon"]


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class DaemonProcess:
    """A ``cranetwin ingest`` child process (see :func:`start_daemon`).

    Attributes:
        proc: The process.
        metrics_url: Its Prometheus ``/metrics`` URL (from its ready line).
        stderr_path: File that receives its log.
        info: Its ready line (with ``--processes N``: ``children``, each index, pid, metrics;
            ``metrics_url`` is then the first child's).
    """

    proc: subprocess.Popen[bytes]
    metrics_url: str
    stderr_path: Path
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def counters(self, timeout_s: float = 5.0) -> dict[str, Any]:
        """The daemon's counters now, scraped from ``/metrics``: ``{name: value}`` without the
        ``cranetwin_ingest_`` prefix and ``_total`` suffix, ``dropped`` as ``{reason: n}``;
        ``{}`` if it does not answer."""
        import urllib.request

        from prometheus_client.parser import text_string_to_metric_families

        try:
            text = urllib.request.urlopen(self.metrics_url, timeout=timeout_s).read().decode()
        except OSError:
            return {}
        out: dict[str, Any] = {"dropped": {}}
        for fam in text_string_to_metric_families(text):
            for smp in fam.samples:
                name = smp.name.removeprefix("cranetwin_ingest_")
                if name.startswith("dropped"):
                    out["dropped"][smp.labels.get("reason", "?")] = int(smp.value)
                elif name.endswith("_total"):
                    out[name.removesuffix("_total")] = smp.value
        return out

    def stop(self, timeout_s: float = 60.0) -> dict[str, Any]:
        """SIGTERM, wait, and return the final counters of its ``stopped`` line ({} if none)."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        self.proc.wait(timeout_s)
        return self._last_line("stopped")

    def kill(self) -> None:
        """SIGKILL (no flush, no goodbye) and reap."""
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(10)

    def poll(self) -> int | None:
        return self.proc.poll()

    def _last_line(self, event: str) -> dict[str, Any]:
        assert self.proc.stdout is not None
        rest = self.proc.stdout.read().decode(errors="replace")
        for line in reversed(rest.splitlines()):
            with contextlib.suppress(ValueError):
                d = json.loads(line)
                if isinstance(d, dict) and d.get("event") == event:
                    return d
        return {}


def wait_ready(proc: subprocess.Popen[bytes], log: Path, ready: bytes,
               timeout_s: float = 300.0) -> bytes:
    """The first stdout line of ``proc`` once it starts with ``ready`` (bounded wait).

    Raises:
        RuntimeError: it exited, printed something else or did not get ready in time (it is
            killed; its log attached).
    """
    assert proc.stdout is not None
    end = time.monotonic() + timeout_s
    buf = b""
    while b"\n" not in buf:
        left = end - time.monotonic()
        got, _, _ = select.select([proc.stdout], [], [], max(0.0, min(left, 0.5)))
        if got:
            chunk = os.read(proc.stdout.fileno(), 4096)
            buf += chunk
            if chunk:
                continue
        if proc.poll() is not None or left <= 0:
            proc.kill()
            proc.wait(10)
            raise RuntimeError(f"{log.name}: did not start: {log.read_text()[-2000:]}")
    line = buf.split(b"\n", 1)[0]
    if not line.startswith(ready):
        proc.kill()
        proc.wait(10)
        raise RuntimeError(f"{log.name}: unexpected first line {line[:200]!r}")
    return line


def start_daemon(db_url: str, port: int, workdir: Path, *extra: str, host: str = "127.0.0.1",
                 prefix: Sequence[str] = (), ready_timeout_s: float = 60.0) -> DaemonProcess:
    """``cranetwin ingest`` in a subprocess on ``host``:``port``, its Prometheus endpoint on a
    free port; returns once its ``ready`` line says it is listening (≤ ``ready_timeout_s``).
    ``prefix`` is put before the command (e.g. ``ip netns exec NAME``: the daemon in a network
    namespace).

    Its log goes to a file in ``workdir``, never to a pipe nobody reads; stdout (two lines: ready,
    stopped) is read with a deadline, so a daemon that hangs at start cannot hang the caller.

    Raises:
        RuntimeError: it exited or did not get ready in time (its log attached).
    """
    workdir.mkdir(parents=True, exist_ok=True)
    cmd = [*prefix, sys.executable, "-c", "from cranetwin.cli import main; main()", "ingest",
           "--bind", f"{host}:{port}", "--db", db_url, "--metrics-bind", "127.0.0.1:0",
           "--log-level", "WARNING", *extra]
    log = workdir / f"ingest-{host}-{port}.stderr"
    with open(log, "ab") as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err)
    line = wait_ready(proc, log, b"{", ready_timeout_s)
    info = json.loads(line)
    metrics = info.get("metrics")
    if isinstance(metrics, list):
        metrics = metrics[0] if metrics else None
    return DaemonProcess(proc, str(metrics or ""), log, info)


def cpu_seconds(pid: int) -> float | None:
    """User + system CPU time of a process so far [s] (Linux /proc), or None."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None
