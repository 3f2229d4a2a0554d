"""``cranetwin bench simulate``: how much faster than real time the simulator runs.

Measures :func:`cranetwin.sim.simulate` on the ``log-loading`` work cycle (hydraulics on, fixed
step 1e-4 s, semi-implicit scheme, truth kept at 1 kHz) on one thread: ``real_time_factor`` =
simulated seconds / wall seconds of the integration (best of ``reps``); on a shared machine
``real_time_factor_cpu`` (simulated / process CPU seconds) and ``load_average_1min`` tell how
much of the wall time was spent waiting for a core. Not timed: JIT compile or numba cache
load (reported as ``compile_seconds``). Also reported: the wall time of a whole
recording (integration + sensor model + joint reaction wrenches), the RK4 scheme's factor, and
the factor at a 5e-4 s step (≈ 25 µm / 0.16 bar from a 5e-5 s reference: fine for a demo fleet),
and the CPU factor of the excavator's ``dig-cycle`` (another topology, with a contact force).

Baseline, in the same run: the very same step function with numba's JIT disabled
(``NUMBA_DISABLE_JIT=1``, i.e. plain Python/NumPy executing the same code), in a subprocess over
a short span (``baseline_simulated_seconds``), scaled per step.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from typing import Any

import typer

from cranetwin.bench import emit

_BASELINE_CODE = """
import json, sys, time
from cranetwin.model import load_machine
from cranetwin.sim import load_scenario, prepare, simulate, SimOptions, SensorModel
span = float(sys.argv[1])
prep = prepare(load_machine("patu655"))
sc = load_scenario("log-loading")
t0 = time.perf_counter()
simulate(prep, sc, duration_s=span, sensors=SensorModel.ideal(), wrenches=False)
print(json.dumps({"wall": time.perf_counter() - t0}))
"""


def _baseline(span_s: float) -> float:
    """Wall seconds of ``span_s`` simulated seconds with the JIT disabled (subprocess)."""
    env = dict(os.environ, NUMBA_DISABLE_JIT="1")
    out = subprocess.run([sys.executable, "-c", _BASELINE_CODE, str(span_s)], env=env,
                         capture_output=True, text=True, check=True, timeout=900)
    return float(json.loads(out.stdout.strip().splitlines()[-1])["wall"])


def run(duration_s: float = 60.0, step_s: float = 1.0e-4, reps: int = 3,
        baseline_span_s: float = 0.05, scenario: str = "log-loading") -> dict[str, Any]:
    """Run the benchmark and return its figures (see the module docstring)."""
    from cranetwin.model import load_machine
    from cranetwin.sim import SensorModel, SimOptions, load_scenario, prepare, simulate

    machine = load_machine("patu655")
    t0 = time.perf_counter()
    prep = prepare(machine)
    sc = load_scenario(scenario, duration_s=duration_s)
    opts = SimOptions(step_s=step_s)
    simulate(prep, sc, duration_s=0.01, options=opts)          # JIT compile / cache load
    simulate(prep, sc, duration_s=0.01, options=SimOptions(step_s=step_s, scheme="rk4"))
    compile_seconds = time.perf_counter() - t0

    best = best_cpu = float("inf")
    for _ in range(reps):
        t1 = time.perf_counter()
        c1 = time.process_time()
        simulate(prep, sc, duration_s=duration_s, options=opts, sensors=SensorModel.ideal(),
                 wrenches=False)
        best = min(best, time.perf_counter() - t1)
        best_cpu = min(best_cpu, time.process_time() - c1)
    t1 = time.perf_counter()
    rec = simulate(prep, sc, duration_s=duration_s, options=opts)
    full = time.perf_counter() - t1
    rk4_span = min(duration_s, 10.0)
    t1 = time.perf_counter()
    simulate(prep, sc, duration_s=rk4_span, options=SimOptions(step_s=step_s, scheme="rk4"),
             sensors=SensorModel.ideal(), wrenches=False)
    rk4 = time.perf_counter() - t1

    coarse = 5.0e-4
    t1 = time.perf_counter()
    simulate(prep, sc, duration_s=duration_s, options=SimOptions(step_s=coarse),
             sensors=SensorModel.ideal(), wrenches=False)
    coarse_wall = time.perf_counter() - t1

    # a second topology: the excavator's dig cycle (contact force at the bucket tip)
    exc = prepare(load_machine("bobcat435"))
    dig = load_scenario("dig-cycle", machine="bobcat435")
    simulate(exc, dig, duration_s=0.01, options=opts)
    c1 = time.process_time()
    simulate(exc, dig, options=opts, sensors=SensorModel.ideal(), wrenches=False)
    exc_cpu = time.process_time() - c1

    steps = int(round(duration_s / step_s))
    result: dict[str, Any] = {
        "benchmark": "simulate",
        "machine": machine.name,
        "scenario": scenario,
        "scheme": "semi-implicit",
        "simulated_seconds": duration_s,
        "wall_seconds": best,
        "step_s": step_s,
        "steps": steps,
        "real_time_factor": duration_s / best,
        "us_per_step": best / steps * 1e6,
        "cpu_seconds": best_cpu,
        "real_time_factor_cpu": duration_s / best_cpu,
        "load_average_1min": os.getloadavg()[0],
        "threads": 1,
        "compile_seconds": compile_seconds,
        "recording_wall_seconds": full,
        "recording_real_time_factor": duration_s / full,
        "recording_samples": int(rec.samples.values.shape[0]),
        "rk4_real_time_factor": rk4_span / rk4,
        "excavator_dig_cycle_real_time_factor_cpu": dig.duration_s / exc_cpu,
        "real_time_factor_step_5e-4": duration_s / coarse_wall,
        "baseline": "same step function, numba JIT disabled (pure Python), short span scaled",
        "baseline_simulated_seconds": baseline_span_s,
    }
    base_wall = _baseline(baseline_span_s)
    base_rtf = baseline_span_s / base_wall
    result["baseline_wall_seconds"] = base_wall
    result["baseline_real_time_factor"] = base_rtf
    result["baseline_us_per_step"] = base_wall / (baseline_span_s / step_s) * 1e6
    result["speedup_vs_baseline"] = result["real_time_factor"] / base_rtf
    return result


def register(bench_app: typer.Typer) -> None:
    @bench_app.command("simulate")
    def simulate_bench(
        as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
        duration: float = typer.Option(60.0, help="Simulated seconds per repetition."),
        step: float = typer.Option(1.0e-4, help="Integration step [s]."),
        reps: int = typer.Option(3, help="Repetitions; the best time is reported."),
        baseline_span: float = typer.Option(0.05, help="Simulated seconds of the baseline."),
    ) -> None:
        """Simulator speed on the log-loading cycle (real-time factor) vs. the same loop
        without JIT."""
        r = run(duration_s=duration, step_s=step, reps=reps, baseline_span_s=baseline_span)
        emit(r, as_json)
