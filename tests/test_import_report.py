"""cranetwin report --recording on a user's file: its samples are replayed by the twin (not a
truth file); the same analysis as of the same samples imported into storage."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from cranetwin.model import load_machine

pytestmark = pytest.mark.timeout(300)
T0 = 1_767_225_600.0


def test_report_on_a_users_file_analyses_its_samples(tmp_path: Path) -> None:
    from cranetwin.cli import app
    from cranetwin.sim import builtin_scenario, simulate
    from cranetwin.storage import Store

    machine = load_machine("patu655")
    s = simulate(machine, builtin_scenario("log-loading", duration_s=30.0),
                 wrenches=False).samples
    cols = {"time": s.t_s + T0}
    for name in s.channels:
        v = s.column(name)
        cols[name] = v / 1e5 if "_p" in name else v  # pressures in bar
    f = tmp_path / "logger.csv"
    np.savetxt(f, np.column_stack(list(cols.values())), delimiter=",",
               fmt=["%.3f", *["%.10g"] * len(s.channels)], header=",".join(cols), comments="")
    m = tmp_path / "map.toml"
    m.write_text("".join(f'[channels.{n}]\nunit = "bar"\n' for n in s.channels if "_p" in n))

    r = CliRunner().invoke(app, ["report", "--recording", str(f), "--mapping", str(m),
                                 "--format", "csv", "--out", str(tmp_path / "rep"), "-q"])
    assert r.exit_code == 0, r.output
    got = re.search(r"(\d+) work cycles, (\d+) events, ([\d,]+) samples", r.output)
    assert got, r.output
    n_file = int(got.group(3).replace(",", ""))
    assert n_file >= 0.9 * s.t_s.size  # the replayed samples, not "1 sample"
    assert "refused" not in r.output

    url = f"sqlite:///{tmp_path / 'db.sqlite'}"
    with Store.open(url) as store:
        store.add_machine("m1", 1, b"k" * 32)
    r1 = CliRunner().invoke(app, ["import", str(f), "--machine", "m1", "--mapping", str(m),
                                  "--db", url, "-q"])
    assert r1.exit_code == 0, r1.output
    r2 = CliRunner().invoke(app, ["report", "--machine", "m1", "--from", str(T0), "--to",
                                  str(T0 + 60), "--db", url, "--format", "csv", "--out",
                                  str(tmp_path / "rep2"), "-q"])
    assert r2.exit_code == 0, r2.output
    got2 = re.search(r"(\d+) work cycles, (\d+) events, ([\d,]+) samples", r2.output)
    assert got2 and got2.groups() == got.groups(), (r.output, r2.output)
