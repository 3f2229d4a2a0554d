"""``cranetwin experiment noise --family``: the twin's accuracy over a family of cranes,
sample rates and sensor-error models it was not tuned on (docs/ACCURACY.md, "Noise family").

Each crane of :func:`cranetwin.sim.family.crane_family` runs each scenario once in the
simulator with quantisation-only sensors at the highest rate; the lower rates are every 2nd,
4th … sample of it. Every (crane, scenario, rate, error model, normalisation, seed) is one case
of :func:`cranetwin.twin.noise_family.evaluate_case`; :func:`cranetwin.twin.noise_targets.evaluate`
judges the targets over all of them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

from rich.console import Console
from rich.table import Table

from cranetwin.errors import SimulationError
from cranetwin.model import Machine
from cranetwin.sim.family import CraneVariant, crane_family, decimate, variant_machine
from cranetwin.sim.sensor_error import DISTRIBUTIONS, data_sheet, inject_error
from cranetwin.twin.noise_family import CaseResult, CaseSpec, evaluate_case
from cranetwin.twin.noise_targets import (
    GroupSummary,
    Target,
    evaluate,
    group_summary,
    in_scope,
    stated_cases,
)

FAMILY_SIZE = 8
LOG_PAYLOAD_KG = 300.0
"""The built-in log-loading scenario's nominal log mass [kg] (scaled by k in the family)."""


@dataclass(frozen=True)
class FamilyPlan:
    """Which cases to run.

    Attributes:
        cranes: Family members.
        scenarios: (built-in scenario name, duration [s]).
        rates_hz: Sample rates; the highest must be an integer multiple of each.
        errors: Error models (:data:`cranetwin.sim.sensor_error.DISTRIBUTIONS`).
        scales: Normalisations (``full``, ``recorded``).
        level: e (fraction).
        seeds: Error seeds per case (0 … seeds − 1).
    """

    cranes: tuple[CraneVariant, ...]
    scenarios: tuple[tuple[str, float], ...]
    rates_hz: tuple[float, ...]
    errors: tuple[str, ...]
    scales: tuple[str, ...]
    level: float
    seeds: int

    @property
    def size(self) -> int:
        """Number of cases."""
        return (len(self.cranes) * len(self.scenarios) * len(self.rates_hz) * len(self.errors)
                * len(self.scales) * self.seeds)


def family_plan(quick: bool, level: float = 0.05, seeds: int = 1) -> FamilyPlan:
    """The full family (8 cranes × fig3 20 s and log-loading 60 s × 50/100/200 Hz × 4 error
    models × 2 normalisations), or ``quick``: one generated crane (k ≈ 0.45), 30 s of
    log-loading at 100 Hz, uniform and biased error, both normalisations."""
    family = crane_family(FAMILY_SIZE)
    if quick:
        return FamilyPlan((family[4],), (("log-loading", 30.0),), (100.0,),
                          ("uniform", "biased"), ("full", "recorded"), level, seeds)
    return FamilyPlan(family, (("fig3", 20.0), ("log-loading", 60.0)), (50.0, 100.0, 200.0),
                      DISTRIBUTIONS, ("full", "recorded"), level, seeds)


def run_family(base: Machine, plan: FamilyPlan,
               progress: Callable[[str], None] | None = None) -> list[CaseResult]:
    """Simulate every crane and scenario once and score every case of ``plan``.

    Raises:
        SimulationError: A rate that does not divide the highest one.
    """
    from cranetwin.sim import SensorModel, builtin_scenario, simulate

    top = max(plan.rates_hz)
    factors = {r: int(round(top / r)) for r in plan.rates_hz}
    if any(abs(top / f - r) > 1e-9 for r, f in factors.items()):
        raise SimulationError(f"rates {plan.rates_hz}: each must divide {top:g} Hz")
    out: list[CaseResult] = []
    for variant in plan.cranes:
        m = variant_machine(base, variant)
        for name, duration in plan.scenarios:
            payload = LOG_PAYLOAD_KG * variant.force_scale if name == "log-loading" else 0.0
            sc = builtin_scenario(name, duration_s=duration,
                                  payload_kg=payload if payload > 0 else None)
            rec = simulate(m, sc, seed=0, sensors=SensorModel.ideal(top), wrenches=False)
            for rate in plan.rates_hz:
                clean = decimate(rec.samples, factors[rate])
                for error in plan.errors:
                    for scale in plan.scales:
                        for seed in range(plan.seeds):
                            spec = CaseSpec(variant.name, name, rate, error, scale, plan.level,
                                            seed, payload)
                            noisy = inject_error(clean, m, plan.level, seed,
                                                 error, scale)  # type: ignore[arg-type]
                            sheet = data_sheet(clean, m, plan.level,
                                               scale)  # type: ignore[arg-type]
                            out.append(evaluate_case(noisy, m, rec.truth, spec, sheet))
                            if progress is not None:
                                progress(f"{len(out)}/{plan.size} {variant.name} {name} "
                                         f"{rate:g} Hz {error}/{scale}")
    return out


