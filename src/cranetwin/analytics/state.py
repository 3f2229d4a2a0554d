"""Incremental analytics of one machine: fold history chunks, take a report at any time.

:class:`AnalyticsState` keeps only what is needed to continue: rainflow residues and from-to
cycle tables per load channel, open event and work-cycle runs, per-day counters. Feeding a
history in any number of chunks gives the same :class:`AnalyticsReport` as feeding it at once
(tested), so a service can update the report as data arrive without recomputing history.
"""

from __future__ import annotations

import pickle
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from cranetwin.analytics.classification import (
    Classification,
    DutyRecord,
    classify,
    duty_record,
)
from cranetwin.analytics.events import (
    Event,
    EventConfig,
    EventDetector,
    EventPart,
    relief_force_n,
)
from cranetwin.analytics.fatigue import (
    LifeEstimate,
    equivalent_stress_range_mpa,
    life_estimate,
    miner_damage,
)
from cranetwin.analytics.history import LoadHistory
from cranetwin.analytics.productivity import (
    DayUsage,
    ProductivityConfig,
    ProductivityPart,
    ProductivityTracker,
    WorkCycle,
)
from cranetwin.analytics.rainflow import CycleTable, RainflowCounter
from cranetwin.errors import AnalyticsError
from cranetwin.model import Machine

F64 = npt.NDArray[np.float64]
G = 9.81
DAY_S = 86400.0
STATE_MAGIC = b"cranetwin-analytics-state-1\n"


def load_channels(machine: Machine) -> list[str]:
    """Every load channel analysed: cylinder forces, then joint moments (``FatigueDetail.load``
    syntax)."""
    return ([f"cylinder:{c.name}:force" for c in machine.cylinders]
            + [f"joint:{j.name}:moment" for j in machine.joints])


def default_class_widths(machine: Machine, classes: int = 200) -> dict[str, float]:
    """Rainflow level width per load channel: 1/``classes`` of a nominal full scale.

    Cylinder force: the push force at relief pressure. Joint moment: twice the largest rated
    load moment (rated payload + tool at the chart's reach), allowing for the booms' own weight;
    without a rated-load chart, the strongest cylinder's relief force times its longest
    pin-to-pin length (a bound on what it can hold; a bin width, not a rating).
    """
    out: dict[str, float] = {}
    rel = relief_force_n(machine)
    for c, f in zip(machine.cylinders, rel.tolist(), strict=True):
        out[f"cylinder:{c.name}:force"] = f / classes
    rl = machine.rated_load
    if rl is not None:
        m_nom = 2 * G * max((p + machine.load_point.tool_mass_kg) * r
                            for p, r in zip(rl.payload_kg, rl.reach_m, strict=True))
    else:  # no chart: the strongest cylinder at relief on its longest pin-to-pin length
        m_nom = max([f * (c.closed_length_m + c.stroke_m)
                     for c, f in zip(machine.cylinders, rel.tolist(), strict=True)]
                    or [d.max_torque_nm for d in machine.torque_drives] or [1.0e4])
    for j in machine.joints:
        out[f"joint:{j.name}:moment"] = m_nom / classes
    return out


@dataclass(frozen=True)
class AnalyticsConfig:
    """Settings of a whole analysis.

    Attributes:
        events: Event thresholds.
        productivity: Work-cycle and working-time thresholds.
        class_widths: Rainflow level width per load channel; defaults from
            :func:`default_class_widths`.
        gamma_mf: Fatigue strength factor γmf of EN 13001-3-1.
        inspection_step: Inspect each time the Miner damage crosses a multiple of this.
        prior_damage: Damage per fatigue detail name accumulated before this history.
        prior_equivalent_cycles: ISO 12482 full-load equivalent cycles used before.
    """

    events: EventConfig = field(default_factory=EventConfig)
    productivity: ProductivityConfig = field(default_factory=ProductivityConfig)
    class_widths: dict[str, float] | None = None
    gamma_mf: float = 1.0
    inspection_step: float = 0.1
    prior_damage: dict[str, float] = field(default_factory=dict)
    prior_equivalent_cycles: float = 0.0


@dataclass(frozen=True)
class Spectrum:
    """Rainflow result of one load channel."""

    channel: str
    unit: str
    cycles: CycleTable


