"""Crane classification (ISO 4301-1:1986 / FEM 1.001) and the ISO 12482 duty record.

* Load spectrum factor (ISO 4301-1, 4.2.2): ``kp = Σ (C_i / C_T)·(P_i / P_max)³`` over the
  working cycles, with P_i the load of cycle i and P_max the rated load.
* Spectrum class Q1–Q4 (ISO 4301-1 Table 2; FEM 1.001 L1–L4 use the same bounds):
  kp ≤ 0.125, ≤ 0.25, ≤ 0.5, ≤ 1.0.
* Class of utilisation U0–U9 from the total number of working cycles C_T (Table 1).
* Group A1–A8 from (Q, U) (Table 3).
* Used design working period (ISO 12482, recording method a — automatic recorder):
  ``S = Σ C_i·(P_i/P_max)³`` full-load equivalent cycles, against the design's
  ``C_T,design·kp,design``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from cranetwin.errors import AnalyticsError

F64 = npt.NDArray[np.float64]

#: Upper bounds of the total number of working cycles of U0..U8 (U9: above 4e6).
U_BOUNDS: tuple[float, ...] = (1.6e4, 3.2e4, 6.3e4, 1.25e5, 2.5e5, 5.0e5, 1.0e6, 2.0e6, 4.0e6)
#: Upper bounds of kp of Q1..Q4.
Q_BOUNDS: tuple[float, ...] = (0.125, 0.25, 0.5, 1.0)
#: ISO 4301-1 Table 3: group number (1..8) by [Q index][U index].
GROUP_TABLE: tuple[tuple[int, ...], ...] = (
    (1, 1, 1, 2, 3, 4, 5, 6, 7, 8),
    (1, 1, 2, 3, 4, 5, 6, 7, 8, 8),
    (1, 2, 3, 4, 5, 6, 7, 8, 8, 8),
    (2, 3, 4, 5, 6, 7, 8, 8, 8, 8),
)


def spectrum_factor(load_ratio: npt.ArrayLike, counts: npt.ArrayLike | None = None) -> float:
    """Load spectrum factor kp = Σ (C_i/C_T)·(P_i/P_max)³.

    Args:
        load_ratio: P_i / P_max per load level (or per cycle), shape (k,), values ≥ 0.
        counts: C_i, cycles at each level, shape (k,); 1 each if None.

    Returns:
        kp (0 if there are no cycles).

    Raises:
        AnalyticsError: Negative ratios or counts, or shapes that differ.
    """
    r = np.asarray(load_ratio, dtype=np.float64).ravel()
    c = np.ones_like(r) if counts is None else np.asarray(counts, dtype=np.float64).ravel()
    if r.shape != c.shape:
        raise AnalyticsError(f"load_ratio {r.shape} and counts {c.shape} differ in shape")
    if np.any(r < 0) or np.any(c < 0):
        raise AnalyticsError("load ratios and cycle counts must be >= 0")
    ct = float(c.sum())
    return 0.0 if ct == 0 else float(np.sum(c / ct * r**3))


def spectrum_class(kp: float) -> int:
    """Spectrum class index 1..4 (Q1–Q4, L1–L4) of kp; kp above 1 is Q4 (overloaded)."""
    if kp < 0:
        raise AnalyticsError(f"kp must be >= 0, got {kp}")
    for i, b in enumerate(Q_BOUNDS):
        if kp <= b:
            return i + 1
    return 4


def utilisation_class(total_cycles: float) -> int:
    """Class of utilisation index 0..9 (U0–U9) of the total number of working cycles."""
    if total_cycles < 0:
        raise AnalyticsError(f"total_cycles must be >= 0, got {total_cycles}")
    for i, b in enumerate(U_BOUNDS):
        if total_cycles <= b:
            return i
    return 9


def group(q_class: int, u_class: int) -> int:
    """Group number 1..8 (A1–A8) from ISO 4301-1 Table 3."""
    if not (1 <= q_class <= 4 and 0 <= u_class <= 9):
        raise AnalyticsError(f"need Q1..Q4 and U0..U9, got Q{q_class}, U{u_class}")
    return GROUP_TABLE[q_class - 1][u_class]


@dataclass(frozen=True)
class Classification:
    """Observed and projected classification.

    Attributes:
        cycles: Working cycles observed C.
        kp: Observed load spectrum factor.
        q_class: Q1..Q4 of kp.
        projected_cycles: C projected to the design life at the observed rate.
        u_class: U0..U9 of the projected cycles.
        group: A1..A8 of (q_class, u_class).
        design_group: The design group from the machine description (or "").
    """

    cycles: int
    kp: float
    q_class: int
    projected_cycles: float
    u_class: int
    group: int
    design_group: str

    @property
    def label(self) -> str:
        """E.g. ``"A5 (Q2/L2, U5)"``."""
        return f"A{self.group} (Q{self.q_class}/L{self.q_class}, U{self.u_class})"


def classify(load_ratios: npt.ArrayLike, observed_days: float, design_life_years: float,
             design_group: str = "") -> Classification:
    """Classify from the load ratio of each working cycle observed.

    Args:
        load_ratios: P_i/P_max per working cycle, shape (C,).
        observed_days: Calendar days the observation covers [d], > 0.
        design_life_years: Design life to project to [years].
        design_group: Design group label, reported alongside.

    Returns:
        The classification, with C projected linearly to the design life.
    """
    r = np.asarray(load_ratios, dtype=np.float64).ravel()
    if not observed_days > 0:
        raise AnalyticsError(f"observed_days must be > 0, got {observed_days}")
    kp = spectrum_factor(r)
    qc = spectrum_class(kp)
    proj = r.size * design_life_years * 365.25 / observed_days
    uc = utilisation_class(proj)
    return Classification(int(r.size), kp, qc, float(proj), uc, group(qc, uc), design_group)


@dataclass(frozen=True)
class DutyRecord:
    """ISO 12482 used design working period, recording method a (automatic recorder).

    Attributes:
        cycles: Σ C_i, working cycles recorded.
        equivalent_cycles: S = Σ C_i·(P_i/P_max)³, full-load equivalent cycles used.
        design_cycles: C_T of the design.
        design_kp: kp of the design.
        design_equivalent: C_T·kp, the full-load equivalent cycles of the design working period.
        used_fraction: S / (C_T·kp).
        formula: The formula as text, for the report.
        prior_equivalent: The part of S recorded before this record (carried in).
    """

    cycles: int
    equivalent_cycles: float
    design_cycles: float
    design_kp: float
    design_equivalent: float
    used_fraction: float
    formula: str = "S = Σ C_i·(P_i/P_max)³ ;  used = S / (C_T·kp)"
    prior_equivalent: float = 0.0


def duty_record(load_ratios: npt.ArrayLike, design_cycles: float, design_kp: float,
                prior_equivalent: float = 0.0) -> DutyRecord:
    """Used design working period per ISO 12482 (method a).

    Args:
        load_ratios: P_i/P_max of each recorded working cycle, shape (C,).
        design_cycles: C_T, total working cycles of the design classification.
        design_kp: kp of the design classification.
        prior_equivalent: Full-load equivalent cycles used before this record.

    Returns:
        The record with formula and inputs.
    """
    r = np.asarray(load_ratios, dtype=np.float64).ravel()
    if not (design_cycles > 0 and 0 < design_kp <= 1):
        raise AnalyticsError(f"need design_cycles > 0 and 0 < design_kp <= 1, got "
                             f"{design_cycles}, {design_kp}")
    s = prior_equivalent + float(np.sum(r**3))
    de = design_cycles * design_kp
    return DutyRecord(int(r.size), s, design_cycles, design_kp, de, s / de,
                      prior_equivalent=prior_equivalent)
