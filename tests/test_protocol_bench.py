"""``cranetwin bench protocol`` runs and reports consistent figures (no timing asserted)."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from cranetwin.cli import app


def test_bench_protocol_json_on_synthetic_data() -> None:
    r = CliRunner().invoke(app, ["bench", "protocol", "--json", "--synthetic", "--seconds", "5",
                                 "--reps", "1"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.output)
    assert out["samples"] == 500 and out["channels"] == 11 and out["lossless"] is True
    assert out["bytes_per_sample"] <= out["target_bytes_per_sample"]
    assert out["max_datagram_bytes"] <= 1200
    assert out["size_ratio"] > 1 and out["baseline_bytes_per_sample"] > out["bytes_per_sample"]
    for k in ("encode_samples_per_second", "decode_samples_per_second",
              "receive_samples_per_second", "baseline_decode_samples_per_second"):
        assert out[k] > 0
