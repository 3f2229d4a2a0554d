"""Misuse and load events: overload, payload above rating, end-stop impacts, over-pressure,
slewing overspeed, shock loads.

:class:`EventDetector` folds a history chunk by chunk (conditions spanning chunks are carried
over by :class:`~cranetwin.analytics.runs.RunTracker`; instants that need the past, such as the
speed before an end-stop entry or a force rate, use an overlap of the last samples). Each
:class:`Event` carries its time, severity and the evidence values that triggered it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial

import numpy as np
import numpy.typing as npt

from cranetwin.analytics.history import LoadHistory, median_step
from cranetwin.analytics.runs import Run, RunTracker, Segments, concat_segments, segments
from cranetwin.errors import AnalyticsError
from cranetwin.model import Machine

F64 = npt.NDArray[np.float64]
G = 9.81

KINDS = ("overload", "payload_above_rating", "end_stop_impact", "over_pressure",
         "slew_overspeed", "shock_load")


@dataclass(frozen=True)
class Event:
    """One detected event.

    Attributes:
        kind: One of :data:`KINDS`.
        t_start: Start [s, timebase of the history].
        t_end: End [s] (= t_start for instantaneous events).
        severity: ``"warning"`` or ``"critical"``.
        component: The cylinder, joint or ``"load"`` concerned.
        value: The peak value of the triggering quantity (in ``unit``).
        limit: The limit it was compared with (in ``unit``).
        unit: Unit of value and limit.
        evidence: Further values at the peak, name → value.
    """

    kind: str
    t_start: float
    t_end: float
    severity: str
    component: str
    value: float
    limit: float
    unit: str
    evidence: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class EventConfig:
    """Thresholds of the event detectors (defaults documented in docs/ANALYTICS.md).

    Attributes:
        min_payload_kg: Ignore overload checks below this payload [kg].
        overload_ratio: Load moment / rated moment above which a lift is an overload.
        critical_ratio: Ratio (of any limit) above which an event is critical.
        overload_min_s: Minimum duration of an overload or payload event [s].
        end_zone_m: Distance from a stroke end that counts as "in the end stop" [m].
        end_stop_speed_fraction: Entry speed, as a fraction of the cylinder's nominal speed,
            above which an end-stop entry is an impact.
        end_stop_window_s: Time before the entry over which the speed is taken [s].
        pressure_tolerance: Pressure above relief·(1 + tolerance) is over-pressure.
        pressure_min_s: Minimum duration of over-pressure [s].
        overspeed_tolerance: Slewing speed above velocity_limit·(1 + tolerance) is overspeed.
        overspeed_min_s: Minimum duration of overspeed [s].
        shock_rate_per_s: Force rate, as a fraction of the cylinder's relief force per second,
            above which a load is a shock [1/s], for cylinders without their own
            ``shock_rate_n_per_s`` in the machine file.
        shock_window_s: Time step of the force-rate difference [s].
        max_gap_s: A gap in the data longer than this ends any condition [s].
    """

    min_payload_kg: float = 20.0
    overload_ratio: float = 1.0
    critical_ratio: float = 1.1
    overload_min_s: float = 0.5
    end_zone_m: float = 0.005
    end_stop_speed_fraction: float = 0.4
    end_stop_window_s: float = 0.2
    pressure_tolerance: float = 0.03
    pressure_min_s: float = 0.02
    overspeed_tolerance: float = 0.05
    overspeed_min_s: float = 0.2
    shock_rate_per_s: float = 15.0
    shock_window_s: float = 0.05
    max_gap_s: float = 1.0


Arrays = tuple[F64, "F64 | None", "F64 | None", F64]


@dataclass
class EventPart:
    """Events of one chunk computed from the chunk alone, folded in order by
    :meth:`EventDetector.apply` (exactly what :meth:`EventDetector.update` does).

    Attributes:
        runs: Raw stretches of every per-sample condition (tracker key → segments).
        late_end_stops: End-stop impacts whose look-back lies inside the chunk.
        shock: Raw stretches of the shock condition from the samples that have ``lag``
            predecessors in the chunk.
        lag: Samples of the force-rate difference.
        head: (t, rod_s, rod_v, force) of the first look-back samples.
        tail: The same of the last look-back samples.
        t_first: First sample time [s].
        t_last: Last sample time [s].
        n: Samples in the chunk.
    """

    runs: dict[str, Segments | None]
    late_end_stops: list[Event]
    shock: dict[str, Segments | None]
    lag: int
    head: Arrays
    tail: Arrays
    t_first: float
    t_last: float
    n: int


def load_force(machine: Machine, h: LoadHistory, end_zone_m: float = 0.005) -> F64:
    """The axial force each cylinder carries [N], shape (n, n_cyl): the pressures' force
    ``h.cyl_force``, and where the rod is within ``end_zone_m`` of a stroke end the
    inverse-dynamics load ``h.cyl_load`` (the stop takes what the oil does not). Without
    ``cyl_load`` or rod positions, ``cyl_force``. What shock loads and the end-stop evidence
    are taken from, in every chunk and every look-back alike."""
    if h.cyl_load is None or h.rod_s is None:
        return h.cyl_force
    stroke = np.array([c.stroke_m for c in machine.cylinders])
    at_end = (h.rod_s <= end_zone_m) | (h.rod_s >= stroke - end_zone_m)
    return np.where(at_end, h.cyl_load, h.cyl_force)


def force_rate(t: F64, f: F64, lag: int, first: int, stop: int) -> F64:
    """|f(t_k) − f(t_{k−lag})| / (t_k − t_{k−lag}) for k in [first, stop) (first ≥ lag): the
    rate of change of each force over ``lag`` samples [N/s], shape (stop − first, n_cyl). The
    shock detector's one formula, for every chunk and every look-back across chunks."""
    return (np.abs(f[first:stop] - f[first - lag:stop - lag])
            / (t[first:stop] - t[first - lag:stop - lag])[:, None])