@dataclass(frozen=True)
class RateBasis:
    """How the damage, cycles and S of a report are turned into rates (remaining life, next
    service, projected class of utilisation, date the design working period is reached).

    Rate per calendar day = (quantity in the range / operating hours in the range) × operating
    hours per calendar day. The operating hours per day come from the machine's whole recorded
    history when it is known (``usage_source = "history"``: the twin worker's operating time from
    the first stored sample to its progress mark), else from the requested range itself
    (``"range"``: operating hours / calendar days of [range_t0_s, range_t1_s)). Both make the
    rate of a repeated duty independent of the report window; neither uses the first-to-last
    sample span. Dates are counted from ``range_t1_s``.

    Attributes:
        range_t0_s: Start of the requested range [s].
        range_t1_s: End of the requested range (exclusive) [s].
        operating_h: Operating hours in the range (time with data, steps ≤ max_gap_s) [h].
        usage_h_per_day: Operating hours per calendar day used for the projection [h/d].
        usage_source: ``"history"`` or ``"range"``.
        history_operating_h: Operating hours of the whole recorded history (if known) [h].
        history_days: Calendar days of the whole recorded history (if known) [d].
    """

    range_t0_s: float
    range_t1_s: float
    operating_h: float
    usage_h_per_day: float
    usage_source: str
    history_operating_h: float | None = None
    history_days: float | None = None

    @property
    def equivalent_days(self) -> float:
        """Calendar days the range's operation stands for at the projected usage [d]
        (rate per day = quantity in the range / this)."""
        if self.usage_h_per_day <= 0:
            return float("inf")
        return self.operating_h / self.usage_h_per_day

    def per_day(self, amount: float) -> float:
        """Rate per calendar day of ``amount`` accumulated over the range [1/d]."""
        d = self.equivalent_days
        return amount / d if d > 0 and np.isfinite(d) else 0.0

    @property
    def description(self) -> str:
        """One sentence for the report."""
        if self.usage_source == "history":
            return (f"rate = (amount in the range / {self.operating_h:.4g} operating h in the "
                    f"range) × {self.usage_h_per_day:.4g} operating h per calendar day, from "
                    f"the machine's whole recorded history ({self.history_operating_h or 0:.4g}"
                    f" h over {self.history_days or 0:.4g} days)")
        span = (self.range_t1_s - self.range_t0_s) / DAY_S
        return (f"rate = (amount in the range / {self.operating_h:.4g} operating h in the range)"
                f" × {self.usage_h_per_day:.4g} operating h per calendar day of the requested "
                f"range ({span:.4g} days), i.e. the amount per calendar day of the range")


def rate_basis(t0_s: float, t1_s: float, recorded_s: float,
               history_operating_s: float | None = None,
               history_calendar_s: float | None = None) -> RateBasis:
    """The :class:`RateBasis` of a range (see there).

    Args:
        t0_s: Start of the requested range [s].
        t1_s: End of the requested range [s], > t0_s.
        recorded_s: Operating time in the range [s].
        history_operating_s: Operating time of the machine's whole recorded history [s], or None.
        history_calendar_s: Calendar time that history covers [s], or None.
    """
    if not t1_s > t0_s:
        raise AnalyticsError(f"range end {t1_s} must be after its start {t0_s}")
    op_h = recorded_s / 3600.0
    if history_operating_s is not None and history_calendar_s is not None \
            and history_calendar_s > 0 and history_operating_s > 0:
        hd = history_calendar_s / DAY_S
        hh = history_operating_s / 3600.0
        return RateBasis(t0_s, t1_s, op_h, hh / hd, "history", hh, hd)
    return RateBasis(t0_s, t1_s, op_h, op_h / ((t1_s - t0_s) / DAY_S), "range")


