"""Palmgren–Miner fatigue damage with EN 13001-3-1 S-N curves, remaining life, next service.

S-N curve (EN 13001-3-1, single slope, no endurance limit):
``N(Δσ) = 2·10⁶ · (Δσc / (γmf·Δσ))^m`` with Δσc the detail category [MPa] at 2·10⁶ cycles,
m the slope (3 for welded details) and γmf the fatigue strength factor (1.0 by default).
Miner's sum: ``D = Σ n_i / N(Δσ_i)``; failure is predicted at D = 1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from cranetwin.errors import AnalyticsError
from cranetwin.model import FatigueDetail

F64 = npt.NDArray[np.float64]

N_REF = 2.0e6


def cycles_to_failure(stress_range_pa: npt.ArrayLike, detail_category_mpa: float,
                      slope_m: float = 3.0, gamma_mf: float = 1.0) -> F64:
    """Endurance N of an EN 13001-3-1 S-N curve.

    Args:
        stress_range_pa: Stress ranges Δσ, shape (k,) [Pa].
        detail_category_mpa: Δσc at 2e6 cycles [MPa].
        slope_m: Slope m of the curve.
        gamma_mf: Fatigue strength factor γmf (≥ 1).

    Returns:
        N per range, shape (k,); inf for a zero range.
    """
    if not (detail_category_mpa > 0 and slope_m > 0 and gamma_mf > 0):
        raise AnalyticsError("detail category, slope and gamma_mf must be > 0")
    ds = np.abs(np.asarray(stress_range_pa, dtype=np.float64)) * gamma_mf
    with np.errstate(divide="ignore"):
        return np.asarray(N_REF * (detail_category_mpa * 1e6 / ds) ** slope_m, dtype=np.float64)


def miner_damage(load_ranges: npt.ArrayLike, counts: npt.ArrayLike, detail: FatigueDetail,
                 gamma_mf: float = 1.0) -> float:
    """Miner damage D = Σ n_i / N_i of cycles of a load acting on a detail.

    Args:
        load_ranges: Load ranges, shape (k,) [N or N·m].
        counts: Cycles per range, shape (k,).
        detail: The structural detail (stress = ``stress_per_load`` × load).
        gamma_mf: Fatigue strength factor.

    Returns:
        Damage D (dimensionless; 1 = predicted end of fatigue life).
    """
    r = np.asarray(load_ranges, dtype=np.float64)
    n = np.asarray(counts, dtype=np.float64)
    if r.shape != n.shape:
        raise AnalyticsError(f"load_ranges {r.shape} and counts {n.shape} differ in shape")
    big_n = cycles_to_failure(r * detail.stress_per_load, detail.detail_category_mpa,
                              detail.slope_m, gamma_mf)
    return float(np.sum(n / big_n))


def equivalent_stress_range_mpa(stress_ranges_pa: npt.ArrayLike, counts: npt.ArrayLike,
                                slope_m: float = 3.0) -> float:
    """Damage-equivalent constant-amplitude stress range at 2e6 cycles [MPa]:
    ``(Σ n_i Δσ_i^m / 2e6)^(1/m)``."""
    s = np.asarray(stress_ranges_pa, dtype=np.float64) / 1e6
    n = np.asarray(counts, dtype=np.float64)
    return float((np.sum(n * s**slope_m) / N_REF) ** (1.0 / slope_m))


@dataclass(frozen=True)
class LifeEstimate:
    """Fatigue state of one detail.

    Attributes:
        name: Detail name.
        damage: Miner damage so far (incl. prior damage).
        damage_rate_per_day: Damage per calendar day at the recent usage rate [1/d].
        remaining_days: Days until D = 1 at that rate (inf if the rate is 0) [d].
        next_service_days: Days until D reaches the next multiple of the inspection step [d].
        next_service_damage: That damage level.
        equivalent_range_mpa: Damage-equivalent stress range at 2e6 cycles [MPa].
    """

    name: str
    damage: float
    damage_rate_per_day: float
    remaining_days: float
    next_service_days: float
    next_service_damage: float
    equivalent_range_mpa: float


def life_estimate(name: str, damage: float, damage_rate_per_day: float,
                  inspection_step: float = 0.1, equivalent_range_mpa: float = 0.0) -> LifeEstimate:
    """Remaining life and next inspection at a constant damage rate.

    Args:
        name: Detail name.
        damage: Miner damage so far.
        damage_rate_per_day: Recent damage rate [1/d], ≥ 0.
        inspection_step: Inspect each time D crosses a multiple of this step (0 < step ≤ 1).
        equivalent_range_mpa: Passed through for the report.
    """
    if not 0 < inspection_step <= 1:
        raise AnalyticsError(f"inspection_step must be in (0, 1], got {inspection_step}")
    if damage_rate_per_day < 0 or damage < 0:
        raise AnalyticsError("damage and damage rate must be >= 0")
    nxt = (np.floor(damage / inspection_step + 1e-12) + 1) * inspection_step
    if damage_rate_per_day == 0:
        rem = nxt_days = float("inf")
    else:
        rem = max(1.0 - damage, 0.0) / damage_rate_per_day
        nxt_days = (nxt - damage) / damage_rate_per_day
    return LifeEstimate(name, damage, damage_rate_per_day, float(rem), float(nxt_days), float(nxt),
                        equivalent_range_mpa)
