"""The model-consistency check (:mod:`cranetwin.twin.consistency`) on the independent crane.

The simulations come from ``CRANETWIN_CACHE_DIR``/indep (``tests/indep_check.py``); a cold
cache costs 35 CPU s per run. The rule's limits were chosen on the noise family and the
independent crane with and without model errors (docs/ACCURACY.md, "Model consistency").
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import indep_check
from cranetwin.model import load_machine
from cranetwin.testing.indep_crane import PATU655
from cranetwin.twin.consistency import ModelConsistency, ResidualStats, inconsistent


def _verdicts(tmp: Path, variant: str | None = None, mapping_error: str | None = None,
              level: float = 0.0) -> dict[str, ModelConsistency]:
    from cranetwin.importer import read_file
    from cranetwin.importer.replay import ReplayNotes, iter_replay_table
    from cranetwin.sim.sensor_error import inject_error

    m = load_machine("patu655")
    p = PATU655 if variant is None else indep_check.VARIANTS[variant](PATU655)
    run = indep_check.simulated("valve-steps", p)
    csv, toml = tmp / "valve-steps.csv", tmp / "map.toml"
    indep_check.write_logger_csv(run, csv)
    toml.write_text(indep_check.mapping_toml(error=mapping_error))
    samples = read_file(csv, m, toml).samples
    if level > 0:
        samples = inject_error(samples, m, level, 0, "uniform", "full")
    notes = ReplayNotes.empty()
    for _ in iter_replay_table(samples, m, notes=notes):
        pass
    return {v.cylinder: v for v in notes.model_consistency(m)}


@pytest.mark.timeout(180)  # a cold cache simulates the crane first (35 s quiet)
@pytest.mark.parametrize("level", [0.0, 0.02])
def test_a_crane_that_matches_its_machine_file_is_consistent(tmp_path: Path,
                                                               level: float) -> None:
    got = _verdicts(tmp_path, level=level)
    assert set(got) == {"lift", "jib", "extension"}
    assert all(v.consistent for v in got.values()), [v.message() for v in got.values()]
    assert not inconsistent(tuple(got.values()))


@pytest.mark.timeout(180)  # a cold cache simulates the crane first (35 s quiet)
def test_swapped_chambers_are_inconsistent_and_named(tmp_path: Path) -> None:
    got = _verdicts(tmp_path, mapping_error="ext-pA-pB-swapped")
    ext = got["extension"]
    assert not ext.consistent
    assert ext.share > 1.0  # the residual exceeds the force the motion needs
    assert "swapped" in ext.hint, ext.message()
    assert got["lift"].consistent and got["jib"].consistent


@pytest.mark.timeout(180)  # a cold cache simulates the crane first (35 s quiet)
def test_a_telescope_bore_unlike_the_machine_file_is_inconsistent(tmp_path: Path) -> None:
    got = _verdicts(tmp_path, variant="telescope-63mm")
    ext = got["extension"]
    assert not ext.consistent, ext.message()
    assert "swapped" not in ext.hint, ext.message()
    # r = (1 − A_true/A_file)·A_A·p_A − …: 63/36 mm against 50/32 mm
    assert ext.c_a == pytest.approx(1 - (0.063**2) / (0.050**2), abs=0.15)
    assert got["lift"].consistent and got["jib"].consistent


@pytest.mark.timeout(180)  # a cold cache simulates the crane first (35 s quiet)
def test_the_replay_command_warns_of_swapped_chambers(tmp_path: Path) -> None:
    from cranetwin.cli import app

    run = indep_check.simulated("valve-steps")
    indep_check.write_logger_csv(run, tmp_path / "rec.csv")
    (tmp_path / "bad.toml").write_text(indep_check.mapping_toml(error="ext-pA-pB-swapped"))
    bad = CliRunner().invoke(app, ["replay", str(tmp_path / "rec.csv"), "--mapping",
                                   str(tmp_path / "bad.toml"), "--out",
                                   str(tmp_path / "o.csv"), "-q"])
    assert bad.exit_code == 0, bad.output
    lines = [x for x in bad.stderr.splitlines() if "INCONSISTENT" in x]
    assert len(lines) == 1 and "'extension'" in lines[0] and "swapped" in lines[0], bad.stderr


@pytest.mark.timeout(180)  # a cold cache simulates the crane first (35 s quiet)
def test_the_result_and_the_api_object_carry_the_verdicts(tmp_path: Path) -> None:
    """The whole result's verdicts (a correct mapping) reach the API's twin object."""
    from cranetwin.importer import read_file
    from cranetwin.service.views import twin_json
    from cranetwin.twin.replay import replay

    m = load_machine("patu655")
    run = indep_check.simulated("valve-steps")
    indep_check.write_logger_csv(run, tmp_path / "rec.csv")
    (tmp_path / "ok.toml").write_text(indep_check.mapping_toml())
    res = replay(read_file(tmp_path / "rec.csv", m, tmp_path / "ok.toml").samples, m,
                 grid_hz=100.0)
    verdicts = res.model_consistency(m)
    assert [v.cylinder for v in verdicts] == ["lift", "jib", "extension"]
    assert all(v.consistent for v in verdicts), [v.message() for v in verdicts]
    obj = twin_json(m, res, float(res.t_s[0]), float(res.t_s[-1]), 10.0)
    assert obj["model_consistency"] == [v.as_json() for v in verdicts]
    assert {c["consistent"] for c in obj["model_consistency"]} == {True}


@pytest.mark.timeout(10)
def test_chunks_collect_the_same_sums_as_the_whole_window() -> None:
    """Residual sums and the pressure fit do not depend on how the window is cut (block
    means aside: blocks do not cross chunks)."""
    m = load_machine("patu655")
    rng = np.random.default_rng(0)
    n = 1000
    t = np.arange(n) * 0.01
    q = np.tile([0.0, 0.5, -0.8, 0.2], (n, 1))
    pa, pb = rng.uniform(5e6, 1e7, (n, 3)), rng.uniform(1e6, 2e6, (n, 3))
    res, idt = rng.normal(0, 100, (n, 4)), rng.normal(0, 1e3, (n, 4))
    gap = np.zeros(n, dtype=bool)
    whole, parts = ResidualStats(), ResidualStats()
    whole.add(m, t, q, res, idt, pa, pb, gap)
    for s in (slice(0, 400), slice(400, 1000)):
        parts.add(m, t[s], q[s], res[s], idt[s], pa[s], pb[s], gap[s])
    np.testing.assert_allclose(parts.raw_sq, whole.raw_sq, rtol=1e-12)
    np.testing.assert_allclose(parts.xtx, whole.xtx, rtol=1e-12)
    np.testing.assert_allclose(parts.xty, whole.xty, rtol=1e-12)
    assert np.array_equal(parts.samples, whole.samples)
