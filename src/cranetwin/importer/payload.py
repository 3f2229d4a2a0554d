"""A known payload as a time series — a column of the user's file named by the mapping's
``[payload]`` table (docs/IMPORT.md) — and the twin's payload estimate compared with it, lift
by lift.

The known payload is not a sensor channel: it is not stored with the samples. It rides along
with a file's samples (:attr:`cranetwin.importer.ImportedFile.payload_kg`); ``cranetwin
replay`` / ``report --recording`` / ``calibrate`` and
:func:`cranetwin.importer.replay.replay_table` feed it into the twin's inverse dynamics where
it is known (:mod:`cranetwin.twin.known_payload`; the estimate where it is NaN), or, with
``payload_column="compare"`` (``--payload-column compare``), put it next to the estimate and
report the estimate's error per lift.

A lift is a maximal stretch where the known payload is at least ``min_kg`` for at least
``min_duration_s``. Its error is the median estimate minus the median known payload over the
lift's middle half: the estimate's sliding window (2 s) straddles pick-up and set-down, so the
ends of a lift say how fast the estimate follows, not how right it is.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

MIN_LIFT_KG = 50.0
MIN_LIFT_S = 2.0


def payload_at(t_ns: I64, raw_t_ns: I64, raw_kg: F64, period_ns: int) -> F64:
    """The known payload [kg] at the sample times ``t_ns``: the value of the file's row
    nearest in time, if within half a period (else NaN) — the samples' period, or the rows'
    own median spacing where that is longer (a payload logged more slowly than the sensors,
    e.g. in an MDF channel group of its own).

    Args:
        t_ns: Sample times [ns since the epoch], shape (n,), increasing.
        raw_t_ns: The file's row times [ns], shape (m,) (rows of any order; NaT rows dropped
            by the caller).
        raw_kg: Payload of each row [kg], shape (m,); NaN = not known.
        period_ns: The samples' period [ns].
    """
    out = np.full(t_ns.shape, np.nan)
    if raw_t_ns.size == 0 or t_ns.size == 0:
        return out
    order = np.argsort(raw_t_ns, kind="stable")
    rt, rv = raw_t_ns[order], raw_kg[order]
    hi = np.clip(np.searchsorted(rt, t_ns), 0, rt.size - 1)
    lo = np.clip(hi - 1, 0, rt.size - 1)
    near = np.where(np.abs(rt[hi] - t_ns) <= np.abs(t_ns - rt[lo]), hi, lo)
    own = int(np.median(np.diff(rt))) if rt.size > 1 else 0
    ok = np.abs(rt[near] - t_ns) <= max(period_ns, own, 1) // 2
    out[ok] = rv[near[ok]]
    return out


def on_grid(t_s: F64, sample_t_s: F64, known_kg: F64,
            max_gap_s: float = float("inf")) -> F64:
    """The known payload at grid instants ``t_s`` [s]: linear between the two samples around
    an instant when both are known and at most ``max_gap_s`` apart (the replay's gap limit,
    5 sample periods by default there), the sample's value at a sample time, NaN elsewhere —
    as the twin's dynamics take it (:func:`cranetwin.twin.known_payload.at_instants`)."""
    from cranetwin.twin.known_payload import at_instants  # (reading a file needs no twin)

    if sample_t_s.size < 2:
        return np.full(t_s.shape, np.nan)
    return at_instants(t_s, sample_t_s, known_kg, max_gap_s)


@dataclass(frozen=True)
class LiftError:
    """The twin's payload estimate over one lift against the known payload.

    Attributes:
        t_start_s, t_end_s: The lift [s since the epoch].
        known_kg: Median known payload over the lift's middle half [kg].
        estimate_kg: Median estimate there [kg] (NaN: no estimate).
    """

    t_start_s: float
    t_end_s: float
    known_kg: float
    estimate_kg: float

    @property
    def error_kg(self) -> float:
        """Estimate − known [kg]."""
        return self.estimate_kg - self.known_kg

    @property
    def error_pct(self) -> float:
        """Error as a share of the known payload [%]."""
        return 100.0 * self.error_kg / self.known_kg

    def line(self) -> str:
        """E.g. ``lift 2026-01-01T00:00:09.000Z, 14.0 s: known 312.3 kg, estimate …``."""
        start = dt.datetime.fromtimestamp(self.t_start_s, dt.UTC).strftime(
            "%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"
        return (f"lift {start}, {self.t_end_s - self.t_start_s:.1f} s: known "
                f"{self.known_kg:.1f} kg, "
                f"estimate {self.estimate_kg:.1f} kg, error {self.error_kg:+.1f} kg "
                f"({self.error_pct:+.1f} %)")


def lift_errors(t_s: F64, known_kg: F64, estimate_kg: F64, min_kg: float = MIN_LIFT_KG,
                min_duration_s: float = MIN_LIFT_S) -> list[LiftError]:
    """The estimate's error per lift (module docstring).

    Args:
        t_s: Instants [s], shape (n,), increasing.
        known_kg: Known payload at them [kg], shape (n,); NaN = not known (ends a lift).
        estimate_kg: The twin's payload at them [kg], shape (n,).
        min_kg: Least known payload of a lift [kg].
        min_duration_s: Shortest lift [s].
    """
    on = np.zeros(t_s.size + 2, dtype=bool)
    with np.errstate(invalid="ignore"):
        on[1:-1] = known_kg >= min_kg
    edges = np.flatnonzero(np.diff(on.astype(np.int8)))
    out: list[LiftError] = []
    for a, b in zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True):
        if b - a < 2 or t_s[b - 1] - t_s[a] < min_duration_s:
            continue
        q = (b - a) // 4
        mid = slice(a + q, b - q)
        est = estimate_kg[mid]
        est = est[np.isfinite(est)]
        out.append(LiftError(float(t_s[a]), float(t_s[b - 1]),
                             float(np.median(known_kg[mid])),
                             float(np.median(est)) if est.size else float("nan")))
    return out


def summary_line(lifts: list[LiftError]) -> str:
    """One line over all lifts: count, mean and largest absolute error."""
    if not lifts:
        return "payload estimate vs known payload: no lift (known payload ≥ " \
               f"{MIN_LIFT_KG:g} kg for ≥ {MIN_LIFT_S:g} s)"
    err = np.array([x.error_kg for x in lifts])
    pct = np.array([x.error_pct for x in lifts])
    return (f"payload estimate vs known payload over {len(lifts)} lift(s): mean |error| "
            f"{np.nanmean(np.abs(err)):.1f} kg ({np.nanmean(np.abs(pct)):.1f} %), largest "
            f"{np.nanmax(np.abs(err)):.1f} kg")


__all__ = ["LiftError", "lift_errors", "on_grid", "payload_at", "summary_line"]
