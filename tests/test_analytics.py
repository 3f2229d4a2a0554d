"""Analytics: rainflow (ASTM E1049), classification (ISO 4301-1), Miner damage (EN 13001-3-1),
events, work cycles, incremental == batch, import purity."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from collections import Counter
from pathlib import Path

import fatpack
import numpy as np
import pytest

from cranetwin.analytics import (
    AnalyticsState,
    LoadHistory,
    RainflowCounter,
    analyse,
    classify,
    cycles_to_failure,
    duty_record,
    four_point,
    group,
    life_estimate,
    miner_damage,
    rainflow,
    spectrum_class,
    spectrum_factor,
    turning_points,
    utilisation_class,
)
from cranetwin.analytics.rainflow import levels
from cranetwin.analytics.runs import RunTracker
from cranetwin.errors import AnalyticsError
from cranetwin.model import FatigueDetail, Machine, load_machine
from cranetwin.testing.histories import CYCLE_S, Misuse, SyntheticCrane

SRC = Path(__file__).resolve().parents[1] / "src" / "cranetwin" / "analytics"


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load_machine("patu655")


def _by_range(ranges: np.ndarray, counts: np.ndarray) -> dict[float, float]:
    out: Counter[float] = Counter()
    for r, c in zip(ranges.tolist(), counts.tolist(), strict=True):
        out[r] += c
    return {k: v for k, v in out.items() if v}


def _astm_three_point(rev: list[float]) -> dict[float, float]:
    """ASTM E1049-85 §5.4.4 rainflow counting, written from the standard's steps 1-6."""
    stack: list[float] = []
    out: Counter[float] = Counter()
    for p in rev:
        stack.append(p)
        while len(stack) >= 3:
            x, y = abs(stack[-1] - stack[-2]), abs(stack[-2] - stack[-3])
            if x < y:
                break
            if len(stack) == 3:  # Y contains the starting point: half cycle, drop the start
                out[y] += 0.5
                stack.pop(0)
            else:
                out[y] += 1.0
                del stack[-3:-1]
    for a, b in zip(stack[:-1], stack[1:], strict=False):
        out[abs(b - a)] += 0.5
    return {k: v for k, v in out.items() if v}


# --- rainflow -------------------------------------------------------------------------------

def test_rainflow_matches_astm_e1049_worked_example() -> None:
    # ASTM E1049 Fig. 6: A..I = -2, 1, -3, 5, -1, 3, -4, 4, -2 -> ranges (units): cycles
    table = rainflow([-2, 1, -3, 5, -1, 3, -4, 4, -2], class_width=1.0)
    assert _by_range(table.ranges, table.count) == {3.0: 0.5, 4.0: 1.5, 6.0: 0.5, 8.0: 1.0,
                                                    9.0: 0.5}
    assert table.total == pytest.approx(4.0)


def test_rainflow_agrees_with_astm_three_point_on_random_sequences() -> None:
    rng = np.random.default_rng(0)
    for _ in range(200):
        y = rng.integers(-20, 20, size=int(rng.integers(3, 300))).astype(float)
        table = rainflow(y, 1.0)
        rev = turning_points(levels(y, 1.0)).astype(float).tolist()
        assert _by_range(table.ranges, table.count) == _astm_three_point(rev)


def test_four_point_equals_fatpack_stack_algorithm() -> None:
    rng = np.random.default_rng(1)
    for trial in range(100):
        n = int(rng.integers(5, 2000))
        y = np.cumsum(rng.normal(size=n)) if trial % 2 else rng.integers(-4, 5, n).astype(float)
        rev = turning_points(levels(y, 0.5)).astype(float)
        mine, res = four_point(rev)
        ref, ref_res = fatpack.find_rainflow_cycles(rev)
        ref = np.asarray(ref).reshape(-1, 2)
        assert sorted(map(tuple, np.sort(mine, axis=1).tolist())) == \
            sorted(map(tuple, np.sort(ref, axis=1).tolist()))
        assert np.array_equal(res, np.asarray(ref_res))


def test_turning_points_equal_fatpack_find_reversals_on_same_classes() -> None:
    rng = np.random.default_rng(2)
    w, k = 0.25, 200
    y = np.clip(np.cumsum(rng.normal(size=20_000)) * 0.1, -20.0, 20.0)
    # fatpack's classes: boundaries ymin - w/2 + i*w; pick ymin so that they sit on multiples of w
    ymin = -25.0 + w / 2
    rev_fp, _ = fatpack.find_reversals(y, k=k, ymin=ymin, ymax=ymin + k * w)
    mine = (turning_points(levels(y, w)) + 0.5) * w
    assert np.allclose(mine[: rev_fp.size], rev_fp)
    assert mine.size - rev_fp.size in (0, 1)  # fatpack may leave out a last half-turn


