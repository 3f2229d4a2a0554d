"""The noise family: generated cranes, error models, the per-case scores and the targets'
evaluation (``cranetwin experiment noise --family``).

The quick subset is run end to end; what is asserted is the table's structure and that every
target is computed from the cases, not that the targets pass (docs/ACCURACY.md has where
they fail)."""

from __future__ import annotations

import dataclasses
import json
from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from cranetwin.model import Machine, load_machine
from cranetwin.samples import SampleArrays
from cranetwin.twin.noise_family import FIXED_WINDOWS, CaseResult, CaseSpec, CylinderScore
from cranetwin.twin.noise_targets import FORCE_MAX, evaluate, in_scope


@lru_cache(maxsize=1)
def _quick() -> tuple[object, list[CaseResult]]:
    from cranetwin.cli._noise_family import family_plan, run_family

    plan = family_plan(quick=True)
    return plan, run_family(load_machine("patu655"), plan)


# -- the family's cranes and error models ------------------------------------------------------

@pytest.mark.timeout(120)
@pytest.mark.parametrize("k", [0.1, 0.45, 2.0])
def test_variant_scales_every_static_load_by_its_force_scale(k: float) -> None:
    """Masses, inertias and tool ×k with the payload ×k: every joint's static load is k times
    the built-in's (gravity is linear in the masses), whatever the cylinders do."""
    from cranetwin import physics
    from cranetwin.sim.family import CraneVariant, variant_machine

    base = load_machine("patu655")
    v = variant_machine(base, CraneVariant.of(k, 1.5, 0.7, 0.01))
    q = np.array([[0.3, 0.5, -1.4, 0.4], [-1.0, 0.9, -0.6, 0.1]])
    z = np.zeros_like(q)
    qdd = np.full_like(q, 0.2)
    expect = physics.joint_torques(base, q, z, qdd, 200.0) * k
    got = physics.joint_torques(v, q, z, qdd, 200.0 * k)
    np.testing.assert_allclose(got, expect, rtol=1e-9, atol=1e-9)
    areas = [c.area_a_m2 for c in v.cylinders]
    base_areas = [c.area_a_m2 for c in base.cylinders]
    np.testing.assert_allclose(areas, np.array(base_areas) * max(1.0, k), rtol=1e-12)
    fc = base.cylinders[0].friction.coulomb
    assert v.cylinders[0].friction.coulomb == pytest.approx(1.5 * fc)
    assert v.hydraulics is not None and base.hydraulics is not None
    bulk = base.hydraulics.oil_bulk_modulus_pa
    assert v.hydraulics.oil_bulk_modulus_pa == pytest.approx(0.7 * bulk)
    assert all(c.valve is not None and c.valve.spool_time_constant_s == 0.01 for c in v.cylinders)


@pytest.mark.timeout(60)
def test_family_spans_the_force_scales_and_starts_with_the_builtin() -> None:
    from cranetwin.sim.family import crane_family

    fam = crane_family(8, seed=0)
    assert len(fam) == 8 and len({v.name for v in fam}) == 8
    assert (fam[0].force_scale, fam[0].friction_scale, fam[0].bulk_scale) == (1.0, 1.0, 1.0)
    ks = [v.force_scale for v in fam[1:]]
    assert min(ks) == pytest.approx(0.1) and max(ks) == pytest.approx(2.0)
    assert crane_family(8, seed=0) == fam  # seeded


def _samples(machine: Machine) -> SampleArrays:
    names = tuple(c.name for c in machine.channels)
    rng = np.random.default_rng(3)
    vals = np.column_stack([c.min + (0.2 + 0.3 * rng.uniform(size=400)) * c.full_range
                            for c in machine.channels])
    return SampleArrays("m", np.arange(400) / 100.0, names, vals, period_ns=10_000_000)


