"""A known payload as a time series: the mapping's [payload] column read with a file's (or
columns') samples; used in the twin's inverse dynamics by replay, report --recording and the
Python API (the default), or put next to the twin's estimate with the estimate's error per lift
(``compare``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from cranetwin.importer import ImportFileError, mapping_from_dict, read_columns, read_file
from cranetwin.importer.payload import lift_errors
from cranetwin.importer.replay import replay_table
from cranetwin.model import Machine, load_machine

T0 = 1_767_225_600.0
MAP = '[payload]\ncolumn = "hook_t"\nunit = "t"\n'
Logged = tuple[Path, Path, np.ndarray, np.ndarray]


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load_machine("patu655")


@pytest.fixture(scope="module")
def logged(machine: Machine, tmp_path_factory: pytest.TempPathFactory) -> Logged:
    """A 30 s log-loading recording (one 312 kg lift from 9 to 23 s) as a logger CSV with the
    known payload in tonnes; its mapping; the sample times and the true payload there."""
    from cranetwin.sim import builtin_scenario, simulate

    rec = simulate(machine, builtin_scenario("log-loading", duration_s=30.0), wrenches=False)
    s = rec.samples
    truth = np.interp(s.t_s, rec.truth.t_s, rec.truth.payload_kg)
    d = tmp_path_factory.mktemp("payload")
    f = d / "logger.csv"
    np.savetxt(f, np.column_stack([s.t_s + T0, s.values, truth / 1000.0]), delimiter=",",
               fmt=["%.6f", *["%.10g"] * (len(s.channels) + 1)],
               header=",".join(["t_s", *s.channels, "hook_t"]), comments="")
    m = d / "map.toml"
    m.write_text(MAP)
    return f, m, s.t_s + T0, truth


@pytest.mark.timeout(300)
def test_payload_column_is_read_at_the_sample_times(machine: Machine, logged: Logged) -> None:
    f, m, t, truth = logged
    got = read_file(f, machine, m)
    assert got.payload_kg is not None and got.payload_kg.shape == got.samples.t_s.shape
    np.testing.assert_allclose(got.samples.t_s, t, rtol=0, atol=1e-6)
    np.testing.assert_allclose(got.payload_kg, truth, rtol=1e-9, atol=1e-6)
    assert read_file(f, machine).payload_kg is None  # no [payload]: none


@pytest.mark.timeout(300)
def test_replay_compares_the_estimate_per_lift(machine: Machine, logged: Logged) -> None:
    f, m, _, _ = logged
    table = replay_table(f, machine, m, payload_column="compare")
    assert table.units["payload_known_kg"] == "kg" and table.units["payload_error_kg"] == "kg"
    names = list(table.columns)
    assert names.index("payload_known_kg") == names.index("payload_std_kg") + 1
    np.testing.assert_allclose(table["payload_error_kg"],
                               table["payload_kg"] - table["payload_known_kg"])
    assert table.lifts is not None and len(table.lifts) == 1
    lift = table.lifts[0]
    assert 8.9 < lift.t_start_s - T0 < 9.2 and 22.8 < lift.t_end_s - T0 < 23.1
    assert abs(lift.known_kg - 312.3) < 0.1
    assert abs(lift.error_pct) < 5.0, lift.line()
    # a wrong known payload is caught: the same estimate against twice the truth
    wrong = replay_table(f, machine, m, known_payload_kg=2 * read_file(f, machine, m).payload_kg,
                         payload_column="compare")
    assert wrong.lifts is not None and wrong.lifts[0].error_pct < -40.0


@pytest.mark.timeout(300)
def test_columns_with_a_payload_series(machine: Machine, logged: Logged) -> None:
    f, _, _, truth = logged
    data = np.genfromtxt(f, delimiter=",", names=True)
    cols = {n: data[n] for n in data.dtype.names or ()}
    cols["hook_kg"] = cols.pop("hook_t") * 1000.0
    mp = mapping_from_dict({"payload": {"column": "hook_kg"}}, machine)
    got = read_columns(cols, machine, mp)
    assert got.payload_kg is not None
    np.testing.assert_allclose(got.payload_kg, truth, rtol=1e-9, atol=1e-6)
    with pytest.raises(ImportFileError, match="no payload column 'load'"):
        read_columns(cols, machine, mapping_from_dict({"payload": {"column": "load"}}, machine))


@pytest.mark.timeout(60)
def test_bad_payload_mapping_names_its_key(machine: Machine) -> None:
    with pytest.raises(ImportFileError, match=r"payload.unit.*'bar'.*pressure"):
        mapping_from_dict({"payload": {"column": "x", "unit": "bar"}}, machine)
    with pytest.raises(ImportFileError, match=r"\[payload\]: unknown key"):
        mapping_from_dict({"payload": {"column": "x", "offset": 3}}, machine)
    with pytest.raises(ImportFileError, match="payload.column"):
        mapping_from_dict({"payload": {"unit": "kg"}}, machine)
    # the payload does not change what is stored: the same import identity
    a = mapping_from_dict({}, machine).identity()
    assert mapping_from_dict({"payload": {"column": "x"}}, machine).identity() == a


@pytest.mark.timeout(60)
def test_lifts_by_hand() -> None:
    t = np.arange(0.0, 10.0, 0.1)
    known = np.where((t >= 2.0) & (t < 6.0), 400.0, 0.0)
    known[(t >= 7.0) & (t < 8.0)] = 300.0  # 1 s: too short to be a lift
    est = known + np.where(t < 4.0, 40.0, 20.0)
    lifts = lift_errors(t, known, est)
    assert len(lifts) == 1
    assert lifts[0].t_start_s == pytest.approx(2.0) and lifts[0].t_end_s == pytest.approx(5.9)
    assert lifts[0].known_kg == 400.0 and lifts[0].error_kg == pytest.approx(30.0)


@pytest.mark.timeout(600)
def test_cli_replay_and_report_print_the_error_per_lift(machine: Machine, logged: Logged,
                                                        tmp_path: Path) -> None:
    from cranetwin.cli import app

    f, m, _, _ = logged
    r = CliRunner().invoke(app, ["replay", str(f), "--mapping", str(m), "--out",
                                 str(tmp_path / "twin.csv"), "-q", "--payload-column",
                                 "compare"])
    assert r.exit_code == 0, r.output
    assert "payload estimate vs known payload over 1 lift(s)" in r.output, r.output
    assert "known 312.3 kg" in r.output
    header = (tmp_path / "twin.csv").read_text().split("\n", 1)[0].split(",")
    assert "payload_known_kg" in header and "payload_error_kg" in header
    r = CliRunner().invoke(app, ["report", "--recording", str(f), "--mapping", str(m),
                                 "--format", "csv", "--out", str(tmp_path / "rep"), "-q",
                                 "--payload-column", "compare"])
    assert r.exit_code == 0, r.output
    assert "payload estimate vs known payload over 1 lift(s)" in r.output, r.output


@pytest.mark.timeout(300)
def test_report_source_analyses_the_known_payload(machine: Machine, logged: Logged) -> None:
    from cranetwin.reports.sources import ImportedFileSource

    f, m, t, truth = logged
    for column in ("compare", "use"):
        src = ImportedFileSource(machine, f, m, payload_column=column)  # type: ignore[arg-type]
        hist = [h for h, _ in src.chunks() if h is not None]
        th = np.concatenate([h.t_s for h in hist])
        ph = np.concatenate([h.payload_kg for h in hist])
        np.testing.assert_allclose(ph, np.interp(th, t, truth), rtol=1e-9, atol=1e-6)
        if column == "compare":  # the same comparison as the replay's, net figures too
            assert src.lifts is not None and len(src.lifts) == 1
            want = replay_table(f, machine, m, payload_column="compare").lifts
            assert want is not None and src.lifts == want
            assert np.isfinite(src.lifts[0].net_kg)
        else:  # used, not compared
            assert src.lifts is None


@pytest.mark.timeout(60)
def test_payload_logged_slower_than_the_sensors_is_held_half_its_spacing() -> None:
    from cranetwin.importer.payload import payload_at

    t = np.arange(0, 3_000_000_000, 10_000_000, dtype=np.int64)  # 100 Hz samples
    raw_t = np.array([0, 1_000_000_000, 2_000_000_000], dtype=np.int64)  # 1 Hz payload
    got = payload_at(t, raw_t, np.array([0.0, 400.0, 410.0]), 10_000_000)
    assert got[0] == 0.0 and got[100] == 400.0 and got[149] == 400.0 and got[151] == 410.0
    assert got[250] == 410.0 and np.isnan(got[251])  # beyond half the rows' 1 s spacing
    far = payload_at(t, raw_t[:1], np.array([5.0]), 10_000_000)  # one row: half a period
    assert far[0] == 5.0 and np.all(np.isnan(far[1:]))


@pytest.mark.timeout(600)
def test_cli_replay_uses_the_payload_column_in_the_dynamics(machine: Machine, logged: Logged,
                                                            tmp_path: Path) -> None:
    """By default the mapped column is the dynamics' payload where known; an empty stretch
    of it falls back to the estimate; ``--payload-column compare`` and a constant
    ``--payload`` keep the estimate (or the constant) in the dynamics."""
    from cranetwin.cli import app

    f, m, t, truth = logged
    rows = f.read_text().splitlines()
    gone = range(1 + 1200, 1 + 1700)  # samples 12 … 17 s of the lift: the column is empty
    for i in gone:
        rows[i] = rows[i].rsplit(",", 1)[0] + ","
    g = tmp_path / "logger_gap.csv"
    g.write_text("\n".join(rows) + "\n")

    def run(*extra: str) -> tuple[str, dict[str, np.ndarray]]:
        out = tmp_path / "twin.csv"
        r = CliRunner().invoke(app, ["replay", str(g), "--mapping", str(m), "--out", str(out),
                                     "-q", *extra])
        assert r.exit_code == 0, r.output
        names = out.read_text().split("\n", 1)[0].split(",")
        data = np.loadtxt(out, delimiter=",", skiprows=1)
        return r.output, {n: data[:, i] for i, n in enumerate(names)}

    said, used = run()
    assert "used in the inverse dynamics at 83.3 % of the samples" in said, said
    assert "payload_known_kg" in used and "payload_error_kg" not in used
    assert used["t_s"].shape == t.shape  # one row per sample (the CSV keeps 10 digits of t)
    known = np.ones(t.shape, dtype=bool)
    known[[i - 1 for i in gone]] = False
    np.testing.assert_allclose(used["payload_kg"][known], truth[known], rtol=1e-9, atol=1e-6)
    assert np.all(used["payload_std_kg"][known] == 0.0)
    assert np.all(np.isnan(used["payload_known_kg"][~known]))
    _, compared = run("--payload-column", "compare")
    # the empty stretch: the estimate, as when only compared
    np.testing.assert_allclose(used["payload_kg"][~known], compared["payload_kg"][~known],
                               rtol=0, atol=1e-9)
    assert np.all(used["payload_std_kg"][~known] > 0.0)
    # elsewhere the dynamics differ: the known payload against the estimate that lags a grab
    lift = "torque_id.theta1"
    assert np.abs(used[lift] - compared[lift])[known].max() > 1e3
    said, const = run("--payload", "100")
    np.testing.assert_allclose(const["payload_kg"], 100.0)
    assert "payload_error_kg" in const and "payload estimate vs known payload" in said
    r = CliRunner().invoke(app, ["replay", str(g), "--mapping", str(m), "--out",
                                 str(tmp_path / "x.csv"), "-q", "--payload-column", "fit"])
    assert r.exit_code != 0 and "expected use or compare" in str(r.exception or r.output)
    r = CliRunner().invoke(app, ["report", "--recording", str(g), "--mapping", str(m),
                                 "--format", "csv", "--out", str(tmp_path / "rep"), "-q"])
    assert r.exit_code == 0, r.output
    assert "used in the inverse dynamics at 83.3 % of the samples" in r.output, r.output
    assert "payload estimate vs known payload" not in r.output
