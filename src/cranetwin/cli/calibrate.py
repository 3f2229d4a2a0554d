"""``cranetwin calibrate (RECORDING | --machine ID --from --to)``: friction and carried mass
from a recording or a stored range."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

import typer
from rich.console import Console
from rich.table import Table

from cranetwin.model import load_machine

if TYPE_CHECKING:
    from cranetwin.model import Machine
    from cranetwin.twin.calibration import Calibration


def _fmt(value: float, std: float, scale: float = 1.0, digits: int = 0) -> str:
    if std == std:  # not NaN
        return f"{value * scale:.{digits}f} ± {std * scale:.{digits}f}"
    return f"{value * scale:.{digits}f}"


def register(app: typer.Typer) -> None:
    @app.command("calibrate")
    def calibrate_cmd(
        recording: Path | None = typer.Argument(
            None, help="Recording: the simulator's .npz or .csv, or a CSV, Parquet or MDF4 "
            "file of your own (with --mapping, docs/IMPORT.md); else --machine ID --from --to: "
            "a stored range (an imported file, or what the daemon stored)."),
        machine: str | None = typer.Option(
            None, "--machine", "-m", help="With RECORDING: built-in machine name or TOML file "
            "(default patu655). Without: the machine id in storage."),
        t_from: str | None = typer.Option(None, "--from", help="Start of the stored range "
                                          "(epoch s or ISO 8601 UTC)."),
        t_to: str | None = typer.Option(None, "--to", help="End, exclusive."),
        db: str | None = typer.Option(None, "--db", help="Storage URL (default: "
                                      "CRANETWIN_DATABASE_URL or sqlite:///cranetwin.db)."),
        mapping: Path | None = typer.Option(None, "--mapping", help="Mapping TOML of your "
                                            "own file (docs/IMPORT.md)."),
        as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
        payload_column: str = typer.Option("use", "--payload-column", help="A known "
                                           "payload column of your file (the mapping's "
                                           "[payload]): 'use' it (the fitted mass is then "
                                           "the tool-mass error alone), or 'compare': fit the "
                                           "carried mass per segment as without one."),
    ) -> None:
        """Estimate cylinder friction (Fc, vc, b; Eq. 2) and the payload/tool mass by least
        squares, and report the force residual before and after; say per parameter whether
        the recording determines it (else the machine file's value is kept)."""
        from cranetwin.errors import TwinError
        from cranetwin.twin.calibration import calibrate

        if payload_column not in ("use", "compare"):
            raise TwinError(f"--payload-column {payload_column!r}: expected use or compare")
        if recording is None:
            if machine is None or t_from is None or t_to is None:
                raise TwinError("give RECORDING [--mapping MAP], or --machine ID --from T0 "
                                "--to T1")
            if mapping is not None:
                raise TwinError("--mapping is for a RECORDING")
            from cranetwin.cli.importer import machine_of
            from cranetwin.cli.report import parse_time
            from cranetwin.service.replayer import read_range
            from cranetwin.settings import Settings, load_settings
            from cranetwin.storage import open_store, store_spec

            with open_store(store_spec(load_settings(Settings, database_url=db))) as store:
                m = machine_of(store.get_machine(machine).model, machine)
                samples, stored = read_range(store, machine, parse_time(t_from),
                                             parse_time(t_to))
            if samples.t_s.shape[0] == 0:
                raise TwinError(f"no samples of {machine!r} stored in [{t_from}, {t_to})")
            name = f"{machine} [{t_from}, {t_to})"
            cal = calibrate(samples, m, payload_kg=stored if payload_column == "use" else None)
        elif t_from is not None or t_to is not None or db is not None:
            raise TwinError("give RECORDING, or --machine ID --from --to [--db]: not both")
        else:
            cal, name = _calibrate_file(recording, load_machine(machine or "patu655"), mapping,
                                        payload_column)
        _print(cal, name, as_json)


def _calibrate_file(recording: Path, m: Machine, mapping: Path | None,
                    payload_column: str) -> tuple[Calibration, str]:
    """Calibrate on a file: the simulator's recording, or a user's through the importer."""
    from cranetwin.reports.sources import is_simulator_recording
    from cranetwin.twin.calibration import calibrate

    known = None
    if mapping is None and is_simulator_recording(recording):
        from cranetwin.sim import Recording

        samples = Recording.load(recording).samples
    else:
        from cranetwin.importer import read_file

        got = read_file(recording, m, mapping)
        samples = got.samples
        known = got.payload_kg if payload_column == "use" else None
    return calibrate(samples, m, payload_kg=known), recording.name


def _print(cal: Calibration, name: str, as_json: bool) -> None:
    """The calibration as JSON or as tables and notes."""
    if as_json:
        typer.echo(json.dumps(asdict(cal)))
        return
    con = Console()
    t = Table(title=f"Friction (Eq. 2) from {name}")
    for col in ("cylinder", "Fc file → fit [N]", "vc file → fit [mm/s]",
                "b file → fit [N·s/m]", "offset [N]", "RMS residual before → after [N]",
                "kept from the file"):
        t.add_column(col)
    for f, off in zip(cal.cylinders, cal.offsets_n, strict=True):
        t.add_row(f.name, f"{f.coulomb_file:.0f} → {_fmt(f.coulomb, f.coulomb_std)}",
                  f"{f.coulomb_velocity_file * 1e3:.2f} → {f.coulomb_velocity * 1e3:.2f}",
                  f"{f.viscous_file:.0f} → {_fmt(f.viscous, f.viscous_std)}", f"{off:.0f}",
                  f"{f.rms_before_n:.0f} → {f.rms_after_n:.0f}", ", ".join(f.prior) or "–")
    con.print(t)
    for f in cal.cylinders:
        for note in f.notes:
            con.print(f"[yellow]{f.name}: {note}[/yellow]")
    if len(cal.segments) > 1:
        con.print(f"The payload changes {len(cal.segments) - 1} time(s): one mass per "
                  f"segment, friction shared (transitions left out):")
        for s in cal.segments:
            val = (f"{s.extra_mass_kg:.1f} ± {s.std_kg:.1f} kg" if s.identified
                   else f"not identified: {s.note}")
            con.print(f"  {s.t0_s:.1f} … {s.t1_s:.1f} s: {val}")
    if cal.mass_note:
        con.print(f"[yellow]Mass at the load point not identified: {cal.mass_note}"
                  "[/yellow]")
    elif cal.payload_known:
        con.print(f"Tool mass error (the known payload column subtracted): "
                  f"{cal.extra_mass_kg:+.2f} ± {cal.extra_mass_std_kg:.2f} kg statistical "
                  f"against the file's {cal.tool_mass_file_kg:g} kg ({cal.samples_used} "
                  "instants)")
    else:
        con.print(f"Mass at the load point beyond the file's tool mass "
                  f"({cal.tool_mass_file_kg:g} kg): {cal.extra_mass_kg:.2f} ± "
                  f"{cal.extra_mass_std_kg:.2f} kg statistical ({cal.samples_used} "
                  f"instants; model error adds ≈ 0.1–0.3 kg on simulated runs, "
                  f"docs/ACCURACY.md)")
    left = ", ".join(f"{v:.1f} s {k}" for k, v in cal.excluded_s.items() if v > 0)
    if left:
        con.print(f"Left out before the fit: {left}.")
    for f in cal.cylinders:
        bad = [name for name, val in (("Fc", f.coulomb), ("vc", f.coulomb_velocity),
                                      ("b", f.viscous)) if not val > 0.0]
        if bad:
            con.print(f"[yellow]Warning: {', '.join(bad)} of {f.name} came out ≤ 0, which is "
                      f"not physical: the recording does not excite that friction enough "
                      f"(10 minutes of varied motion determine b within 10 %).[/yellow]")
    passes, width = cal.filter_passes_width
    con.print(f"Offset: constant force per cylinder (pressure-transducer bias). Low-pass: "
              f"{passes} moving average(s) of {width} instants on both sides.")
