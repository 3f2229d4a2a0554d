"""``cranetwin model show|validate|list``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

from cranetwin.errors import MachineFileError
from cranetwin.model import Machine, builtin_machines, load_machine

model_app = typer.Typer(help="Inspect and validate machine descriptions.", no_args_is_help=True)


def _kinematic_problems(machine: Machine) -> list[str]:
    # physics owns kinematics; imported lazily so that `model show` works on any schema-valid file
    from cranetwin.physics.kinematics import reach_problems

    problems: list[str] = reach_problems(machine)
    return problems


@model_app.command("list")
def list_machines() -> None:
    """List the built-in machine descriptions."""
    for name in builtin_machines():
        typer.echo(name)


@model_app.command("show")
def show(machine: str = typer.Argument(..., help="Built-in name or TOML file.")) -> None:
    """Print a readable summary of a machine description."""
    m = load_machine(machine)
    con = Console()
    con.print(f"[bold]{m.name}[/bold]: {m.machine.description}")
    t = Table(title="Bodies")
    for col in ("body", "mass [kg]", "COM [m]", "principal inertia [kg·m²]", "assumed"):
        t.add_column(col)
    for b in m.bodies:
        eig = np.linalg.eigvalsh(np.asarray(b.inertia_kgm2))
        t.add_row(b.name, f"{b.mass_kg:.2f}", str(tuple(round(x, 4) for x in b.com_m)),
                  ", ".join(f"{e:.3g}" for e in eig), ", ".join(b.assumed))
    con.print(t)
    t = Table(title="Joints (chain order)")
    for col in ("joint", "kind", "parent → child", "axis", "origin [m]", "limits"):
        t.add_column(col)
    for j in m.joints:
        lim = (f"{np.degrees(j.lower):.1f}° … {np.degrees(j.upper):.1f}°" if j.kind == "revolute"
               else f"{j.lower:.3f} … {j.upper:.3f} m")
        t.add_row(j.name, j.kind, f"{j.parent} → {j.child}", str(j.axis), str(j.origin_m), lim)
    con.print(t)
    t = Table(title="Actuators")
    for col in ("actuator", "joint", "bore/rod [mm]", "A1/A2 [m²]", "closed+stroke [m]",
                "friction Fc, vc, b", "linkage"):
        t.add_column(col)
    for c in m.cylinders:
        f = c.friction
        t.add_row(c.name, c.joint, f"{c.bore_m * 1e3:.0f}/{c.rod_m * 1e3:.0f}",
                  f"{c.area_a_m2:.4g}/{c.area_b_m2:.4g}", f"{c.closed_length_m}+{c.stroke_m}",
                  f"{f.coulomb:g} N, {f.coulomb_velocity:g} m/s, {f.viscous:g} N·s/m",
                  c.linkage.kind if c.linkage else "direct")
    for d in m.torque_drives:
        f = d.friction
        t.add_row(d.name, d.joint, "torque drive", "", f"max {d.max_torque_nm:g} N·m",
                  f"{f.coulomb:g} N·m, {f.coulomb_velocity:g} rad/s, {f.viscous:g}", "")
    con.print(t)
    t = Table(title="Sensor channels")
    for col in ("channel", "quantity", "source", "range", "resolution", "optional"):
        t.add_column(col)
    for ch in m.channels:
        rng = ("unknown" if ch.min is None or ch.max is None
               else f"{ch.min:g} … {ch.max:g} {ch.unit}")
        t.add_row(ch.name, ch.quantity, ch.source, rng,
                  f"{ch.resolution:g} {ch.unit}", "yes" if ch.optional else "")
    con.print(t)
    lp = m.load_point
    con.print(f"Load point: {lp.point_m} m on {lp.body}; tool mass {lp.tool_mass_kg:g} kg")
    rl = m.rated_load
    chart = ("unknown (no [rated_load] chart)" if rl is None else
             ", ".join(f"{r:g} m: {p:g} kg" for r, p in zip(rl.reach_m, rl.payload_kg,
                                                            strict=True)))
    con.print(f"Rated load: {chart}")


@model_app.command("validate")
def validate(
    path: Path = typer.Argument(..., help="Machine TOML file (or built-in name)."),
) -> None:
    """Check a machine file: schema, units/shapes, physical plausibility and cylinder reach.

    Prints every problem with its field path; exit status 1 when there are problems.
    """
    try:
        m = load_machine(str(path) if not path.exists() else path)
        problems = _kinematic_problems(m)
    except MachineFileError as exc:
        problems = exc.problems
    if problems:
        typer.echo(f"{path}: {len(problems)} problem(s)")
        for p in problems:
            typer.echo(f"  - {p}")
        raise typer.Exit(1)
    typer.echo(f"{path}: OK")
    for note in m.unknowns():  # optional fields left out: said, not invented
        typer.echo(f"  unknown: {note}")


def register(app: typer.Typer) -> None:
    app.add_typer(model_app, name="model")