def nominal_speed_mps(machine: Machine) -> F64:
    """Nominal rod speed of each cylinder at full valve opening [m/s], shape (n_cyl,).

    ``Qn·U_max·sqrt(p_supply/2) / A1`` (half the supply pressure across the metering edge);
    0.1 m/s for a cylinder without a valve description.
    """
    out = np.full(len(machine.cylinders), 0.1)
    if machine.hydraulics is not None:
        for i, c in enumerate(machine.cylinders):
            if c.valve is not None:
                q = c.valve.flow_gain * c.valve.max_voltage_v * np.sqrt(
                    machine.hydraulics.supply_pressure_pa / 2)
                out[i] = q / c.area_a_m2
    return out


def relief_force_n(machine: Machine) -> F64:
    """Push force at relief pressure on the piston side, per cylinder [N], shape (n_cyl,)."""
    p = machine.hydraulics.relief_pressure_pa if machine.hydraulics else 20e6
    return np.array([p * c.area_a_m2 for c in machine.cylinders])


def shock_limits_n_per_s(machine: Machine, rate_per_s: float = 15.0) -> F64:
    """Force rate above which a cylinder's load is a shock, per cylinder [N/s], shape
    (n_cyl,): the machine file's ``shock_rate_n_per_s``, else ``rate_per_s`` × the push force
    at relief pressure (PATU 655: 2.1 MN/s lift and jib, 0.53 MN/s extension)."""
    relief = relief_force_n(machine)
    return np.array([c.shock_rate_n_per_s if c.shock_rate_n_per_s is not None
                     else rate_per_s * float(relief[i])
                     for i, c in enumerate(machine.cylinders)])


def _severity(ratio: float, critical: float) -> str:
    return "critical" if ratio >= critical else "warning"


Converter = Callable[[Run], Event]