@dataclass(frozen=True)
class AnalyticsReport:
    """A snapshot of everything analytics knows about a machine's history.

    Times in the history's timebase [s]; ``observed_days`` is the calendar span of the data
    (for plots only); rates use :attr:`basis`. ``assumptions`` lists, as sentences, every
    assumption the figures rest on (fatigue details, prior damage, design class, rate basis).
    """

    machine: str
    t_start: float
    t_end: float
    n_samples: int
    spectra: list[Spectrum]
    life: list[LifeEstimate]
    classification: Classification | None
    duty: DutyRecord | None
    events: list[Event]
    cycles: list[WorkCycle]
    days: dict[int, DayUsage]
    recorded_s: float
    idle_s: float
    basis: RateBasis | None = None
    assumptions: tuple[str, ...] = ()

    @property
    def observed_days(self) -> float:
        """Calendar days covered (at least one recorded second) [d]."""
        return max(self.t_end - self.t_start, 1.0) / DAY_S

    @property
    def working_s(self) -> float:
        """Recorded time the machine was working [s]."""
        return self.recorded_s - self.idle_s

    @property
    def payload_per_working_hour_kg(self) -> float:
        """Payload moved per working hour [kg/h]."""
        return sum(c.payload_kg for c in self.cycles) / max(self.working_s / 3600, 1e-9)

    @property
    def mean_cycle_time_s(self) -> float:
        """Mean time from one grab to the next within a working day [s] (NaN if < 2 cycles)."""
        if len(self.cycles) < 2:
            return float("nan")
        t = np.array([c.t_grab for c in self.cycles])
        d = np.diff(t)
        d = d[d < 600.0]  # a pause longer than 10 min ends a sequence of cycles
        return float(d.mean()) if d.size else float("nan")

    @property
    def utilisation(self) -> float:
        """Working time / recorded time."""
        return self.working_s / self.recorded_s if self.recorded_s > 0 else 0.0


@dataclass
class AnalyticsPart:
    """Everything the analyses need of one stretch of history, computed from it alone, so that
    stored parts of consecutive stretches (e.g. one per minute) fold into exactly the report of
    the whole (:meth:`AnalyticsState.apply`): rainflow counters (closed cycles as a from-to
    table and the open residue) per load channel, raw stretches of every event and work-cycle
    condition with their statistics, look-back samples at both ends, recorded time per day.

    Attributes:
        t_first: First sample time [s].
        t_last: Last sample time [s].
        n: Samples.
        rainflow: Counter per load channel.
        events: Event detector part.
        productivity: Work-cycle and time part.
    """

    t_first: float
    t_last: float
    n: int
    rainflow: dict[str, RainflowCounter]
    events: EventPart
    productivity: ProductivityPart