def _pct(x: float, digits: int = 2) -> str:
    return "–" if x != x else f"{100 * x:.{digits}f}"


def case_table(cases: list[CaseResult], level: float) -> Table:
    """One row per case."""
    t = Table(title=f"Noise family at e = ±{100 * level:g} %: NRMSE [%] at the sample "
                    "instants; (w) best fixed pressure window; ! = flagged not observable; "
                    "* = outside the force target's scope (range < 10 % of A_A·p_s); "
                    "m = model-based force (twin.force_model)")
    for col in ("crane", "scenario", "Hz", "error", "Fc lift", "Fc jib", "Fc ext",
                "best fixed lift / jib", "Xc / input (worst)", "RMS z", "lift err [%]"):
        t.add_column(col)
    for case in cases:
        s = case.spec
        fc = []
        for c in case.cylinders:
            mark = ("m" if c.model_based else "") + ("!" if not c.observable else "") + (
                "*" if c.cylinder in ("lift", "jib") and not in_scope(c) else "")
            fc.append(f"{_pct(c.force)}{mark}")
        best = " / ".join(f"{_pct(c.best_fixed[1])} ({c.best_fixed[0]})"
                          for c in case.cylinders[:2])
        worst = max(case.cylinders, key=lambda c: c.position / c.position_input)
        lifts = ", ".join(f"{100 * e:+.1f}" for e in case.lift_errors) or "–"
        t.add_row(s.crane, s.scenario, f"{s.rate_hz:g}", f"{s.error}/{s.scale}", *fc[:3],
                  best, f"{_pct(worst.position)} / {_pct(worst.position_input)}",
                  "–" if case.z_count == 0 else f"{case.rms_z:.2f}", lifts)
    return t


def target_table(targets: list[Target]) -> Table:
    """One row per target: pass/fail, counts, the worst item."""
    t = Table(title="Targets over the family")
    for col in ("target", "verdict", "failed / checked", "worst"):
        t.add_column(col)
    for g in targets:
        verdict = {True: "PASS", False: "FAIL", None: "not checked"}[g.passed]
        t.add_row(g.text, verdict, f"{g.failed} / {g.checked}", g.worst)
    return t


def summary_table(groups: list[GroupSummary], title: str) -> Table:
    """One row per error model and normalisation: payload z, lift means, flag counts."""
    t = Table(title=title)
    for col in ("error", "RMS z net (gross)", "cases z in 0.7–1.5", "lifts", "lift bias [%]",
                "mean |lift err| [%]",
                "RMS lift z (all σ/√k)", "> 4 % flagged (noise share only)",
                "flagged / all (noise share only)"):
        t.add_column(col)
    for g in groups:
        t.add_row(g.group, f"{g.rms_z:.2f} ({g.rms_z_gross:.2f})",
                  f"{g.z_cases_within} / {g.z_cases}", str(g.lifts), _pct(g.lift_bias),
                  _pct(g.lift_abs), f"{g.lift_rms_z:.2f} ({g.lift_rms_z_all_random:.2f})",
                  f"{g.over_flagged} / {g.over} ({g.over_flagged_noise})",
                  f"{g.flagged} / {g.cylinders} ({g.flagged_noise})")
    return t


def as_json(plan: FamilyPlan, cases: list[CaseResult], targets: list[Target]) -> dict[str, Any]:
    """The plan, every case, every target and the per-group figures as plain data, without
    and (``*_stated``) with the stated accuracy."""
    stated = stated_cases(cases)
    return {"level": plan.level, "seeds": plan.seeds, "rates_hz": list(plan.rates_hz),
            "scenarios": [list(s) for s in plan.scenarios], "errors": list(plan.errors),
            "scales": list(plan.scales), "cranes": [asdict(v) for v in plan.cranes],
            "cases": [c.as_json() for c in cases],
            "targets": [{**asdict(g), "passed": g.passed} for g in targets],
            "targets_stated": [{**asdict(g), "passed": g.passed} for g in evaluate(stated)],
            "groups": [asdict(g) for g in group_summary(cases)],
            "groups_stated": [asdict(g) for g in group_summary(stated)]}


