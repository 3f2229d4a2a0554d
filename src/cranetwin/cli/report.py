"""``cranetwin report``: load-history report (PDF, HTML or CSV) of one machine.

Data from storage (``--machine ID --from --to``, replayed by the twin), from a simulator
recording (``--recording rec.npz``, its ground truth) or synthetic (``--demo``).
"""

from __future__ import annotations

import datetime as dt
import functools
import os
from pathlib import Path

import typer
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from cranetwin.errors import ReportError
from cranetwin.model import load_machine


def parse_time(text: str) -> float:
    """Epoch seconds from ``1700000000``, ``2023-11-14`` or ``2023-11-14T06:00:00[+00:00]``
    (naive times are UTC)."""
    try:
        return float(text)
    except ValueError:
        pass
    try:
        t = dt.datetime.fromisoformat(text)
    except ValueError as exc:
        raise ReportError(f"bad time {text!r}: expected epoch seconds or ISO 8601, e.g. "
                          "2023-11-14T06:00:00") from exc
    if t.tzinfo is None:
        t = t.replace(tzinfo=dt.UTC)
    return t.timestamp()


SUFFIX = {"pdf": ".pdf", "html": ".html", "csv": ".zip"}


def output_paths(formats: str, out: Path) -> dict[str, Path]:
    """Where each of the comma-separated ``formats`` is written, checked before any analysis.

    One format: ``out`` as given (CSV: a directory, or a zip if it ends ``.zip``). Several:
    ``out`` without its suffix plus ``.pdf``, ``.html`` and ``.zip`` (CSV tables).

    Raises:
        ReportError: No format, a format twice, or an output that cannot be written (its
            directory missing or not writable, a file where a directory is needed or the
            reverse).
    """
    names = [f.strip().lower() for f in formats.split(",") if f.strip()]
    if not names or len(set(names)) != len(names):
        raise ReportError(f"--format {formats!r}: give pdf, html or csv, each at most once "
                          "(comma-separated)")
    if len(names) == 1:
        targets = {names[0]: out}
    else:
        stem = out.with_suffix("") if out.suffix.lower() in (".pdf", ".html", ".zip") else out
        targets = {f: stem.with_name(stem.name + SUFFIX.get(f, "")) for f in names}
    for f, path in targets.items():
        csv_dir = f == "csv" and path.suffix.lower() != ".zip"
        parent = path if csv_dir and path.is_dir() else path.parent
        if csv_dir and path.exists() and not path.is_dir():
            raise ReportError(f"{path} exists and is not a directory; CSV output is a "
                              "directory (or give a .zip)")
        if not csv_dir and path.is_dir():
            raise ReportError(f"{path} is a directory; give a file name for {f}")
        if not parent.is_dir() or not os.access(parent, os.W_OK):
            raise ReportError(f"cannot write {path}: {parent} is not a writable directory")
    return targets


