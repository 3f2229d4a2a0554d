"""The accuracy targets, evaluated over the cases of the noise family.

At ±5 % error (every error model and normalisation of the family):

1. ``force``: force NRMSE ≤ 4 % for every lift and jib case whose true force range is at
   least 10 % of the cylinder's full-pressure force A_A·p_supply;
2. ``vs-fixed``: on those cases, the default smoothing's force NRMSE ≤ 1.1 × the best fixed
   pressure window's (in hindsight, per case and cylinder);
3. ``position``: rod-position NRMSE ≤ ½ the input's, every cylinder and case;
4. ``flag``: a force whose NRMSE exceeds 4 % is flagged not observable (every cylinder: no
   silent failure);
5. ``payload-z``: the RMS of the payload's z over steady lifts lies within 0.7–1.5, pooled
   per error model and normalisation;
6. ``lift-bias``: the mean over lifts of (lift mean − truth)/truth lies within ±1 % (grab and
   release do not bias it), per error model and normalisation.

Each :class:`Target` counts what was checked and what failed, and names the worst. The
targets are judged on the replay without a stated accuracy and, where the cases have it, on
the replay given the data sheet (:attr:`CaseResult.stated`, :func:`stated_cases`).
:func:`group_summary` gives the per-error-model figures behind targets 4–6, including the RMS
z of the lift means (how well the lift σ covers the lift error).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from cranetwin.twin.noise_family import CaseResult, CylinderScore
from cranetwin.twin.observability import FORCE_ACCURACY_TARGET, RESOLVABLE_SHARE

FORCE_MAX = FORCE_ACCURACY_TARGET
IN_SCOPE_SHARE = 0.10
VS_FIXED = 1.10
POSITION_RATIO = 0.5
Z_RANGE = (0.7, 1.5)
LIFT_BIAS_MAX = 0.01
SCOPE_CYLINDERS = ("lift", "jib")


@dataclass(frozen=True)
class Target:
    """One target over the family.

    Attributes:
        name: Short key (module docstring).
        text: The target in words.
        checked: Items checked (cylinder cases, groups).
        failed: Items that missed it.
        worst: The worst item, in words.
    """

    name: str
    text: str
    checked: int
    failed: int
    worst: str

    @property
    def passed(self) -> bool | None:
        """True/False; None when nothing was checked."""
        return None if self.checked == 0 else self.failed == 0


def _label(case: CaseResult, cyl: CylinderScore | None = None) -> str:
    s = case.spec
    head = f"{s.crane} {s.scenario} {s.rate_hz:g} Hz {s.error}/{s.scale}"
    return head if cyl is None else f"{head} {cyl.cylinder}"


def in_scope(cyl: CylinderScore) -> bool:
    """A lift or jib force whose range is at least 10 % of the full-pressure force."""
    return cyl.cylinder in SCOPE_CYLINDERS and cyl.range_share >= IN_SCOPE_SHARE


def _per_cylinder(cases: Sequence[CaseResult], name: str, text: str,
                  keep: Callable[[CylinderScore], bool],
                  excess: Callable[[CylinderScore], float], fmt: str) -> Target:
    """excess > 0 fails; the worst is the largest excess."""
    checked = failed = 0
    worst, worst_x = "–", -np.inf
    for case in cases:
        for c in case.cylinders:
            if not keep(c):
                continue
            checked += 1
            x = excess(c)
            failed += bool(x > 0)
            if x > worst_x:
                worst_x, worst = x, f"{_label(case, c)}: " + fmt.format(c=c)
    return Target(name, text, checked, failed, worst)


def _groups(cases: Sequence[CaseResult]) -> dict[str, list[CaseResult]]:
    out: dict[str, list[CaseResult]] = {}
    for case in cases:
        out.setdefault(f"{case.spec.error}/{case.spec.scale}", []).append(case)
    return out


def _z_target(cases: Sequence[CaseResult]) -> Target:
    checked = failed = 0
    worst, worst_x = "–", -np.inf
    for group, items in _groups(cases).items():
        n = sum(c.z_count for c in items)
        if n == 0:
            continue
        rms = float(np.sqrt(sum(c.z_sq_sum for c in items) / n))
        checked += 1
        x = max(Z_RANGE[0] - rms, rms - Z_RANGE[1])
        failed += bool(x > 0)
        if x > worst_x:
            worst_x, worst = x, f"{group}: RMS z {rms:.2f}"
    return Target("payload-z", "payload RMS z (net of the empty reading) within 0.7–1.5 "
                  "(per error model)", checked,
                  failed, worst)


def _lift_target(cases: Sequence[CaseResult]) -> Target:
    checked = failed = 0
    worst, worst_x = "–", -np.inf
    for group, items in _groups(cases).items():
        errs = [e for c in items for e in c.lift_errors]
        if not errs:
            continue
        bias = float(np.mean(errs))
        checked += 1
        failed += bool(abs(bias) > LIFT_BIAS_MAX)
        if abs(bias) > worst_x:
            worst_x = abs(bias)
            worst = (f"{group}: mean {100 * bias:+.2f} % over {len(errs)} lifts "
                     f"({100 * min(errs):+.1f} … {100 * max(errs):+.1f} %)")
    return Target("lift-bias", "lift means unbiased: mean error within ±1 % (per error model)",
                  checked, failed, worst)


def evaluate(cases: Sequence[CaseResult]) -> list[Target]:
    """Every target over ``cases``."""
    return [
        _per_cylinder(cases, "force", "force NRMSE ≤ 4 % (lift, jib; range ≥ 10 % of A_A·p_s)",
                      in_scope, lambda c: c.force - FORCE_MAX,
                      "{c.force:.2%} (range {c.range_share:.0%})"),
        _per_cylinder(cases, "vs-fixed", "force ≤ 1.1 × best fixed window (same scope)",
                      in_scope, lambda c: c.force / c.best_fixed[1] - VS_FIXED,
                      "{c.force:.2%} vs {c.best_fixed[1]:.2%} (window {c.best_fixed[0]})"),
        _per_cylinder(cases, "position", "position NRMSE ≤ ½ input (every cylinder)",
                      lambda c: True, lambda c: c.position / c.position_input - POSITION_RATIO,
                      "{c.position:.2%} vs input {c.position_input:.2%}"),
        _per_cylinder(cases, "flag", "force NRMSE > 4 % ⇒ flagged not observable",
                      lambda c: c.force > FORCE_MAX, lambda c: 0.0 if not c.observable else
                      c.force, "{c.force:.2%}, error share {c.error_share:.0%}"),
        _z_target(cases),
        _lift_target(cases),
    ]


def stated_cases(cases: Sequence[CaseResult]) -> list[CaseResult]:
    """The cases' scores given the stated accuracy (those that have them)."""
    return [c.stated for c in cases if c.stated is not None]


