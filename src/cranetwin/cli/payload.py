"""``cranetwin payload list|delete``: the known payload series stored for a machine (the import
mapping's ``[payload]`` column, docs/IMPORT.md).

``list`` shows the stored series as stretches without a gap; ``delete`` removes the values of a
time range (runs straddling a bound are cut there) and has the twin worker process the windows
it changes again (:mod:`cranetwin.storage.redo`). Exit status 2 on an error.
"""

from __future__ import annotations

import json

import typer

from cranetwin.settings import Settings, load_settings

payload_app = typer.Typer(help="Known payload series stored with a machine's samples: list, "
                          "delete.", no_args_is_help=True)

_DB_HELP = "Storage URL (default: CRANETWIN_DATABASE_URL or sqlite:///cranetwin.db)."
_MACHINE_HELP = "Registered machine id."


def _iso(t_ns: int) -> str:
    from cranetwin.service.timerange import iso

    return str(iso(t_ns / 1e9))


@payload_app.command("list")
def list_cmd(
    machine: str = typer.Option(..., "--machine", "-m", help=_MACHINE_HELP),
    t_from: str | None = typer.Option(None, "--from", help="Only runs starting at or after "
                                      "this time (epoch s or ISO 8601 UTC)."),
    t_to: str | None = typer.Option(None, "--to", help="Only runs starting before this time."),
    db: str | None = typer.Option(None, "--db", help=_DB_HELP),
    as_json: bool = typer.Option(False, "--json", help="Print JSON: a list of stretches."),
) -> None:
    """List the stored known payload of a machine: one line per stretch of runs without a gap
    (first and last time, runs, values, known values, smallest and largest known payload)."""
    from cranetwin.cli.report import parse_time
    from cranetwin.storage import open_store, store_spec

    t0 = parse_time(t_from) if t_from is not None else None
    t1 = parse_time(t_to) if t_to is not None else None
    with open_store(store_spec(load_settings(Settings, database_url=db))) as store:
        got = store.payload_stretches(machine, t0, t1)
    if as_json:
        typer.echo(json.dumps([
            {"t_first": _iso(s.t_first_ns), "t_last": _iso(s.t_last_ns),
             "t_first_ns": s.t_first_ns, "t_last_ns": s.t_last_ns, "runs": s.runs,
             "values": s.values, "known": s.known,
             "min_kg": None if s.known == 0 else s.min_kg,
             "max_kg": None if s.known == 0 else s.max_kg} for s in got], indent=1))
        return
    if not got:
        typer.echo(f"machine {machine}: no known payload stored")
        return
    for s in got:
        kg = (f"{s.min_kg:.1f} … {s.max_kg:.1f} kg" if s.known else "none known")
        typer.echo(f"{_iso(s.t_first_ns)} – {_iso(s.t_last_ns)}  "
                   f"{(s.t_last_ns - s.t_first_ns) / 1e9:.1f} s  {s.runs} run(s)  "
                   f"{s.values} value(s), {s.known} known  {kg}")


@payload_app.command("delete")
def delete_cmd(
    machine: str = typer.Option(..., "--machine", "-m", help=_MACHINE_HELP),
    t_from: str | None = typer.Option(None, "--from", help="Start of the range (epoch s or "
                                      "ISO 8601 UTC)."),
    t_to: str | None = typer.Option(None, "--to", help="End of the range, exclusive."),
    every: bool = typer.Option(False, "--all", help="The whole stored series (instead of "
                               "--from/--to)."),
    db: str | None = typer.Option(None, "--db", help=_DB_HELP),
    as_json: bool = typer.Option(False, "--json", help="Print the result as one JSON object."),
) -> None:
    """Delete the stored known payload of a machine with from ≤ t < to (a run straddling a
    bound is cut there), in one transaction; the twin worker then processes the windows it
    changes again (with the estimate, or a payload imported anew)."""
    from cranetwin.cli.report import parse_time
    from cranetwin.errors import StorageError
    from cranetwin.storage import open_store, store_spec
    from cranetwin.storage.redo import merged

    ranged = t_from is not None or t_to is not None
    if every == ranged or ranged and (t_from is None or t_to is None):
        raise StorageError("give --from T0 --to T1, or --all (not both)")
    t0 = None if every or t_from is None else parse_time(t_from)
    t1 = None if every or t_to is None else parse_time(t_to)
    if t0 is not None and t1 is not None and t1 <= t0:
        raise StorageError(f"--to ({t_to}) must be after --from ({t_from})")
    with open_store(store_spec(load_settings(Settings, database_url=db))) as store:
        res = store.delete_payload(machine, -float("inf") if t0 is None else t0,
                                   float("inf") if t1 is None else t1)
    redo = merged(res.changed_ns)
    if as_json:
        typer.echo(json.dumps({"runs_deleted": res.runs_deleted, "runs_cut": res.runs_cut,
                               "values_deleted": res.values_deleted,
                               "known_deleted": res.known_deleted,
                               "ranges_to_redo": [[_iso(a), _iso(b)] for a, b in redo]}))
        return
    typer.echo(f"machine {machine}: {res.values_deleted} value(s) deleted "
               f"({res.known_deleted} known), {res.runs_deleted} run(s) whole, "
               f"{res.runs_cut} cut at the range's bounds"
               + (f"; the twin worker processes {len(redo)} range(s) again: "
                  + ", ".join(f"{_iso(a)} – {_iso(b)}" for a, b in redo) if redo else ""))


def register(app: typer.Typer) -> None:
    """Add ``cranetwin payload``."""
    app.add_typer(payload_app, name="payload")