class AnalyticsState:
    """Folds :class:`LoadHistory` chunks of one machine; :meth:`report` at any time."""

    def __init__(self, machine: Machine, config: AnalyticsConfig | None = None) -> None:
        self.machine = machine
        self.cfg = config or AnalyticsConfig()
        widths = self.cfg.class_widths or default_class_widths(machine)
        self.channels = load_channels(machine)
        missing = [c for c in self.channels if c not in widths]
        if missing:
            raise AnalyticsError(f"class_widths lacks {missing}")
        self.counters = {c: RainflowCounter(widths[c]) for c in self.channels}
        self.events = EventDetector(machine, self.cfg.events)
        self.productivity = ProductivityTracker(machine, self.cfg.productivity)
        self.t_start: float | None = None
        self.t_end: float | None = None
        self.n_samples = 0

    def update(self, h: LoadHistory) -> AnalyticsState:
        """Fold the next chunk (must follow the previous one in time); returns self."""
        if h.n == 0:
            return self
        if self.t_end is not None and not h.t_s[0] > self.t_end:
            raise AnalyticsError(f"chunk starts at {h.t_s[0]} s, not after the previous end "
                                 f"{self.t_end} s")
        if self.t_start is None:
            self.t_start = float(h.t_s[0])
        self.t_end = float(h.t_s[-1])
        self.n_samples += h.n
        for ch, counter in self.counters.items():
            counter.update(h.load_channel(self.machine, ch))
        self.events.update(h)
        self.productivity.update(h)
        return self

    def part(self, h: LoadHistory) -> AnalyticsPart | None:
        """The :class:`AnalyticsPart` of one stretch (this state is not changed; only its
        machine and configuration are used); None for an empty history."""
        if h.n == 0:
            return None
        rf = {}
        for ch, counter in self.counters.items():
            c = RainflowCounter(counter.class_width)
            c.update(h.load_channel(self.machine, ch))
            rf[ch] = c
        ev = self.events.part(h)
        pr = self.productivity.part(h)
        assert ev is not None and pr is not None
        return AnalyticsPart(float(h.t_s[0]), float(h.t_s[-1]), h.n, rf, ev, pr)

    def apply(self, p: AnalyticsPart | None) -> AnalyticsState:
        """Fold the part of the next stretch (must follow the previous one in time); the same
        state as :meth:`update` with its history. Returns self."""
        if p is None:
            return self
        if self.t_end is not None and not p.t_first > self.t_end:
            raise AnalyticsError(f"part starts at {p.t_first} s, not after the previous end "
                                 f"{self.t_end} s")
        if self.t_start is None:
            self.t_start = p.t_first
        self.t_end = p.t_last
        self.n_samples += p.n
        for ch, counter in self.counters.items():
            counter.absorb(p.rainflow[ch])
        self.events.apply(p.events)
        self.productivity.apply(p.productivity)
        return self

    def merge_parts(self, a: AnalyticsPart, b: AnalyticsPart) -> AnalyticsPart:
        """One part of stretch ``a`` followed by stretch ``b``: folding it is folding both (roll
        minute parts up into hours and days). Neither part is changed.

        Raises:
            AnalyticsError: b does not follow a, or a part is not longer than the look-back of
                the event detectors (a fraction of a second).
        """
        import copy

        if not b.t_first > a.t_last:
            raise AnalyticsError("parts out of order")
        ev = self.events.merge_parts(a.events, b.events)
        rf = {ch: copy.deepcopy(c).absorb(b.rainflow[ch]) for ch, c in a.rainflow.items()}
        pr = self.productivity.merge_parts(a.productivity, b.productivity)
        return AnalyticsPart(a.t_first, b.t_last, a.n + b.n, rf, ev, pr)

    def dumps(self) -> bytes:
        """The whole state as bytes, to keep between runs (e.g. in the database) and continue
        with :meth:`loads` where this one stopped.

        The format is Python's pickle behind a version tag: store it only where the service
        itself writes (loading bytes from an untrusted source can run code).
        """
        return STATE_MAGIC + pickle.dumps(self, protocol=pickle.HIGHEST_PROTOCOL)

    @staticmethod
    def loads(data: bytes) -> AnalyticsState:
        """A state written by :meth:`dumps` (same cranetwin state version).

        Raises:
            AnalyticsError: Not a state of this version.
        """
        if not data.startswith(STATE_MAGIC):
            raise AnalyticsError("not an analytics state of version "
                                 f"{STATE_MAGIC.decode(errors='replace').strip()}")
        state = pickle.loads(data[len(STATE_MAGIC):])
        if not isinstance(state, AnalyticsState):
            raise AnalyticsError(f"expected an AnalyticsState, got {type(state).__name__}")
        return state

    def report(self, t0_s: float | None = None, t1_s: float | None = None,
               history_operating_s: float | None = None,
               history_calendar_s: float | None = None) -> AnalyticsReport:
        """A snapshot of the analysis so far (the state is not changed).

        Args:
            t0_s: Start of the requested range [s] (default: the first sample).
            t1_s: End of the requested range, exclusive [s] (default: the last sample; without
                a range the data span is the range).
            history_operating_s: Operating time of the machine's whole recorded history [s]
                (None: unknown; the range's own usage is projected).
            history_calendar_s: Calendar time of that history [s].

        The rate basis is described in :class:`RateBasis`.
        """
        ml = self.machine
        if self.t_start is None or self.t_end is None:
            raise AnalyticsError("no data folded yet")
        spectra = [Spectrum(ch, "N" if ch.endswith(":force") else "N*m",
                            self.counters[ch].snapshot()) for ch in self.channels]
        by_channel = {s.channel: s.cycles for s in spectra}
        cycles, recorded, idle, per_day = self.productivity.snapshot()
        r0 = self.t_start if t0_s is None else t0_s
        r1 = self.t_end if t1_s is None else t1_s
        if not r1 > r0:
            r1 = r0 + 1.0
        basis = rate_basis(r0, r1, recorded, history_operating_s, history_calendar_s)
        life: list[LifeEstimate] = []
        for d in ml.fatigue:
            if d.load not in by_channel:
                raise AnalyticsError(f"fatigue detail {d.name!r}: unknown load {d.load!r}")
            tab = by_channel[d.load]
            dmg = miner_damage(tab.ranges, tab.count, d, self.cfg.gamma_mf)
            prior = self.cfg.prior_damage.get(d.name, 0.0)
            eq = equivalent_stress_range_mpa(tab.ranges * d.stress_per_load, tab.count, d.slope_m)
            life.append(life_estimate(d.name, prior + dmg, basis.per_day(dmg),
                                      self.cfg.inspection_step, eq))
        ratios = np.array([c.load_ratio for c in cycles])
        cls = ml.classification
        classification = duty = None
        if cls is not None and ml.rated_load is not None:  # no chart: load ratios unknown
            eq_days = basis.equivalent_days
            classification = classify(ratios, eq_days if 0 < eq_days < np.inf else 1e-9,
                                      cls.design_life_years, cls.design_group)
            duty = duty_record(ratios, cls.design_total_cycles, cls.design_spectrum_factor,
                               self.cfg.prior_equivalent_cycles)
        return AnalyticsReport(ml.name, self.t_start, self.t_end, self.n_samples, spectra, life,
                               classification, duty, self.events.all_events(), cycles, per_day,
                               recorded, idle, basis, assumptions(ml, self.cfg, basis))


