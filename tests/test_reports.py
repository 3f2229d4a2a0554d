"""Reports: events on simulator runs with injected misuse, PDF pages and headings, HTML, CSV,
the ``cranetwin report`` command."""

from __future__ import annotations

import csv
import io
import re
import shutil
import subprocess
import zipfile
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from cranetwin.analytics import AnalyticsReport, analyse
from cranetwin.model import Machine, load_machine
from cranetwin.reports import (
    SECTIONS,
    DemoSource,
    RecordingSource,
    build_report,
    history_from_recording,
    write,
)
from cranetwin.sim import Recording, builtin_scenario, scenario_from_dict, simulate


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load_machine("patu655")


@pytest.fixture(scope="module")
def demo(machine: Machine) -> tuple[AnalyticsReport, str]:
    src = DemoSource(machine, days=2, rate_hz=20.0)
    return build_report(src), src.label


# --- simulator scenarios ----------------------------------------------------------------------

@pytest.fixture(scope="module")
def clean_run(machine: Machine) -> Recording:
    return simulate(machine, builtin_scenario("log-loading", duration_s=30.0))


def test_clean_log_loading_run_has_no_event(machine: Machine, clean_run: Recording) -> None:
    rep = analyse(machine, history_from_recording(machine, clean_run))
    assert rep.events == []
    assert len(rep.cycles) >= 1 and all(c.lift and c.swing for c in rep.cycles)
    logs = [e.mass_kg for e in builtin_scenario("log-loading", duration_s=30.0).payload
            if e.mass_kg > 0]
    assert rep.cycles[0].payload_kg == pytest.approx(logs[0], rel=1e-6)


def test_overload_lift_in_simulator_is_found(machine: Machine) -> None:
    rec = simulate(machine, builtin_scenario("log-loading", duration_s=20.0, payload_kg=700.0))
    h = history_from_recording(machine, rec)
    rep = analyse(machine, h)
    over = [e for e in rep.events if e.kind == "overload"]
    assert len(over) == 1
    e = over[0]
    grab = next(p.t_s for p in builtin_scenario("log-loading", duration_s=20.0,
                                                payload_kg=700.0).payload if p.mass_kg > 0)
    assert e.t_start == pytest.approx(rec.start_epoch_s + grab, abs=0.01)
    rated = machine.rated_load.payload_at(np.array(e.evidence["reach_m"]))
    assert e.evidence["moment_ratio"] == pytest.approx(e.evidence["payload_kg"] / rated, rel=0.05)
    assert e.evidence["moment_ratio"] > 1.0 and e.severity == "critical"


def test_hard_end_stop_hit_in_simulator_is_found(machine: Machine) -> None:
    sc = scenario_from_dict({"name": "end-stop-hit", "duration_s": 6.0,
                             "initial": {"q": [0.0, 0.6, -1.6, 0.3]},
                             "actuators": {"lift": {"voltage": [[0, 0], [0.2, 10], [6, 10]]}}})
    rec = simulate(machine, sc)
    h = history_from_recording(machine, rec)
    rep = analyse(machine, h)
    hits = [e for e in rep.events if e.kind == "end_stop_impact"]
    assert len(hits) == 1 and hits[0].component == "lift"
    assert h.rod_s is not None
    stroke = machine.cylinder("lift").stroke_m
    first_in = h.t_s[np.argmax(h.rod_s[:, 0] >= stroke - 0.005)]
    assert hits[0].t_start == pytest.approx(first_in)
    assert hits[0].value > hits[0].limit
    assert any(e.kind == "shock_load" and e.component == "lift" for e in rep.events)


def test_recording_source_equals_direct_analysis(machine: Machine, clean_run: Recording,
                                                 tmp_path: Path) -> None:
    path = clean_run.save(tmp_path / "run.npz")
    src = RecordingSource(machine, path)
    rep = build_report(src)
    direct = analyse(machine, history_from_recording(machine, clean_run))
    assert rep.n_samples == direct.n_samples == clean_run.truth.n
    assert [c.t_grab for c in rep.cycles] == [c.t_grab for c in direct.cycles]
    for a, b in zip(rep.spectra, direct.spectra, strict=True):
        assert np.array_equal(a.cycles.count, b.cycles.count)


# --- exports --------------------------------------------------------------------------------------

def test_pdf_has_a_page_per_section_with_its_heading(machine: Machine,
                                                     demo: tuple[AnalyticsReport, str],
                                                     tmp_path: Path) -> None:
    pypdf = pytest.importorskip("pypdf")
    rep, label = demo
    out = write(rep, machine, "pdf", tmp_path / "r.pdf", label)
    reader = pypdf.PdfReader(str(out))
    texts = [p.extract_text() for p in reader.pages]
    starts = [t.splitlines()[0].strip() for t in texts]
    assert [s for s in starts if s in SECTIONS] == list(SECTIONS)
    assert len(reader.pages) >= len(SECTIONS)
    assert "Σ" in "".join(texts)  # the font covers the formulas
    assert "overload" in texts[starts.index("Events")]


def test_pdf_pages_render_with_pdftoppm(machine: Machine, demo: tuple[AnalyticsReport, str],
                                        tmp_path: Path) -> None:
    if shutil.which("pdftoppm") is None:
        pytest.skip("pdftoppm (poppler-utils) is not installed")
    pypdf = pytest.importorskip("pypdf")
    rep, label = demo
    out = write(rep, machine, "pdf", tmp_path / "r.pdf", label)
    subprocess.run(["pdftoppm", "-r", "30", "-png", str(out), str(tmp_path / "pg")], check=True)
    pngs = sorted(tmp_path.glob("pg-*.png"))
    assert len(pngs) == len(pypdf.PdfReader(str(out)).pages)
    from matplotlib.image import imread

    usage = imread(str(pngs[1]))
    assert usage[..., :3].std() > 0.05  # the usage page carries a chart, not a blank page


