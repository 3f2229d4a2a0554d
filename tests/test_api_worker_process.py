"""``cranetwin worker`` as its own process: results appear in the database the API reads, and
SIGTERM ends it cleanly (exit status 0)."""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cranetwin.model import load_machine
from cranetwin.service.backend import Backend
from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

T0 = 1795420800.0  # a whole minute
MID = "crane-p"


def _readline(proc: subprocess.Popen[str], timeout_s: float) -> str:
    assert proc.stdout is not None
    ready, _, _ = select.select([proc.stdout], [], [], timeout_s)
    return proc.stdout.readline() if ready else ""


@pytest.mark.timeout(180)
def test_worker_process_replays_stored_samples_and_stops_on_sigterm(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'worker.db'}"
    machine = load_machine("patu655")
    b = Backend.open(url)
    b.store.add_machine(MID, wire_id=3, secret=b"s" * 32)
    base = kinematic_samples(machine, 120.0)
    b.store.write_blocks(list(tiled_blocks(MID, machine, T0, 130.0, 1.0, base=base,
                                           origin_s=T0)))
    env = {**os.environ, "CRANETWIN_WORKER_INTERVAL_S": "0.1"}
    env.pop("CRANETWIN_DATABASE_URL", None)
    proc = subprocess.Popen([sys.executable, "-c", "from cranetwin.cli import main; main()",
                             "worker", "--db", url, "--log-level", "warning"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        line = _readline(proc, 60.0)
        assert line.startswith("cranetwin worker ready"), (line, proc.stderr and
                                                            proc.stderr.read())
        deadline = time.monotonic() + 120.0
        prog = None
        while time.monotonic() < deadline:
            prog = b.progress(MID)
            if prog is not None and prog.windows >= 2:
                break
            assert proc.poll() is None, proc.stderr and proc.stderr.read()
            time.sleep(0.2)
        assert prog is not None and prog.windows == 2 and prog.watermark_s == T0 + 120
        hist = b.summaries(MID, ["payload", "force:lift"], T0, T0 + 120, 1000)
        assert hist["payload"][0].shape[0] == 120 and hist["force:lift"][0].shape[0] == 120
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert "stopped" in out
    b.close()
