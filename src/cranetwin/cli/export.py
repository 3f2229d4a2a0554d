"""``cranetwin export``: raw or derived series of one stored machine as CSV or Parquet.

The same export as ``GET /api/v1/machines/{id}/export`` (:mod:`cranetwin.service.export`),
written chunk by chunk to a file (never the whole range in memory). The database is the one
of ``CRANETWIN_DATABASE_URL`` (credentials stay out of the command line).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import typer

from cranetwin.errors import CraneTwinError


def export_cmd(
    machine: str = typer.Option(..., "--machine", "-m", help="Machine id in storage."),
    t_from: str = typer.Option(..., "--from", help="Start (ISO 8601 UTC or epoch s)."),
    t_to: str = typer.Option(..., "--to", help="End, exclusive (ISO 8601 UTC or epoch s)."),
    series: str = typer.Option("raw", "--series", "-s", help="raw | forces | joint_loads | "
                               "payload | cycles | events"),
    fmt: str | None = typer.Option(None, "--format", "-f", help="csv | parquet (default: "
                                   "from the --out suffix)"),
    out: Path = typer.Option(..., "--out", "-o", help="Output file (.csv or .parquet)."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No summary line."),
) -> None:
    """Export a series of one machine over [from, to) as CSV or Parquet (docs/API.md
    "Export" lists the columns)."""
    from cranetwin.service import export as ex
    from cranetwin.service.timerange import TimeRange
    from cranetwin.settings import Settings, load_settings

    fmt = (fmt or out.suffix.lstrip(".")).lower()
    ex.check(series, fmt)  # before the database is opened
    if out.is_dir() or not out.parent.is_dir():
        raise CraneTwinError(f"--out {out}: expected a file in an existing directory")
    rng = TimeRange.parse(t_from, t_to)
    from cranetwin.service.fleet import FleetService

    settings = load_settings(Settings)
    fleet = FleetService.open(settings)
    tmp = out.with_name(f".{out.name}.{os.getpid()}.part")
    try:
        rec = fleet.backend.machine(machine)
        a = time.perf_counter()
        exp = ex.export_series(fleet, rec, rng, series, fmt)
        size = 0
        with tmp.open("wb") as f:
            for piece in exp.body:
                f.write(piece)
                size += len(piece)
        tmp.replace(out)  # a complete file or none
    finally:
        tmp.unlink(missing_ok=True)
        fleet.backend.close()
    if not quiet:
        typer.echo(f"{out}: {series} of {machine}, {size:,} bytes in "
                   f"{time.perf_counter() - a:.2f} s")


def register(app: typer.Typer) -> None:
    """Add ``cranetwin export``."""
    app.command("export")(export_cmd)
