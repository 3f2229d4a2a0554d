"""``cranetwin demo`` and ``cranetwin bench dynamics`` run end to end (no timing asserted)."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from cranetwin.cli import app


def test_demo_prints_positions_and_forces() -> None:
    res = CliRunner().invoke(app, ["demo", "--duration", "2", "--step", "0.5"])
    assert res.exit_code == 0, res.output
    assert "positions" in res.output and "forces, payload 300 kg" in res.output
    assert res.output.count("│ 2.00 │") == 2          # last row of both tables


def test_bench_dynamics_json_small() -> None:
    res = CliRunner().invoke(app, ["bench", "dynamics", "--json", "--samples", "20000",
                                   "--chunk", "4096", "--reps", "1"])
    assert res.exit_code == 0, res.output
    r = json.loads(res.output)
    assert r["samples"] == 20000 and r["seconds"] > 0
    for key in ("baseline_seconds", "speedup", "compile_seconds", "peak_rss_mib",
                "generic_ratio", "tau_ns_per_sample", "pinocchio_batch",
                "pinocchio_batch_ratio"):
        assert key in r
    # the generic kernel is timed against the generated one in the same run
    assert r["generic_ratio"] == pytest.approx(r["generic_kernel_ns_per_sample"]
                                               / r["tau_wrench_ns_per_sample"])
    if r["pinocchio_batch_ns_per_sample"] is not None:
        assert r["pinocchio_batch_ratio"] == pytest.approx(r["pinocchio_batch_ns_per_sample"]
                                                           / r["tau_ns_per_sample"])
    if r["max_rel_error"] is not None:
        assert r["max_rel_error"] <= 1e-9
