"""The twin on a recording it did not make: the independent crane simulation through the user path.

:mod:`cranetwin.testing.indep_sim` simulates the PATU 655 without any of the project's
physics. Its run is written as a data logger would (:func:`write_logger_csv`: pressures in bar,
cylinder **pin-to-pin lengths** in mm, slew in degrees, torque in kN·m, time relative to a
start), read back with a mapping TOML (:func:`mapping_toml`, docs/IMPORT.md: ``pin_to_pin``
with an explicit offset), disturbed with sensor error (:func:`cranetwin.sim.sensor_error.
inject_error`, uniform, of full or recorded range) and replayed by
:func:`cranetwin.importer.replay.iter_replay_table` against the machine file. Joint angles, rod
positions and cylinder forces are compared with the simulation's truth (NRMSE over the truth's
range, docs/ACCURACY.md) together with the force observability flag of each cylinder.

``python tests/indep_check.py`` prints the table of docs/ACCURACY.md ("Independent crane
simulation"). Simulations are cached as ``.npz`` under ``CRANETWIN_CACHE_DIR``/indep, keyed by
the simulation's source text. This module lives with the tests, not in ``cranetwin.testing``:
it drives the importer, which the synthetic-data package may not import (docs/ARCHITECTURE.md);
the simulation itself is :mod:`cranetwin.testing.indep_sim`.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import numpy.typing as npt

from cranetwin.testing import indep_crane, indep_scenarios, indep_sim
from cranetwin.testing.indep_crane import CYLINDERS, PATU655, CraneParams
from cranetwin.testing.indep_sim import Run

F64 = npt.NDArray[np.float64]

START_EPOCH_S = 1_780_000_000.0
"""Epoch [s] of the logger's relative time 0 (2026-05-28)."""

SCENARIOS = ("valve-steps", "log-cycle")
CHANNEL_OF = {"lift": "lift", "jib": "jib", "extension": "ext"}
JOINTS = ("theta0", "theta1", "theta2", "L")


def _cache_dir() -> Path:
    env = os.environ.get("CRANETWIN_CACHE_DIR")
    base = Path(env) if env else Path.home() / ".cache" / "cranetwin"
    return base / "indep"


def _source_key(p: CraneParams, name: str) -> str:
    h = hashlib.sha256()
    for mod in (indep_crane, indep_sim, indep_scenarios):
        h.update(Path(str(mod.__file__)).read_bytes())
    h.update(repr(p).encode())
    h.update(name.encode())
    return h.hexdigest()[:16]


def scenario(p: CraneParams, name: str) -> indep_sim.Scenario:
    """A scenario of :data:`SCENARIOS` by name."""
    if name == "valve-steps":
        return indep_scenarios.valve_steps(p)
    if name == "log-cycle":
        return indep_scenarios.log_cycle(p)
    raise ValueError(f"unknown scenario {name!r}; expected one of {SCENARIOS}")


def simulated(name: str, p: CraneParams = PATU655, cache: bool = True) -> Run:
    """The run of scenario ``name``, from the cache when there (1–2 CPU minutes otherwise)."""
    path = _cache_dir() / f"{name}-{_source_key(p, name)}.npz"
    if cache and path.exists():
        return Run.load(str(path))
    run = indep_sim.simulate(p, scenario(p, name))
    if cache:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")  # xdist workers may race
        run.save(str(tmp))
        tmp.replace(path)
    return run


def _telescope_63(p: CraneParams) -> CraneParams:
    cyl = (p.cyl[0], p.cyl[1], replace(p.cyl[2], bore_m=0.063, rod_m=0.036))
    return replace(p, cyl=cyl)


def _friction_x4(p: CraneParams) -> CraneParams:
    cyl = tuple(replace(c, fc_n=4 * c.fc_n, b_nspm=4 * c.b_nspm) for c in p.cyl)
    return replace(p, cyl=cyl)  # type: ignore[arg-type]