@pytest.mark.timeout(60)
@pytest.mark.parametrize("distribution", ["uniform", "gaussian", "quantised", "biased"])
@pytest.mark.parametrize("scale", ["full", "recorded"])
def test_error_models_stay_within_their_stated_bounds(distribution: str, scale: str) -> None:
    """Uniform, quantised and biased error stay within ±e·R (R the full or recorded range);
    the biased one has a constant part per channel; quantised values lie on steps of 2e·R;
    untouched quantities (the torque) keep their values."""
    from cranetwin.sim.sensor_error import inject_error

    m = load_machine("patu655")
    s = _samples(m)
    out = inject_error(s, m, 0.05, 7, distribution, scale)  # type: ignore[arg-type]
    err = out.values - s.values
    for j, ch in enumerate(m.channels):
        if ch.quantity not in ("pressure_a", "pressure_b", "position"):
            assert np.all(err[:, j] == 0)
            continue
        r = ch.full_range if scale == "full" else float(np.ptp(s.values[:, j]))
        if distribution == "gaussian":
            assert 0.04 * r < np.std(err[:, j]) < 0.06 * r
            continue
        assert np.abs(err[:, j]).max() <= 0.05 * r * (1 + 1e-9)
        if distribution == "quantised":
            steps = out.values[:, j] / (0.1 * r)
            np.testing.assert_allclose(steps, np.round(steps), atol=1e-6)
        if distribution == "biased":
            assert abs(np.mean(err[:, j])) > 0.002 * r  # an offset no filter removes


@pytest.mark.timeout(60)
@pytest.mark.parametrize("scale", ["full", "recorded"])
def test_data_sheet_states_the_error_bound_of_each_noisy_channel(scale: str) -> None:
    """The data sheet's accuracy is e·R (R the full or the recorded range) on the pressures
    and positions, and is left unstated on the other channels."""
    from cranetwin.sim.sensor_error import data_sheet

    m = load_machine("patu655")
    s = _samples(m)
    sheet = data_sheet(s, m, 0.05, scale)  # type: ignore[arg-type]
    for j, ch in enumerate(sheet.channels):
        assert ch.name == m.channels[j].name
        if ch.quantity not in ("pressure_a", "pressure_b", "position"):
            assert ch.accuracy is None
            continue
        r = m.channels[j].full_range if scale == "full" else float(np.ptp(s.values[:, j]))
        assert ch.accuracy == pytest.approx(0.05 * r, rel=1e-12)
    assert m.channels[0].accuracy is None  # the machine itself is not changed


@pytest.mark.timeout(60)
def test_decimate_keeps_every_nth_sample_and_the_period() -> None:
    from cranetwin.sim.family import decimate

    s = _samples(load_machine("patu655"))
    d = decimate(s, 4)
    np.testing.assert_array_equal(d.t_s, s.t_s[::4])
    np.testing.assert_array_equal(d.values, s.values[::4])
    assert d.period_ns == 40_000_000


@pytest.mark.timeout(60)
def test_fixed_choices_change_only_the_pressure_windows() -> None:
    from cranetwin.signal import SmoothingChoice
    from cranetwin.twin.noise_family import fixed_choices

    m = load_machine("patu655")
    default = {c.name: SmoothingChoice(131, 3, 2.0, 1.0, adaptive=c.quantity.startswith("press"))
               for c in m.channels}
    default["lift_s'"] = SmoothingChoice(45, 3, 1e-4, float("nan"))
    out = dict(zip(default, fixed_choices(default, m, 21), strict=True))
    for name, c in out.items():
        if name.endswith(("_pA", "_pB")):
            assert (c.window, c.polyorder, c.adaptive, c.sigma) == (21, 3, False, 2.0)
        else:
            assert c == default[name]
    assert all(c.window == 1 for n, c in zip(default, fixed_choices(default, m, 1), strict=True)
               if n.endswith(("_pA", "_pB")))


# -- the targets' evaluation can fail ----------------------------------------------------------

def _case(force: float, fixed_best: float, pos: float, observable: bool, z: float,
          lift_err: float) -> CaseResult:
    fixed = tuple([fixed_best] + [fixed_best * 2] * (len(FIXED_WINDOWS) - 1))
    cyl = CylinderScore("lift", force, fixed, pos, 0.1, 0.5, observable, 0.05)
    spec = CaseSpec("c", "log-loading", 100.0, "uniform", "full", 0.05, 0, 300.0)
    return CaseResult(spec, (cyl,), z * z * 100, 100, (lift_err,), (0.0,))