def test_rainflow_counter_is_independent_of_chunking() -> None:
    rng = np.random.default_rng(3)
    y = np.cumsum(rng.normal(size=50_000))
    batch = rainflow(y, 0.7)
    counter = RainflowCounter(0.7)
    cuts = np.sort(rng.choice(np.arange(1, y.size), 40, replace=False))
    for a, b in zip(np.r_[0, cuts], np.r_[cuts, y.size], strict=True):
        counter.update(y[a:b])
    inc = counter.snapshot()
    assert np.array_equal(inc.lower, batch.lower) and np.array_equal(inc.upper, batch.upper)
    assert np.array_equal(inc.count, batch.count)
    # every full cycle closed on the way is also a closed cycle of fatpack's one pass
    closed, _ = fatpack.find_rainflow_cycles(turning_points(levels(y, 0.7)).astype(float))
    assert counter._closed.total == len(closed)


# --- classification and duty ------------------------------------------------------------------

def test_spectrum_factor_of_known_spectra() -> None:
    assert spectrum_factor([1.0] * 10) == pytest.approx(1.0)
    # 10 % at full load, 40 % at half load, 50 % empty: kp = 0.1 + 0.4/8 = 0.15
    assert spectrum_factor([1.0, 0.5, 0.0], [1, 4, 5]) == pytest.approx(0.15)
    per_cycle = [1.0] + [0.5] * 4 + [0.0] * 5
    assert spectrum_factor(per_cycle) == pytest.approx(spectrum_factor([1.0, 0.5, 0.0], [1, 4, 5]))
    with pytest.raises(AnalyticsError):
        spectrum_factor([-0.1])


@pytest.mark.parametrize(("kp", "q"), [(0.0, 1), (0.125, 1), (0.126, 2), (0.25, 2), (0.3, 3),
                                      (0.5, 3), (0.51, 4), (1.0, 4)])
def test_spectrum_class_bounds(kp: float, q: int) -> None:
    assert spectrum_class(kp) == q


@pytest.mark.parametrize(("cycles", "u"), [(1.6e4, 0), (1.6e4 + 1, 1), (6.3e4, 2), (5e5, 5),
                                          (5e5 + 1, 6), (4e6, 8), (4e6 + 1, 9)])
def test_utilisation_class_bounds(cycles: float, u: int) -> None:
    assert utilisation_class(cycles) == u


def test_group_table_iso4301() -> None:
    assert group(1, 0) == 1 and group(4, 9) == 8
    assert group(2, 5) == 5 and group(3, 4) == 5 and group(4, 3) == 5 and group(1, 6) == 5
    # the group never decreases with heavier spectrum or more cycles
    for q in range(1, 5):
        for u in range(10):
            assert group(q, u) <= group(min(q + 1, 4), u)
            assert group(q, u) <= group(q, min(u + 1, 9))


def test_classify_projects_cycles_to_the_design_life() -> None:
    # 1000 cycles at kp 0.15 in 10 days, 10-year life -> 365 250 cycles: U5, Q2 -> A5
    ratios = [1.0] * 100 + [0.5] * 400 + [0.0] * 500
    c = classify(ratios, observed_days=10.0, design_life_years=10.0, design_group="A5")
    assert c.projected_cycles == pytest.approx(365_250.0)
    assert (c.q_class, c.u_class, c.group) == (2, 5, 5)
    assert c.label == "A5 (Q2/L2, U5)"


def test_duty_record_iso12482_method_a() -> None:
    ratios = np.array([1.0, 0.5, 0.5, 0.0])
    d = duty_record(ratios, design_cycles=1000.0, design_kp=0.25, prior_equivalent=2.0)
    assert d.equivalent_cycles == pytest.approx(2.0 + 1.0 + 2 * 0.125)
    assert d.design_equivalent == pytest.approx(250.0)
    assert d.used_fraction == pytest.approx(3.25 / 250.0)


# --- fatigue ------------------------------------------------------------------------------------

def test_sn_curve_passes_through_detail_category() -> None:
    assert cycles_to_failure(71e6, 71.0)[()] == pytest.approx(2e6)
    assert cycles_to_failure(142e6, 71.0)[()] == pytest.approx(2e6 / 8)
    assert cycles_to_failure(71e6, 71.0, slope_m=5)[()] == pytest.approx(2e6)