def _light(p: CraneParams) -> CraneParams:
    return replace(p, lift=replace(p.lift, mass_kg=p.lift.mass_kg / 2),
                   jib=replace(p.jib, mass_kg=p.jib.mass_kg / 2),
                   ext=replace(p.ext, mass_kg=p.ext.mass_kg / 2), tool_kg=p.tool_kg / 2)


VARIANTS: dict[str, Callable[[CraneParams], CraneParams]] = {
    "telescope-63mm": _telescope_63, "friction-x4": _friction_x4, "light": _light}
"""Cranes that differ from the machine file the twin replays with (``--variant``): telescope
cylinder 63/36 mm instead of 50/32 (the file's values are assumed), every cylinder's friction
×4, booms and tool at half mass."""

MAPPING_ERRORS: dict[str, tuple[str, str]] = {
    "ext-offset+200mm": ("offset = 1500.0", "offset = 1700.0"),
    "lift-offset+50mm": ("offset = 820.0", "offset = 870.0"),
    "ext-pA-pB-swapped": ('[channels.ext_pA]\ncolumn = "Tele p piston [bar]"',
                          '[channels.ext_pA]\ncolumn = "Tele p rod [bar]"'),
}
"""A user's mistakes in the mapping (``--mapping-error``): the telescope's or the lift's
pin-to-pin offset wrong, the telescope's chamber pressures swapped (``old``, ``new`` text)."""


# --- the logger's file -----------------------------------------------------------------------

LOGGER_COLUMNS = {
    "lift_pA": "Boom p piston [bar]", "lift_pB": "Boom p rod [bar]",
    "jib_pA": "Jib p piston [bar]", "jib_pB": "Jib p rod [bar]",
    "ext_pA": "Tele p piston [bar]", "ext_pB": "Tele p rod [bar]",
    "lift_s": "Boom cyl length [mm]", "jib_s": "Jib cyl length [mm]",
    "ext_s": "Tele cyl length [mm]", "slew_torque": "Slew torque [kNm]",
    "slew_angle": "Slew angle [deg]",
}


def write_logger_csv(run: Run, path: str | Path) -> None:
    """The run as a logger's CSV: relative time [s], pressures [bar, 0.01], pin-to-pin lengths
    [mm, 0.01], slew torque [kN·m, 0.001], slew angle [deg, 0.001], known payload [kg]."""
    cols: dict[str, F64] = {"t [s]": np.round(run.t_s, 6)}
    for k, cyl in enumerate(CYLINDERS):
        ch = CHANNEL_OF[cyl]
        cols[LOGGER_COLUMNS[f"{ch}_pA"]] = np.round(run.pa_pa[:, k] / 1e5, 2)
        cols[LOGGER_COLUMNS[f"{ch}_pB"]] = np.round(run.pb_pa[:, k] / 1e5, 2)
    for k, cyl in enumerate(CYLINDERS):
        cols[LOGGER_COLUMNS[f"{CHANNEL_OF[cyl]}_s"]] = np.round(run.length_m[:, k] * 1e3, 2)
    cols[LOGGER_COLUMNS["slew_torque"]] = np.round(run.slew_torque_nm / 1e3, 3)
    cols[LOGGER_COLUMNS["slew_angle"]] = np.round(run.q[:, 0] * (180.0 / np.pi), 3)
    cols["Scale [kg]"] = np.round(run.payload_kg, 1)
    lines = [",".join(cols)]
    rows = np.column_stack(list(cols.values()))
    lines += [",".join(f"{v:.6g}" if j else f"{v:.2f}" for j, v in enumerate(r)) for r in rows]
    Path(path).write_text("\n".join(lines) + "\n")


