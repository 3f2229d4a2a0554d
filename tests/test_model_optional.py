"""Optional ratings really optional: a machine file without a rated-load chart, joint velocity
limits or sensor ranges (tests/data/patu655_minimal.toml) loads, validates, imports, replays and
reports, and every consumer says what is unknown instead of crashing or inventing a value."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from cranetwin.analytics import LoadHistory
from cranetwin.analytics.events import EventDetector
from cranetwin.errors import MachineFileError, SimulationError
from cranetwin.importer import read_file
from cranetwin.importer.replay import column_units, replay_table
from cranetwin.model import Machine, load_machine, machine_from_dict

MINIMAL = Path(__file__).parent / "data" / "patu655_minimal.toml"
T0 = 1_767_225_600.0


@pytest.fixture(scope="module")
def full() -> Machine:
    return load_machine("patu655")


@pytest.fixture(scope="module")
def minimal() -> Machine:
    return load_machine(MINIMAL)


@pytest.fixture(scope="module")
def csv_file(full: Machine, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """30 s of log-loading simulated on the full crane, as a logger CSV (time in epoch s)."""
    from cranetwin.sim import builtin_scenario, simulate

    s = simulate(full, builtin_scenario("log-loading", duration_s=30.0), wrenches=False).samples
    f = tmp_path_factory.mktemp("minimal") / "logger.csv"
    np.savetxt(f, np.column_stack([s.t_s + T0, s.values]), delimiter=",",
               fmt=["%.6f", *["%.10g"] * len(s.channels)], header=",".join(["t_s", *s.channels]),
               comments="")
    return f


@pytest.mark.timeout(60)
def test_minimal_file_loads_and_names_what_is_unknown(minimal: Machine) -> None:
    assert minimal.rated_load is None
    assert all(j.velocity_limit is None for j in minimal.joints)
    assert all(c.min is None and c.max is None and c.full_range is None
               for c in minimal.channels)
    notes = minimal.unknowns()
    assert notes[0].startswith("rated_load:")
    assert any(n.startswith("joints.0.velocity_limit:") for n in notes)
    assert any(n.startswith("channels.0.min/max:") for n in notes)
    assert load_machine("patu655").unknowns() == []


@pytest.mark.timeout(60)
def test_half_a_range_is_a_problem_with_its_path(full: Machine) -> None:
    data = full.model_dump()
    del data["channels"][2]["max"]
    with pytest.raises(MachineFileError) as exc:
        machine_from_dict(data)
    assert any(p.startswith("channels.2:") and "both min and max" in p
               for p in exc.value.problems), exc.value.problems


@pytest.mark.timeout(120)
def test_validate_prints_ok_and_the_unknowns() -> None:
    from cranetwin.cli import app

    r = CliRunner().invoke(app, ["model", "validate", str(MINIMAL)])
    assert r.exit_code == 0, r.output
    assert "OK" in r.output and "unknown: rated_load:" in r.output
    r = CliRunner().invoke(app, ["model", "show", str(MINIMAL)])
    assert r.exit_code == 0, r.output
    assert "Rated load: unknown" in r.output


def _history(machine: Machine, payload_kg: float, slew_rad_s: float) -> LoadHistory:
    n = 1000
    t = T0 + np.arange(n) * 0.01
    q = np.tile([0.0, 0.3, -0.5, 0.5], (n, 1))
    qd = np.zeros((n, 4))
    qd[:, 0] = slew_rad_s
    return LoadHistory.from_arrays(machine, t_s=t, cyl_force=np.full((n, 3), 1e4), q=q, qd=qd,
                                   payload_kg=np.full(n, payload_kg),
                                   reach_m=np.full(n, 5.0), joint_moment=np.zeros((n, 4)))


@pytest.mark.timeout(120)
def test_events_skip_what_the_file_does_not_rate(full: Machine, minimal: Machine) -> None:
    kinds = set()
    for m in (full, minimal):
        det = EventDetector(m)
        det.update(_history(m, 2000.0, 1.0))  # 2 t at 5 m; slewing at 1 rad/s
        kinds = {e.kind for e in det.all_events()}
        if m is full:
            assert {"overload", "payload_above_rating", "slew_overspeed"} <= kinds
            assert det.unchecked() == []
    assert not kinds & {"overload", "payload_above_rating", "slew_overspeed"}
    det = EventDetector(minimal)
    assert [u.split(":")[0] for u in det.unchecked()] == [
        "overload and payload above rating", "slew overspeed"]


@pytest.mark.timeout(300)
def test_import_does_not_range_check_an_unknown_range(full: Machine, minimal: Machine,
                                                      csv_file: Path, tmp_path: Path) -> None:
    lines = csv_file.read_text().splitlines()
    f = lines[30].split(",")
    f[1] = "3.0e7"  # lift_pA 300 bar: beyond the full crane's 250 bar sensor
    lines[30] = ",".join(f)
    p = tmp_path / "wide.csv"
    p.write_text("\n".join(lines) + "\n")
    assert read_file(p, full).report.rows_refused == 1
    got = read_file(p, minimal)
    assert got.report.rows_refused == 0
    assert np.nanmax(got.samples.column("lift_pA")) == pytest.approx(3.0e7)


@pytest.mark.timeout(600)
def test_replay_and_report_on_the_minimal_file(full: Machine, minimal: Machine,
                                               csv_file: Path, tmp_path: Path) -> None:
    from cranetwin.cli import app

    table = replay_table(csv_file, minimal)
    ref = replay_table(csv_file, full)
    assert list(table.columns) == list(column_units(minimal))
    # the ratings do not enter the twin: the same motion and loads
    np.testing.assert_array_equal(table["force.lift"], ref["force.lift"])
    np.testing.assert_array_equal(table["payload_kg"], ref["payload_kg"])

    out = tmp_path / "rep"
    r = CliRunner().invoke(app, ["report", "--recording", str(csv_file), "--machine",
                                 str(MINIMAL), "--format", "csv,html", "--out", str(out),
                                 "-q"])
    assert r.exit_code == 0, r.output
    assert "note: rated_load:" in r.output
    html = out.with_name("rep.html").read_text()
    assert "No rated-load chart in the machine file" in html
    import zipfile

    with zipfile.ZipFile(out.with_name("rep.zip")) as z:
        names = z.namelist()
        text = z.read(next(n for n in names if n.endswith("work_cycles.csv"))).decode()
        ev = z.read(next(n for n in names if n.endswith("events.csv"))).decode()
        duty = z.read(next(n for n in names if n.endswith("duty.csv"))).decode()
    rows = text.strip().splitlines()[1:]
    assert rows and all(",unknown," in r for r in rows), text  # the load ratio column
    assert "nan" not in text.lower()
    assert "overload" not in ev and "slew_overspeed" not in ev
    assert "Spectrum class" not in duty  # no duty class without the chart


@pytest.mark.timeout(300)
def test_simulator_says_what_it_needs(minimal: Machine) -> None:
    from cranetwin.sim import builtin_scenario, simulate

    with pytest.raises(SimulationError, match=r"joints\.0\.velocity_limit: unknown"):
        simulate(minimal, builtin_scenario("fig3", duration_s=1.0), wrenches=False)


@pytest.mark.timeout(60)
def test_wire_layout_of_unknown_ranges_has_no_range_check(minimal: Machine) -> None:
    from cranetwin.protocol.wire import Layout

    lay = Layout.from_channels(minimal.channels)
    assert all(c.min == -np.inf and c.max == np.inf for c in lay.channels)
    assert lay.layout_id == Layout.from_channels(load_machine("patu655").channels).layout_id