def test_miner_damage_constant_amplitude_closed_form() -> None:
    detail = FatigueDetail(name="d", load="cylinder:lift:force", stress_per_load=1000.0,
                           detail_category_mpa=71.0)
    n = 500
    # 0, 10 kN, 0, 10 kN ... : n full cycles of range 10 kN -> 10 MPa
    y = np.tile([0.0, 10_000.0], n)
    y = np.append(y, 0.0)
    table = rainflow(y, 500.0)
    assert table.total == pytest.approx(n)
    d = miner_damage(table.ranges, table.count, detail)
    expected = n * (10e6) ** 3 / (2e6 * (71e6) ** 3)
    assert d == pytest.approx(expected, rel=1e-12)
    assert miner_damage(table.ranges, table.count, detail, gamma_mf=1.1) == \
        pytest.approx(expected * 1.1**3)


def test_life_estimate_linear_projection() -> None:
    e = life_estimate("x", damage=0.25, damage_rate_per_day=0.01, inspection_step=0.1)
    assert e.remaining_days == pytest.approx(75.0)
    assert e.next_service_damage == pytest.approx(0.3)
    assert e.next_service_days == pytest.approx(5.0)
    assert life_estimate("x", 0.0, 0.0).remaining_days == float("inf")


# --- histories, events, productivity -------------------------------------------------------------

def _window(sc: SyntheticCrane, first: int, last: int, rate: float = 100.0) -> LoadHistory:
    t0 = sc.cycle_start(first)
    t = t0 + np.arange(int((last - first) * CYCLE_S * rate)) / rate
    return sc.history(t)


def test_clean_cycles_raise_no_event(machine: Machine) -> None:
    sc = SyntheticCrane(machine, seed=4, days=1)
    rep = analyse(machine, _window(sc, 0, 40))
    assert rep.events == []
    assert len(rep.cycles) == 40 and all(c.complete for c in rep.cycles)


def test_injected_overload_and_end_stop_hit_are_found(machine: Machine) -> None:
    sc = SyntheticCrane(machine, seed=4, days=1,
                        misuse=Misuse(overload=(5,), end_stop=(12,), overspeed=(20,)))
    rep = analyse(machine, _window(sc, 0, 30))
    kinds = Counter(e.kind for e in rep.events)
    assert kinds == Counter({"overload": 1, "end_stop_impact": 1, "slew_overspeed": 1})
    ev = {e.kind: e for e in rep.events}
    ov = ev["overload"]
    assert sc.cycle_start(5) < ov.t_start < sc.cycle_start(6)
    assert ov.evidence["moment_ratio"] == pytest.approx(1.35, rel=0.1)
    assert ov.severity == "critical" and ov.value > ov.limit
    hit = ev["end_stop_impact"]
    assert hit.component == "lift" and sc.cycle_start(12) < hit.t_start < sc.cycle_start(13)
    assert hit.evidence["end_extended"] == 1.0 and hit.value > hit.limit
    assert sc.cycle_start(20) < ev["slew_overspeed"].t_start < sc.cycle_start(21)


def test_over_pressure_and_shock_detected_on_synthetic_spike(machine: Machine) -> None:
    sc = SyntheticCrane(machine, seed=4, days=1)
    h = _window(sc, 0, 4)
    assert h.p_a is not None and machine.hydraulics is not None
    p_a = h.p_a.copy()
    f = h.cyl_force.copy()
    i = 5000
    p_a[i:i + 10, 0] = 1.2 * machine.hydraulics.relief_pressure_pa
    f[i:i + 10, 0] += 200_000.0  # 200 kN in one sample: 4 MN/s over the 50 ms window
    from dataclasses import replace

    rep = analyse(machine, replace(h, p_a=p_a, cyl_force=f))
    kinds = Counter(e.kind for e in rep.events)
    assert kinds["over_pressure"] == 1 and kinds["shock_load"] >= 1
    op = next(e for e in rep.events if e.kind == "over_pressure")
    assert op.component == "lift:A" and op.severity == "critical"
    assert op.t_start == pytest.approx(h.t_s[i])