class EventDetector:
    """Incremental event detection over consecutive :class:`LoadHistory` chunks."""

    def __init__(self, machine: Machine, config: EventConfig | None = None) -> None:
        self.machine = machine
        self.cfg = config or EventConfig()
        c = self.cfg
        self._speed = nominal_speed_mps(machine)
        self._shock_lim = shock_limits_n_per_s(machine, c.shock_rate_per_s)
        self._relief_p = machine.hydraulics.relief_pressure_pa if machine.hydraulics else None
        rl = machine.rated_load
        self._max_rated = float(max(rl.payload_kg)) if rl is not None else None
        self._slew = next((i for i, j in enumerate(machine.joints) if j.kind == "revolute"
                           and abs(j.axis[2]) > 0.99), None)
        self._slew_limit = (None if self._slew is None
                            else machine.joints[self._slew].velocity_limit)
        self._trackers: dict[str, tuple[RunTracker, Converter]] = {
            "overload": (RunTracker(c.overload_min_s, 0.0, c.max_gap_s), self._overload_event),
            "payload": (RunTracker(c.overload_min_s, 0.0, c.max_gap_s), self._payload_event),
            "overspeed": (RunTracker(c.overspeed_min_s, 0.0, c.max_gap_s), self._overspeed_event),
        }
        for i, cyl in enumerate(machine.cylinders):
            for side in "AB":
                self._trackers[f"p:{i}:{side}"] = (
                    RunTracker(c.pressure_min_s, 0.0, c.max_gap_s),
                    partial(self._pressure_event, cyl.name, side))
            self._trackers[f"shock:{i}"] = (RunTracker(0.0, 0.5, c.max_gap_s),
                                            partial(self._shock_event, i))
        self._tail: tuple[F64, F64 | None, F64 | None, F64] | None = None
        self.events: list[Event] = []

    # -- run -> event ---------------------------------------------------------------------------
    def _overload_event(self, r: Run) -> Event:
        ratio, payload, reach, rated = r.at_peak
        return Event(
            "overload", r.t_start, r.t_end, _severity(ratio, self.cfg.critical_ratio), "load",
            float(ratio * G * rated * reach), float(G * rated * reach), "N*m",
            {"moment_ratio": float(ratio), "payload_kg": float(payload),
             "reach_m": float(reach), "rated_payload_kg": float(rated),
             "duration_s": r.duration_s})

    def unchecked(self) -> list[str]:
        """Event kinds this machine description cannot check, each with what is unknown."""
        out = []
        if self._max_rated is None:
            out.append("overload and payload above rating: not checked, rated-load chart "
                       "unknown")
        if self._slew is not None and self._slew_limit is None:
            name = self.machine.joints[self._slew].name
            out.append(f"slew overspeed: not checked, velocity limit of joint {name!r} unknown")
        return out

    def _payload_event(self, r: Run) -> Event:
        ratio = float(r.vmax[0])
        assert self._max_rated is not None
        return Event(
            "payload_above_rating", r.t_start, r.t_end, _severity(ratio, self.cfg.critical_ratio),
            "load", float(r.vmax[1]), self._max_rated, "kg",
            {"payload_ratio": ratio, "reach_m": float(r.at_peak[2]), "duration_s": r.duration_s,
             "t_peak": r.t_peak})

    def _overspeed_event(self, r: Run) -> Event:
        assert self._slew is not None
        j = self.machine.joints[self._slew]
        assert self._slew_limit is not None
        ratio = float(r.vmax[0] / self._slew_limit)
        return Event(
            "slew_overspeed", r.t_start, r.t_end, _severity(ratio, self.cfg.critical_ratio),
            j.name, float(r.vmax[0]), self._slew_limit, "rad/s",
            {"speed_ratio": ratio, "duration_s": r.duration_s, "t_peak": r.t_peak})

    def _pressure_event(self, name: str, side: str, r: Run) -> Event:
        relief = float(self._relief_p or 1.0)
        ratio = float(r.vmax[0] / relief)
        return Event("over_pressure", r.t_start, r.t_end,
                     _severity(ratio, self.cfg.critical_ratio), f"{name}:{side}",
                     float(r.vmax[0]), relief, "Pa",
                     {"pressure_ratio": ratio, "duration_s": r.duration_s, "t_peak": r.t_peak})

    def _shock_event(self, i: int, r: Run) -> Event:
        lim = float(self._shock_lim[i])
        ratio = float(r.vmax[0] / lim)
        return Event("shock_load", r.t_start, r.t_end, _severity(ratio, 2.0),
                     self.machine.cylinders[i].name, float(r.vmax[0]), lim, "N/s",
                     {"rate_ratio": ratio, "force_max_n": float(r.vmax[1]),
                      "force_min_n": float(r.vmin[1]), "t_peak": r.t_peak})

    def _feed(self, key: str, t: F64, mask: npt.NDArray[np.bool_],
              vals: Sequence[F64]) -> None:
        tracker, conv = self._trackers[key]
        self.events.extend(conv(r) for r in tracker.feed(t, mask, vals))

    def _feed_segments(self, key: str, seg: Segments | None) -> None:
        tracker, conv = self._trackers[key]
        self.events.extend(conv(r) for r in tracker.feed_segments(seg))

    # -- detectors ------------------------------------------------------------------------------
    def _run_segments(self, h: LoadHistory) -> dict[str, Segments | None]:
        """Raw stretches of every per-sample condition of a chunk (no look-back needed)."""
        c = self.cfg
        g = c.max_gap_s
        out: dict[str, Segments | None] = {}
        rl = self.machine.rated_load
        if rl is not None and self._max_rated is not None:  # unknown chart: not checked
            rated = rl.payload_at(h.reach_m)
            ratio = h.payload_kg / rated
            loaded = h.payload_kg >= c.min_payload_kg
            out["overload"] = segments(h.t_s, loaded & (ratio > c.overload_ratio),
                                       (ratio, h.payload_kg, h.reach_m, rated), g)
            pr = h.payload_kg / self._max_rated
            out["payload"] = segments(h.t_s, pr > 1.0, (pr, h.payload_kg, h.reach_m), g)
        if self._slew is not None and self._slew_limit is not None:  # unknown: not checked
            w = np.abs(h.qd[:, self._slew])
            lim = self._slew_limit * (1 + c.overspeed_tolerance)
            out["overspeed"] = segments(h.t_s, w > lim, (w,), g)
        if h.p_a is not None and h.p_b is not None and self._relief_p is not None:
            lim = self._relief_p * (1 + c.pressure_tolerance)
            for i in range(len(self.machine.cylinders)):
                for side, p in (("A", h.p_a[:, i]), ("B", h.p_b[:, i])):
                    out[f"p:{i}:{side}"] = segments(h.t_s, p > lim, (p,), g)
        return out

    def _end_stops(self, t: F64, rod_s: F64 | None, rod_v: F64 | None, f: F64, e_lo: int,
                   e_hi: int) -> list[Event]:
        """End-stop impacts at entries with index in [e_lo, e_hi) of the arrays (which may
        start with a carried tail: the look-back reaches into it)."""
        c = self.cfg
        out: list[Event] = []
        if rod_s is None or rod_v is None or e_hi <= max(e_lo, 1):
            return out
        lo_all = rod_s <= c.end_zone_m  # every cylinder at once: most chunks have no entry
        hi_all = rod_s >= np.array([cyl.stroke_m for cyl in self.machine.cylinders]) \
            - c.end_zone_m
        ent_lo = lo_all[1:] & ~lo_all[:-1]
        ent_hi = hi_all[1:] & ~hi_all[:-1]
        if not (ent_lo.any() or ent_hi.any()):
            return out
        for i, cyl in enumerate(self.machine.cylinders):
            s, v = rod_s[:, i], rod_v[:, i]
            for ent, end, sign in ((ent_lo[:, i], 0.0, -1.0), (ent_hi[:, i], 1.0, 1.0)):
                entry = np.flatnonzero(ent) + 1
                for e in entry[(entry >= e_lo) & (entry < e_hi)].tolist():
                    w0 = int(np.searchsorted(t, t[e] - c.end_stop_window_s))
                    toward = float(np.max(sign * v[w0:e + 1]))
                    ratio = toward / float(self._speed[i])
                    if ratio > c.end_stop_speed_fraction:
                        out.append(Event(
                            "end_stop_impact", float(t[e]), float(t[e]),
                            _severity(ratio, 2 * c.end_stop_speed_fraction), cyl.name,
                            toward, float(c.end_stop_speed_fraction * self._speed[i]),
                            "m/s", {"speed_ratio_to_nominal": ratio, "rod_s_m": float(s[e]),
                                    "end_extended": end, "force_n": float(f[e, i])}))
        return out

    def _shock_segments(self, t: F64, f: F64, lag: int, first: int,
                        stop: int) -> dict[str, Segments | None]:
        """Raw stretches of the shock condition at samples [first, stop) (first ≥ lag)."""
        out: dict[str, Segments | None] = {}
        if stop <= first:
            return out
        c = self.cfg
        tt = t[first:stop]
        rate = force_rate(t, f, lag, first, stop)
        for i in range(len(self.machine.cylinders)):
            lim = float(self._shock_lim[i])
            out[f"shock:{i}"] = segments(tt, rate[:, i] > lim, (rate[:, i], f[first:stop, i]),
                                         c.max_gap_s)
        return out

    def _keep(self, dt: float) -> int:
        """Samples of look-back carried between chunks."""
        return int(np.ceil(max(self.cfg.end_stop_window_s, self.cfg.shock_window_s)
                           / max(dt, 1e-6))) + 2

    def _lag(self, dt: float) -> int:
        return max(int(round(self.cfg.shock_window_s / dt)), 1)

    # -- public ---------------------------------------------------------------------------------
    def part(self, h: LoadHistory) -> EventPart | None:
        """What :meth:`apply` needs of one chunk, computed from the chunk alone (to store per
        window and merge later); None for an empty chunk.

        Look-back detectors are evaluated here only where the chunk's own samples suffice
        (end-stop entries from ``head`` samples on, force rates from ``lag`` on); the first
        samples (``head``) are kept and re-evaluated by :meth:`apply` with the previous chunk's
        tail. Exact for a constant sample period (the twin's grid)."""
        if h.n == 0:
            return None
        t, f = h.t_s, load_force(self.machine, h, self.cfg.end_zone_m)  # one force for both
        dt = median_step(t[:100]) if t.shape[0] > 1 else 1.0
        keep, lag = self._keep(dt), self._lag(dt)
        n = t.shape[0]
        hd = min(keep, n)
        late = self._end_stops(t, h.rod_s, h.rod_v, f, hd, n)
        shock = self._shock_segments(t, f, lag, min(max(lag, hd), n), n) if n > lag else {}

        def cut(a: F64 | None, sl: slice) -> F64 | None:
            return None if a is None else a[sl].copy()
        head, tail = slice(0, hd), slice(max(n - keep, 0), None)
        return EventPart(
            runs=self._run_segments(h), late_end_stops=late, shock=shock, lag=lag,
            head=(t[head].copy(), cut(h.rod_s, head), cut(h.rod_v, head), f[head].copy()),
            tail=(t[tail].copy(), cut(h.rod_s, tail), cut(h.rod_v, tail), f[tail].copy()),
            t_first=float(t[0]), t_last=float(t[-1]), n=n)

    def apply(self, p: EventPart | None) -> None:
        """Fold the part of the next chunk (see :meth:`part`); events found are appended to
        :attr:`events`."""
        if p is None:
            return
        for key, seg in p.runs.items():
            self._feed_segments(key, seg)
        ht, hrs, hrv, hf = p.head
        if self._tail is None:
            t, rs, rv, f, k0 = ht, hrs, hrv, hf, 0
        else:
            tt, trs, trv, tf = self._tail
            k0 = tt.shape[0]
            t = np.concatenate([tt, ht])
            rs = None if trs is None or hrs is None else np.concatenate([trs, hrs])
            rv = None if trv is None or hrv is None else np.concatenate([trv, hrv])
            f = np.concatenate([tf, hf])
        hd = ht.shape[0]
        self.events.extend(self._end_stops(t, rs, rv, f, k0, k0 + hd))
        self.events.extend(p.late_end_stops)
        # force rates of the head samples the part could not compute alone (the lag from the
        # carried samples too, as update() did, when the chunk alone is one sample)
        lag = p.lag
        if p.n < 2 and t.shape[0] > 1:
            lag = self._lag(median_step(t[:100]))
        first = max(k0, lag)
        stop = k0 + min(max(lag, hd), p.n) if p.n > lag else k0 + hd
        head_shock = self._shock_segments(t, f, lag, first, stop) if t.shape[0] > lag else {}
        for i in range(len(self.machine.cylinders)):
            key = f"shock:{i}"
            self._feed_segments(key, head_shock.get(key))
            self._feed_segments(key, p.shock.get(key))
        # carried look-back: the last `keep` samples of (tail, chunk)
        pt, prs, prv, pf = p.tail
        if self._tail is None:
            ct, crs, crv, cf = pt, prs, prv, pf
        elif p.n > pt.shape[0]:
            ct, crs, crv, cf = pt, prs, prv, pf
        else:  # the chunk is shorter than the look-back: keep some of the previous tail
            tt, trs, trv, tf = self._tail
            ct = np.concatenate([tt, pt])
            crs = None if trs is None or prs is None else np.concatenate([trs, prs])
            crv = None if trv is None or prv is None else np.concatenate([trv, prv])
            cf = np.concatenate([tf, pf])
        dt = median_step(ct[:100]) if ct.shape[0] > 1 else 1.0
        keep = self._keep(dt)
        sl = slice(max(ct.shape[0] - keep, 0), None)
        self._tail = (ct[sl].copy(), None if crs is None else crs[sl].copy(),
                      None if crv is None else crv[sl].copy(), cf[sl].copy())

    def _head_of_next(self, tail: Arrays, p: EventPart) -> tuple[list[Event],
                                                                 dict[str, Segments | None]]:
        """End-stop impacts and shock stretches of ``p``'s head samples, after ``tail``."""
        tt, trs, trv, tf = tail
        ht, hrs, hrv, hf = p.head
        k0 = tt.shape[0]
        t = np.concatenate([tt, ht])
        rs = None if trs is None or hrs is None else np.concatenate([trs, hrs])
        rv = None if trv is None or hrv is None else np.concatenate([trv, hrv])
        f = np.concatenate([tf, hf])
        hd = ht.shape[0]
        ends = self._end_stops(t, rs, rv, f, k0, k0 + hd)
        lag = p.lag
        first = max(k0, lag)
        stop = k0 + min(max(lag, hd), p.n) if p.n > lag else k0 + hd
        shock = self._shock_segments(t, f, lag, first, stop) if t.shape[0] > lag else {}
        return ends, shock

    def merge_parts(self, a: EventPart, b: EventPart) -> EventPart:
        """One part of chunk ``a`` followed by chunk ``b`` (folding it = folding both).

        Raises:
            AnalyticsError: A part is not longer than its look-back (keep such parts apart).
        """
        if not (a.n > a.head[0].shape[0] and b.n > b.tail[0].shape[0]):
            raise AnalyticsError("parts shorter than the look-back cannot be merged")
        g = self.cfg.max_gap_s
        ends, head_shock = self._head_of_next(a.tail, b)
        keys = dict.fromkeys([*a.runs, *b.runs])
        runs = {k: concat_segments(a.runs.get(k), b.runs.get(k), g) for k in keys}
        skeys = dict.fromkeys([*a.shock, *head_shock, *b.shock])
        shock = {k: concat_segments(concat_segments(a.shock.get(k), head_shock.get(k), g),
                                    b.shock.get(k), g) for k in skeys}
        return EventPart(runs, [*a.late_end_stops, *ends, *b.late_end_stops], shock, a.lag,
                         a.head, b.tail, a.t_first, b.t_last, a.n + b.n)

    def update(self, h: LoadHistory) -> None:
        """Fold the next chunk (``apply(part(h))``); new events are appended to
        :attr:`events`."""
        self.apply(self.part(h))

    def all_events(self) -> list[Event]:
        """Events so far, including runs still open at the end of the record, by start time."""
        ev = list(self.events)
        for tracker, conv in self._trackers.values():
            ev.extend(conv(r) for r in tracker.flush())
        return sorted(ev, key=lambda e: (e.t_start, e.kind, e.component))