def test_html_is_self_contained(machine: Machine, demo: tuple[AnalyticsReport, str],
                                tmp_path: Path) -> None:
    rep, label = demo
    text = write(rep, machine, "html", tmp_path / "r.html", label).read_text()
    assert re.search(r"(src|href)=['\"](https?:)?//", text) is None
    assert text.count("data:image/png;base64,") == 5
    for head in SECTIONS:
        assert f"<h1>{head}</h1>" in text


def test_csv_zip_holds_consistent_tables(machine: Machine, demo: tuple[AnalyticsReport, str],
                                         tmp_path: Path) -> None:
    rep, label = demo
    out = write(rep, machine, "csv", tmp_path / "r.zip", label)
    with zipfile.ZipFile(out) as z:
        names = set(z.namelist())
        assert names == {"summary.csv", "usage.csv", "spectra.csv", "cycles.csv", "damage.csv",
                         "duty.csv", "events.csv", "work_cycles.csv", "assumptions.csv"}
        read = {n: list(csv.DictReader(io.StringIO(z.read(n).decode()))) for n in names}
    assert len(read["events.csv"]) == len(rep.events) == 3
    assert Counter(r["kind"] for r in read["events.csv"]) == Counter(
        {"overload": 1, "end_stop_impact": 1, "slew_overspeed": 1})
    assert len(read["work_cycles.csv"]) == len(rep.cycles)
    for s in rep.spectra:
        rows = [r for r in read["cycles.csv"] if r["channel"] == s.channel]
        binned = [r for r in read["spectra.csv"] if r["channel"] == s.channel]
        total = sum(float(r["count"]) for r in rows)
        assert total == pytest.approx(s.cycles.total)
        assert sum(float(r["cycles"]) for r in binned) == pytest.approx(total, rel=1e-6)
    dirout = write(rep, machine, "csv", tmp_path / "dir", label)
    assert sorted(p.name for p in dirout.iterdir()) == sorted(names)


def test_report_command_demo_csv_and_bad_input(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from cranetwin.cli import app

    runner = CliRunner()
    res = runner.invoke(app, ["report", "--demo", "--days", "1", "--rate-hz", "10", "--format",
                              "csv", "--out", str(tmp_path / "o"), "-q"])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "o" / "events.csv").exists()
    res = runner.invoke(app, ["report", "--format", "pdf", "--out", str(tmp_path / "x.pdf")])
    assert res.exit_code != 0
    assert "--machine" in str(res.exception)


def test_storage_source_replays_through_the_twin(machine: Machine, clean_run: Recording,
                                                 tmp_path: Path) -> None:
    from dataclasses import replace

    from cranetwin.reports import StoreSource
    from cranetwin.storage import Store

    url = f"sqlite:///{tmp_path / 't.db'}"
    store = Store.open(url)
    store.add_machine("crane-1", 7, b"0123456789abcdef0123")
    store.write_blocks([replace(b, machine_id="crane-1") for b in clean_run.blocks(100)])
    t0 = clean_run.start_epoch_s
    rep = build_report(StoreSource(url, "crane-1", t0 - 1.0, t0 + clean_run.duration_s + 1.0))
    truth = analyse(machine, history_from_recording(machine, clean_run))
    assert rep.events == []
    assert len(rep.cycles) == len(truth.cycles)
    for a, b in zip(rep.cycles, truth.cycles, strict=True):
        assert a.t_grab == pytest.approx(b.t_grab, abs=1.0)
        assert a.payload_kg == pytest.approx(b.payload_kg, rel=0.2)  # the twin's estimate
    lift = next(i for i, d in enumerate(machine.fatigue) if d.load == "cylinder:lift:force")
    assert rep.life[lift].damage == pytest.approx(truth.life[lift].damage, rel=0.25)


def test_report_window_limits_the_data(machine: Machine) -> None:
    from cranetwin.errors import ReportError

    src = DemoSource(machine, days=3, rate_hz=5.0)
    t0, _ = src.crane.shift_bounds(1)
    rep = build_report(src, t0_s=t0 - 3600.0, t1_s=t0 + 86400.0 - 3600.0)
    assert len(rep.days) == 1 and rep.t_start == pytest.approx(t0)
    assert rep.n_samples == 8 * 3600 * 5
    with pytest.raises(ReportError, match="no data"):
        build_report(src, t0_s=0.0, t1_s=1.0)


def test_render_gives_downloadable_bytes(machine: Machine,
                                         demo: tuple[AnalyticsReport, str]) -> None:
    from cranetwin.reports import render

    rep, label = demo
    pdf, media, name = render(rep, machine, "pdf", label)
    assert pdf.startswith(b"%PDF") and media == "application/pdf" and name.endswith(".pdf")
    zipped, media, name = render(rep, machine, "csv", label)
    assert media == "application/zip" and zipfile.ZipFile(io.BytesIO(zipped)).testzip() is None
    html_bytes, media, _ = render(rep, machine, "html", label)
    assert html_bytes.startswith(b"<!doctype html>") and media.startswith("text/html")


@pytest.mark.postgres
def test_report_names_its_database_without_the_password(pg_url: str) -> None:
    from cranetwin.reports import StoreSource
    from cranetwin.storage import Store

    url = pg_url.replace("postgres@", "postgres:s3cret-pw@", 1)  # trust auth ignores it
    assert "s3cret-pw" in url
    Store.open(url).add_machine("crane-1", 1, b"k" * 16)
    src = StoreSource(url, "crane-1", 0.0, 60.0)
    assert "s3cret-pw" not in src.label and "***" in src.label
