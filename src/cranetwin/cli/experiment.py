"""``cranetwin experiment noise``: the paper's Fig. 7 accuracy experiment."""

from __future__ import annotations

import json

import typer
from rich.console import Console
from rich.table import Table

from cranetwin.errors import TwinError
from cranetwin.model import load_machine

experiment_app = typer.Typer(help="Accuracy experiments of the twin.", no_args_is_help=True)


def _levels(spec: str) -> list[float]:
    """``start:stop:step`` in percent (inclusive) or a comma list, as fractions."""
    try:
        if ":" in spec:
            a, b, c = (float(x) for x in spec.split(":"))
            n = int(round((b - a) / c)) + 1
            return [round(a + i * c, 9) / 100 for i in range(n)]
        return [float(x) / 100 for x in spec.split(",")]
    except ValueError as exc:
        raise TwinError(f"--levels {spec!r}: expected start:stop:step or a comma list "
                        "of percentages") from exc


@experiment_app.command("noise")
def noise(
    scenario: str = typer.Option("fig3", help="Built-in scenario (fig3, log-loading, random)."),
    levels: str = typer.Option("0:10:1", help="Error levels e [%]: start:stop:step or list."),
    seeds: int = typer.Option(20, help="Noise realisations per level."),
    duration: float | None = typer.Option(
        None, help="Simulated duration in seconds (default: the scenario's)."),
    machine: str = typer.Option("patu655", help="Machine name or TOML file."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
    plot: str | None = typer.Option(None, "--plot", help="Write a Fig. 7-like PNG here."),
) -> None:
    """Simulate, sample at 100 Hz (quantisation only), add uniform error e, replay, and
    report NRMSE of Xc1, Xc2 (lift/jib rod positions) and Fc1, Fc2 (forces) vs the truth."""
    from cranetwin.sim import SensorModel, builtin_scenario, simulate
    from cranetwin.twin import experiment as ex

    m = load_machine(machine)
    rec = simulate(m, builtin_scenario(scenario, duration_s=duration), seed=0,
                   sensors=SensorModel.ideal(100.0), wrenches=False)
    results = ex.run_levels(rec, m, _levels(levels), seeds)
    if plot:
        ex.plot(results, plot, f"{m.name}, scenario {scenario}, {seeds} seeds")
    if as_json:
        typer.echo(json.dumps({"scenario": scenario, "seeds": seeds,
                               "duration_s": rec.duration_s, "levels": ex.as_json(results)}))
        return
    con = Console()
    t = Table(title=f"NRMSE [%] vs truth, scenario {scenario} ({seeds} seeds; mean ± std; "
                    "input = raw noisy data)")
    for col in ("e [%]", *ex.METRICS, "in Xc1", "in Fc1", "payload RMSE [kg]",
                "[% rated]"):
        t.add_column(col)
    for r in results:
        t.add_row(f"{r.level * 100:g}",
                  *(f"{r.mean[k] * 100:.3f} ± {r.std[k] * 100:.3f}" for k in ex.METRICS),
                  f"{r.input_mean['Xc1'] * 100:.2f}", f"{r.input_mean['Fc1'] * 100:.2f}",
                  f"{r.payload_rmse_kg:.1f}", f"{r.payload_rmse_rated * 100:.2f}")
    con.print(t)


def register(app: typer.Typer) -> None:
    app.add_typer(experiment_app, name="experiment")