def mapping_toml(p: CraneParams = PATU655, error: str | None = None) -> str:
    """The logger's mapping (docs/IMPORT.md): relative time, bar, pin-to-pin mm with the
    cylinders' closed lengths as offsets, kN·m, degrees, a known payload column; with one of
    :data:`MAPPING_ERRORS` when ``error`` names it."""
    text = _mapping_toml(p)
    if error is None:
        return text
    old, new = MAPPING_ERRORS[error]
    if old not in text:
        raise ValueError(f"mapping error {error!r} does not apply")
    if error.endswith("swapped"):
        text = text.replace('[channels.ext_pB]\ncolumn = "Tele p rod [bar]"',
                            '[channels.ext_pB]\ncolumn = "Tele p piston [bar]"')
    return text.replace(old, new)


def _mapping_toml(p: CraneParams) -> str:
    out = [f'[time]\ncolumn = "t [s]"\nformat = "relative_s"\nstart = {START_EPOCH_S:.0f}\n'
           "period_s = 0.01\n"]
    for k, cyl in enumerate(CYLINDERS):
        ch = CHANNEL_OF[cyl]
        for side in ("pA", "pB"):
            out.append(f'[channels.{ch}_{side}]\ncolumn = "{LOGGER_COLUMNS[f"{ch}_{side}"]}"\n'
                       'unit = "bar"\n')
        out.append(f'[channels.{ch}_s]\ncolumn = "{LOGGER_COLUMNS[f"{ch}_s"]}"\nunit = "mm"\n'
                   f'convention = "pin_to_pin"\noffset = {p.cyl[k].closed_m * 1e3:.1f}\n')
    out.append(f'[channels.slew_torque]\ncolumn = "{LOGGER_COLUMNS["slew_torque"]}"\n'
               'unit = "kN*m"\n')
    out.append(f'[channels.slew_angle]\ncolumn = "{LOGGER_COLUMNS["slew_angle"]}"\n'
               'unit = "deg"\n')
    out.append('[payload]\ncolumn = "Scale [kg]"\nunit = "kg"\n')
    return "\n".join(out)


# --- replay and comparison -------------------------------------------------------------------

@dataclass(frozen=True)
class Comparison:
    """One replay against the truth (NRMSE as fractions of the truth's range).

    Attributes:
        joints: theta0, theta1, theta2, L. rods, forces: lift, jib, extension.
        force_input: the raw (noisy) pressures through Eq. 1 with the true velocity.
        share, observable: the force observability verdict per cylinder.
        force_range_n: the truth's force range per cylinder [N].
        payload_rmse_kg: payload estimate in steady lifts (payload on, no step within 1.5 s).
    """

    scenario: str
    distribution: str
    scale: str
    level: float
    seed: int
    joints: tuple[float, ...]
    rods: tuple[float, ...]
    forces: tuple[float, ...]
    force_input: tuple[float, ...]
    share: tuple[float, ...]
    observable: tuple[bool, ...]
    force_range_n: tuple[float, ...]
    payload_rmse_kg: float
    rows_refused: int = 0


def _nrmse(est: F64, truth: F64) -> float:
    span = float(np.nanmax(truth) - np.nanmin(truth))
    return float(np.sqrt(np.nanmean((est - truth) ** 2)) / span) if span > 0 else float("nan")


