"""``cranetwin bench replay``: one hour of 100 Hz sensor data replayed onto a 1 kHz grid.

Input: a synthetic hour (:mod:`cranetwin.testing.recordings`: analytic motion of the PATU 655
through its kinematics and inverse dynamics, the paper's channel set without the slew angle,
so theta0 is integrated from the pillar torque) with 0.5 % uniform sensor error, so that the
smoothing windows are real. Input generation and numba compile/cache load are not timed.

Timed: :func:`cranetwin.twin.iter_replay` over the whole hour, chunk by chunk (from the raw
samples: regularisation, the window choice, smoothing, payload, the 1 kHz stage), each chunk's
outputs then reduced by the consumer (maxima of the joint wrenches and cylinder forces, as a
load-history job would) and dropped. ``wall_seconds``/``cpu_seconds`` and
``real_time_factor`` are the replay's: the loop minus the consumer's own time, which is
reported apart (``consumer_seconds``, ``consumer_cpu_seconds``; ``total_wall_seconds`` is the
whole loop). On a busy shared machine the wall time is longer than the CPU time.
``peak_rss_mib`` is the process's peak resident memory.

``machine_hours_per_core_hour`` is replayed hours per CPU-hour (``time.process_time``) at the
worker's settings (payload estimated, wrenches with the forward-dynamics correction), from the
median run's CPU time; ``baseline_machine_hours_per_core_hour`` is the same with the generic
build (no kernels generated for the machine: ``ReplayOptions(generated_kernels=False)``),
measured in the same run, the same number of times (``generic_cpu_seconds`` its median,
``cpu_seconds_runs`` and ``generic_cpu_seconds_runs`` every run). Run with
``NUMBA_NUM_THREADS=1`` for figures per core.

A second baseline in the same run: scipy ``CubicSpline(bc_type="natural")`` per channel and a plain
per-grid-instant path (kinematics, Eq. 1–2 and inverse dynamics called one instant at a time
through the same physics functions), timed on ``baseline_seconds_of_data`` of the recording and
scaled to the hour; ``speedup`` = scaled baseline / measured.
"""

from __future__ import annotations

import resource
import sys
import time
from typing import Any

import numpy as np
import typer
from scipy.interpolate import CubicSpline

from cranetwin import physics
from cranetwin.bench import emit
from cranetwin.model import load_machine
from cranetwin.signal import inject_uniform_noise
from cranetwin.testing.recordings import make
from cranetwin.twin import ReplayOptions, iter_replay


def _peak_rss_mib() -> float:
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024.0 * 1024.0) if sys.platform == "darwin" else peak / 1024.0


def _baseline(samples: Any, machine: Any, grid_hz: float, seconds: float) -> float:
    """Seconds for the per-instant path on the first ``seconds`` of data."""
    t = samples.t_s
    n = int(seconds * 100) + 1
    t_sub = t[:n]
    vals = samples.values[:n]
    grid = np.arange(int(round((t_sub[-1] - t_sub[0]) * grid_hz)) + 1) / grid_hz + t_sub[0]
    names = samples.channels
    start = time.perf_counter()
    splines = [CubicSpline(t_sub, vals[:, j], bc_type="natural") for j in range(len(names))]
    col = {nm: i for i, nm in enumerate(names)}
    cyls = machine.cylinders
    for tk in grid:
        s = np.array([[float(splines[col[c]](tk)) for c in ("lift_s", "jib_s", "ext_s")]])
        v = np.array([[float(splines[col[c]](tk, 1)) for c in ("lift_s", "jib_s", "ext_s")]])
        a = np.array([[float(splines[col[c]](tk, 2)) for c in ("lift_s", "jib_s", "ext_s")]])
        q, qd, qdd = physics.joint_motion_from_cylinders(machine, s, v, a)
        f = [physics.cylinder_force(float(splines[col[p + "_pA"]](tk)),
                                    float(splines[col[p + "_pB"]](tk)), v[0, i], cyls[i])
             for i, p in enumerate(("lift", "jib", "ext"))]
        physics.actuator_torques(machine, q, np.array([f]))
        physics.inverse_dynamics(machine, q, qd, qdd, 150.0)
    return time.perf_counter() - start


def _timed_replay(noisy: Any, machine: Any, grid_hz: float, force_max: Any,
                  generated: bool = True) -> tuple[float, float, float, float, float, int]:
    """One timed replay of the recording: (replay wall, replay CPU, consumer wall, consumer CPU,
    whole loop wall [s], grid instants); the consumer keeps the maxima in ``force_max``."""
    start = time.perf_counter()
    cpu0 = time.process_time()
    n_grid = 0
    wrench_max = np.zeros((machine.n_joints, 6))
    use_wall = 0.0
    use_cpu = 0.0
    opt = ReplayOptions(grid_hz=grid_hz, generated_kernels=generated)
    for part in iter_replay(noisy, machine, grid_hz, options=opt):
        u0, c0 = time.perf_counter(), time.process_time()
        n_grid += part.n
        np.maximum(wrench_max, np.abs(part.joint_wrench).max(axis=0), out=wrench_max)
        np.maximum(force_max, np.abs(part.cyl_force).max(axis=0), out=force_max)
        use_wall += time.perf_counter() - u0
        use_cpu += time.process_time() - c0
    total_wall = time.perf_counter() - start
    total_cpu = time.process_time() - cpu0
    return (total_wall - use_wall, total_cpu - use_cpu, use_wall, use_cpu, total_wall, n_grid)


