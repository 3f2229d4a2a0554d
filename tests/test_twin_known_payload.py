"""A known payload series in the replay's inverse dynamics (cranetwin.twin.known_payload):
used where known, the estimate where NaN, streaming = batch across seams, and the loads closer
to the simulator's truth than with the estimate."""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np
import pytest

from cranetwin.errors import TwinError
from cranetwin.model import Machine, load_machine
from cranetwin.samples import SampleArrays
from cranetwin.twin import ReplayOptions, TwinResult, TwinStream, replay
from cranetwin.twin.known_payload import at_instants

NAN_STRETCH = slice(1200, 1700)  # samples 12 … 17 s (inside the first lift) not known


@lru_cache(maxsize=1)
def _loading() -> tuple[Machine, Any, np.ndarray]:
    """30 s of log-loading (one 312 kg lift, 9 … 23 s), quantisation-only sensors, and the
    logger's known payload at the sample times (the truth at that instant: a step at a grab)."""
    from cranetwin.sim import SensorModel, builtin_scenario, simulate

    m = load_machine("patu655")
    rec = simulate(m, builtin_scenario("log-loading", duration_s=30.0), seed=0,
                   sensors=SensorModel.ideal(), wrenches=True)
    tr = rec.truth
    k = np.clip(np.searchsorted(tr.t_s, rec.samples.t_s + 1e-9, side="right") - 1, 0, tr.n - 1)
    return m, rec, tr.payload_kg[k]


def _truth_at(res: TwinResult) -> np.ndarray:
    _, rec, _ = _loading()
    gi = np.clip(np.searchsorted(rec.truth.t_s, res.t_s - 1e-9), 0, rec.truth.n - 1)
    assert np.abs(rec.truth.t_s[gi] - res.t_s).max() < 1e-6
    return gi


@pytest.mark.timeout(60)
def test_at_instants_keeps_steps_and_does_not_bridge_long_gaps() -> None:
    t = np.array([0.0, 0.01, 0.02, 0.03, 0.5, 0.51])
    k = np.array([0.0, 0.0, 300.0, np.nan, 300.0, 310.0])
    grid = np.array([-0.01, 0.0, 0.015, 0.02, 0.025, 0.2, 0.5, 0.505, 0.51, 0.52])
    got = at_instants(grid, t, k, max_gap_s=0.05)
    want = [np.nan, 0.0, 150.0, 300.0, np.nan, np.nan, 300.0, 305.0, 310.0, np.nan]
    np.testing.assert_allclose(got, want, rtol=1e-12)
    # a step across a long gap stays NaN (the estimate fills it), not a ramp over it
    assert np.isnan(at_instants(np.array([0.2]), np.array([0.0, 0.5]),
                                np.array([0.0, 300.0]), 0.05)[0])


@pytest.mark.timeout(600)
def test_known_series_is_used_where_known_and_the_estimate_where_nan() -> None:
    m, rec, known = _loading()
    est = replay(rec.samples, m, grid_hz=100.0)
    part = known.copy()
    part[NAN_STRETCH] = np.nan
    got = replay(rec.samples, m, grid_hz=100.0, payload=part)
    assert got.n == est.n == known.shape[0]  # grid = the samples
    ok = np.isfinite(part)
    np.testing.assert_array_equal(got.payload_kg[ok], part[ok])
    assert np.all(got.payload_std_kg[ok] == 0.0)
    # NaN: the estimate, as without a series; and so the loads there
    np.testing.assert_array_equal(got.payload_kg[~ok], est.payload_kg[~ok])
    np.testing.assert_array_equal(got.payload_std_kg[~ok], est.payload_std_kg[~ok])
    np.testing.assert_allclose(got.id_torque[~ok], est.id_torque[~ok], rtol=0, atol=1e-9)
    assert np.abs(est.payload_kg[ok] - part[ok]).max() > 50.0  # the estimate lags the steps
    # a series known everywhere is the same replay as that constant
    const = replay(rec.samples, m, grid_hz=100.0, payload=np.full(known.shape, 312.0))
    ref = replay(rec.samples, m, grid_hz=100.0, payload=312.0)
    for name in ("payload_kg", "payload_std_kg", "id_torque", "joint_wrench", "cyl_force"):
        np.testing.assert_array_equal(getattr(const, name), getattr(ref, name), err_msg=name)
    # an all-NaN series is the estimate
    none = replay(rec.samples, m, grid_hz=100.0, payload=np.full(known.shape, np.nan))
    np.testing.assert_array_equal(none.payload_kg, est.payload_kg)
    np.testing.assert_array_equal(none.id_torque, est.id_torque)


