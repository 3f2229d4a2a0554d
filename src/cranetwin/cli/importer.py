"""``cranetwin import FILE --machine ID``: a user's CSV, Parquet or MDF4 recording into storage.

Exit status: 0 when every row was imported, 1 when some rows (or known payload values of the
mapping's ``[payload]`` column) were refused (the others are stored; the summary names row,
column and reason), 2 on an error (nothing of the file stored
when the error is about the file, its mapping or a convention mix-up). docs/IMPORT.md.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import typer
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from cranetwin.model import Machine, builtin_machines, load_machine, machine_from_dict


def machine_of(model: str, machine_id: str) -> Machine:
    """The machine description stored for a machine (a built-in name or TOML text)."""
    if model in builtin_machines() or "\n" not in model and Path(model).suffix == ".toml":
        return load_machine(model)
    return machine_from_dict(tomllib.loads(model), f"machine {machine_id!r} (stored model)")


def import_cmd(
    file: Path = typer.Argument(..., help="CSV, Parquet (.parquet) or ASAM MDF4 (.mf4) file."),
    machine: str = typer.Option(..., "--machine", "-m", help="Registered machine id "
                                "(cranetwin machines add)."),
    mapping: Path | None = typer.Option(None, "--mapping", help="Mapping TOML: columns → "
                                        "channels, units, position convention, time "
                                        "(docs/IMPORT.md). Default: columns named as the "
                                        "channels, in their units, time column t_s in epoch s."),
    db: str | None = typer.Option(None, "--db", help="Storage URL (default: "
                                  "CRANETWIN_DATABASE_URL or sqlite:///cranetwin.db)."),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as one JSON object."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
) -> None:
    """Import a recording into storage, as the ingest daemon stores it: checked, converted to
    each channel's unit, quantised to its resolution, split into regular runs. Importing the
    same file again stores nothing new."""
    from cranetwin.importer import import_file
    from cranetwin.settings import Settings, load_settings
    from cranetwin.storage import open_store, store_spec

    with open_store(store_spec(load_settings(Settings, database_url=db))) as store:
        m = machine_of(store.get_machine(machine).model, machine)
        with Progress(TextColumn("{task.description}"), BarColumn(),
                      TextColumn("{task.percentage:>3.0f}%"), TimeElapsedColumn(),
                      TimeRemainingColumn(), disable=quiet or as_json,
                      transient=False) as bar:
            task = bar.add_task(f"importing {file.name}", total=None)

            def progress(done: int, total: int) -> None:
                bar.update(task, completed=done, total=total)

            res = import_file(file, m, store, machine, mapping, progress=progress)
    rep = res.report
    if as_json:
        typer.echo(json.dumps({
            "rows_read": rep.rows_read, "rows_accepted": rep.rows_accepted,
            "rows_refused": rep.rows_refused,
            "refused": [{"column": c, "reason": k, "rows": n}
                        for (c, k), n in sorted(rep.refused.items())],
            "first_refusals": [{"row": r.row, "line": r.line, "column": r.column,
                                "reason": r.reason} for r in rep.first_refusals],
            "runs": rep.runs, "blocks": rep.blocks, "blocks_stored": res.stored,
            "blocks_duplicate": res.duplicate, "blocks_refused": dict(res.refused),
            "samples_stored": res.samples_stored, "period_ns": rep.period_ns,
            "max_time_shift_ns": rep.max_time_shift_ns, "channels": list(rep.channels),
            "absent": list(rep.absent), "t_first_ns": rep.t_first_ns,
            "t_last_ns": rep.t_last_ns, "epoch": res.epoch,
            "payload_rows": rep.payload_rows, "payload_refused": rep.payload_refused,
            "payload_runs_stored": res.payload_runs_stored,
            "payload_runs_duplicate": res.payload_runs_duplicate,
            "payload_runs_differing": res.payload_runs_differing}))
    else:
        typer.echo(rep.summary())
        typer.echo(f"{res.stored} block(s) stored ({res.samples_stored} samples), "
                   f"{res.duplicate} already stored"
                   + (f", {sum(res.refused.values())} refused by storage "
                      f"({', '.join(f'{k}: {v}' for k, v in res.refused.items())}; first: "
                      f"{res.refused_detail})" if res.refused else "")
                   + f"; times moved to the run grid by at most "
                     f"{rep.max_time_shift_ns / 1e6:.3g} ms")
        if res.payload_runs_stored or res.payload_runs_duplicate or res.payload_runs_differing:
            typer.echo(f"known payload: {res.payload_runs_stored} run(s) stored (one per "
                       f"block), {res.payload_runs_duplicate} already stored"
                       + (f", {res.payload_runs_differing} already stored with other values "
                          "(kept as stored)" if res.payload_runs_differing else ""))
    if rep.rows_refused or res.refused or rep.payload_refused:
        raise typer.Exit(1)


def register(app: typer.Typer) -> None:
    """Add ``cranetwin import``."""
    app.command("import")(import_cmd)
