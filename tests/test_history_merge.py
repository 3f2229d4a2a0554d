"""Analytics as stored, mergeable state: parts of any split of a history fold into exactly the
report of the whole. Rainflow residues are re-counted with the next part's, runs of
events and work cycles join across parts, look-back detectors use the previous part's tail."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cranetwin.analytics import (
    AnalyticsPart,
    AnalyticsReport,
    AnalyticsState,
    LoadHistory,
    RainflowCounter,
    analyse,
    rainflow,
)
from cranetwin.model import Machine, load_machine
from cranetwin.testing.histories import Misuse, SyntheticCrane


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load_machine("patu655")


@pytest.fixture(scope="module")
def history(machine: Machine) -> LoadHistory:
    """Two 1-h shifts at 20 Hz with an overload, an end-stop hit and a slewing overspeed."""
    sc = SyntheticCrane(machine, seed=6, days=2, shift_h=1.0,
                        misuse=Misuse(overload=(3,), end_stop=(30,), overspeed=(83,)))
    t = np.concatenate([sc.shift_bounds(d)[0] + np.arange(72_000) / 20.0 for d in range(2)])
    return sc.history(t)


@pytest.fixture(scope="module")
def direct(machine: Machine, history: LoadHistory) -> AnalyticsReport:
    return analyse(machine, history)


def _assert_same(a: AnalyticsReport, b: AnalyticsReport) -> None:
    assert (a.t_start, a.t_end, a.n_samples) == (b.t_start, b.t_end, b.n_samples)
    for sa, sb in zip(a.spectra, b.spectra, strict=True):
        assert np.array_equal(sa.cycles.lower, sb.cycles.lower), sa.channel
        assert np.array_equal(sa.cycles.upper, sb.cycles.upper), sa.channel
        assert np.array_equal(sa.cycles.count, sb.cycles.count), sa.channel
    assert [e.damage for e in a.life] == [e.damage for e in b.life]
    assert [(e.kind, e.t_start, e.t_end, e.severity, e.component, e.value) for e in a.events] \
        == [(e.kind, e.t_start, e.t_end, e.severity, e.component, e.value) for e in b.events]
    assert [(c.t_grab, c.t_release, c.lift, c.swing, c.reach_max_m) for c in a.cycles] == \
        [(c.t_grab, c.t_release, c.lift, c.swing, c.reach_max_m) for c in b.cycles]
    # means and time sums are added in another order: equal to rounding
    assert [x for c in b.cycles for x in (c.payload_kg, c.load_ratio)] == pytest.approx(
        [x for c in a.cycles for x in (c.payload_kg, c.load_ratio)], rel=1e-12)
    assert b.recorded_s == pytest.approx(a.recorded_s, rel=1e-12)
    assert b.idle_s == pytest.approx(a.idle_s, rel=1e-12)
    assert a.days.keys() == b.days.keys()
    for k, v in a.days.items():
        assert (b.days[k].recorded_s, b.days[k].working_s, b.days[k].cycles) == \
            pytest.approx((v.recorded_s, v.working_s, v.cycles), rel=1e-12)
    assert a.classification == b.classification or (
        a.classification is not None and b.classification is not None
        and a.classification.cycles == b.classification.cycles
        and a.classification.kp == pytest.approx(b.classification.kp, rel=1e-12))


@pytest.mark.timeout(120)
@settings(max_examples=25, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_parts_of_random_splits_fold_into_the_direct_analysis(
        machine: Machine, history: LoadHistory, direct: AnalyticsReport,
        data: st.DataObject) -> None:
    n = history.n
    k = data.draw(st.integers(1, 40), label="cuts")
    cuts = sorted(set(data.draw(st.lists(st.integers(1, n - 1), min_size=k, max_size=k),
                                label="at")))
    # short parts too: a few cuts one or two samples apart (shorter than the look-back)
    extra = data.draw(st.lists(st.integers(1, n - 3), max_size=3), label="short")
    cuts = sorted(set(cuts) | {c for x in extra for c in (x, x + 1, x + 2)})
    # and cuts within the look-back of every event and next to grabs and releases
    marks = [e.t_start for e in direct.events] + [e.t_end for e in direct.events] + \
        [c.t_grab for c in direct.cycles[:5]] + [c.t_release for c in direct.cycles[:5]]
    offs = data.draw(st.lists(st.integers(-25, 25), min_size=len(marks), max_size=len(marks)),
                     label="near")
    idx = np.searchsorted(history.t_s, marks)
    cuts = sorted(set(cuts) | {int(i + o) for i, o in zip(idx, offs, strict=True)
                               if 0 < i + o < n})
    bounds = [0, *cuts, n]
    proto = AnalyticsState(machine)
    parts = [proto.part(history.slice(a, b)) for a, b in zip(bounds[:-1], bounds[1:],
                                                              strict=True)]
    st_ = AnalyticsState(machine)
    for p in parts:
        st_.apply(p)
    _assert_same(direct, st_.report())
    # rolled up: neighbouring parts merged into one (minutes into hours), then folded
    merged: list[AnalyticsPart] = []
    for p in parts:
        assert p is not None
        if merged and merged[-1].n > 30 and p.n > 30 and data.draw(st.booleans(), label="roll"):
            merged[-1] = proto.merge_parts(merged[-1], p)
        else:
            merged.append(p)
    st2 = AnalyticsState(machine)
    for p in merged:
        st2.apply(p)
    _assert_same(direct, st2.report())


@pytest.mark.timeout(60)
def test_the_history_has_what_the_merge_must_get_right(direct: AnalyticsReport) -> None:
    # otherwise the test above could pass on an empty analysis
    assert {e.kind for e in direct.events} >= {"overload", "end_stop_impact", "slew_overspeed"}
    assert len(direct.cycles) > 50 and direct.idle_s > 1000
    assert all(s.cycles.total > 100 for s in direct.spectra)


@pytest.mark.timeout(60)
@settings(max_examples=300, deadline=None)
@given(y=st.lists(st.integers(-20, 20), min_size=1, max_size=80),
       cuts=st.lists(st.integers(1, 79), max_size=8))
def test_rainflow_residues_merge_exactly(y: list[int], cuts: list[int]) -> None:
    """Counting stretches alone and absorbing them in order (the stored residues re-counted
    with the next stretch's) gives the direct count, half cycles included."""
    arr = np.asarray(y, dtype=float)
    bounds = [0, *sorted({c for c in cuts if c < arr.size}), arr.size]
    merged = RainflowCounter(1.0)
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        c = RainflowCounter(1.0)
        c.update(arr[a:b])
        merged.absorb(c)
    want, got = rainflow(arr, 1.0), merged.snapshot()
    assert np.array_equal(want.lower, got.lower)
    assert np.array_equal(want.upper, got.upper)
    assert np.array_equal(want.count, got.count)
