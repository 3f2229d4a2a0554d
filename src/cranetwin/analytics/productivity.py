"""Work cycles (grab → lift → swing → release), payload moved, utilisation, idle vs working.

A work cycle is a run of "loaded" (payload ≥ ``grab_kg``) lasting at least ``min_loaded_s``;
dips shorter than ``merge_gap_s`` do not split it. Within it the tool must rise (``lift``) and
the crane must slew (``swing``) for the cycle to be complete. Its payload is the mean over the
run's steady instants (:attr:`LoadHistory.payload_steady`: a sliding-window estimate smears
grab and release into ramps, which a mean over the whole run takes in and reads low), or over
the whole run if none is steady; a cycle needs a load: a run whose payload is below
``grab_kg`` is no cycle. Working time: the machine is
working while any joint moves faster than ``moving_fraction`` of its velocity limit; pauses
shorter than ``min_idle_s`` count as working. Time is only counted while data arrive: a gap in the
timestamps longer than ``max_gap_s`` is "off" (neither working nor idle).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from cranetwin.analytics.history import LoadHistory
from cranetwin.analytics.runs import Run, RunTracker, Segments, concat_segments, segments
from cranetwin.model import Machine

F64 = npt.NDArray[np.float64]
DAY_S = 86400.0


@dataclass(frozen=True)
class ProductivityConfig:
    """Thresholds for work cycles and working time (see the module docstring)."""

    grab_kg: float = 50.0
    min_loaded_s: float = 2.0
    merge_gap_s: float = 1.0
    lift_m: float = 0.2
    lift_rad: float = 0.05
    swing_rad: float = 0.15
    moving_fraction: float = 0.03
    moving_speed_unknown_limit: float = 0.02
    min_idle_s: float = 30.0
    max_gap_s: float = 1.0


@dataclass(frozen=True)
class WorkCycle:
    """One detected work cycle.

    Attributes:
        t_grab: Time the load was picked up [s].
        t_release: Time the load was released [s].
        payload_kg: Mean payload while loaded [kg] (over the steady instants, see the module
            docstring).
        load_ratio: NaN when the machine has no rated-load chart (unknown). Mean of payload /
            rated payload at the current reach (P_i/P_max of
            ISO 4301-1 for this cycle), over the same instants.
        lift: Whether the load was lifted.
        swing: Whether the crane slewed while loaded.
        reach_max_m: Largest reach while loaded [m].
    """

    t_grab: float
    t_release: float
    payload_kg: float
    load_ratio: float
    lift: bool
    swing: bool
    reach_max_m: float

    @property
    def complete(self) -> bool:
        """grab → lift → swing → release all seen."""
        return self.lift and self.swing


@dataclass
class DayUsage:
    """Per-UTC-day accumulators [s, kg, count]."""

    recorded_s: float = 0.0
    working_s: float = 0.0
    cycles: int = 0
    payload_kg: float = 0.0


@dataclass
class ProductivityPart:
    """Productivity of one chunk computed from the chunk alone, to be folded in order by
    :meth:`ProductivityTracker.apply` (exactly what :meth:`ProductivityTracker.update` does).

    Attributes:
        t_first: First sample time [s].
        t_last: Last sample time [s].
        inner_recorded_s: Recorded time between the chunk's samples per UTC day (day number →
            s); the step from the previous chunk is added when folding.
        idle: Raw stretches of "not moving".
        loaded: Raw stretches of "loaded" with (payload, ratio, reach, slew angle, rise,
            steady, steady·payload, steady·ratio) (steady: 1 or 0).
        has_height: The history carried the height of the load point.
    """

    t_first: float
    t_last: float
    inner_recorded_s: dict[int, float]
    idle: Segments | None
    loaded: Segments | None
    has_height: bool


class ProductivityTracker:
    """Incremental work-cycle detection and time accounting."""

    def __init__(self, machine: Machine, config: ProductivityConfig | None = None) -> None:
        self.machine = machine
        self.cfg = config or ProductivityConfig()
        self._loaded = RunTracker(self.cfg.min_loaded_s, self.cfg.merge_gap_s,
                                  self.cfg.max_gap_s)
        self._idle = RunTracker(self.cfg.min_idle_s, 0.0, self.cfg.max_gap_s)
        # a joint moves above moving_fraction of its velocity limit; where that limit is
        # unknown, above moving_speed_unknown_limit [rad/s or m/s]
        self._moving = np.array([self.cfg.moving_speed_unknown_limit if j.velocity_limit is None
                                 else self.cfg.moving_fraction * j.velocity_limit
                                 for j in machine.joints])
        self._slew = next((i for i, j in enumerate(machine.joints) if j.kind == "revolute"
                           and abs(j.axis[2]) > 0.99), 0)
        self._lift_joint = 1 if machine.n_joints > 1 else 0
        self._last_t: float | None = None
        self.cycles: list[WorkCycle] = []
        self.days: dict[int, DayUsage] = {}
        self.recorded_s = 0.0
        self.idle_s = 0.0

    def day(self, t: float) -> DayUsage:
        """The accumulator of the UTC day containing time ``t`` [s]."""
        return self.days.setdefault(int(t // DAY_S), DayUsage())

    def _cycle(self, r: Run, has_height: bool) -> WorkCycle | None:
        # columns: payload, ratio, reach, slew angle, rise (height or lift angle), steady,
        # steady·payload, steady·ratio
        lift_tol = self.cfg.lift_m if has_height else self.cfg.lift_rad
        if r.vsum[5] > 0:
            payload, ratio = r.vsum[6] / r.vsum[5], r.vsum[7] / r.vsum[5]
        else:
            payload, ratio = r.mean[0], r.mean[1]
        if not payload >= self.cfg.grab_kg:
            return None
        wc = WorkCycle(r.t_start, r.t_end, float(payload), float(ratio),
                       bool(r.vmax[4] - r.first[4] > lift_tol),
                       bool(r.vmax[3] - r.vmin[3] > self.cfg.swing_rad), float(r.vmax[2]))
        d = self.day(r.t_start)
        d.cycles += 1
        d.payload_kg += wc.payload_kg
        return wc

    def _idle_run(self, r: Run) -> None:
        # an idle run [t_start, t_end]: credit it to the days it covers
        dur = r.duration_s
        self.idle_s += dur
        t0 = r.t_start
        while dur > 0:
            end_day = (np.floor(t0 / DAY_S) + 1) * DAY_S
            part = min(dur, end_day - t0)
            self.day(t0).working_s -= part
            t0, dur = end_day, dur - part

    def part(self, h: LoadHistory) -> ProductivityPart | None:
        """What :meth:`apply` needs of one chunk, computed from the chunk alone (to store per
        window and merge later); None for an empty chunk."""
        if h.n == 0:
            return None
        t = h.t_s
        dt = np.diff(t)
        dt[dt > self.cfg.max_gap_s] = 0.0
        inner: dict[int, float] = {}
        if dt.size:
            day = (t[1:] // DAY_S).astype(np.int64)
            d0, d1 = int(day[0]), int(day[-1])
            cut = np.searchsorted(t[1:], np.arange(d0 + 1, d1 + 1) * DAY_S)
            for dkey, part in zip(range(d0, d1 + 1), np.split(dt, cut), strict=True):
                inner[dkey] = float(part.sum())
        moving = np.abs(h.qd[:, 0]) > self._moving[0]
        for j in range(1, h.qd.shape[1]):
            moving |= np.abs(h.qd[:, j]) > self._moving[j]
        idle = segments(t, ~moving, (t,), self.cfg.max_gap_s)
        rl = self.machine.rated_load  # no chart: load ratios unknown (NaN)
        rated = rl.payload_at(h.reach_m) if rl is not None else np.full(h.n, np.nan)
        has_h = h.height_m is not None
        rise = h.height_m if h.height_m is not None else h.q[:, self._lift_joint]
        ratio = h.payload_kg / rated
        w = (np.ones(h.n) if h.payload_steady is None
             else h.payload_steady.astype(np.float64))
        vals = (h.payload_kg, ratio, h.reach_m, h.q[:, self._slew], rise, w, w * h.payload_kg,
                w * ratio)
        loaded = segments(t, h.payload_kg >= self.cfg.grab_kg, vals, self.cfg.max_gap_s)
        return ProductivityPart(float(t[0]), float(t[-1]), inner, idle, loaded, has_h)

    def merge_parts(self, a: ProductivityPart, b: ProductivityPart) -> ProductivityPart:
        """One part of chunk ``a`` followed by chunk ``b`` (folding it = folding both)."""
        inner = dict(a.inner_recorded_s)
        for k, v in b.inner_recorded_s.items():
            inner[k] = inner.get(k, 0.0) + v
        dt0 = b.t_first - a.t_last
        if dt0 <= self.cfg.max_gap_s:
            k = int(b.t_first // DAY_S)
            inner[k] = inner.get(k, 0.0) + dt0
        g = self.cfg.max_gap_s
        return ProductivityPart(a.t_first, b.t_last, inner, concat_segments(a.idle, b.idle, g),
                                concat_segments(a.loaded, b.loaded, g),
                                a.has_height and b.has_height)

    def apply(self, p: ProductivityPart | None) -> None:
        """Fold the part of the next chunk (see :meth:`part`)."""
        if p is None:
            return
        dt0 = 0.0 if self._last_t is None else p.t_first - self._last_t
        if dt0 > self.cfg.max_gap_s:
            dt0 = 0.0
        self._last_t = p.t_last
        self.recorded_s += dt0 + sum(p.inner_recorded_s.values())
        first = self.days.setdefault(int(p.t_first // DAY_S), DayUsage())
        first.recorded_s += dt0
        first.working_s += dt0
        for dkey, v in p.inner_recorded_s.items():
            du = self.days.setdefault(dkey, DayUsage())
            du.recorded_s += v
            du.working_s += v
        for r in self._idle.feed_segments(p.idle):
            self._idle_run(r)
        for r in self._loaded.feed_segments(p.loaded):
            if (wc := self._cycle(r, p.has_height)) is not None:
                self.cycles.append(wc)
        self._has_height = p.has_height

    def update(self, h: LoadHistory) -> None:
        """Fold the next chunk (``apply(part(h))``)."""
        self.apply(self.part(h))

    def snapshot(self) -> tuple[list[WorkCycle], float, float, dict[int, DayUsage]]:
        """(work cycles, recorded s, idle s, per-day usage) including runs open at the end."""
        import copy

        days = copy.deepcopy(self.days)
        cycles = list(self.cycles)
        idle = self.idle_s
        probe = copy.copy(self)
        probe.days = days
        probe.idle_s = idle
        for r in self._loaded.flush():
            if (wc := probe._cycle(r, getattr(self, "_has_height", False))) is not None:
                cycles.append(wc)
        for r in self._idle.flush():
            probe._idle_run(r)
        return cycles, self.recorded_s, probe.idle_s, days