def replay_run(run: Run, workdir: str | Path, level: float = 0.0, seed: int = 0,
               distribution: str = "uniform", scale: str = "full",
               mapping_error: str | None = None) -> Comparison:
    """Write the run as a logger's file, import it with the mapping (with ``mapping_error``
    of :data:`MAPPING_ERRORS` if given), add sensor error, replay it against the built-in
    ``patu655`` and compare with the truth."""
    from cranetwin.importer import read_file
    from cranetwin.importer.replay import ReplayNotes, iter_replay_table
    from cranetwin.model import load_machine
    from cranetwin.sim.sensor_error import inject_error

    machine = load_machine("patu655")
    wd = Path(workdir)
    csv, toml = wd / f"{run.name}.csv", wd / f"{run.name}-{mapping_error or 'ok'}.toml"
    if not csv.exists():
        write_logger_csv(run, csv)
    if not toml.exists():
        toml.write_text(mapping_toml(error=mapping_error))
    got = read_file(csv, machine, toml)
    samples = got.samples
    if level > 0:
        samples = inject_error(samples, machine, level, seed, distribution,  # type: ignore[arg-type]
                               scale)  # type: ignore[arg-type]
    notes = ReplayNotes.empty()
    parts = list(iter_replay_table(samples, machine, notes=notes, known_payload_kg=got.payload_kg))
    cols = {k: np.concatenate([c[k] for c in parts]) for k in parts[0]}
    idx = np.rint((cols["t_s"] - START_EPOCH_S) * 100.0).astype(int)
    ok = (idx >= 0) & (idx < run.t_s.shape[0]) & (np.abs(cols["t_s"] - START_EPOCH_S
                                                          - idx / 100.0) < 1e-4)
    i = idx[ok]
    joints = tuple(_nrmse(cols[f"q.{j}"][ok], run.q[i, n]) for n, j in enumerate(JOINTS))
    rods = tuple(_nrmse(cols[f"rod_s.{c}"][ok], run.s_m[i, k]) for k, c in enumerate(CYLINDERS))
    forces = tuple(_nrmse(cols[f"force.{c}"][ok], run.force_n[i, k])
                   for k, c in enumerate(CYLINDERS))
    pa = np.column_stack([samples.column(f"{CHANNEL_OF[c]}_pA") for c in CYLINDERS])
    pb = np.column_stack([samples.column(f"{CHANNEL_OF[c]}_pB") for c in CYLINDERS])
    a1 = np.array([c.area_a_m2 for c in machine.cylinders])
    a2 = np.array([c.area_b_m2 for c in machine.cylinders])
    # Eq. 1 on the noisy pressures with the true friction (truth's pA·A1 − pB·A2 − F)
    js = np.rint((samples.t_s - START_EPOCH_S) * 100.0).astype(int)
    raw = pa * a1 - pb * a2 - (run.pa_pa[js] * a1 - run.pb_pa[js] * a2 - run.force_n[js])
    force_input = tuple(_nrmse(raw[:, k], run.force_n[js, k]) for k in range(3))
    verdicts = notes.force_observability(machine)
    steady = _steady(run.t_s, run.payload_kg)[i]
    err = cols["payload_kg"][ok][steady] - run.payload_kg[i][steady]
    return Comparison(run.name, distribution, scale, level, seed, joints, rods, forces,
                      force_input, tuple(v.share for v in verdicts),
                      tuple(v.observable for v in verdicts),
                      tuple(float(np.ptp(run.force_n[:, k])) for k in range(3)),
                      float(np.sqrt(np.mean(err ** 2))) if err.size else float("nan"),
                      got.report.rows_refused)


def _steady(t: F64, payload: F64, margin_s: float = 1.5) -> npt.NDArray[np.bool_]:
    """Instants with a payload on and no payload step within ``margin_s``."""
    steps = t[1:][np.diff(payload) != 0]
    far = np.ones(t.shape, dtype=bool)
    for ts in steps:
        far &= np.abs(t - ts) > margin_s
    return far & (payload > 0)


LEVELS = (0.0, 0.01, 0.02, 0.05)


def table(seeds: int = 3, workdir: str | Path | None = None, variant: str | None = None,
          mapping_error: str | None = None, scenarios: tuple[str, ...] = SCENARIOS,
          scales: tuple[str, ...] = ("full", "recorded")) -> list[Comparison]:
    """Every scenario × (noise-free; uniform error of ``scales`` at 1, 2, 5 %) × seeds, the
    crane simulated as :data:`PATU655` or its ``variant`` (:data:`VARIANTS`), the mapping with
    ``mapping_error`` (:data:`MAPPING_ERRORS`)."""
    import tempfile

    p = PATU655 if variant is None else VARIANTS[variant](PATU655)
    out: list[Comparison] = []
    with tempfile.TemporaryDirectory() as tmp:
        wd = Path(workdir or tmp) / (variant or "patu655")
        wd.mkdir(parents=True, exist_ok=True)
        for name in scenarios:
            run = simulated(name, p)
            out.append(replay_run(run, wd, mapping_error=mapping_error))
            for scale in scales:
                for level in LEVELS[1:]:
                    for seed in range(seeds):
                        out.append(replay_run(run, wd, level, seed, "uniform", scale,
                                              mapping_error))
    return out


