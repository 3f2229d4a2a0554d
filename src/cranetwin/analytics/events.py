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

from cranetwin.analytics.history import LoadHistory
from cranetwin.analytics.runs import Run, RunTracker
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
            above which a load is a shock [1/s].
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
        self._relief_f = relief_force_n(machine)
        self._relief_p = machine.hydraulics.relief_pressure_pa if machine.hydraulics else None
        self._max_rated = float(max(machine.rated_load.payload_kg))
        self._slew = next((i for i, j in enumerate(machine.joints) if j.kind == "revolute"
                           and abs(j.axis[2]) > 0.99), None)
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

    def _payload_event(self, r: Run) -> Event:
        ratio = float(r.vmax[0])
        return Event(
            "payload_above_rating", r.t_start, r.t_end, _severity(ratio, self.cfg.critical_ratio),
            "load", float(r.vmax[1]), self._max_rated, "kg",
            {"payload_ratio": ratio, "reach_m": float(r.at_peak[2]), "duration_s": r.duration_s,
             "t_peak": r.t_peak})

    def _overspeed_event(self, r: Run) -> Event:
        assert self._slew is not None
        j = self.machine.joints[self._slew]
        ratio = float(r.vmax[0] / j.velocity_limit)
        return Event(
            "slew_overspeed", r.t_start, r.t_end, _severity(ratio, self.cfg.critical_ratio),
            j.name, float(r.vmax[0]), j.velocity_limit, "rad/s",
            {"speed_ratio": ratio, "duration_s": r.duration_s, "t_peak": r.t_peak})

    def _pressure_event(self, name: str, side: str, r: Run) -> Event:
        relief = float(self._relief_p or 1.0)
        ratio = float(r.vmax[0] / relief)
        return Event("over_pressure", r.t_start, r.t_end,
                     _severity(ratio, self.cfg.critical_ratio), f"{name}:{side}",
                     float(r.vmax[0]), relief, "Pa",
                     {"pressure_ratio": ratio, "duration_s": r.duration_s, "t_peak": r.t_peak})

    def _shock_event(self, i: int, r: Run) -> Event:
        lim = self.cfg.shock_rate_per_s * float(self._relief_f[i])
        ratio = float(r.vmax[0] / lim)
        return Event("shock_load", r.t_start, r.t_end, _severity(ratio, 2.0),
                     self.machine.cylinders[i].name, float(r.vmax[0]), lim, "N/s",
                     {"rate_ratio": ratio, "force_max_n": float(r.vmax[1]),
                      "force_min_n": float(r.vmin[1]), "t_peak": r.t_peak})

    def _feed(self, key: str, t: F64, mask: npt.NDArray[np.bool_],
              vals: Sequence[F64]) -> None:
        tracker, conv = self._trackers[key]
        self.events.extend(conv(r) for r in tracker.feed(t, mask, vals))

    # -- detectors ------------------------------------------------------------------------------
    def _run_events(self, h: LoadHistory) -> None:
        c = self.cfg
        rated = self.machine.rated_load.payload_at(h.reach_m)
        ratio = h.payload_kg / rated
        loaded = h.payload_kg >= c.min_payload_kg
        self._feed("overload", h.t_s, loaded & (ratio > c.overload_ratio),
                   (ratio, h.payload_kg, h.reach_m, rated))
        pr = h.payload_kg / self._max_rated
        self._feed("payload", h.t_s, pr > 1.0, (pr, h.payload_kg, h.reach_m))
        if self._slew is not None:
            w = np.abs(h.qd[:, self._slew])
            lim = self.machine.joints[self._slew].velocity_limit * (1 + c.overspeed_tolerance)
            self._feed("overspeed", h.t_s, w > lim, (w,))
        if h.p_a is not None and h.p_b is not None and self._relief_p is not None:
            lim = self._relief_p * (1 + c.pressure_tolerance)
            for i in range(len(self.machine.cylinders)):
                for side, p in (("A", h.p_a[:, i]), ("B", h.p_b[:, i])):
                    self._feed(f"p:{i}:{side}", h.t_s, p > lim, (p,))

    def _overlap_events(self, t: F64, rod_s: F64 | None, rod_v: F64 | None, f: F64,
                        k0: int) -> None:
        """End-stop impacts and shock loads, which look back in time. Arrays are the carried
        tail followed by the new chunk; samples from index ``k0`` on are new."""
        c = self.cfg
        if rod_s is not None and rod_v is not None:
            for i, cyl in enumerate(self.machine.cylinders):
                s, v = rod_s[:, i], rod_v[:, i]
                lo, hi = s <= c.end_zone_m, s >= cyl.stroke_m - c.end_zone_m
                for zone, end, sign in ((lo, 0.0, -1.0), (hi, 1.0, 1.0)):
                    entry = np.flatnonzero(zone[1:] & ~zone[:-1]) + 1
                    for e in entry[entry >= k0].tolist():
                        w0 = int(np.searchsorted(t, t[e] - c.end_stop_window_s))
                        toward = float(np.max(sign * v[w0:e + 1]))
                        ratio = toward / float(self._speed[i])
                        if ratio > c.end_stop_speed_fraction:
                            self.events.append(Event(
                                "end_stop_impact", float(t[e]), float(t[e]),
                                _severity(ratio, 2 * c.end_stop_speed_fraction), cyl.name,
                                toward, float(c.end_stop_speed_fraction * self._speed[i]),
                                "m/s", {"speed_ratio_to_nominal": ratio, "rod_s_m": float(s[e]),
                                        "end_extended": end, "force_n": float(f[e, i])}))
        n = t.shape[0]
        if n < 2:
            return
        dt = float(np.median(np.diff(t[: min(n, 100)])))
        lag = max(int(round(c.shock_window_s / dt)), 1)
        if n <= lag:
            return
        first = max(k0, lag)
        tt = t[first:]
        rate = np.abs(f[first:] - f[first - lag:n - lag]) / (tt - t[first - lag:n - lag])[:, None]
        for i in range(len(self.machine.cylinders)):
            lim = c.shock_rate_per_s * float(self._relief_f[i])
            self._feed(f"shock:{i}", tt, rate[:, i] > lim,
                       (rate[:, i], f[first:, i]))

    # -- public ---------------------------------------------------------------------------------
    def update(self, h: LoadHistory) -> None:
        """Fold the next chunk; new events are appended to :attr:`events`."""
        if h.n == 0:
            return
        self._run_events(h)
        if self._tail is None:
            t, rs, rv, f, k0 = h.t_s, h.rod_s, h.rod_v, h.cyl_force, 0
        else:
            tt, trs, trv, tf = self._tail
            k0 = tt.shape[0]
            t = np.concatenate([tt, h.t_s])
            rs = None if trs is None or h.rod_s is None else np.concatenate([trs, h.rod_s])
            rv = None if trv is None or h.rod_v is None else np.concatenate([trv, h.rod_v])
            f = np.concatenate([tf, h.cyl_force])
        self._overlap_events(t, rs, rv, f, k0)
        dt = float(np.median(np.diff(t[: min(t.shape[0], 100)]))) if t.shape[0] > 1 else 1.0
        keep = int(np.ceil(max(self.cfg.end_stop_window_s, self.cfg.shock_window_s)
                           / max(dt, 1e-6))) + 2
        cut = slice(max(t.shape[0] - keep, 0), None)
        self._tail = (t[cut].copy(), None if rs is None else rs[cut].copy(),
                      None if rv is None else rv[cut].copy(), f[cut].copy())

    def all_events(self) -> list[Event]:
        """Events so far, including runs still open at the end of the record, by start time."""
        ev = list(self.events)
        for tracker, conv in self._trackers.values():
            ev.extend(conv(r) for r in tracker.flush())
        return sorted(ev, key=lambda e: (e.t_start, e.kind, e.component))
