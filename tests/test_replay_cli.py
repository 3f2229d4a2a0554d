"""cranetwin replay and cranetwin.importer.replay: named, documented columns from a file or a
stored range; rod positions that are not stroke positions refused before the twin clips them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from cranetwin.errors import TwinError
from cranetwin.importer.replay import column_units, replay_table
from cranetwin.model import Machine, load_machine
from cranetwin.samples import SampleArrays

pytestmark = pytest.mark.timeout(300)
T0 = 1_767_225_600.0


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load_machine("patu655")


@pytest.fixture(scope="module")
def rec(machine: Machine) -> SampleArrays:
    from cranetwin.sim import builtin_scenario, simulate

    s = simulate(machine, builtin_scenario("fig3", duration_s=6.0), wrenches=False).samples
    return SampleArrays("m1", s.t_s + T0, s.channels, s.values)


def _csv(path: Path, rec: SampleArrays) -> Path:
    np.savetxt(path, np.column_stack([rec.t_s, rec.values]), delimiter=",", fmt="%.10f",
               header=",".join(["t_s", *rec.channels]), comments="")
    return path


def test_columns_match_the_twin_result(machine: Machine, rec: SampleArrays) -> None:
    from cranetwin.twin import replay

    table = replay_table(rec, machine)
    res = replay(rec, machine, grid_hz=100.0)
    assert list(table.columns) == list(column_units(machine)) and len(table.columns) == 81
    np.testing.assert_array_equal(table["force.jib"], res.cyl_force[:, 1])
    np.testing.assert_array_equal(table["q.theta2"], res.q[:, 2])
    np.testing.assert_array_equal(table["wrench.theta1.mz"], res.joint_wrench[:, 1, 5])
    np.testing.assert_array_equal(table["tip.z"], res.tip_path(machine)[:, 2])
    assert table.units["q.L"] == "m" and table.units["torque_act.L"] == "N"
    assert table.units["wrench.theta1.mz"] == "N*m" and table.units["p_a.lift"] == "Pa"


def test_pin_to_pin_samples_refused_by_replay(machine: Machine, rec: SampleArrays) -> None:
    v = rec.values.copy()
    v[:, rec.channels.index("jib_s")] += machine.cylinder("jib").closed_length_m
    with pytest.raises(TwinError, match="jib_s.*pin-to-pin"):
        replay_table(SampleArrays("m1", rec.t_s, rec.channels, v), machine)


def test_cli_replay_file_to_csv_and_store_range_to_parquet(tmp_path: Path, machine: Machine,
                                                          rec: SampleArrays) -> None:
    from cranetwin.cli import app
    from cranetwin.storage import Store

    f = _csv(tmp_path / "rec.csv", rec)
    out = tmp_path / "twin.csv"
    r = CliRunner().invoke(app, ["replay", str(f), "--out", str(out), "-q"])
    assert r.exit_code == 0, r.output
    header = out.read_text().splitlines()[0].split(",")
    assert header == list(column_units(machine))
    data = np.loadtxt(out, delimiter=",", skiprows=1)
    assert data.shape == (rec.t_s.size, 81)
    assert np.isfinite(data[:, header.index("force.lift")]).all()

    pq = pytest.importorskip("pyarrow.parquet")
    url = f"sqlite:///{tmp_path / 'db.sqlite'}"
    with Store.open(url) as store:
        store.add_machine("m1", 1, b"k" * 32)
    r = CliRunner().invoke(app, ["import", str(f), "--machine", "m1", "--db", url, "-q"])
    assert r.exit_code == 0, r.output
    pout = tmp_path / "twin.parquet"
    r = CliRunner().invoke(app, ["replay", "--machine", "m1", "--from", str(T0), "--to",
                                 str(T0 + 60), "--db", url, "--out", str(pout), "-q"])
    assert r.exit_code == 0, r.output
    t = pq.read_table(pout)
    assert t.num_rows == rec.t_s.size
    assert t.schema.field("force.lift").metadata == {b"unit": b"N"}
    np.testing.assert_allclose(t.column("force.lift").to_numpy(),
                               data[:, header.index("force.lift")], rtol=1e-6, atol=1.0)
    r = CliRunner().invoke(app, ["replay", "--machine", "m1", "--out", str(pout)])
    assert r.exit_code != 0


def test_channel_flags_and_columns_in(machine: Machine, rec: SampleArrays) -> None:
    """A dict of arrays (as a DataFrame's columns) in; per-channel missing flags out."""
    cols = {"t_s": rec.t_s, **{c: rec.column(c).copy() for c in rec.channels}}
    cols["jib_pA"][200] = np.nan  # a dropout of one channel
    keep = np.r_[0:300, 303:rec.t_s.size]  # a gap of three samples in all channels
    cols = {k: v[keep] for k, v in cols.items()}
    table = replay_table(cols, machine)
    t = table["t_s"]
    flag = table["missing.jib_pA"]
    at = int(np.argmin(np.abs(t - rec.t_s[200])))
    assert flag[at] == 1 and flag[at - 1] == 0 and flag[at + 1] == 0
    assert table["missing.lift_pA"][at] == 0
    in_gap = (t > rec.t_s[299] + 0.006) & (t < rec.t_s[303] - 0.006)
    assert in_gap.sum() >= 2
    assert all(table[f"missing.{c}"][in_gap].all() for c in rec.channels)
    quiet = ~in_gap
    quiet[at] = False
    assert not table["missing.lift_s"][quiet].any()


def test_cli_replay_warns_about_a_force_the_pressures_cannot_resolve(
        tmp_path: Path, machine: Machine, rec: SampleArrays) -> None:
    """With 3 % of full-range error on the pressures, the telescope cylinder's force (a few
    kN behind 250 bar sensors) is mostly sensor error: ``cranetwin replay`` says so, naming
    the cylinder and the numbers; the lift's is not named."""
    from cranetwin.cli import app
    from cranetwin.signal import inject_uniform_noise

    noisy = inject_uniform_noise(rec, machine, 0.03, seed=0)
    f = _csv(tmp_path / "noisy.csv", noisy)
    r = CliRunner().invoke(app, ["replay", str(f), "--out", str(tmp_path / "t.csv"), "-q"])
    assert r.exit_code == 0, r.output
    text = r.output + (r.stderr if r.stderr_bytes is not None else "")
    lines = [x for x in text.splitlines() if x.startswith("warning:")]
    assert any("'extension'" in x and "NOT observable" in x and "N (1σ" in x for x in lines), text
    assert not any("'lift'" in x for x in lines)
