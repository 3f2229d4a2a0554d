"""``cranetwin simulate`` end to end (short runs)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from cranetwin.cli import app
from cranetwin.sim import Recording


def test_simulate_writes_a_seeded_recording(tmp_path: Path) -> None:
    runner = CliRunner()
    outs = []
    for name in ("a.npz", "b.npz"):
        out = tmp_path / name
        res = runner.invoke(app, ["simulate", "--scenario", "random", "--duration", "0.5",
                                  "--rate", "50", "--seed", "4", "--payload", "200",
                                  "--machine-id", "crane-7", "--quiet", "--out", str(out)])
        assert res.exit_code == 0, res.output
        outs.append(Recording.load(out))
    a, b = outs
    assert a.samples.values.shape == (26, 11)
    assert np.array_equal(a.samples.values, b.samples.values, equal_nan=True)
    assert a.scenario == "random" and a.seed == 4 and a.samples.machine_id == "crane-7"


def test_simulate_csv_and_bad_scenario(tmp_path: Path) -> None:
    runner = CliRunner()
    out = tmp_path / "r.csv"
    res = runner.invoke(app, ["simulate", "--duration", "0.3", "--quiet", "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert out.exists() and (tmp_path / "r.truth.csv").exists()
    bad = tmp_path / "bad.json"
    bad.write_text('{"name": "x", "actuators": {"lift": {"gain": -1}}}')
    res = runner.invoke(app, ["simulate", "--scenario", str(bad), "--quiet",
                              "--out", str(tmp_path / "x.npz")])
    assert res.exit_code != 0
    assert "actuators.lift.gain" in str(res.exception)


def test_sim_imports_no_web_or_database_stack() -> None:
    import subprocess
    import sys

    code = ("import sys, cranetwin.sim; "
            "print(sorted(m for m in ('fastapi', 'sqlalchemy', 'uvicorn') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "[]"


def test_simulate_the_excavator_dig_cycle_to_csv(tmp_path: Path) -> None:
    out = tmp_path / "dig.csv"
    res = CliRunner().invoke(app, ["simulate", "--machine", "bobcat435", "--scenario",
                                   "dig-cycle", "--duration", "0.4", "--quiet", "--out",
                                   str(out)])
    assert res.exit_code == 0, res.output
    rec = Recording.load(out)
    assert rec.machine == "bobcat435" and rec.scenario == "dig-cycle"
    assert "swing_torque" in rec.samples.channels and "boom_pA" in rec.samples.channels
    assert rec.topology.cylinders == ("boom", "arm", "bucket")
    header = (tmp_path / "dig.truth.csv").read_text().splitlines()[0].split(",")
    assert "rod_s_bucket" in header and "drive_torque_swing" in header
    assert "contact_force_fz" in header
