"""``cranetwin simulate``: run the machine-side simulator and write a recording."""

from __future__ import annotations

import time
from pathlib import Path

import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

from cranetwin.errors import SimulationError
from cranetwin.model import load_machine


def simulate_command(
    machine: str = typer.Option("patu655", "--machine", "-m",
                                help="Built-in machine name or machine TOML file."),
    scenario: str = typer.Option("fig3", "--scenario", "-s",
                                 help="fig3, log-loading, random (PATU 655), a scenario shipped "
                                      "with the machine (e.g. dig-cycle), or a .toml/.json file."),
    duration: float | None = typer.Option(None, "--duration", "-d",
                                          help="Simulated time [s] (default: the scenario's)."),
    rate: float = typer.Option(100.0, "--rate", help="Sensor sampling rate [Hz]."),
    out: Path = typer.Option(Path("recording.npz"), "--out", "-o",
                             help="Output file, .npz (lossless) or .csv (+ .truth.csv)."),
    seed: int = typer.Option(0, "--seed", help="Seed of scenario and sensor randomness."),
    payload: float | None = typer.Option(
        None, "--payload",
        help="Payload [kg]: fig3 initial payload, log-loading log mass, random maximum; "
             "for scenario files, overrides initial.payload_kg."),
    step: float = typer.Option(1e-4, "--step", help="Integration step [s]."),
    truth_rate: float = typer.Option(1000.0, "--truth-rate",
                                     help="Rate at which the ground truth is kept [Hz]."),
    ideal: bool = typer.Option(False, "--ideal-sensors",
                               help="Quantisation only: no noise, bias, dropouts or jitter."),
    noise: float | None = typer.Option(None, "--noise",
                                       help="Sensor noise std, fraction of channel range."),
    dropout: float | None = typer.Option(None, "--dropout", help="Dropout probability."),
    start_epoch: float = typer.Option(0.0, "--start-epoch",
                                      help="Epoch time of t = 0 [s] (0 = simulation time)."),
    machine_id: str | None = typer.Option(None, "--machine-id",
                                          help="Identifier on the samples (default: name)."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
) -> None:
    """Simulate a crane (hydraulics + multibody, 1e-4 s step) and write sensor samples and
    ground truth, e.g. ``cranetwin simulate --scenario fig3 --duration 20 --out rec.npz``."""
    from cranetwin.sim import SensorModel, SimOptions, load_scenario, simulate
    from cranetwin.sim.scenario import InitialState

    if out.suffix not in (".npz", ".csv"):
        raise SimulationError(f"--out {out}: expected a .npz or .csv file name")
    m = load_machine(machine)
    from cranetwin.sim.scenario import BUILTIN, builtin_scenario

    if scenario in BUILTIN:
        sc = builtin_scenario(scenario, seed=seed, payload_kg=payload)
    else:
        sc = load_scenario(scenario, machine=m.name)
        if payload is not None:
            init = sc.initial.model_dump() | {"payload_kg": payload}
            sc = sc.model_copy(update={"initial": InitialState(**init)})
    sensors = SensorModel.ideal(rate) if ideal else SensorModel(rate_hz=rate)
    changes: dict[str, float] = {}
    if noise is not None:
        changes["noise_fraction"] = noise
    if dropout is not None:
        changes["dropout_probability"] = dropout
    if changes:
        sensors = SensorModel(**(sensors.model_dump() | changes))
    total = float(duration if duration is not None else sc.duration_s)
    con = Console(stderr=True)
    wall = time.perf_counter()
    with Progress(TextColumn("[bold]simulating[/bold] {task.description}"), BarColumn(),
                  TextColumn("{task.completed:.1f}/{task.total:.1f} s"), TimeRemainingColumn(),
                  console=con, disable=quiet, transient=True) as bar:
        task = bar.add_task(f"{sc.name} on {m.name}", total=total)
        rec = simulate(m, sc, duration_s=total, options=SimOptions(step_s=step,
                                                                   truth_rate_hz=truth_rate),
                       sensors=sensors, seed=seed, start_epoch_s=start_epoch,
                       machine_id=machine_id,
                       progress=lambda done, _tot: bar.update(task, completed=done))
    wall = time.perf_counter() - wall
    path = rec.save(out)
    typer.echo(f"{path}: {rec.samples.values.shape[0]} samples x "
               f"{len(rec.samples.channels)} channels at {rate:g} Hz, truth {rec.truth.n} rows; "
               f"{total:g} s simulated in {wall:.2f} s ({total / wall:.1f}x real time)")


def register(app: typer.Typer) -> None:
    app.command("simulate")(simulate_command)
