"""``cranetwin demo``: replay a built-in motion of the PATU 655 through the physics and print
where the crane was and what forces acted (a stand-in until the web demo exists)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import typer
from rich.console import Console
from rich.table import Table

from cranetwin.model import Machine, load_machine
from cranetwin.physics import (
    cylinder_forces_from_torques,
    cylinder_kinematics,
    horizontal_reach,
    inverse_dynamics,
    load_point_position,
)

F64 = npt.NDArray[np.float64]

# start and end of the built-in motion: slew 0 -> 60°, lift 10° -> 35°, jib −100° -> −55°,
# telescope 0.2 -> 0.9 m (a log swung out and lifted)
START = np.array([0.0, np.radians(10.0), np.radians(-100.0), 0.2])
END = np.array([np.radians(60.0), np.radians(35.0), np.radians(-55.0), 0.9])


def motion_ends(machine: Machine) -> tuple[F64, F64]:
    """START/END for a 4-joint machine whose limits contain them; else 35 % -> 65 % of each
    joint's range."""
    lo = np.array([j.lower for j in machine.joints])
    hi = np.array([j.upper for j in machine.joints])
    if machine.n_joints == 4 and np.all((START >= lo) & (START <= hi) & (END >= lo)
                                        & (END <= hi)):
        return START, END
    return lo + 0.35 * (hi - lo), lo + 0.65 * (hi - lo)


def builtin_motion(machine: Machine, t: F64, duration_s: float) -> tuple[F64, F64, F64]:
    """Quintic rest-to-rest blend between :func:`motion_ends`: q, qd, qdd, shape (len(t), nj)."""
    a, b = motion_ends(machine)
    x = np.clip(t / duration_s, 0.0, 1.0)[:, None]
    h = 10 * x**3 - 15 * x**4 + 6 * x**5
    hd = (30 * x**2 - 60 * x**3 + 30 * x**4) / duration_s
    hdd = (60 * x - 180 * x**2 + 120 * x**3) / duration_s**2
    d = b - a
    return a + h * d, hd * d, hdd * d


def replay_tables(machine: Machine, duration_s: float, payload_kg: float, step_s: float,
                  rate_hz: float = 1000.0) -> tuple[Table, Table]:
    """Run the motion at ``rate_hz`` through kinematics and inverse dynamics; tabulate the
    positions and the forces every ``step_s``."""
    t = np.arange(0.0, duration_s + 0.5 / rate_hz, 1.0 / rate_hz)
    q, qd, qdd = builtin_motion(machine, t, duration_s)
    tau, wrench = inverse_dynamics(machine, q, qd, qdd, payload_kg)
    s, _ = cylinder_kinematics(machine, q)
    force = cylinder_forces_from_torques(machine, q, tau)
    tip = load_point_position(machine, q)
    reach = horizontal_reach(machine, q)
    rated = (machine.rated_load.payload_at(reach) if machine.rated_load is not None
             else np.full(reach.shape, np.nan))  # no chart: unknown
    rows = np.arange(0, len(t), max(1, int(round(step_s * rate_hz))))

    pos = Table(title=f"{machine.name}: positions (built-in motion, computed at {rate_hz:g} Hz)")
    cols = ["t [s]"]
    cols += [f"{j.name} [{'°' if j.kind == 'revolute' else 'm'}]" for j in machine.joints]
    cols += ["tip x [m]", "tip y [m]", "tip z [m]", "reach [m]"]
    cols += [f"s {c.name} [m]" for c in machine.cylinders]
    for c in cols:
        pos.add_column(c, justify="right")
    for k in rows:
        cells = [f"{t[k]:.2f}"]
        cells += [f"{np.degrees(q[k, i]):.1f}" if j.kind == "revolute" else f"{q[k, i]:.3f}"
                  for i, j in enumerate(machine.joints)]
        cells += [f"{x:.2f}" for x in tip[k]] + [f"{reach[k]:.2f}"]
        cells += [f"{x:.3f}" for x in s[k]]
        pos.add_row(*cells)

    frc = Table(title=f"{machine.name}: forces, payload {payload_kg:g} kg "
                      f"(+ tool {machine.load_point.tool_mass_kg:g} kg)")
    cols = ["t [s]", "load/rated"]
    cols += [f"F {c.name} [kN]" for c in machine.cylinders]
    cols += [f"T {d.name} [kN·m]" for d in machine.torque_drives]
    cols += [f"|M| {j.name} [kN·m]" for j in machine.joints if j.kind == "revolute"]
    for c in cols:
        frc.add_column(c, justify="right")
    for k in rows:
        cells = [f"{t[k]:.2f}", f"{payload_kg / rated[k]:.0%}"]
        cells += [f"{x / 1e3:.2f}" for x in force[k]]
        cells += [f"{tau[k, machine.joint_index(d.joint)] / 1e3:.2f}"
                  for d in machine.torque_drives]
        cells += [f"{np.linalg.norm(wrench[k, i, 3:]) / 1e3:.2f}"
                  for i, j in enumerate(machine.joints) if j.kind == "revolute"]
        frc.add_row(*cells)
    return pos, frc


def register(app: typer.Typer) -> None:
    @app.command("demo")
    def demo(
        duration: float = typer.Option(6.0, min=0.5, max=60.0, help="Motion duration [s]."),
        payload: float = typer.Option(300.0, min=0.0, help="Payload on the hook [kg]."),
        step: float = typer.Option(0.5, min=0.01, help="Table row spacing [s]."),
        machine: str = typer.Option("patu655", help="Built-in name or machine TOML file."),
    ) -> None:
        """Replay a built-in crane motion: joint angles, tip position, cylinder forces."""
        m = load_machine(machine)
        console = Console(width=max(Console().width, 110))
        for table in replay_tables(m, duration, payload, step):
            console.print(table)
        console.print("F > 0 pushes. Forces from inverse dynamics (rigid bodies, friction "
                      "excluded): what the hydraulics must deliver for this motion. |M|: "
                      "magnitude of the reaction moment transmitted across the joint.")
