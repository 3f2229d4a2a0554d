"""Synthetic load histories of a log crane working shifts, for the demo, tests and benchmark.

Not physics: a closed-form, quasi-static approximation (loads = weights × lever arms of a planar
two-boom crane, plus a damped 1.8 Hz boom oscillation after each grab and stop), good enough to
exercise the analytics with realistic magnitudes. Every channel is a pure function of time, so
any split into chunks gives identical samples (what the incremental-equals-batch test needs).
The smooth profiles of a cycle are tabulated every millisecond and looked up (exact on any
sample grid that is a multiple of 1 ms, the nearest millisecond otherwise).

One work cycle of ``CYCLE_S`` seconds: reach out empty (0–8 s) → grab (payload ramps in
8.5–9.5 s) → lift (11–17 s) → swing loaded (17–29 s) → lower and release (29–33 s, payload ramps
out 31–32 s) → pause. Misuse can be injected per cycle index (:class:`Misuse`).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from cranetwin.analytics.events import nominal_speed_mps
from cranetwin.analytics.history import LoadHistory
from cranetwin.model import Machine

F64 = npt.NDArray[np.float64]
G = 9.81
CYCLE_S = 45.0
TPL_S = 0.001  # time step of the tabulated cycle profiles [s]
DAY_S = 86400.0


@dataclass(frozen=True)
class Misuse:
    """Injected misuse, by global cycle index (cycles counted from the first shift).

    Attributes:
        overload: Cycles whose payload is ``overload_factor`` × the rated payload at the reach.
        end_stop: Cycles whose lift runs the lift cylinder into its end stop at full speed.
        overspeed: Cycles whose loaded swing is done in 2 s (slewing overspeed).
        overload_factor: See ``overload``.
    """

    overload: tuple[int, ...] = ()
    end_stop: tuple[int, ...] = ()
    overspeed: tuple[int, ...] = ()
    overload_factor: float = 1.35


def _ramp(tau: F64, t0: float | F64, t1: float | F64) -> tuple[F64, F64]:
    """Smooth step 0→1 over [t0, t1] (half cosine) and its time derivative."""
    d = np.asarray(t1 - t0, dtype=np.float64)
    s = np.clip((tau - t0) / d, 0.0, 1.0)
    inside = (s > 0) & (s < 1)
    return 0.5 - 0.5 * np.cos(np.pi * s), np.where(inside, 0.5 * np.pi * np.sin(np.pi * s) / d, 0.0)


def _osc(tau: F64, t0: float) -> F64:
    """Damped 1.8 Hz oscillation starting at t0 (0 before)."""
    x = np.maximum(tau - t0, 0.0)
    return np.where(tau > t0, np.exp(-x / 1.5) * np.sin(2 * np.pi * 1.8 * x), 0.0)


@dataclass
class SyntheticCrane:
    """A crane working ``shift_h``-hour shifts from ``shift_start_h`` UTC every day.

    Attributes:
        machine: The machine (limits, rated load, cylinders).
        seed: Seed of the per-cycle random parameters.
        start_epoch_s: Midnight (UTC) of the first day [s since the epoch].
        days: Number of days.
        shift_start_h: Start of the shift [h after midnight].
        shift_h: Shift length [h]; a 30-minute idle break sits in its middle.
        misuse: Misuse to inject.
    """

    machine: Machine
    seed: int = 0
    start_epoch_s: float = 1.7e9 - (1.7e9 % DAY_S)
    days: int = 30
    shift_start_h: float = 6.0
    shift_h: float = 8.0
    misuse: Misuse = field(default_factory=Misuse)

    def __post_init__(self) -> None:
        per_shift = int(self.shift_h * 3600 // CYCLE_S) + 1
        self._per_shift = per_shift
        n = per_shift * self.days
        rng = np.random.default_rng(self.seed)
        self._a_pick = 0.8 + rng.uniform(-0.4, 0.4, n)
        self._down = 0.15 + rng.uniform(-0.1, 0.1, n)
        self._l_pick = rng.uniform(0.2, 1.1, n)
        grab_reach = self._reach(self._down, np.full(n, -0.9), self._l_pick)
        rl = self.machine.rated_load
        if rl is None:
            raise ValueError(f"{self.machine.name}: synthetic shifts size their loads by the "
                             "rated-load chart, which this machine does not state")
        cap = 0.85 * rl.payload_at(grab_reach)
        self._mass = np.minimum(np.clip(rng.lognormal(np.log(230.0), 0.4, n), 60.0, None), cap)
        self._lift_to = np.full(n, 0.6)
        self._hit = np.zeros(n, dtype=bool)
        self._fast = np.zeros(n, dtype=bool)
        ml = self.machine
        for k in self.misuse.overload:
            self._mass[k] = self.misuse.overload_factor * float(
                rl.payload_at(grab_reach[k]))
        j1 = ml.joints[1]
        for k in self.misuse.end_stop:
            self._lift_to[k] = j1.upper
            self._hit[k] = True
        for k in self.misuse.overspeed:
            self._fast[k] = True
        mid = per_shift // 2
        self._idle = np.zeros(n, dtype=bool)
        brk = int(1800 // CYCLE_S)
        for d in range(self.days):
            self._idle[d * per_shift + mid: d * per_shift + mid + brk] = True
        self._mass[self._idle] = 0.0
        self._nominal_v = nominal_speed_mps(ml)
        # Profiles of one cycle tabulated every TPL_S (exact at every sample time on a 1 ms grid)
        tau: F64 = np.arange(int(round(CYCLE_S / TPL_S)) + 1, dtype=np.float64) * TPL_S
        tpl: dict[str, F64] = {}
        for name, (a, b) in {"1": (0.0, 8.0), "2": (17.0, 29.0), "2f": (17.0, 19.0),
                             "3": (11.0, 17.0), "4": (29.0, 33.0), "g1": (8.5, 9.5),
                             "g2": (31.0, 32.0)}.items():
            tpl["r" + name], tpl["d" + name] = _ramp(tau, a, b)
        tpl["lin"] = np.clip((tau - 11.0) / 4.0, 0.0, 1.0)
        tpl["dlin"] = np.where((tau > 11.0) & (tau < 15.0), 0.25, 0.0)
        tpl["osc"] = _osc(tau, 9.5) + _osc(tau, 17.0) + _osc(tau, 29.0)
        self._tpl = tpl

    @staticmethod
    def _reach(q1: F64, q2: F64, ext: F64) -> F64:
        return np.asarray(-0.09 + 2.881 * np.cos(q1) + (2.1 + ext) * np.cos(q1 + q2))

    @property
    def cycles_per_shift(self) -> int:
        """Cycle slots per shift (including the idle break)."""
        return self._per_shift

    def shift_bounds(self, day: int) -> tuple[float, float]:
        """Start and end of the shift of day ``day`` [s since the epoch]."""
        t0 = self.start_epoch_s + day * DAY_S + self.shift_start_h * 3600
        return t0, t0 + self.shift_h * 3600

    def cycle_start(self, k: int) -> float:
        """Start time of global cycle ``k`` [s]."""
        d, i = divmod(k, self._per_shift)
        return self.shift_bounds(d)[0] + i * CYCLE_S

    def history(self, t: F64) -> LoadHistory:
        """The history at times ``t`` (all inside shifts), shape (n,) [s]."""
        ml = self.machine
        t = np.asarray(t, dtype=np.float64)
        rel = t - self.start_epoch_s
        day = np.floor(rel / DAY_S).astype(np.int64)
        in_shift = rel - day * DAY_S - self.shift_start_h * 3600
        i = np.minimum((in_shift // CYCLE_S).astype(np.int64), self._per_shift - 1)
        k = np.clip(day * self._per_shift + i, 0, self._mass.size - 1)
        tau = in_shift - i * CYCLE_S
        it = np.clip(np.rint(tau / TPL_S).astype(np.int64), 0, self._tpl["r1"].size - 1)
        tp = self._tpl
        idle = self._idle[k]
        a_drop = -0.8
        r1, d1 = tp["r1"][it], tp["d1"][it]
        r2, d2 = tp["r2"][it], tp["d2"][it]
        fast = self._fast[k]
        if fast.any():
            r2 = np.where(fast, tp["r2f"][it], r2)
            d2 = np.where(fast, tp["d2f"][it], d2)
        r3, d3 = tp["r3"][it], tp["d3"][it]
        hit = self._hit[k]
        if hit.any():
            r3 = np.where(hit, tp["lin"][it], r3)
            d3 = np.where(hit, tp["dlin"][it], d3)
        r4, d4 = tp["r4"][it], tp["d4"][it]
        move = np.where(idle, 0.0, 1.0)
        dq0 = self._a_pick[k] - a_drop
        q0 = a_drop + move * dq0 * (r1 - r2)
        qd0 = move * dq0 * (d1 - d2)
        down, lift_to = self._down[k], self._lift_to[k]
        q1 = 0.6 + move * ((down - 0.6) * r1 + (lift_to - down) * r3 + (0.6 - lift_to) * r4)
        qd1 = move * ((down - 0.6) * d1 + (lift_to - down) * d3 + (0.6 - lift_to) * d4)
        q2 = -1.2 + move * 0.3 * (r1 - r2)
        qd2 = move * 0.3 * (d1 - d2)
        dl = self._l_pick[k] - 0.1
        ext = 0.1 + move * dl * (r1 - r2)
        extd = move * dl * (d1 - d2)
        payload = self._mass[k] * (tp["rg1"][it] - tp["rg2"][it])
        c1, s12 = np.cos(q1), np.cos(q1 + q2)
        reach = -0.09 + 2.881 * c1 + (2.1 + ext) * s12
        height = 1.426 + 2.881 * np.sin(q1) + (2.1 + ext) * np.sin(q1 + q2)
        w = G * (payload + ml.load_point.tool_mass_kg)
        dyn = 1.0 + 0.15 * move * tp["osc"][it]
        self_m1 = G * (143.66 * 1.229 * c1 + 76.7 * (2.881 * c1 + 0.6 * s12)
                       + 58.63 * (2.881 * c1 + (1.0 + ext) * s12))
        m1 = w * dyn * (reach + 0.09) + self_m1
        m2 = w * dyn * (2.1 + ext) * s12 + G * (76.7 * 0.6 + 58.63 * (1.0 + ext)) * s12
        m0 = m1 + 0.09 * (w + G * 279.0)
        m3 = np.abs(w * dyn * (2.075 + ext) * s12 + G * 58.63 * (0.83 + ext) * s12)
        # deterministic pseudo-noise from the sample time (uniform, ±0.2 % of the load)
        h32 = (np.rint(t * 1000.0).astype(np.int64) * 2654435761) & 0xFFFFFFFF
        noise = 0.004 * (h32 / 4294967296.0 - 0.5)
        jm = np.column_stack([m0, m1, np.abs(m2), m3]) * (1.0 + noise)[:, None]
        f_lift = m1 / 0.35
        f_jib = m2 / 0.30
        f_ext = w * np.sin(q1 + q2) + 250.0 * np.tanh(extd / 0.005)
        f = np.column_stack([f_lift, f_jib, f_ext]) * (1.0 + noise)[:, None]
        cyl = ml.cylinders
        j = ml.joints
        s_lift = cyl[0].stroke_m * (q1 - j[1].lower) / (j[1].upper - j[1].lower)
        v_lift = cyl[0].stroke_m * qd1 / (j[1].upper - j[1].lower)
        s_jib = cyl[1].stroke_m * (q2 - j[2].lower) / (j[2].upper - j[2].lower)
        v_jib = cyl[1].stroke_m * qd2 / (j[2].upper - j[2].lower)
        rod_s = np.column_stack([s_lift, s_jib, ext])
        rod_v = np.column_stack([v_lift, v_jib, extd])
        a1 = np.array([c.area_a_m2 for c in cyl])
        a2 = np.array([c.area_b_m2 for c in cyl])
        p_a = 1.0e6 + np.maximum(f, 0.0) / a1
        p_b = 1.0e6 + np.maximum(-f, 0.0) / a2
        return LoadHistory(
            t_s=t, cyl_force=f, joint_moment=jm, q=np.column_stack([q0, q1, q2, ext]),
            qd=np.column_stack([qd0, qd1, qd2, extd]), payload_kg=payload, reach_m=reach,
            height_m=height, rod_s=rod_s, rod_v=rod_v, p_a=p_a, p_b=p_b)

    def chunks(self, rate_hz: float = 100.0, chunk_s: float = 3600.0,
               days: int | None = None) -> Iterator[LoadHistory]:
        """Histories of the shifts, ``chunk_s`` seconds at a time, sampled at ``rate_hz``."""
        dt = 1.0 / rate_hz
        for d in range(self.days if days is None else days):
            t0, t1 = self.shift_bounds(d)
            n_total = int(round((t1 - t0) * rate_hz))
            step = int(round(chunk_s * rate_hz))
            for a in range(0, n_total, step):
                b = min(a + step, n_total)
                yield self.history(t0 + np.arange(a, b, dtype=np.float64) * dt)
