"""``cranetwin replay``: the twin's motion and loads of a file or a stored range, written as a
table of documented columns (docs/IMPORT.md, :mod:`cranetwin.importer.replay`)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import typer
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from cranetwin.errors import TwinError
from cranetwin.model import load_machine
from cranetwin.samples import F64


def replay_cmd(
    file: Path | None = typer.Argument(None, help="CSV, Parquet or MDF4 file to replay "
                                       "(else --machine ID --from --to: a stored range)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output table: .parquet or .csv."),
    mapping: Path | None = typer.Option(None, "--mapping", help="The file's mapping TOML "
                                        "(docs/IMPORT.md)."),
    machine: str | None = typer.Option(None, "--machine", "-m",
                                       help="With FILE: built-in machine name or TOML file "
                                            "(default patu655). Without: the machine id in "
                                            "storage."),
    t_from: str | None = typer.Option(None, "--from", help="Start of the stored range (epoch "
                                      "s or ISO 8601 UTC)."),
    t_to: str | None = typer.Option(None, "--to", help="End, exclusive."),
    db: str | None = typer.Option(None, "--db", help="Storage URL (default: "
                                  "CRANETWIN_DATABASE_URL or sqlite:///cranetwin.db)."),
    payload: float | None = typer.Option(None, "--payload", help="Known constant payload "
                                         "[kg] (default: estimated; a known payload column "
                                         "is then only compared)."),
    payload_column: str = typer.Option("use", "--payload-column", help="A known payload "
                                       "column (the mapping's [payload]): 'use' it in the "
                                       "inverse dynamics where known (the estimate "
                                       "elsewhere), or only 'compare' the estimate with it "
                                       "per lift (the gross estimate, and the twin's lift "
                                       "payload net of the empty reading ± σ)."),
    grid_hz: float | None = typer.Option(None, "--grid-hz", help="Output rate [Hz], an "
                                         "integer multiple of the sample rate (default: the "
                                         "sample rate)."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress display."),
) -> None:
    """Replay samples through the twin and write joint q/qd/qdd, rod s/v, pressures, cylinder
    forces, joint torques and reaction wrenches, tip position, payload ± σ and gap flags; with
    a known payload column (the mapping's [payload]; for a stored range, the one the import
    stored), the dynamics use it where known (--payload-column compare: the estimate's error
    per lift instead, gross and net of the empty reading)."""
    from cranetwin.importer.payload import summary_line
    from cranetwin.importer.replay import (
        PayloadColumn,
        ReplayNotes,
        column_units,
        iter_replay_table,
        load_source_and_payload,
        uses_known,
        write_table,
    )

    if file is not None:
        if t_from is not None or t_to is not None or db is not None:
            raise TwinError("give FILE, or --machine ID --from --to [--db]: not both")
        m = load_machine(machine or "patu655")
        source, known = load_source_and_payload(file, m, mapping)
        where = "the mapping's [payload] column"
    else:
        if machine is None or t_from is None or t_to is None:
            raise TwinError("give FILE [--mapping MAP], or --machine ID --from T0 --to T1")
        if mapping is not None:
            raise TwinError("--mapping is for a FILE")
        from cranetwin.cli.importer import machine_of
        from cranetwin.cli.report import parse_time
        from cranetwin.service.replayer import read_range
        from cranetwin.settings import Settings, load_settings
        from cranetwin.storage import open_store, store_spec

        with open_store(store_spec(load_settings(Settings, database_url=db))) as store:
            m = machine_of(store.get_machine(machine).model, machine)
            # with the known payload stored with them (an imported [payload] column), as the
            # service's replays take it
            source, known = read_range(store, machine, parse_time(t_from), parse_time(t_to))
        if source.t_s.shape[0] == 0:
            raise TwinError(f"no samples of {machine!r} stored in [{t_from}, {t_to})")
        where = "stored with the samples"
    if payload_column not in ("use", "compare"):
        raise TwinError(f"--payload-column {payload_column!r}: expected use or compare")
    column: PayloadColumn = "use" if payload_column == "use" else "compare"
    use = uses_known(known, payload, column)
    units = column_units(m, source.channels, known is not None, not use)
    notes = ReplayNotes.empty()
    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.fields[rows]}"
                  " rows"), TimeElapsedColumn(), disable=quiet) as bar:
        task = bar.add_task(f"replaying into {out.name}", total=None, rows=0)

        def chunks() -> Iterator[dict[str, F64]]:
            for ch in iter_replay_table(source, m, payload=payload, grid_hz=grid_hz,
                                        notes=notes, known_payload_kg=known,
                                        payload_column=column):
                bar.update(task, rows=bar.tasks[task].fields["rows"] + ch["t_s"].shape[0])
                yield ch

        rows = write_table(chunks(), out, units)
    typer.echo(f"{out}: {rows} rows × {len(units)} columns (docs/IMPORT.md lists them)")
    if use:
        assert known is not None
        typer.echo(f"known payload ({where}) used in the inverse "
                   f"dynamics at {100.0 * float(np.isfinite(known).mean()):.1f} % of the "
                   "samples, the estimate elsewhere")
    lifts = notes.lifts()
    if lifts is not None:  # a known payload series: the estimate's error per lift, gross and net
        typer.echo(summary_line(lifts))
        for lift in lifts:
            typer.echo(f"  {lift.line()}")
    from cranetwin.twin.observability import unobservable

    for line in unobservable(notes.force_observability(m)):
        typer.echo(f"warning: {line}", err=True)
    from cranetwin.twin.consistency import inconsistent

    for line in inconsistent(notes.model_consistency(m)):
        typer.echo(f"warning: {line}", err=True)


def register(app: typer.Typer) -> None:
    """Add ``cranetwin replay``."""
    app.command("replay")(replay_cmd)
