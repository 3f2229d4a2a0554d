"""``cranetwin experiment noise``: the paper's Fig. 7 accuracy experiment."""

from __future__ import annotations

import json

import typer
from rich.console import Console
from rich.table import Table

from cranetwin.errors import TwinError
from cranetwin.model import Machine, load_machine

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
    levels: str | None = typer.Option(
        None, help="Error levels e [%]: start:stop:step or list (default 0:10:1; with "
        "--family one level, default 5)."),
    seeds: int | None = typer.Option(
        None, help="Noise realisations per level (default 20; with --family 1)."),
    duration: float | None = typer.Option(
        None, help="Simulated duration in seconds (default: the scenario's)."),
    machine: str = typer.Option("patu655", help="Machine name or TOML file."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
    plot: str | None = typer.Option(None, "--plot", help="Write a Fig. 7-like PNG here."),
    family: bool = typer.Option(
        False, "--family", help="Run the family of cranes, sample rates (50–200 Hz) and "
        "error models (uniform, Gaussian, quantised, biased; share of full and of recorded "
        "range) instead, and judge the accuracy targets (--scenario, --duration ignored)."),
    quick: bool = typer.Option(False, "--quick", help="With --family: a small subset."),
    csv_out: str | None = typer.Option(
        None, "--csv", help="With --family: also write every case as one row of this CSV "
        "(the columns of docs/accuracy-noise-family.csv)."),
) -> None:
    """Simulate, sample at 100 Hz (quantisation only), add uniform error e, replay, and
    report NRMSE of Xc1, Xc2 (lift/jib rod positions) and Fc1, Fc2 (forces) vs the truth.
    With --family: the accuracy over a generated family of cranes and error models."""
    from cranetwin.sim import SensorModel, builtin_scenario, simulate
    from cranetwin.twin import experiment as ex

    m = load_machine(machine)
    if family:
        _family(m, levels, seeds, quick, as_json, csv_out)
        return
    if quick or csv_out is not None:
        raise TwinError("--quick and --csv need --family")
    seeds = 20 if seeds is None else seeds
    levels = "0:10:1" if levels is None else levels
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


def _family(m: Machine, levels: str | None, seeds: int | None, quick: bool,
            as_json: bool, csv_out: str | None = None) -> None:
    from cranetwin.cli import _noise_family as nf
    from cranetwin.twin.noise_targets import evaluate

    lv = _levels(levels) if levels is not None else [0.05]
    if len(lv) != 1 or not lv[0] > 0:
        raise TwinError(f"--family takes one positive error level, got {levels!r}")
    plan = nf.family_plan(quick, lv[0], 1 if seeds is None else seeds)
    err = Console(stderr=True)
    cases = nf.run_family(m, plan, progress=lambda msg: err.print(msg, highlight=False))
    if csv_out is not None:
        nf.write_csv([c.as_json() for c in cases], csv_out)
    if as_json:
        typer.echo(json.dumps(nf.as_json(plan, cases, evaluate(cases))))
        return
    nf.print_family(cases, plan, Console(width=200))


def register(app: typer.Typer) -> None:
    app.add_typer(experiment_app, name="experiment")