def markdown(rows: list[Comparison]) -> str:
    """Mean over seeds per (scenario, scale, level): NRMSE [%] and the flag."""
    head = ("| run | error | θ1 / θ2 / L [%] | rod s lift / jib / ext [%] | "
            "force lift / jib / ext [%] | input force lift / jib / ext [%] | "
            "flag share lift / jib / ext [%] (! = not observable) | payload RMSE [kg] |\n"
            "|---|---|---|---|---|---|---|---|")
    lines = [head]
    keys: list[tuple[str, str, float]] = []
    for r in rows:
        key = (r.scenario, r.scale, r.level)
        if key not in keys:
            keys.append(key)
    for key in keys:
        group = [r for r in rows if (r.scenario, r.scale, r.level) == key]

        def mean(attr: str, group: list[Comparison] = group) -> F64:
            return np.asarray(np.mean([getattr(r, attr) for r in group], axis=0),
                              dtype=np.float64)

        def fmt(v: F64, digits: int = 2) -> str:
            return " / ".join(f"{x * 100:.{digits}f}" for x in v)

        flags = " / ".join(
            f"{s * 100:.0f}{'!' * (sum(not r.observable[k] for r in group) > 0)}"
            + (f" ({sum(not r.observable[k] for r in group)}/{len(group)})"
               if 0 < sum(not r.observable[k] for r in group) < len(group) else "")
            for k, s in enumerate(mean("share")))
        err = "none" if key[2] == 0 else f"±{key[2] * 100:.0f} % {key[1]}"
        digits = 3 if key[2] == 0 else 2
        lines.append(f"| {key[0]} | {err} | {fmt(mean('joints')[1:], digits)} | "
                     f"{fmt(mean('rods'), digits)} | {fmt(mean('forces'), digits)} | "
                     f"{fmt(mean('force_input'), digits)} | {flags} | "
                     f"{_kg(float(mean('payload_rmse_kg')))} |")
    return "\n".join(lines)


def _kg(x: float) -> str:
    return "–" if not np.isfinite(x) else f"{x:.1f}"


def main(argv: list[str] | None = None) -> int:
    """``python tests/indep_check.py [--seeds N] [--json] [--variant …] [--mapping-error …]``."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--json", action="store_true", help="every replay as JSON lines")
    ap.add_argument("--workdir", default=None, help="keep the logger CSV and mapping here")
    ap.add_argument("--variant", choices=sorted(VARIANTS), default=None,
                    help="simulate a crane that differs from the machine file")
    ap.add_argument("--mapping-error", choices=sorted(MAPPING_ERRORS), default=None,
                    help="replay with a mistaken mapping")
    ap.add_argument("--scenario", choices=SCENARIOS, action="append", default=None)
    ap.add_argument("--scale", choices=("full", "recorded"), action="append", default=None)
    a = ap.parse_args(argv)
    rows = table(a.seeds, a.workdir, a.variant, a.mapping_error,
                 tuple(a.scenario or SCENARIOS), tuple(a.scale or ("full", "recorded")))
    if a.json:
        for r in rows:
            print(json.dumps(r.__dict__))
    else:
        ranges = {r.scenario: r.force_range_n for r in rows}
        for name, fr in ranges.items():
            print(f"{name}: truth force range lift / jib / ext "
                  + " / ".join(f"{x / 1e3:.1f}" for x in fr) + " kN")
        print(markdown(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