@pytest.mark.timeout(60)
def test_targets_pass_on_good_cases_and_fail_on_each_kind_of_bad_one() -> None:
    good = evaluate([_case(0.02, 0.02, 0.01, True, 1.0, 0.001)])
    assert [t.passed for t in good] == [True, True, True, None, True, True]
    bad = {t.name: t for t in evaluate([_case(0.06, 0.03, 0.08, True, 3.0, 0.05)])}
    assert not bad["force"].passed and "6.00%" in bad["force"].worst
    assert not bad["vs-fixed"].passed and not bad["position"].passed
    assert not bad["flag"].passed  # 6 % and still called observable
    assert not bad["payload-z"].passed and not bad["lift-bias"].passed
    flagged = {t.name: t for t in evaluate([_case(0.06, 0.06, 0.01, False, 1.0, 0.0)])}
    assert flagged["flag"].passed and not flagged["force"].passed


@pytest.mark.timeout(60)
def test_group_summary_counts_flags_and_pools_lift_z() -> None:
    from cranetwin.twin.noise_targets import group_summary

    a = _case(0.06, 0.06, 0.01, False, 1.0, 0.02)
    b = _case(0.05, 0.05, 0.01, True, 2.0, -0.01)
    b = CaseResult(b.spec, b.cylinders, b.z_sq_sum, b.z_count, b.lift_errors, (3.0,))
    (g,) = group_summary([a, b])
    assert g.group == "uniform/full" and g.lifts == 2
    assert (g.over, g.over_flagged, g.flagged, g.cylinders) == (2, 1, 1, 2)
    assert g.lift_bias == pytest.approx(0.005) and g.lift_abs == pytest.approx(0.015)
    assert g.rms_z == pytest.approx(np.sqrt(2.5))
    assert g.lift_rms_z == pytest.approx(np.sqrt(4.5))
    assert (g.z_cases, g.z_cases_within) == (2, 1)  # z 1 is within 0.7–1.5, z 2 is not
    # a pooled RMS z can pass where no case does: z 0.3 and 1.6 pool to 1.2
    lo, hi = _case(0.02, 0.02, 0.01, True, 0.3, 0.0), _case(0.02, 0.02, 0.01, True, 1.6, 0.0)
    (g,) = group_summary([lo, hi])
    assert 0.7 <= g.rms_z <= 1.5 and g.z_cases_within == 0


# -- the quick family, end to end ----------------------------------------------------------------

@pytest.mark.timeout(300)
def test_quick_family_scores_every_case_and_judges_every_target() -> None:
    """Four cases (uniform and biased error, full and recorded range) of one generated crane:
    every number is finite where it must be, and each target's counts follow from the cases."""
    plan, cases = _quick()
    assert len(cases) == plan.size == 4  # type: ignore[attr-defined]
    assert {(c.spec.error, c.spec.scale) for c in cases} == {
        (e, s) for e in ("uniform", "biased") for s in ("full", "recorded")}
    for case in cases:
        assert [c.cylinder for c in case.cylinders] == ["lift", "jib", "extension"]
        for c in case.cylinders:
            assert len(c.fixed) == len(FIXED_WINDOWS) and np.all(np.isfinite(c.fixed))
            assert np.isfinite([c.force, c.position, c.position_input, c.range_share]).all()
            assert 0 < c.position < c.position_input + 1  # a fraction, and computed
        assert case.z_count > 100 and np.isfinite(case.rms_z)
        assert len(case.lift_errors) >= 1 and np.isfinite(case.lift_errors).all()
    for case in cases:  # replayed again given the data sheet, sharing the fixed windows
        st = case.stated
        assert st is not None and st.spec == case.spec
        assert [c.fixed for c in st.cylinders] == [c.fixed for c in case.cylinders]
        assert st.z_count > 100 and np.isfinite(st.rms_z)
    from cranetwin.twin.noise_targets import group_summary, stated_cases

    stated = stated_cases(cases)
    assert len(stated) == 4 and len(evaluate(stated)) == 6
    # the stated ±5 % (mostly an offset the data do not show as noise) widens the gross
    # estimate's σ of the biased cases; the uniform noise is within the stated bound and is not
    # counted twice
    z0 = {g.group: g.rms_z_gross for g in group_summary(cases)}
    z1 = {g.group: g.rms_z_gross for g in group_summary(stated)}
    assert z1["biased/full"] < 0.8 * z0["biased/full"]
    assert z1["uniform/full"] == pytest.approx(z0["uniform/full"], rel=0.1)
    # the offset's empty reading taken off each lift's instants shrinks their z further
    net = {g.group: g.rms_z for g in group_summary(cases)}
    assert net["biased/full"] < 0.8 * z0["biased/full"]
    targets = {t.name: t for t in evaluate(cases)}
    assert set(targets) == {"force", "vs-fixed", "position", "flag", "payload-z", "lift-bias"}
    scoped = [c for case in cases for c in case.cylinders if in_scope(c)]
    assert targets["force"].checked == len(scoped) > 0
    assert targets["force"].failed == sum(c.force > FORCE_MAX for c in scoped)
    assert targets["position"].checked == 12
    assert targets["payload-z"].checked == targets["lift-bias"].checked == 4
    assert all(t.passed in (True, False) for n, t in targets.items() if n != "flag")