def run(recording_seconds: float = 3600.0, grid_hz: float = 1000.0,
        baseline_seconds_of_data: float = 2.0, repeat: int = 1) -> dict[str, Any]:
    """Run the benchmark; return its figures (see the module docstring). With ``repeat`` > 1
    the hour is replayed that many times: ``wall_seconds`` and the consumer's times are the
    median run's by wall time, ``cpu_seconds`` the median CPU time (the lower middle one for
    an even count); ``wall_seconds_runs`` and ``cpu_seconds_runs`` list every run."""
    if repeat < 1:
        raise ValueError(f"repeat must be at least 1, got {repeat}")
    machine = load_machine("patu655")
    warm = make(machine, duration_s=20.0, fine_hz=None, scale=0.5)
    t0 = time.perf_counter()
    for generated in (True, False):
        for _ in iter_replay(warm.samples, machine, grid_hz,
                             options=ReplayOptions(grid_hz=grid_hz, generated_kernels=generated)):
            pass
    compile_seconds = time.perf_counter() - t0
    syn = make(machine, duration_s=recording_seconds, fine_hz=None, scale=0.5,
               payload=lambda t: 150.0 + 100.0 * np.sin(2 * np.pi * t / 600.0))
    noisy = inject_uniform_noise(syn.samples, machine, 0.005, seed=0)
    runs: list[tuple[float, float, float, float, float, int]] = []
    generic_cpu: list[float] = []
    force_max = np.zeros(len(machine.cylinders))
    for _ in range(repeat):  # interleaved, so that both builds see the same machine load
        runs.append(_timed_replay(noisy, machine, grid_hz, force_max))
        generic_cpu.append(_timed_replay(noisy, machine, grid_hz, force_max, False)[1])
    cpu_runs = [round(r[1], 3) for r in runs]
    mid = (len(runs) - 1) // 2
    cpu = sorted(r[1] for r in runs)[mid]  # the median CPU time, whichever run had it
    runs.sort()
    wall, _, use_wall, use_cpu, total_wall, n_grid = runs[mid]
    g_cpu = sorted(generic_cpu)[mid]
    peak = _peak_rss_mib()
    base = _baseline(noisy, machine, grid_hz, baseline_seconds_of_data)
    base_scaled = base * recording_seconds / baseline_seconds_of_data
    return {
        "recording_seconds": recording_seconds,
        "sample_hz": 100.0,
        "grid_hz": grid_hz,
        "grid_points": n_grid,
        "wall_seconds": round(wall, 3),
        "wall_seconds_runs": [round(r[0], 3) for r in runs],
        "real_time_factor": round(recording_seconds / wall, 1),
        "cpu_seconds": round(cpu, 3),  # on a shared machine wall > cpu when others run
        "cpu_seconds_runs": cpu_runs,
        "machine_hours_per_core_hour": round(recording_seconds / cpu, 1),
        "generic_cpu_seconds": round(g_cpu, 3),
        "generic_cpu_seconds_runs": [round(c, 3) for c in generic_cpu],
        "baseline_machine_hours_per_core_hour": round(recording_seconds / g_cpu, 1),
        "consumer_seconds": round(use_wall, 3),
        "consumer_cpu_seconds": round(use_cpu, 3),
        "total_wall_seconds": round(total_wall, 3),
        "peak_rss_mib": round(peak, 1),
        "compile_seconds": round(compile_seconds, 3),
        "baseline": "scipy CubicSpline + per-instant physics calls, "
                    f"{baseline_seconds_of_data:g} s of data timed and scaled",
        "baseline_seconds": round(base_scaled, 1),
        "speedup": round(base_scaled / wall, 1),
        "max_cylinder_force_n": [round(float(x), 1) for x in force_max],
    }


def register(bench_app: typer.Typer) -> None:
    @bench_app.command("replay")
    def replay_cmd(
        seconds: float = typer.Option(3600.0, help="Recording length in seconds, at 100 Hz."),
        grid_hz: float = typer.Option(1000.0, help="Output grid rate in Hz."),
        as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
        repeat: int = typer.Option(1, min=1, help="Replay the hour this many times and report "
                                                  "the median run (every run is listed)."),
    ) -> None:
        """Replay one hour of 100 Hz data onto a 1 kHz grid; time, memory, baseline ratio."""
        out = run(seconds, grid_hz, repeat=repeat)
        emit(out, as_json)
