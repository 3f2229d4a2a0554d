"""The Fig. 7 experiment on a short simulated run: error grows with e, the twin beats raw data."""

from __future__ import annotations

import numpy as np

from cranetwin.model import load_machine
from cranetwin.sim import SensorModel, builtin_scenario, simulate
from cranetwin.twin.experiment import METRICS, as_json, run_levels


def test_noise_experiment_on_short_fig3_run() -> None:
    m = load_machine("patu655")
    rec = simulate(m, builtin_scenario("fig3", duration_s=8.0), seed=0,
                   sensors=SensorModel.ideal(100.0), wrenches=False)
    res = run_levels(rec, m, [0.0, 0.05], seeds=2)
    clean, noisy = res
    for k in METRICS:
        assert clean.mean[k] < 0.003  # interpolation only: well under the paper's 1 %
        assert noisy.mean[k] > clean.mean[k]
        assert noisy.mean[k] < noisy.input_mean[k]  # smoothing beats the raw data
    assert noisy.mean["Xc1"] < 0.5 * noisy.input_mean["Xc1"]
    out = as_json(res)
    assert out[0]["payload_rmse_kg"] is None and np.isfinite(out[1]["mean"]["Fc1"])