def test_productivity_counts_cycles_payload_and_idle(machine: Machine) -> None:
    sc = SyntheticCrane(machine, seed=5, days=1, shift_h=2.0)
    st = AnalyticsState(machine)
    for h in sc.chunks(rate_hz=20.0, chunk_s=900.0):
        st.update(h)
    rep = st.report()
    per_shift = sc.cycles_per_shift
    brk = int(1800 // CYCLE_S)
    assert len(rep.cycles) == per_shift - brk - 1  # the last slot is cut by the shift end
    assert rep.recorded_s == pytest.approx(2 * 3600, abs=1.0)
    # the 30-minute break is idle (plus the pause before and after it)
    assert 1800 <= rep.idle_s <= 1800 + 2 * CYCLE_S
    assert rep.mean_cycle_time_s == pytest.approx(CYCLE_S, rel=1e-3)
    moved = sum(c.payload_kg for c in rep.cycles)
    assert rep.payload_per_working_hour_kg == pytest.approx(moved / (rep.working_s / 3600))


def test_incremental_equals_batch(machine: Machine) -> None:
    sc = SyntheticCrane(machine, seed=6, days=2, shift_h=1.0,
                        misuse=Misuse(overload=(3,), end_stop=(30,), overspeed=(83,)))
    t = np.concatenate([sc.shift_bounds(d)[0] + np.arange(72_000) / 20.0 for d in range(2)])
    h = sc.history(t)
    batch = analyse(machine, h)
    rng = np.random.default_rng(7)
    cuts = np.sort(rng.choice(np.arange(1, h.n), 60, replace=False))
    st = AnalyticsState(machine)
    for j, (a, b) in enumerate(zip(np.r_[0, cuts], np.r_[cuts, h.n], strict=True)):
        st.update(h.slice(int(a), int(b)))
        if j == 30:  # persist and resume half-way, as a service between runs would
            st = AnalyticsState.loads(st.dumps())
    inc = st.report()
    for sb, si in zip(batch.spectra, inc.spectra, strict=True):
        assert np.array_equal(sb.cycles.lower, si.cycles.lower)
        assert np.array_equal(sb.cycles.count, si.cycles.count)
    assert len(batch.events) == 3 and len(inc.events) == 3
    for eb, ei in zip(batch.events, inc.events, strict=True):
        assert (eb.kind, eb.t_start, eb.t_end, eb.severity, eb.component) == \
            (ei.kind, ei.t_start, ei.t_end, ei.severity, ei.component)
        assert ei.value == pytest.approx(eb.value, rel=1e-12)
        assert ei.evidence == pytest.approx(eb.evidence, rel=1e-12)
    assert len(inc.cycles) == len(batch.cycles) > 50
    assert batch.idle_s > 2 * 1700
    for cb, ci in zip(batch.cycles, inc.cycles, strict=True):
        assert (cb.t_grab, cb.t_release, cb.lift, cb.swing) == \
            (ci.t_grab, ci.t_release, ci.lift, ci.swing)
        assert ci.payload_kg == pytest.approx(cb.payload_kg, rel=1e-12)
    assert inc.idle_s == pytest.approx(batch.idle_s)
    assert inc.days.keys() == batch.days.keys()
    for k, v in batch.days.items():
        assert (inc.days[k].recorded_s, inc.days[k].working_s, inc.days[k].cycles) == \
            pytest.approx((v.recorded_s, v.working_s, v.cycles))
    assert [x.damage for x in inc.life] == pytest.approx([x.damage for x in batch.life])


def test_run_tracker_merges_and_splits_at_gaps() -> None:
    t = np.r_[np.arange(0, 10, 0.1), np.arange(100, 110, 0.1)]
    mask = np.ones(t.size, dtype=bool)
    mask[20:23] = False
    tr = RunTracker(min_duration_s=0.0, merge_gap_s=1.0, max_gap_s=1.0)
    runs = tr.feed(t, mask, (t,)) + tr.flush()
    assert [(round(r.t_start, 1), round(r.t_end, 1)) for r in runs] == [(0.0, 9.9),
                                                                       (100.0, 109.9)]


def test_load_history_rejects_bad_input(machine: Machine) -> None:
    n = 5
    ok = {"t_s": np.arange(n, dtype=float), "cyl_force": np.zeros((n, 3)),
          "q": np.zeros((n, 4)), "payload_kg": np.zeros(n), "reach_m": np.ones(n),
          "joint_wrench": np.zeros((n, 4, 6))}
    h = LoadHistory.from_arrays(machine, **ok)
    assert h.joint_moment.shape == (n, 4)
    with pytest.raises(AnalyticsError, match="cyl_force"):
        LoadHistory.from_arrays(machine, **{**ok, "cyl_force": np.zeros((n, 2))})
    with pytest.raises(AnalyticsError, match="increasing"):
        LoadHistory.from_arrays(machine, **{**ok, "t_s": np.zeros(n)})
    with pytest.raises(AnalyticsError, match="joint_wrench"):
        LoadHistory.from_arrays(machine, **{k: v for k, v in ok.items() if k != "joint_wrench"})
    with pytest.raises(AnalyticsError, match="unknown component"):
        h.load_channel(machine, "cylinder:nope:force")


def test_joint_moment_is_magnitude_of_wrench_moment(machine: Machine) -> None:
    n = 3
    w = np.zeros((n, 4, 6))
    w[:, 1, 3:] = [3.0, 4.0, 12.0]
    w[:, 1, :3] = 99.0  # forces do not count
    h = LoadHistory.from_arrays(machine, t_s=np.arange(n, dtype=float),
                                cyl_force=np.zeros((n, 3)), q=np.zeros((n, 4)),
                                payload_kg=np.zeros(n), reach_m=np.ones(n), joint_wrench=w)
    assert np.allclose(h.load_channel(machine, "joint:theta1:moment"), 13.0)


# --- purity ---------------------------------------------------------------------------------------

ALLOWED = {"__future__", "numpy", "numpy.typing", "fatpack", "dataclasses", "collections.abc",
           "copy", "typing", "math", "pickle", "functools"}


def test_analytics_imports_only_numpy_fatpack_model_errors() -> None:
    for path in SRC.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            for name in names:
                ok = name in ALLOWED or name.startswith(("cranetwin.analytics",
                                                         "cranetwin.model", "cranetwin.errors"))
                assert ok, f"{path.name} imports {name}"
    code = ("import sys, json; import cranetwin.analytics; "
            "print(json.dumps(sorted(sys.modules)))")
    mods = json.loads(subprocess.run([sys.executable, "-c", code], capture_output=True,
                                     text=True, check=True).stdout)
    for banned in ("fastapi", "sqlalchemy", "starlette", "uvicorn", "websockets", "asyncio",
                   "cranetwin.physics", "cranetwin.twin", "cranetwin.storage", "cranetwin.api"):
        assert banned not in mods, banned


def test_payload_above_hook_rating_is_its_own_event(machine: Machine) -> None:
    from dataclasses import replace

    sc = SyntheticCrane(machine, seed=4, days=1)
    h = _window(sc, 0, 2)
    pl = h.payload_kg.copy()
    cap = max(machine.rated_load.payload_kg)
    pl[2000:2200] = 1.2 * cap  # 2 s at 120 % of the chart's largest payload
    rep = analyse(machine, replace(h, payload_kg=pl))
    ev = [e for e in rep.events if e.kind == "payload_above_rating"]
    assert len(ev) == 1
    assert ev[0].value == pytest.approx(1.2 * cap) and ev[0].limit == cap
    assert ev[0].t_start == pytest.approx(h.t_s[2000]) and ev[0].t_end == pytest.approx(h.t_s[2199])
    assert any(e.kind == "overload" and e.t_start == ev[0].t_start for e in rep.events)


def test_state_loads_rejects_foreign_bytes() -> None:
    with pytest.raises(AnalyticsError, match="not an analytics state"):
        AnalyticsState.loads(b"\x80\x04junk")


def test_median_step_equals_numpy_median_to_the_bit() -> None:
    from cranetwin.analytics.history import median_step

    rng = np.random.default_rng(7)
    for n in [2, 3, 4, 5, 8, 41, 80, 81, 100, 257, 258, 6000]:
        grid = 1.78e9 + np.arange(n) / 10.0  # a replay grid: steps differing in the last bits
        jitter = np.cumsum(rng.uniform(0.01, 0.2, n))
        ties = np.cumsum(rng.choice([0.1, 0.2], n))
        for t in (grid, jitter, ties):
            assert median_step(t) == float(np.median(np.diff(t))), n


def test_rainflow_counter_table_equals_merging_into_an_empty_one() -> None:
    from cranetwin.analytics.rainflow import merge_tables

    rng = np.random.default_rng(3)
    y = np.cumsum(rng.normal(size=400))
    fresh = RainflowCounter(0.5)
    first = fresh.update(y)  # the first cycles closed: the counter's table
    assert first.lower.size > 5
    merged = merge_tables(RainflowCounter(0.5)._closed, first)
    for a, b in ((fresh._closed, merged), (first, merged)):
        for k in ("lower", "upper", "count"):
            x, z = getattr(a, k), getattr(b, k)
            assert x.dtype == z.dtype and x.tobytes() == z.tobytes(), k
