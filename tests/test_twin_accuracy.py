"""Accuracy claims of the twin that a user's data can break: the payload's stated σ, the
payload per lift, and the flag on cylinder forces the pressure sensors cannot resolve.

Each claim is checked on a simulated crane with sensor error injected by more than one error
model (uniform and Gaussian, share of full range and of the recorded range)."""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np
import pytest

from cranetwin.model import Machine, load_machine
from cranetwin.twin import TwinResult, replay

LEVELS = (0.01, 0.02, 0.05)


@lru_cache(maxsize=1)
def _loading() -> tuple[Machine, Any]:
    """60 s of log-loading (two lifts of ~312 and ~279 kg), quantisation-only sensors."""
    from cranetwin.sim import SensorModel, builtin_scenario, simulate

    m = load_machine("patu655")
    return m, simulate(m, builtin_scenario("log-loading"), seed=0, sensors=SensorModel.ideal())


@lru_cache(maxsize=32)
def _replayed(level: float, seed: int, distribution: str = "uniform",
              scale: str = "full") -> tuple[TwinResult, np.ndarray]:
    """The replay at 100 Hz and the true payload at its instants."""
    from cranetwin.sim.sensor_error import inject_error

    m, rec = _loading()
    s = rec.samples if level == 0 else inject_error(rec.samples, m, level, seed,
                                                    distribution, scale)  # type: ignore[arg-type]
    res = replay(s, m, grid_hz=100.0)
    idx = np.clip(np.searchsorted(rec.truth.t_s, res.t_s - 1e-9), 0, rec.truth.t_s.shape[0] - 1)
    return res, rec.truth.payload_kg[idx]


def _steady_lift(res: TwinResult, truth: np.ndarray, away_s: float = 1.5) -> np.ndarray:
    """Instants with a payload on and no grab or release within ``away_s``."""
    steady = np.ones(res.n, dtype=bool)
    for c in np.flatnonzero(np.diff(truth) != 0):
        steady &= np.abs(res.t_s - res.t_s[c]) > away_s
    return steady & (truth > 0)


# -- payload σ -----------------------------------------------------------------------------

@pytest.mark.timeout(900)
@pytest.mark.parametrize(("distribution", "scale"), [("uniform", "full"), ("gaussian", "full"),
                                                     ("gaussian", "recorded")])
def test_payload_sigma_matches_the_actual_error(distribution: str, scale: str) -> None:
    """Over steady lifts and two noise seeds, RMS of (estimate − truth)/σ lies within
    [0.7, 1.5] at 1, 2 and 5 % sensor error: the stated σ is neither 3–9× too small (the
    previous σ: 5.8–9.3 at 1 %, 2.7–4.3 at 5 %) nor uselessly large. Not met, and so not
    asserted: uniform error of 1 % of the recorded range, RMS z 0.60 (σ 1.7× too large where
    the error is 0.46 kg; docs/ACCURACY.md)."""
    for level in LEVELS:
        z: list[np.ndarray] = []
        for seed in (0, 1):
            res, truth = _replayed(level, seed, distribution, scale)
            lift = _steady_lift(res, truth)
            assert lift.sum() > 1000
            z.append((res.payload_kg[lift] - truth[lift]) / res.payload_std_kg[lift])
        rms = float(np.sqrt(np.mean(np.concatenate(z) ** 2)))
        assert 0.7 <= rms <= 1.5, (distribution, scale, level, rms)


# -- payload per lift ------------------------------------------------------------------------

@pytest.mark.timeout(900)
def test_payload_per_lift_leaves_out_grab_and_release() -> None:
    """The mean of every instant of a lift reads 3–5 % low (the window smears grab and
    release); the per-lift mean with the transitions left out is within 2 % of the truth,
    at 0–5 % sensor error, and its σ covers the error (|z| < 3)."""
    from cranetwin.twin.lifts import result_lifts

    for level in (0.0, *LEVELS):
        res, truth = _replayed(level, 0)
        lifts = result_lifts(res, 0.01, threshold_kg=30.0)
        assert len(lifts) == 2 and all(lf.complete for lf in lifts)
        for lf in lifts:
            true = float(np.median(truth[(res.t_s >= lf.t0_s) & (res.t_s <= lf.t1_s)]))
            assert true > 250
            assert abs(lf.payload_kg / true - 1) < 0.02, (level, lf, true)
            assert abs(lf.payload_kg - true) < 3 * lf.std_kg + 0.5
            on = (res.t_s >= lf.grab_s) & (res.t_s <= lf.release_s) & (truth > 0)
            assert np.mean(res.payload_kg[on]) / true - 1 < -0.02  # what it corrects


