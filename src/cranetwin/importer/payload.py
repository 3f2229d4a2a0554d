"""A known payload as a time series — a column of the user's file named by the mapping's
``[payload]`` table (docs/IMPORT.md) — and the twin's payload estimate compared with it, lift
by lift.

The known payload is not a sensor channel: it is not in the sample blocks. It rides along
with a file's samples (:attr:`cranetwin.importer.ImportedFile.payload_kg`), and ``cranetwin
import`` stores it next to them (:mod:`cranetwin.storage.payloads`, one run per stored block at
its sample times) for the replays of stored ranges; ``cranetwin replay`` / ``report
--recording`` / ``calibrate`` and
:func:`cranetwin.importer.replay.replay_table` feed it into the twin's inverse dynamics where
it is known (:mod:`cranetwin.twin.known_payload`; the estimate where it is NaN), or, with
``payload_column="compare"`` (``--payload-column compare``), put it next to the estimate and
report the estimate's error per lift.

A lift is a maximal stretch where the known payload is at least ``min_kg`` for at least
``min_duration_s``. Two figures of the twin's are compared with it:

* the gross estimate: the median per-instant estimate over the lift's middle half, minus the
  median known payload there (the estimate's sliding window straddles pick-up and set-down, so
  the ends of a lift say how fast the estimate follows, not how right it is);
* the net lift payload: the twin's own payload of the lift that overlaps the known one longest
  (:func:`cranetwin.twin.lifts.lift_payloads`: grab and release ramps left out, net of the
  empty reading next to the lift when that is an offset, with its σ) — what the twin reports
  for a lift elsewhere (the analytics' work-cycle payloads). A sensor's zero offset moves the
  gross figure and is taken off the net one.

A file's payload value is refused (with row and column, never clipped; the row's samples are
kept and the payload is not known there) when it is below zero, or above the largest accepted
payload (:func:`payload_limit_kg`), by more than the mapping's ``checks.range_tolerance`` share
of that payload (:class:`PayloadCheck`). A value below zero within the tolerance (a load cell's
zero offset at an empty hook) is read as 0 kg and counted in the import's report.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import numpy.typing as npt

from cranetwin.importer.readers import Refusal
from cranetwin.model import Machine

if TYPE_CHECKING:  # (reading a file needs no twin)
    from cranetwin.twin.lifts import Lift

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

MIN_LIFT_KG = 50.0
MIN_LIFT_S = 2.0
RATED_FACTOR = 3.0
"""Default largest accepted payload: this many times the machine's largest rated payload (a
reading no crane of that chart could hold: a logger's glitch, or the wrong unit)."""


def payload_limit_kg(machine: Machine, max_kg: float | None) -> float | None:
    """Largest accepted payload [kg]: the mapping's ``[payload] max`` (``max_kg``), else
    :data:`RATED_FACTOR` × the largest payload of the machine's rated-load chart, else None (no
    chart: no upper check)."""
    if max_kg is not None:
        return float(max_kg)
    if machine.rated_load is None:
        return None
    return RATED_FACTOR * float(max(machine.rated_load.payload_kg))


class Checked(NamedTuple):
    """A payload column after :meth:`PayloadCheck.apply`.

    Attributes:
        kg: Payload per row [kg], shape (n,); NaN = empty or refused; 0 where it was below zero
            within the tolerance.
        negative, high: The refusals (below zero beyond the tolerance; above the largest
            accepted), with row and column.
        zeroed: Values below zero within the tolerance, read as 0 kg.
    """

    kg: F64
    negative: list[Refusal]
    high: list[Refusal]
    zeroed: int