def report(
    out: Path = typer.Option(..., "--out", "-o", help="Output file (.pdf, .html) or CSV "
                             "directory / .zip; with several formats, the path without suffix "
                             "(STEM.pdf, STEM.html, STEM.zip for csv)."),
    fmt: str = typer.Option("pdf", "--format", "-f", help="pdf | html | csv, or several "
                            "comma-separated (csv,pdf,html): one analysis, every file."),
    machine: str | None = typer.Option(None, "--machine", "-m",
                                       help="Machine id in storage (or, with --recording/--demo, "
                                            "a built-in machine or TOML file)."),
    t_from: str | None = typer.Option(None, "--from", help="Start (epoch s or ISO 8601 UTC); "
                                      "also limits --recording/--demo data."),
    t_to: str | None = typer.Option(None, "--to", help="End, exclusive (epoch s or ISO 8601 "
                                    "UTC)."),
    db: str | None = typer.Option(None, "--db", help="Storage URL (default: "
                                  "CRANETWIN_DATABASE_URL or sqlite:///cranetwin.db)."),
    recording: Path | None = typer.Option(None, "--recording", help="Simulator recording "
                                          "(.npz or .csv: its ground truth), or a user's "
                                          "CSV/Parquet/MDF4 file (replayed by the twin; "
                                          "docs/IMPORT.md) to analyse instead of storage."),
    mapping: Path | None = typer.Option(None, "--mapping", help="Mapping TOML of a user's "
                                        "--recording file (docs/IMPORT.md)."),
    payload: float | None = typer.Option(None, "--payload", help="Known payload [kg] of a "
                                         "user's --recording file (default: estimated; a "
                                         "known payload column: the mapping's [payload])."),
    payload_column: str = typer.Option("use", "--payload-column", help="A known payload "
                                       "column of a --recording file: 'use' it in the "
                                       "inverse dynamics where known, or only 'compare' the "
                                       "estimate with it per lift."),
    demo: bool = typer.Option(False, "--demo", help="Synthetic 8-hour shifts with a few "
                              "injected misuse events."),
    days: int = typer.Option(30, "--days", help="Days of --demo data."),
    rate_hz: float = typer.Option(100.0, "--rate-hz", help="Sample rate of --demo data [Hz]."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
) -> None:
    """Write a load-history report: usage, load spectra, damage and remaining life, duty class,
    events, productivity."""
    from cranetwin.reports import (
        SECTIONS,
        DemoSource,
        RecordingSource,
        Source,
        StoreSource,
        build_report,
        check_format,
        write,
    )
    from cranetwin.reports.sources import ImportedFileSource, is_simulator_recording

    targets = output_paths(fmt, out)
    for f in targets:
        check_format(f)  # an unknown format or a missing extra, before any analysis
    src: Source
    if demo:
        src = DemoSource(load_machine(machine or "patu655"), days=days, rate_hz=rate_hz)
    elif recording is not None and (mapping is not None or not is_simulator_recording(recording)):
        if payload_column not in ("use", "compare"):
            raise ReportError(f"--payload-column {payload_column!r}: expected use or compare")
        src = ImportedFileSource(load_machine(machine or "patu655"), recording, mapping, payload,
                                 payload_column="use" if payload_column == "use" else "compare")
        if src.import_report.rows_refused:
            typer.echo(src.import_report.summary(), err=True)
    elif recording is not None:
        from cranetwin.sim import Recording

        name = machine or Recording.load(recording).machine
        src = RecordingSource(load_machine(name), recording)
    else:
        if machine is None or t_from is None or t_to is None:
            raise ReportError("give --machine ID --from T0 --to T1 (storage), or --recording "
                              "FILE, or --demo")
        from cranetwin.settings import Settings, load_settings
        from cranetwin.storage import store_spec

        settings = load_settings(Settings, database_url=db)
        src = StoreSource(store_spec(settings), machine, parse_time(t_from), parse_time(t_to),
                          margin_s=settings.twin_margin_s)
    with Progress(TextColumn("{task.description}"), BarColumn(),
                  TextColumn("{task.percentage:>3.0f}%"), TimeElapsedColumn(),
                  TimeRemainingColumn(), disable=quiet) as bar:
        task = bar.add_task("analysing", total=src.total())
        window = (None if t_from is None else parse_time(t_from),
                  None if t_to is None else parse_time(t_to))
        rep = build_report(src, progress=lambda n: bar.advance(task, n), t0_s=window[0],
                           t1_s=window[1])
        bar.update(task, completed=src.total())
        schedule = src.schedule() if isinstance(src, StoreSource) else None
        paths = []
        for f, target in targets.items():
            wtask = bar.add_task(f"writing {f}", total=len(SECTIONS))
            paths.append(write(rep, src.machine, f, target, src.label,
                               progress=functools.partial(bar.advance, wtask),
                               schedule=schedule))
            bar.update(wtask, completed=len(SECTIONS))
    typer.echo(f"{', '.join(map(str, paths))}: {len(rep.cycles)} work cycles, "
               f"{len(rep.events)} events, {rep.n_samples:,} samples")
    for line in getattr(src, "warnings", []):
        typer.echo(f"warning: {line}", err=True)
    for note in src.machine.unknowns():
        typer.echo(f"note: {note}", err=True)
    share = src.known_used_share() if isinstance(src, ImportedFileSource) else None
    if share is not None:
        typer.echo(f"known payload (the mapping's [payload] column) used in the inverse "
                   f"dynamics at {100.0 * share:.1f} % of the samples, the estimate elsewhere")
    lifts = getattr(src, "lifts", None)
    if lifts is not None:  # a known payload series: the twin's estimate against it
        from cranetwin.importer.payload import summary_line

        typer.echo(summary_line(lifts))
        for lift in lifts:
            typer.echo(f"  {lift.line()}")


def register(app: typer.Typer) -> None:
    """Add ``cranetwin report``."""
    app.command("report")(report)
