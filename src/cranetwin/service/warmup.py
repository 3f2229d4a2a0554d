"""Warm-up of the service right after start, so that the first machine page is not the one that
pays for loading the twin.

The first replay in a fresh process loads the twin's compiled (numba) kernels and imports the
physics, signal and view modules; the first scene imports trimesh and meshes the crane. Done on
the first request, that made the cold first paint of a machine page ~3 s against ~1.25 s warm.
:func:`warm_up` does it once on a few seconds of synthetic samples of the built-in crane
(:mod:`cranetwin.testing.blocks`). The service runs it before it starts serving (about 0.5 s
after the imports): run in a background thread instead, it competed with the first requests for
the interpreter and doubled their p95 latency for the first seconds; :func:`start_warm_up` is
the background variant.

The first replay of a machine with at least 20 s of samples also chooses its smoothing (about
two thirds of the cost of a replay, :mod:`cranetwin.service.replayer`), which short windows such
as the page's first 1-s frame then reuse; the service therefore replays the newest 30 s of its four
most recently seen machines after the generic warm-up (``then``).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

from cranetwin.errors import CraneTwinError

log = logging.getLogger(__name__)


def warm_up(model: str = "patu655") -> float:
    """Replay 6 s of synthetic samples of ``model`` at 100 Hz through everything a machine page
    asks for (twin JSON, live frames, 3D scene), discarding the results.

    Returns:
        Time taken [s].
    """
    t = time.perf_counter()
    from cranetwin.model import load_machine
    from cranetwin.service.views import LiveKinematics, twin_json
    from cranetwin.testing.blocks import kinematic_samples
    from cranetwin.twin import replay
    from cranetwin.viz.scene import build_scene

    machine = load_machine(model)
    samples = kinematic_samples(machine, 6.0, t0_s=1_800_000_000.0)
    res = replay(samples, machine, grid_hz=100.0)
    twin_json(machine, res, float(samples.t_s[100]), float(samples.t_s[-100]), 50.0)
    LiveKinematics(machine, samples.channels).frames(samples.t_s[-1:], samples.values[-1:],
                                                      samples.values[-2], samples.t_s[-2])
    build_scene(machine)
    return time.perf_counter() - t


def run_warm_up(model: str = "patu655", then: Callable[[], object] | None = None) -> None:
    """Run :func:`warm_up` and then ``then`` (e.g. per-machine warm-up); failures are logged,
    never raised."""
    try:
        log.info("warm-up done in %.2f s", warm_up(model))
        if then is not None:
            t = time.perf_counter()
            then()
            log.info("machine warm-up done in %.2f s", time.perf_counter() - t)
    except (CraneTwinError, ImportError, ValueError, RuntimeError) as exc:
        log.warning("warm-up failed (the first requests will be slower): %s", exc)


def start_warm_up(model: str = "patu655",
                  then: Callable[[], object] | None = None) -> threading.Thread:
    """:func:`run_warm_up` in a daemon thread."""
    th = threading.Thread(target=run_warm_up, args=(model, then), name="warm-up", daemon=True)
    th.start()
    return th
