"""Rates that do not move with the report window: the remaining life,
next service and class of utilisation of a repeated daily duty are the same in reports of 1 day,
1 week and 30 days; every assumption is printed."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from cranetwin.analytics import AnalyticsReport, AnalyticsState, LoadHistory, rate_basis
from cranetwin.errors import AnalyticsError
from cranetwin.model import Machine, load_machine
from cranetwin.testing.histories import SyntheticCrane

DAY_S = 86400.0
RATE_HZ = 10.0


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load_machine("patu655")


@pytest.fixture(scope="module")
def shift(machine: Machine) -> tuple[SyntheticCrane, list[LoadHistory]]:
    """One 2-hour shift (06:00-08:00 UTC) at 10 Hz, the duty repeated every day."""
    crane = SyntheticCrane(machine, seed=3, days=1, shift_h=2.0)
    return crane, list(crane.chunks(RATE_HZ, 3600.0))


def _report(machine: Machine, shift: tuple[SyntheticCrane, list[LoadHistory]], days: int,
            **kw: float) -> AnalyticsReport:
    crane, one = shift
    st = AnalyticsState(machine)
    for d in range(days):
        for h in one:
            st.update(replace(h, t_s=h.t_s + d * DAY_S))
    t0 = crane.start_epoch_s
    return st.report(t0, t0 + days * DAY_S, **kw)


@pytest.mark.timeout(60)
@pytest.mark.parametrize("history", [False, True])
def test_remaining_life_of_a_repeated_shift_does_not_depend_on_the_window(
        machine: Machine, shift: tuple[SyntheticCrane, list[LoadHistory]], history: bool) -> None:
    # whole recorded history: the same shift on 30 days
    kw = {"history_operating_s": 30 * 2 * 3600.0, "history_calendar_s": 30 * DAY_S} \
        if history else {}
    reps = {d: _report(machine, shift, d, **kw) for d in (1, 7, 30)}
    for d, rep in reps.items():
        assert rep.basis is not None
        assert rep.basis.usage_source == ("history" if history else "range")
        assert rep.basis.usage_h_per_day == pytest.approx(2.0, rel=1e-3)
        # the old basis (first-to-last sample span) gave 17 / 180 / 201 years here. What
        # remains is rainflow itself: the half cycles of the residue of one shift pair up
        # with the next shift's in a longer record (measured: ≤ 1.3e-4 relative, lift cylinder)
        for e1, e in zip(reps[1].life, rep.life, strict=True):
            assert e.damage_rate_per_day == pytest.approx(e1.damage_rate_per_day, rel=5e-4)
            # remaining life counts from the end of the range: the same end-of-life date
            end1 = DAY_S + e1.remaining_days * DAY_S
            end = d * DAY_S + e.remaining_days * DAY_S
            assert end == pytest.approx(end1, rel=5e-4)
        assert rep.classification is not None and reps[1].classification is not None
        assert rep.classification.projected_cycles == pytest.approx(
            reps[1].classification.projected_cycles, rel=1e-9)
        assert rep.classification.label == reps[1].classification.label
    # the damage itself grows with the window: 30 shifts hold 30× the damage of one
    assert reps[30].life[0].damage == pytest.approx(30 * reps[1].life[0].damage, rel=1e-3)
    # per day = damage of one shift (one shift per calendar day)
    assert reps[1].life[0].damage_rate_per_day == pytest.approx(reps[1].life[0].damage,
                                                                rel=1e-3)


@pytest.mark.timeout(60)
def test_history_basis_scales_a_short_window_by_the_machine_usage(
        machine: Machine, shift: tuple[SyntheticCrane, list[LoadHistory]]) -> None:
    # the first hour of the shift alone, the machine working 2 h a day over its history:
    # rate = damage per operating hour of that hour × 2 h/day, not damage / (1 h as a day)
    crane, one = shift
    a = crane.shift_bounds(0)[0]
    st = AnalyticsState(machine)
    h = one[0]
    st.update(h)
    rep = st.report(a, a + 3600.0, history_operating_s=60 * 3600.0,
                    history_calendar_s=30 * DAY_S)
    assert rep.basis is not None
    op_h = rep.recorded_s / 3600
    assert op_h == pytest.approx(1.0, rel=1e-3)
    dmg = rep.life[0].damage
    assert rep.life[0].damage_rate_per_day == pytest.approx(dmg / op_h * 2.0, rel=1e-12)
    # the range basis of the same hour counts it once per 1/24 day
    rng = st.report(a, a + 3600.0)
    assert rng.life[0].damage_rate_per_day == pytest.approx(dmg * 24, rel=1e-12)


@pytest.mark.timeout(60)
def test_report_states_every_assumption(machine: Machine,
                                        shift: tuple[SyntheticCrane, list[LoadHistory]]) -> None:
    rep = _report(machine, shift, 1)
    text = "\n".join(rep.assumptions)
    for d in machine.fatigue:
        assert f"Fatigue detail '{d.name}' (ASSUMED" in text
        assert f"Prior damage of '{d.name}' before the range: D = 0 (taken as zero" in text
        assert f"Δσc = {d.detail_category_mpa:g} MPa" in text
    cls = machine.classification
    assert cls is not None
    assert f"C_T = {cls.design_total_cycles:g} working cycles" in text
    assert f"design life {cls.design_life_years:g} years" in text
    assert "Rate basis:" in text and "operating h per calendar day of the requested range" in text
    from cranetwin.reports import csv_tables

    tabs = csv_tables(rep, machine, "test")
    assert [r[1] for r in tabs["assumptions.csv"].rows] == list(rep.assumptions)
    summary = {r[0]: r[1] for r in tabs["summary.csv"].rows}
    assert summary["Prior damage / prior equivalent cycles"] == "taken as zero (no earlier record)"
    assert "Rate basis" in " ".join(str(k) for k in summary)


def test_rate_basis_rejects_an_empty_range() -> None:
    with pytest.raises(AnalyticsError):
        rate_basis(10.0, 10.0, 0.0)
    b = rate_basis(0.0, DAY_S, 0.0)
    assert b.per_day(1.0) == 0.0  # no operation: no rate, no division by zero
    assert np.isinf(b.equivalent_days)
