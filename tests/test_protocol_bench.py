"""``cranetwin bench protocol`` on synthetic data: its JSON is complete and typed, its baseline
is measured in the same run on the same samples, and every ratio follows from the figures it
reports. Timings are never asserted: speed targets are met in the benchmark itself."""

from __future__ import annotations

import json
import math
from typing import Any

import pytest
from typer.testing import CliRunner

from cranetwin.cli import app
from cranetwin.protocol import IP_UDP_OVERHEAD_V4, TAG_BYTES

pytestmark = pytest.mark.timeout(300)

SECONDS, BATCH, CHANNELS = 5, 50, 11

KEYS: dict[str, type | tuple[type, ...]] = {
    "source": str, "samples": int, "channels": int, "rate_hz": float, "batch_samples": int,
    "datagrams": int, "bytes_per_sample": float, "ip_udp_bytes_per_sample": float,
    "max_datagram_bytes": int, "lossless": bool, "target_bytes_per_sample": float,
    "paper_bytes_per_sample": float, "baseline": str, "baseline_bytes_per_sample": float,
    "size_ratio": float, "paper_ratio": float, "bandwidth_kbit_s_per_machine": float,
    "encode_samples_per_second": int, "decode_samples_per_second": int,
    "receive_samples_per_second": int, "baseline_decode_samples_per_second": int,
    "decode_slowdown": float,
}


def _no_nan(token: str) -> Any:
    raise AssertionError(f"{token} in the JSON output (not valid JSON)")


@pytest.fixture(scope="module")
def out() -> dict[str, Any]:
    r = CliRunner().invoke(app, ["bench", "protocol", "--json", "--synthetic", "--seconds",
                                 str(SECONDS), "--batch", str(BATCH), "--reps", "1"])
    assert r.exit_code == 0, r.output
    figures = json.loads(r.output, parse_constant=_no_nan)
    assert isinstance(figures, dict)
    return figures


def test_bench_json_has_every_figure_with_its_type(out: dict[str, Any]) -> None:
    assert set(out) == set(KEYS)
    for key, kind in KEYS.items():
        value = out[key]
        ok = isinstance(value, kind) and (kind is bool or not isinstance(value, bool))
        assert ok, (key, value)


def test_bench_encodes_what_was_asked_losslessly(out: dict[str, Any]) -> None:
    assert out["source"] == "synthetic" and out["rate_hz"] == 100.0
    assert out["samples"] == SECONDS * 100 and out["channels"] == CHANNELS
    assert out["batch_samples"] == BATCH
    assert out["datagrams"] >= math.ceil(out["samples"] / BATCH)  # split only when too large
    assert out["lossless"] is True
    assert out["bytes_per_sample"] <= out["target_bytes_per_sample"]
    assert TAG_BYTES < out["max_datagram_bytes"] <= 1200
    # every datagram carries at least its header and tag; none exceeds the largest
    per_dg = out["bytes_per_sample"] * out["samples"] / out["datagrams"]
    assert TAG_BYTES < per_dg <= out["max_datagram_bytes"] + 1e-6


def test_bench_baseline_is_the_same_samples_as_float32(out: dict[str, Any]) -> None:
    n = out["samples"]
    base_dgs = math.ceil(n / BATCH)
    # bytes beyond 4 per value are the baseline's fixed per-datagram overhead (header + tag)
    overhead = (out["baseline_bytes_per_sample"] - 4 * CHANNELS) * n / base_dgs
    assert abs(overhead - round(overhead)) < 0.5 * 10.0 ** -3 * n / base_dgs + 1e-9
    assert TAG_BYTES < round(overhead) < 200
    assert out["baseline_bytes_per_sample"] > out["bytes_per_sample"]


def test_bench_ratios_follow_from_the_reported_figures(out: dict[str, Any]) -> None:
    bps = out["bytes_per_sample"]
    # figures are rounded: bytes to 0.001, ratios to 0.01
    assert math.isclose(out["size_ratio"], out["baseline_bytes_per_sample"] / bps, rel_tol=1e-3,
                        abs_tol=0.006)
    assert math.isclose(out["paper_ratio"], out["paper_bytes_per_sample"] / bps, rel_tol=1e-3,
                        abs_tol=0.006)
    assert math.isclose(out["ip_udp_bytes_per_sample"],
                        IP_UDP_OVERHEAD_V4 * out["datagrams"] / out["samples"], abs_tol=6e-4)
    kbit = (bps + IP_UDP_OVERHEAD_V4 * out["datagrams"] / out["samples"]) * 8 * 100 / 1e3
    assert math.isclose(out["bandwidth_kbit_s_per_machine"], kbit, rel_tol=1e-3, abs_tol=0.006)
    # decode_slowdown = our decode time / baseline decode time = baseline rate / our rate
    assert math.isclose(out["decode_slowdown"], out["baseline_decode_samples_per_second"]
                        / out["decode_samples_per_second"], rel_tol=0.01, abs_tol=0.006)
    for k in ("encode_samples_per_second", "decode_samples_per_second",
              "receive_samples_per_second", "baseline_decode_samples_per_second"):
        assert out[k] > 0