@pytest.mark.timeout(600)
@pytest.mark.parametrize("e", [0.0, 0.02])
def test_known_series_brings_the_joint_loads_closer_to_the_truth(e: float) -> None:
    """log-loading 30 s, 1 kHz grid: the inverse-dynamics loads of the cylinder joints with
    the known series against those of the true motion and payload. Measured NRMSE (60 s run,
    docs/ACCURACY.md): estimate 4.1 / 3.2 / 4.8 %, known 1.8 / 1.6 / 1.6 % at e = 0; at 2 %
    6.0 / 5.1 / 6.1 % and 4.0 / 3.9 / 2.9 %. The payload is the series at the samples."""
    from cranetwin.physics import joint_torques
    from cranetwin.sim.sensor_error import inject_error

    m, rec, known = _loading()
    s = rec.samples if e == 0 else inject_error(rec.samples, m, e, 0, "uniform", "full")
    cj = [m.joint_index(c.joint) for c in m.cylinders]
    tr = rec.truth
    err, f_err = {}, {}
    for label, pay in (("estimate", None), ("known", known)):
        res = replay(s, m, 1000.0, payload=pay)
        gi = _truth_at(res)
        want = joint_torques(m, tr.q[gi], tr.qd[gi], tr.qdd[gi], tr.payload_kg[gi])[:, cj]
        got = res.id_torque[:, cj]
        err[label] = np.sqrt(np.mean((got - want) ** 2, axis=0)) / np.ptp(want, axis=0)
        f_err[label] = np.sqrt(np.mean((res.cyl_force - tr.cyl_force[gi]) ** 2, axis=0))
        if pay is not None:  # the series at the samples (every 10th grid row)
            np.testing.assert_array_equal(res.payload_kg[::10], known[: (res.n - 1) // 10 + 1])
    assert np.all(err["known"] < 0.8 * err["estimate"]), err
    # the cylinder forces at least as good (Eq. 1–2 of the pressures; a model-based force
    # uses the payload)
    assert np.all(f_err["known"] <= 1.001 * f_err["estimate"]), f_err


@pytest.mark.timeout(600)
def test_streaming_with_a_known_series_equals_batch_across_seams() -> None:
    m, rec, known = _loading()
    from cranetwin.sim.sensor_error import inject_error

    s = inject_error(rec.samples, m, 0.02, 1, "uniform", "full")
    part = known.copy()
    part[NAN_STRETCH] = np.nan
    first = replay(s, m, grid_hz=100.0)
    opt = ReplayOptions(smoothing=tuple(first.smoothing.values()), sample_period_s=0.01,
                        chunk_samples=700, grid_hz=200.0)
    n = s.t_s.shape[0]
    rng = np.random.default_rng(3)
    cuts = [0]
    while cuts[-1] < n:
        cuts.append(min(n, cuts[-1] + int(rng.integers(1, 400))))
    i0 = next(c for c in cuts if c >= 150)  # the series' first push: NaN before it
    part[:i0] = np.nan
    batch = replay(s, m, grid_hz=200.0, payload=part, options=opt)
    st = TwinStream(m, s.channels, opt)
    parts: list[TwinResult] = []
    for i, j in zip(cuts[:-1], cuts[1:], strict=True):
        out = st.push(SampleArrays(s.machine_id, s.t_s[i:j], s.channels, s.values[i:j]),
                      None if i < i0 else part[i:j])
        if out is not None:
            parts.append(out)
    last = st.flush()
    if last is not None:
        parts.append(last)
    streamed = TwinResult.concat(parts)
    assert streamed.n == batch.n
    np.testing.assert_array_equal(streamed.t_s, batch.t_s)
    assert np.isfinite(part).sum() > 1000 and np.all(streamed.payload_std_kg[::2][
        np.isfinite(part[: (streamed.n - 1) // 2 + 1])] == 0.0)
    for name in ("q", "qd", "qdd", "cyl_force", "actuator_torque", "id_torque", "joint_wrench",
                 "payload_kg", "payload_std_kg"):
        a, b = getattr(streamed, name), getattr(batch, name)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-8 * np.abs(b).max(), err_msg=name)
    with pytest.raises(TwinError, match="give one"):
        TwinStream(m, s.channels, opt, 300.0).push(s.take(slice(0, 10)), part[:10])
    with pytest.raises(TwinError, match="shape"):
        replay(s, m, grid_hz=100.0, payload=part[:-1])


@pytest.mark.timeout(60)
def test_at_instants_takes_a_sample_missed_by_rounding() -> None:
    """Regular instants origin + k·period miss epoch sample times by rounding: the sample's
    own value, even next to an unknown neighbour."""
    t = 1.767e9 + np.arange(5) * 0.01
    k = np.array([np.nan, 300.0, np.nan, 310.0, 320.0])
    grid = 1.767e9 + np.array([0.01 + 2e-7, 0.03 - 2e-7, 0.035])
    # (the midpoint: epoch seconds carry 0.24 µs of rounding, 1e-6 of the step's ramp)
    np.testing.assert_allclose(at_instants(grid, t, k, 0.05), [300.0, 310.0, 315.0],
                               rtol=1e-6)
