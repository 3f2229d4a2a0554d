"""``cranetwin calibrate RECORDING``: friction and carried mass from a recording."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from cranetwin.model import load_machine


def register(app: typer.Typer) -> None:
    @app.command("calibrate")
    def calibrate_cmd(
        recording: Path = typer.Argument(..., help="Recording (.npz or .csv from `simulate`)."),
        machine: str = typer.Option("patu655", help="Built-in machine name or TOML file."),
        as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
    ) -> None:
        """Estimate cylinder friction (Fc, vc, b; Eq. 2) and the payload/tool mass by least
        squares, and report the force residual before and after."""
        from cranetwin.sim import Recording
        from cranetwin.twin.calibration import calibrate

        m = load_machine(machine)
        rec = Recording.load(recording)
        cal = calibrate(rec.samples, m)
        if as_json:
            typer.echo(json.dumps(asdict(cal)))
            return
        con = Console()
        t = Table(title=f"Friction (Eq. 2) from {recording.name}")
        for col in ("cylinder", "Fc file → fit [N]", "vc file → fit [mm/s]",
                    "b file → fit [N·s/m]", "offset [N]", "RMS residual before → after [N]"):
            t.add_column(col)
        for f, off in zip(cal.cylinders, cal.offsets_n, strict=True):
            t.add_row(f.name, f"{f.coulomb_file:.0f} → {f.coulomb:.0f}",
                      f"{f.coulomb_velocity_file * 1e3:.2f} → {f.coulomb_velocity * 1e3:.2f}",
                      f"{f.viscous_file:.0f} → {f.viscous:.0f}", f"{off:.0f}",
                      f"{f.rms_before_n:.0f} → {f.rms_after_n:.0f}")
        con.print(t)
        con.print(f"Mass at the load point beyond the file's tool mass "
                  f"({cal.tool_mass_file_kg:g} kg): {cal.extra_mass_kg:.2f} ± "
                  f"{cal.extra_mass_std_kg:.2f} kg statistical ({cal.samples_used} instants; "
                  f"model error adds ≈ 0.1–0.3 kg on simulated runs, docs/ACCURACY.md)")
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