def test_lift_detection_on_a_synthetic_ramp() -> None:
    """A 200 kg step up at 10 s and down at 30 s, smeared into 3 s ramps: one complete lift,
    its steady part starts after the ramp, and its mean is the plateau."""
    from cranetwin.twin.lifts import lift_payloads

    t = np.arange(0.0, 40.0, 0.01)
    truth = np.where((t >= 10) & (t < 30), 200.0, 0.0)
    k = 300
    m = np.convolve(np.pad(truth, k // 2, mode="edge"), np.ones(k) / k, "valid")[: t.shape[0]]
    lifts = lift_payloads(t, m, np.full_like(t, 2.0), smear_s=3.0, threshold_kg=20.0)
    assert len(lifts) == 1
    lf = lifts[0]
    assert lf.complete and 8.4 < lf.grab_s < 10 and 30 < lf.release_s < 31.6
    assert lf.t0_s >= 11.5 and lf.t1_s <= 28.5
    assert lf.payload_kg == pytest.approx(200.0, abs=1e-9)
    assert lf.std_kg == pytest.approx(2.0 / np.sqrt((lf.t1_s - lf.t0_s) / 3.0))


# -- force observability ---------------------------------------------------------------------

@pytest.mark.timeout(900)
def test_small_cylinder_force_is_flagged_not_observable() -> None:
    """The telescope (extension) cylinder sees a force range of ~6 kN behind 0–250 bar
    sensors: at 3 % uniform error of full range its per-sample force error (~990 N) is more
    than 10 % of that range and it is flagged, naming the cylinder and the numbers; the lift
    and jib cylinders (60–100 kN ranges) are not. Without error nothing is flagged (at 2 %
    the extension sits on the limit: 658 N against 6.6 kN, 9.98 %)."""
    from cranetwin.twin.observability import RESOLVABLE_SHARE, unobservable

    m, _ = _loading()
    clean, _ = _replayed(0.0, 0)
    assert all(v.observable for v in clean.force_observability(m))
    res, _ = _replayed(0.03, 0)
    verdicts = {v.cylinder: v for v in res.force_observability(m)}
    ext = verdicts["extension"]
    assert not ext.observable and ext.source == "estimated noise"
    # σ_F = σ_p·sqrt(A_A² + A_B²), σ_p = 3 % × 250 bar / √3 (uniform)
    cyl = m.cylinder("extension")
    expect = 0.03 * 25e6 / np.sqrt(3) * np.hypot(cyl.area_a_m2, cyl.area_b_m2)
    assert ext.sigma_n == pytest.approx(expect, rel=0.1)
    assert 4000 < ext.range_n < 9000 and ext.share > RESOLVABLE_SHARE
    assert verdicts["lift"].observable and verdicts["jib"].observable
    lines = unobservable(tuple(verdicts.values()))
    assert len(lines) == 1 and "'extension'" in lines[0] and f"{ext.range_n:.0f} N" in lines[0]


@pytest.mark.timeout(600)
def test_stated_sensor_accuracy_flags_a_force_on_clean_data() -> None:
    """A stated ±2 % of full range on the extension's pressure sensors flags its force even
    when the data look clean (offset and gain error do not show as noise), with the stated
    accuracy named as the source."""
    m, _ = _loading()
    chans = [c.model_copy(update={"accuracy": 0.02 * c.full_range})
             if c.source == "extension" and c.quantity.startswith("pressure") else c
             for c in m.channels]
    stated = m.model_copy(update={"channels": chans})
    clean, _ = _replayed(0.0, 0)
    verdicts = {v.cylinder: v for v in clean.force_observability(stated)}
    assert not verdicts["extension"].observable
    assert verdicts["extension"].source == "stated accuracy"
    assert verdicts["lift"].observable


@pytest.mark.timeout(600)
def test_force_observability_reaches_the_replay_table_and_the_api_object() -> None:
    """The chunked replay (what ``cranetwin replay`` writes) collects the same verdicts as
    the whole result, and the API's twin object carries them."""
    from cranetwin.importer.replay import ReplayNotes, iter_replay_table
    from cranetwin.service.views import twin_json
    from cranetwin.sim.sensor_error import inject_error

    m, rec = _loading()
    noisy = inject_error(rec.samples, m, 0.03, 0)
    notes = ReplayNotes.empty()
    for _ in iter_replay_table(noisy, m, grid_hz=100.0, notes=notes):
        pass
    res, _ = _replayed(0.03, 0)
    assert notes.force_observability(m) == res.force_observability(m)
    obj = twin_json(m, res, float(res.t_s[0]), float(res.t_s[-1]), 10.0)
    flags = {f["cylinder"]: f["observable"] for f in obj["force_observability"]}
    assert flags == {"lift": True, "jib": True, "extension": False}