CYLINDER_COLUMNS = ("force_pct", "pressure_only_pct", "model_based", "best_fixed_pct",
                    "best_window", "range_share_pct", "observable", "error_share_pct",
                    "position_pct", "position_input_pct")
STATED_COLUMNS = ("stated_force_pct", "stated_model_based", "stated_observable",
                  "stated_error_share_pct")


def csv_header(cylinders: tuple[str, ...]) -> list[str]:
    """The columns of :func:`csv_row` (docs/accuracy-noise-family.csv)."""
    return (["crane", "scenario", "rate_hz", "error", "scale"]
            + [f"{c}_{k}" for c in cylinders for k in CYLINDER_COLUMNS]
            + ["payload_rms_z", "payload_z_instants", "lift_errors_pct"]
            + [f"{c}_{k}" for c in cylinders for k in STATED_COLUMNS]
            + ["stated_payload_rms_z", "lift_z", "stated_lift_z"]
            + [f"{c}_stated_systematic_share_pct" for c in cylinders]
            + ["stated_lift_z_all_random", "payload_rms_z_gross"])


def csv_row(case: dict[str, Any]) -> list[str]:
    """One case of :func:`as_json` (``CaseResult.as_json``) as the cells of :func:`csv_header`:
    shares in per cent (3 decimals), flags 0/1, z to 3 decimals, per-lift lists space-separated
    (2 decimals), empty where there is no value."""
    def num(x: float | None, scale: float = 1.0, digits: int = 3) -> str:
        return "" if x is None else f"{scale * x:.{digits}f}"

    def flag(x: bool | None) -> str:
        return "" if x is None else str(int(x))

    def many(xs: list[float | None], scale: float = 1.0) -> str:
        return " ".join(num(x, scale, 2) for x in xs)

    spec, cyls, stated = case["spec"], case["cylinders"], case["stated"]
    row = [spec["crane"], spec["scenario"], f"{spec['rate_hz']:g}", spec["error"], spec["scale"]]
    for c in cyls:
        row += [num(c["force"], 100), num(c["pressure_only"], 100), flag(c["model_based"]),
                num(c["best_fixed"], 100), str(c["best_fixed_window"]),
                num(c["range_share"], 100), flag(c["observable"]), num(c["error_share"], 100),
                num(c["position"], 100), num(c["position_input"], 100)]
    row += [num(case["rms_z"]), str(case["z_count"]), many(case["lift_errors"], 100)]
    st_cyls = stated["cylinders"] if stated else [None] * len(cyls)
    for c in st_cyls:
        row += (["", "", "", ""] if c is None else
                [num(c["force"], 100), flag(c["model_based"]), flag(c["observable"]),
                 num(c["error_share"], 100)])
    row += [num(stated["rms_z"]) if stated else "", many(case["lift_z"]),
            many(stated["lift_z"]) if stated else ""]
    row += ["" if c is None else num(c["systematic_share"], 100) for c in st_cyls]
    row += [many(stated["lift_z_all_random"]) if stated else "", num(case.get("rms_z_gross"))]
    return row


def write_csv(cases: list[dict[str, Any]], path: str) -> None:
    """Every case of :func:`as_json`'s ``cases`` as one row of :func:`csv_header` into
    ``path`` (the accuracy section's table of every case)."""
    import csv

    cylinders = tuple(c["cylinder"] for c in cases[0]["cylinders"]) if cases else ()
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(csv_header(cylinders))
        w.writerows(csv_row(c) for c in cases)


def print_family(cases: list[CaseResult], plan: FamilyPlan, console: Console) -> list[Target]:
    """Print the case table, the targets and the per-group figures, without and with the
    stated accuracy; return the targets without it."""
    targets = evaluate(cases)
    stated = stated_cases(cases)
    console.print(case_table(cases, plan.level))
    console.print(target_table(targets))
    console.print(summary_table(group_summary(cases), "Without a stated accuracy"))
    if stated:
        st = target_table(evaluate(stated))
        st.title = "Targets given the data sheet (each channel's accuracy = the error's bound)"
        console.print(st)
        console.print(summary_table(group_summary(stated), "Given the data sheet"))
    return targets