@dataclass(frozen=True)
class PayloadCheck:
    """The accepted range of a payload column: [−tolerance · max, max + tolerance · max] [kg],
    values below zero read as 0 kg (storage keeps no negative payload; without a max there is
    no upper bound and no tolerance below zero); values in the column's ``unit`` are ``scale``
    kg."""

    column: str
    unit: str
    scale: float
    max_kg: float | None
    tolerance: float = 0.0

    @property
    def negative_kind(self) -> str:
        """The report's kind of refusal for a negative payload."""
        if self.max_kg is None:
            return "negative payload"
        return (f"negative payload, beyond −{self.tolerance * self.max_kg:g} kg (the mapping's "
                "[checks] range_tolerance × the largest accepted payload: a load cell's zero "
                "offset within it is read as 0 kg)")

    @property
    def high_kind(self) -> str:
        """The report's kind of refusal for a payload above the max (or infinite)."""
        return ("infinite payload" if self.max_kg is None
                else f"payload above the largest accepted, {self.max_kg:g} kg")

    def apply(self, kg: F64, rows: I64, lines: I64 | None) -> Checked:
        """``kg`` with the refused values NaN and those below zero within the tolerance 0, and
        the refusals.

        Args:
            kg: Payload per row [kg], shape (n,); NaN = empty (not known, not refused).
            rows: 1-based data row numbers, shape (n,).
            lines: CSV line numbers, shape (n,), or None.
        """
        floor = 0.0 if self.max_kg is None else -self.tolerance * self.max_kg
        with np.errstate(invalid="ignore"):
            below = kg < 0.0
            neg = kg < floor
            high = np.isinf(kg) & ~neg
            if self.max_kg is not None:
                high |= kg > self.max_kg * (1.0 + self.tolerance)

        def refusals(mask: npt.NDArray[np.bool_], kind: str) -> list[Refusal]:
            return [Refusal(int(rows[i]), self.column,
                            f"{kg[i] / self.scale:g} {self.unit}: {kind}",
                            None if lines is None else int(lines[i]))
                    for i in np.flatnonzero(mask)]

        zeroed = below & ~neg
        out = np.where(neg | high, np.nan, np.where(zeroed, 0.0, kg))
        return Checked(out, refusals(neg, self.negative_kind), refusals(high, self.high_kind),
                       int(zeroed.sum()))


