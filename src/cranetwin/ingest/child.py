"""One daemon process of ``cranetwin ingest --processes N`` (run by
:class:`~cranetwin.ingest.processes.ProcessGroup` as ``python -m cranetwin.ingest.child``).

Reads its settings as one JSON object on stdin (:func:`~cranetwin.ingest.processes.child_spec`:
database URL, ``DaemonConfig`` fields, the fleet bus's ``BusConfig`` fields or null, the
inherited socket's descriptor), serves on that socket until SIGTERM — writing to the database,
or publishing to the fleet bus (:func:`~cranetwin.ingest.bus_serve.serve_to_bus`) — and prints
two JSON lines on stdout as ``cranetwin ingest`` does:
``{"event": "ready", "index", "pid", "metrics"}`` and ``{"event": "stopped", <counters>}``.
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import logging
import os
import signal
import sys
from typing import Any

from cranetwin.ingest.config import DaemonConfig, IngestConfigError
from cranetwin.protocol import Limits

__all__ = ["main"]

_PR_SET_PDEATHSIG = 1


def _die_with_parent(parent_pid: int) -> None:
    """SIGTERM when the parent dies (Linux); exit now if it is gone already."""
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
    if os.getppid() != parent_pid:
        sys.exit(1)


def _emit(event: dict[str, Any]) -> None:
    with contextlib.suppress(BrokenPipeError):  # the parent is gone: nobody to tell
        sys.stdout.write(json.dumps(event) + "\n")
        sys.stdout.flush()


def main() -> None:
    """Serve one member socket of the group (blocking)."""
    from cranetwin.errors import CraneTwinError
    from cranetwin.ingest.daemon import IngestDaemon, serve
    from cranetwin.storage.live import open_bus
    from cranetwin.storage.shardmap import StoreSpec

    spec = json.loads(sys.stdin.read())
    _die_with_parent(int(spec["parent_pid"]))
    index = int(spec["index"])
    logging.basicConfig(level=str(spec["log_level"]).upper(),
                        format=f"%(asctime)s %(levelname)s %(name)s[{index}]: %(message)s")
    cfg = DaemonConfig(**spec["config"], limits=Limits(**spec["limits"]),
                       socket_fd=int(spec["fd"]))

    def ready(d: IngestDaemon) -> None:
        _emit({"event": "ready", "index": index, "pid": os.getpid(), "metrics": d.metrics_url})

    busy = float(spec["busy_timeout_s"])
    db = StoreSpec.from_json(spec["db_url"])
    try:
        live = open_bus(spec["live_url"]) if spec["live_url"] else None
        if spec.get("bus"):
            from cranetwin.bus.subjects import BusConfig
            from cranetwin.ingest.bus_serve import serve_to_bus

            final = serve_to_bus(db, BusConfig(**spec["bus"]), cfg, live,
                                 on_ready=ready, busy_timeout_s=busy)
        else:
            final = serve(db, cfg, live, on_ready=ready, busy_timeout_s=busy)
    except (IngestConfigError, CraneTwinError) as exc:
        sys.stderr.write(f"error: ingest process {index}: {exc}\n")
        sys.exit(2)
    _emit({"event": "stopped", "index": index, **final})


if __name__ == "__main__":
    main()