@pytest.mark.timeout(300)
def test_cli_prints_the_family_table_and_a_verdict_per_target(tmp_path: Path) -> None:
    from cranetwin.cli import app

    csv_path = tmp_path / "family.csv"
    r = CliRunner().invoke(app, ["experiment", "noise", "--family", "--quick", "--json",
                                 "--csv", str(csv_path)])
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout.strip().splitlines()[-1])
    # the CSV holds the JSON's cases, one row each, in the documented table's columns
    import csv

    rows = list(csv.DictReader(csv_path.open(encoding="utf-8")))
    assert len(rows) == 4
    for row, case in zip(rows, out["cases"], strict=True):
        assert (row["crane"], row["error"], row["scale"]) == (
            case["spec"]["crane"], case["spec"]["error"], case["spec"]["scale"])
        assert float(row["lift_force_pct"]) == pytest.approx(
            100 * case["cylinders"][0]["force"], abs=6e-4)
        assert int(row["payload_z_instants"]) == case["z_count"]
        assert float(row["payload_rms_z"]) == pytest.approx(case["rms_z"], abs=6e-4)
        assert float(row["payload_rms_z_gross"]) == pytest.approx(case["rms_z_gross"], abs=6e-4)
        assert len(row["lift_errors_pct"].split()) == len(case["lift_errors"])
    with open(csv_path, encoding="utf-8") as f:
        head = f.readline().strip().split(",")
    assert head[:6] == ["crane", "scenario", "rate_hz", "error", "scale", "lift_force_pct"]
    assert len(out["cases"]) == 4 and len(out["targets"]) == 6
    assert len(out["targets_stated"]) == 6 and len(out["groups_stated"]) == 4
    assert out["cases"][0]["stated"]["cylinders"][0]["fixed"] == out["cases"][0]["cylinders"][0][
        "fixed"]
    assert {t["name"] for t in out["targets"]} >= {"force", "vs-fixed", "lift-bias"}
    assert all(t["passed"] in (True, False, None) for t in out["targets"])
    first = out["cases"][0]["cylinders"][0]
    assert set(first["fixed"]) == {str(w) for w in FIXED_WINDOWS}
    from cranetwin.cli._noise_family import case_table, target_table

    plan, cases = _quick()
    assert case_table(cases, 0.05).row_count == 4
    assert target_table(evaluate(cases)).row_count == 6


@pytest.mark.timeout(60)
def test_group_summary_counts_the_noise_share_flag_apart_from_the_floor() -> None:
    """A force flagged by its systematic floor alone (error share 5 %, under the 10 %) counts
    as flagged but not in the noise-share-only counts; the lift z with all of σ over √k is
    pooled apart."""
    from cranetwin.twin.noise_targets import group_summary

    a = _case(0.06, 0.06, 0.01, False, 1.0, 0.02)  # error share 0.05, flagged
    noisy = dataclasses.replace(a.cylinders[0], error_share=0.2)
    b = dataclasses.replace(a, cylinders=(noisy,), lift_z=(1.0,), lift_z_all_random=(2.0,))
    (g,) = group_summary([a, b])
    assert (g.over, g.over_flagged, g.over_flagged_noise) == (2, 2, 1)
    assert (g.flagged, g.flagged_noise) == (2, 1)
    assert g.lift_rms_z_all_random == pytest.approx(2.0)