def payload_at(t_ns: I64, raw_t_ns: I64, raw_kg: F64, period_ns: int,
               own_ns: int | None = None) -> F64:
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
        own_ns: The rows' own median spacing [ns], when the caller passes a slice of the rows
            around ``t_ns`` (None: from ``raw_t_ns``).
    """
    out = np.full(t_ns.shape, np.nan)
    if raw_t_ns.size == 0 or t_ns.size == 0:
        return out
    order = np.argsort(raw_t_ns, kind="stable")
    rt, rv = raw_t_ns[order], raw_kg[order]
    hi = np.clip(np.searchsorted(rt, t_ns), 0, rt.size - 1)
    lo = np.clip(hi - 1, 0, rt.size - 1)
    near = np.where(np.abs(rt[hi] - t_ns) <= np.abs(t_ns - rt[lo]), hi, lo)
    own = own_ns if own_ns is not None else int(np.median(np.diff(rt))) if rt.size > 1 else 0
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
    """The twin's payload over one lift against the known payload.

    Attributes:
        t_start_s, t_end_s: The lift [s since the epoch].
        known_kg: Median known payload over the lift's middle half [kg].
        estimate_kg: Median (gross) estimate there [kg] (NaN: no estimate).
        net_kg: The twin's payload of the lift that overlaps this one longest, net of its
            empty reading (:attr:`cranetwin.twin.lifts.Lift.payload_kg`) [kg] (NaN: no lift of
            the twin's over this one, or not compared).
        net_std_kg: Its one-sigma uncertainty [kg] (NaN with ``net_kg``; inf: the twin's lift
            had no steady part).
        tare_kg: The empty reading taken off it [kg] (0: none; NaN with ``net_kg``).
    """

    t_start_s: float
    t_end_s: float
    known_kg: float
    estimate_kg: float
    net_kg: float = float("nan")
    net_std_kg: float = float("nan")
    tare_kg: float = float("nan")

    @property
    def error_kg(self) -> float:
        """Gross estimate − known [kg]."""
        return self.estimate_kg - self.known_kg

    @property
    def error_pct(self) -> float:
        """Gross error as a share of the known payload [%]."""
        return 100.0 * self.error_kg / self.known_kg

    @property
    def net_error_kg(self) -> float:
        """Net lift payload − known [kg]."""
        return self.net_kg - self.known_kg

    @property
    def net_error_pct(self) -> float:
        """Net error as a share of the known payload [%]."""
        return 100.0 * self.net_error_kg / self.known_kg

    def line(self) -> str:
        """E.g. ``lift 2026-01-01T00:00:09.000Z, 14.0 s: known 312.3 kg, estimate …`` — the
        gross estimate and its error, then (where the twin found the lift) the net lift
        payload ± σ, the empty reading taken off and its error."""
        start = dt.datetime.fromtimestamp(self.t_start_s, dt.UTC).strftime(
            "%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"
        out = (f"lift {start}, {self.t_end_s - self.t_start_s:.1f} s: known "
               f"{self.known_kg:.1f} kg, "
               f"estimate {self.estimate_kg:.1f} kg, error {self.error_kg:+.1f} kg "
               f"({self.error_pct:+.1f} %)")
        if np.isnan(self.tare_kg):  # no lift of the twin's over it (or not compared)
            return out
        if np.isnan(self.net_kg):
            return f"{out}; net: none (the twin's lift is too short for a steady part)"
        tare = "no tare" if self.tare_kg == 0.0 else f"tare {self.tare_kg:+.1f} kg"
        return (f"{out}; net {self.net_kg:.1f} ± {self.net_std_kg:.1f} kg ({tare}), error "
                f"{self.net_error_kg:+.1f} kg ({self.net_error_pct:+.1f} %)")


def lift_errors(t_s: F64, known_kg: F64, estimate_kg: F64, min_kg: float = MIN_LIFT_KG,
                min_duration_s: float = MIN_LIFT_S,
                twin_lifts: Sequence[Lift] | None = None) -> list[LiftError]:
    """The estimate's error per lift (module docstring).

    Args:
        t_s: Instants [s], shape (n,), increasing.
        known_kg: Known payload at them [kg], shape (n,); NaN = not known (ends a lift).
        estimate_kg: The twin's payload at them [kg], shape (n,).
        min_kg: Least known payload of a lift [kg].
        min_duration_s: Shortest lift [s].
        twin_lifts: The twin's lifts in the same estimate
            (:func:`cranetwin.twin.lifts.lift_payloads`), for the net figures; None: not
            compared (NaN).
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
        t0, t1 = float(t_s[a]), float(t_s[b - 1])
        gross = LiftError(t0, t1, float(np.median(known_kg[mid])),
                          float(np.median(est)) if est.size else float("nan"))
        twin = _overlapping(twin_lifts or (), t0, t1)
        out.append(gross if twin is None else
                   replace(gross, net_kg=twin.payload_kg, net_std_kg=twin.std_kg,
                           tare_kg=twin.tare_kg))
    return out


def _overlapping(lifts: Sequence[Lift], t0_s: float, t1_s: float) -> Lift | None:
    """The lift of ``lifts`` whose grab-to-release overlaps [t0_s, t1_s] longest (the first
    of equals), or None where none overlaps it."""
    best, most = None, 0.0
    for lf in lifts:
        over = min(lf.release_s, t1_s) - max(lf.grab_s, t0_s)
        if over > most:
            best, most = lf, over
    return best


def summary_line(lifts: list[LiftError]) -> str:
    """One line over all lifts: count, mean and largest absolute error of the gross estimate,
    and of the net lift payload where the twin found the lift (with how many of them lie
    within 2σ)."""
    if not lifts:
        return "payload estimate vs known payload: no lift (known payload ≥ " \
               f"{MIN_LIFT_KG:g} kg for ≥ {MIN_LIFT_S:g} s)"
    err = np.array([x.error_kg for x in lifts])
    pct = np.array([x.error_pct for x in lifts])
    out = (f"payload estimate vs known payload over {len(lifts)} lift(s): mean |error| "
           f"{np.nanmean(np.abs(err)):.1f} kg ({np.nanmean(np.abs(pct)):.1f} %), largest "
           f"{np.nanmax(np.abs(err)):.1f} kg")
    net = [x for x in lifts if not np.isnan(x.net_kg)]
    if not net:
        return out
    nerr = np.array([x.net_error_kg for x in net])
    npct = np.array([x.net_error_pct for x in net])
    within = sum(abs(x.net_error_kg) <= 2.0 * x.net_std_kg for x in net)
    found = "" if len(net) == len(lifts) else f" over the {len(net)} the twin found"
    return (f"{out}; net of the empty reading{found}: mean |error| "
            f"{np.mean(np.abs(nerr)):.1f} kg ({np.mean(np.abs(npct)):.1f} %), largest "
            f"{np.max(np.abs(nerr)):.1f} kg, {within} of {len(net)} within 2σ")


__all__ = ["LiftError", "PayloadCheck", "lift_errors", "on_grid", "payload_at",
           "payload_limit_kg", "summary_line"]