@dataclass(frozen=True)
class GroupSummary:
    """Per error model and normalisation: the figures behind targets 4–6.

    Attributes:
        group: ``error/scale``.
        rms_z: Pooled RMS payload z over steady lifts (NaN: none).
        lifts: Complete lifts.
        lift_bias: Mean of (lift mean − truth)/truth (fraction; NaN: no lift).
        lift_abs: Mean |lift mean − truth|/truth (fraction; NaN: no lift).
        lift_rms_z: RMS of (lift mean − truth)/lift σ (NaN: no lift).
        over: Cylinder cases whose force NRMSE exceeds 4 %.
        over_flagged: Of those, flagged not observable.
        flagged: All cylinder cases flagged not observable.
        cylinders: All cylinder cases.
        over_flagged_noise, flagged_noise: The same counts for the flag by the noise share
            alone (without the systematic floor, :mod:`cranetwin.twin.observability`).
        lift_rms_z_all_random: RMS lift z with all of the σ divided by √k
            (:attr:`CaseResult.lift_z_all_random`; NaN: no lift).
        rms_z_gross: ``rms_z`` of the gross estimate (:attr:`CaseResult.rms_z_gross`).
        z_cases, z_cases_within: Cases with a payload z, and of those the cases whose own RMS
            z lies within ``Z_RANGE`` (the pooled figure can pass on cases too wide and too
            narrow).
    """

    group: str
    rms_z: float
    lifts: int
    lift_bias: float
    lift_abs: float
    lift_rms_z: float
    over: int
    over_flagged: int
    flagged: int
    cylinders: int
    over_flagged_noise: int = 0
    flagged_noise: int = 0
    lift_rms_z_all_random: float = float("nan")
    rms_z_gross: float = float("nan")
    z_cases: int = 0
    z_cases_within: int = 0


def _noise_flag(c: CylinderScore) -> bool:
    """Flagged by the noise share alone (the verdict without the systematic floor)."""
    return not c.error_share <= RESOLVABLE_SHARE


def group_summary(cases: Sequence[CaseResult]) -> list[GroupSummary]:
    """One :class:`GroupSummary` per error model and normalisation (first-seen order)."""
    out = []
    nan = float("nan")
    for group, items in _groups(cases).items():
        n = sum(c.z_count for c in items)
        rms = float(np.sqrt(sum(c.z_sq_sum for c in items) / n)) if n else nan
        errs = np.array([e for c in items for e in c.lift_errors])
        lz = np.array([z for c in items for z in c.lift_z])
        lz0 = np.array([z for c in items for z in c.lift_z_all_random])
        cyls = [c for case in items for c in case.cylinders]
        over = [c for c in cyls if c.force > FORCE_MAX]
        out.append(GroupSummary(
            group, rms, int(errs.size), float(errs.mean()) if errs.size else nan,
            float(np.abs(errs).mean()) if errs.size else nan,
            float(np.sqrt(np.mean(lz**2))) if lz.size else nan, len(over),
            sum(not c.observable for c in over), sum(not c.observable for c in cyls),
            len(cyls), sum(_noise_flag(c) for c in over), sum(_noise_flag(c) for c in cyls),
            float(np.sqrt(np.mean(lz0**2))) if lz0.size else nan,
            float(np.sqrt(sum(c.gross_z_sq_sum for c in items) / n)) if n else nan,
            sum(c.z_count > 0 for c in items),
            sum(c.z_count > 0 and Z_RANGE[0] <= c.rms_z <= Z_RANGE[1] for c in items)))
    return out
