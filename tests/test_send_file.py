"""``cranetwin send --file``: a user's recording streamed live, read as ``cranetwin import``
reads it, every row stored once, in order, on the sender's clock."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from cranetwin.cli import app
from cranetwin.storage import Store

pytest.importorskip("pyarrow")

SECRET = "00112233445566778899aabbccddeeff"


def _recording(tmp_path: Path, rows: int, gap_after: int | None = None) -> Path:
    """A logger CSV of ``rows`` 100 Hz rows of every PATU 655 channel (the import bench's
    random walk), optionally with a 2 s hole after row ``gap_after``."""
    from cranetwin.bench.importer import write_files
    from cranetwin.model import load_machine

    csv_path, _ = write_files(load_machine("patu655"), rows, tmp_path)
    if gap_after is not None:
        lines = csv_path.read_text().splitlines()
        head, body = lines[0], lines[1:]
        shifted = []
        for i, line in enumerate(body):
            t, rest = line.split(",", 1)
            shifted.append(f"{float(t) + (2.0 if i > gap_after else 0.0):.2f},{rest}")
        csv_path.write_text("\n".join([head, *shifted]) + "\n")
    return csv_path


@pytest.mark.timeout(120)
def test_send_file_stores_every_row_of_the_recording_once(sqlite_url: str, tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    from conftest import running_daemon
    from cranetwin.importer import read_file
    from cranetwin.model import load_machine

    rows = 450
    path = _recording(tmp_path, rows, gap_after=200)
    store = Store.open(sqlite_url)
    store.add_machine("crane-7", 7, bytes.fromhex(SECRET))
    monkeypatch.setenv("CRANETWIN_MACHINE_KEY", SECRET)
    with running_daemon(store) as d:
        out = CliRunner().invoke(app, [
            "send", "--machine", "crane-7", "--wire-id", "7", "--journal", str(tmp_path / "j"),
            "--file", str(path), "--batch", "25", "--speed", "10", "--json",
            "--host", f"{d.address[0]}:{d.address[1]}"])
        assert out.exit_code == 0, out.output
    assert "1 time gap(s), 2 s in all, closed up" in out.output
    stats = json.loads(out.output.strip().splitlines()[-1])
    assert stats["unacked"] == 0
    got = store.read_samples("crane-7", 0.0, 4e9)
    want = read_file(path, load_machine("patu655")).samples
    assert got.t_s.size == rows  # the file once: no row lost, none sent twice, no wrap-around
    np.testing.assert_allclose(np.diff(got.t_s), 0.01, atol=1e-6)  # the gap closed up
    cols = [want.channels.index(c) for c in got.channels]
    np.testing.assert_array_equal(got.values, want.values[:, cols])


@pytest.mark.timeout(60)
def test_send_file_refuses_a_recording_that_lacks_a_channel(tmp_path: Path,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    path = _recording(tmp_path, 50)
    lines = path.read_text().splitlines()
    drop = lines[0].split(",").index("p_lift_a") if "p_lift_a" in lines[0] else 1
    path.write_text("\n".join(",".join(c for j, c in enumerate(line.split(",")) if j != drop)
                              for line in lines) + "\n")
    monkeypatch.setenv("CRANETWIN_MACHINE_KEY", SECRET)
    out = CliRunner().invoke(app, ["send", "--machine", "crane-7", "--wire-id", "7",
                                   "--journal", str(tmp_path / "j"), "--file", str(path),
                                   "--host", "127.0.0.1:9"])
    assert out.exit_code != 0
    assert "lacks required channel" in str(out.exception) + out.output
