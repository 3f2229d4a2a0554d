"""What the replay keeps or shares to cut its fixed cost per call gives the values it gave
computed anew: regularisation splines the channels with the same dropouts together (bitwise
the values of one spline per channel), and the plan of a machine and channel set is kept
(the caller's options on it)."""

from __future__ import annotations

import numpy as np
import pytest

from cranetwin.model import load_machine
from cranetwin.signal import regularize
from cranetwin.signal.spline import NaturalCubicSpline
from cranetwin.twin import ReplayOptions
from cranetwin.twin.plan import ReplayPlan

pytestmark = pytest.mark.timeout(60)


def test_regularize_equals_one_spline_per_channel() -> None:
    rng = np.random.default_rng(3)
    n, k = 120, 11
    t = 1795420800.0 + np.arange(n) * 0.1
    v = rng.standard_normal((n, k)).cumsum(axis=0)
    v[rng.random((n, k)) < 0.01] = np.nan  # a few channels with a dropout each
    v[40:47, 2] = np.nan  # one gap longer than 5 periods
    v[40:47, 5] = np.nan  # the same pattern on another channel
    assert np.isnan(v).any(axis=0).sum() >= 3
    got = regularize(t, v, period=0.1)
    grid = got.t
    for j in range(k):
        ok = np.isfinite(v[:, j])
        want = NaturalCubicSpline(t[ok], v[ok, j])(grid)
        assert np.array_equal(got.values[:, j], want), j
    assert got.gap[:, 2].any() and np.array_equal(got.gap[:, 2], got.gap[:, 5])
    assert not got.gap[:, 0].any()


def test_plan_is_kept_per_machine_and_channels() -> None:
    machine = load_machine("patu655")
    chans = tuple(c.name for c in machine.channels)
    a = ReplayPlan.of(machine, chans, ReplayOptions(grid_hz=10.0))
    b = ReplayPlan.of(machine, chans, ReplayOptions(grid_hz=10.0, theta0_initial=0.3))
    assert b.opt.theta0_initial == 0.3 and a.opt.theta0_initial == 0.0
    assert b.cylinders is a.cylinders and b.kernels is a.kernels  # the constants are shared
    fresh = ReplayPlan.build(machine, chans, ReplayOptions(grid_hz=10.0))
    assert np.array_equal(fresh.cylinders.table, a.cylinders.table)
    other = ReplayPlan.of(machine, chans, ReplayOptions(grid_hz=10.0, velocity="newton"))
    # velocity enters the constants (the spline layout reads derivatives): a plan of its own
    assert not np.array_equal(other.layout[3], a.layout[3])
    assert ReplayPlan.of(machine, chans[:-1], ReplayOptions(grid_hz=10.0)).cols != a.cols
