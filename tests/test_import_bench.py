"""cranetwin bench import: the documented keys, measured on a tiny file."""

from __future__ import annotations

import pytest

pytest.importorskip("pyarrow")


@pytest.mark.timeout(120)
def test_bench_import_reports_the_documented_keys() -> None:
    from cranetwin.bench.importer import run

    out = run(hours=0.005, db=None)  # 1800 samples
    assert out["samples"] == 1800
    for key in ("parquet_samples_per_second", "csv_samples_per_second", "peak_rss_mib",
                "parquet_command_seconds", "parquet_command_cpu_seconds",
                "parquet_cpu_seconds", "parquet_cpu_samples_per_second", "csv_cpu_seconds",
                "csv_peak_rss_mib"):
        assert out[key] > 0, key
    try:
        import pandas  # noqa: F401
    except ImportError:
        assert out["pandas_samples_per_second"] is None and out["speedup_vs_pandas"] is None
    else:
        assert out["pandas_samples_per_second"] > 0
        assert out["speedup_vs_pandas"] == pytest.approx(
            out["parquet_samples_per_second"] / out["pandas_samples_per_second"], rel=0.05)