def assumptions(machine: Machine, cfg: AnalyticsConfig, basis: RateBasis) -> tuple[str, ...]:
    """Every assumption behind a report's figures, one sentence each."""
    out: list[str] = []
    for d in machine.fatigue:
        how = "ASSUMED in the machine file" if d.assumed else "as given in the machine file"
        out.append(
            f"Fatigue detail '{d.name}' ({how}): load {d.load}, stress = "
            f"{d.stress_per_load:g} Pa per unit load, detail category Δσc = "
            f"{d.detail_category_mpa:g} MPa, slope m = "
            f"{d.slope_m:g}, no endurance limit (EN 13001-3-1).")
        prior = cfg.prior_damage.get(d.name, 0.0)
        out.append(f"Prior damage of '{d.name}' before the range: D = {prior:g}"
                   + (" (taken as zero: no earlier record given)." if prior == 0 else "."))
    out.append(f"Fatigue strength factor γmf = {cfg.gamma_mf:g}; mean stress ignored; "
               f"inspection each time D crosses a multiple of {cfg.inspection_step:g}.")
    cls = machine.classification
    if cls is not None:
        out.append(f"Design classification (from the machine file, assumed unless the "
                   f"manufacturer states it): group {cls.design_group}, C_T = "
                   f"{cls.design_total_cycles:g} working cycles, kp = "
                   f"{cls.design_spectrum_factor:g}, design life {cls.design_life_years:g} years.")
        out.append(f"Prior full-load equivalent cycles (ISO 12482 S) before the range: "
                   f"{cfg.prior_equivalent_cycles:g}"
                   + (" (taken as zero)." if cfg.prior_equivalent_cycles == 0 else "."))
    else:
        out.append("No design classification in the machine file: no duty record.")
    if machine.rated_load is None:
        out.append("No rated-load chart in the machine file: the load ratio of each work "
                   "cycle, the duty class (ISO 4301-1), the used design working period "
                   "(ISO 12482) and overload and payload-above-rating events are unknown "
                   "(not computed).")
    for i, j in enumerate(machine.joints):
        if j.velocity_limit is None:
            out.append(f"Velocity limit of joint '{j.name}' unknown (joints.{i}.velocity_limit): "
                       "no overspeed check on it; it counts as moving above "
                       f"{cfg.productivity.moving_speed_unknown_limit:g} rad/s or m/s.")
    out.append("Rate basis: " + basis.description + ". Remaining life, next service, the "
               "projected class of utilisation and the date the design working period is "
               "reached assume this usage continues.")
    return tuple(out)


def analyse(machine: Machine, history: LoadHistory,
            config: AnalyticsConfig | None = None) -> AnalyticsReport:
    """Batch analysis of one history (equivalent to one :meth:`AnalyticsState.update`)."""
    return AnalyticsState(machine, config).update(history).report()
