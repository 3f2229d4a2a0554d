"""``cranetwin report``: one analysis writes several formats; formats and output paths are
checked before the analysis starts."""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

pytestmark = pytest.mark.timeout(300)

DEMO = ["report", "--demo", "--days", "1", "--rate-hz", "10", "-q"]


@pytest.fixture
def analyses(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Counts the analyses the command runs (``cranetwin.reports.build_report`` calls)."""
    import cranetwin.reports as reports

    calls: list[int] = []
    real = reports.build_report

    def counted(*a: Any, **kw: Any) -> Any:
        calls.append(1)
        return real(*a, **kw)

    monkeypatch.setattr(reports, "build_report", counted)
    return calls


def test_one_analysis_writes_every_format(tmp_path: Path, analyses: list[int]) -> None:
    pytest.importorskip("reportlab")
    pytest.importorskip("matplotlib")
    from cranetwin.cli import app

    res = CliRunner().invoke(app, [*DEMO, "--format", "csv,pdf,html",
                                   "--out", str(tmp_path / "rep.pdf")])
    assert res.exit_code == 0, res.output
    assert analyses == [1]
    assert (tmp_path / "rep.pdf").read_bytes().startswith(b"%PDF")
    assert "<html" in (tmp_path / "rep.html").read_text(encoding="utf-8")
    with zipfile.ZipFile(tmp_path / "rep.zip") as z:
        assert "events.csv" in z.namelist()


@pytest.mark.parametrize(("fmt", "out"), [
    ("csv,docx", "rep"),          # unknown format
    ("pdf,pdf", "rep"),           # twice
    ("", "rep"),                  # none
    ("pdf", "missing/rep.pdf"),   # no such directory
    ("html", "."),                # a directory where a file is needed
    ("csv", "file.txt"),          # a file where the CSV directory goes
])
def test_bad_format_or_output_fails_before_the_analysis(tmp_path: Path, analyses: list[int],
                                                        fmt: str, out: str) -> None:
    from cranetwin.cli import app

    (tmp_path / "file.txt").write_text("x")
    res = CliRunner().invoke(app, [*DEMO, "--format", fmt, "--out", str(tmp_path / out)])
    assert res.exit_code != 0
    assert analyses == []
