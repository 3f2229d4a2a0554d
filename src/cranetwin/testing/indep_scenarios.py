"""Operator programs for the independent crane simulation (:mod:`cranetwin.testing.indep_sim`).

* :func:`valve_steps` — open-loop valve-voltage steps and ramps of the lift, jib and telescope
  valves (like Figure 3 of Zhidchenko & Handroos 2022, with the telescope moving too) and a
  slewing swing, no payload, 20 s.
* :func:`log_cycle` — timber loading: swing to the pile, lower, grab a log (payload step at the
  tip), lift, swing to the load space, lower, release, raise; The operator
  tracks minimum-jerk rod-position and slew-angle waypoints with proportional valve commands
  and a PD slewing torque. 52 s (two cycles).

numpy only, besides the simulation module.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from cranetwin.testing.indep_crane import NC, CraneParams, cylinder_lengths, joints_from_rods
from cranetwin.testing.indep_sim import SQ, SQD, Scenario, holding_state

F64 = npt.NDArray[np.float64]


def _trapezoids(t: float, pulses: tuple[tuple[float, float, float, float, float], ...]) -> float:
    """Sum of trapezoid pulses (t_start, t_ramp_up, t_hold, t_ramp_down, level) at t."""
    out = 0.0
    for t0, up, hold, down, level in pulses:
        a = t - t0
        if a <= 0 or a >= up + hold + down:
            continue
        if a < up:
            out += level * a / up
        elif a < up + hold:
            out += level
        else:
            out += level * (1.0 - (a - up - hold) / down)
    return out


def _min_jerk(t: float, knots: list[tuple[float, float]]) -> tuple[float, float]:
    """Position and rate of a minimum-jerk path through (t, value) waypoints, held outside."""
    if t <= knots[0][0]:
        return knots[0][1], 0.0
    for (t0, y0), (t1, y1) in zip(knots[:-1], knots[1:], strict=True):
        if t0 <= t < t1:
            r = (t - t0) / (t1 - t0)
            s = r ** 3 * (10 - 15 * r + 6 * r * r)
            ds = 30 * r * r * (1 - r) ** 2 / (t1 - t0)
            return y0 + (y1 - y0) * s, (y1 - y0) * ds
    return knots[-1][1], 0.0


def _slew_pd(theta: float, omega: float, ref: float, rate: float) -> float:
    """Slewing torque command of a PD operator [N·m] (ω_n ≈ 2 rad/s on ≈ 3000 kg·m²)."""
    return 12000.0 * (ref - theta) + 14000.0 * (rate - omega)


def valve_steps(p: CraneParams, duration_s: float = 20.0) -> Scenario:
    """Valve-voltage steps and ramps [V] of lift, jib and telescope, and a slewing swing
    (0 → 0.5 rad → 0) by a PD torque; boom starts at rest, held by its pressures."""
    pulses = (
        ((1.0, 0.0, 3.0, 0.0, 6.0), (8.0, 1.0, 2.0, 1.0, -5.0), (15.0, 0.0, 2.0, 0.0, 4.0)),
        ((3.0, 0.5, 2.5, 0.5, -5.0), (11.0, 0.0, 2.5, 0.0, 6.0), (16.5, 1.0, 1.0, 1.0, -4.0)),
        ((2.0, 0.0, 2.5, 0.0, 7.0), (7.0, 0.5, 2.0, 0.5, -6.0), (13.0, 0.0, 1.5, 0.0, 8.0),
         (17.0, 0.5, 1.0, 0.5, -8.0)),
    )
    slew = [(0.0, 0.0), (5.0, 0.0), (9.0, 0.5), (12.0, 0.5), (16.0, 0.0)]

    def commands(t: float, x: F64) -> tuple[F64, float]:
        u = np.array([_trapezoids(t, pk) for pk in pulses])
        ref, rate = _min_jerk(t, slew)
        return u, _slew_pd(float(x[0]), float(x[4]), ref, rate)

    q0 = np.array([0.0, 0.45, -1.5, 0.3])
    return Scenario("valve-steps", duration_s, holding_state(p, q0, 0.0), commands)


UP = (0.40, 0.30, 0.35)        # lift, jib, telescope rod positions with the load raised [m]
DOWN = (0.22, 0.48, 0.75)      # ... lowered to the pile or the load space [m]


def log_cycle(p: CraneParams, duration_s: float = 52.0,
              logs_kg: tuple[float, ...] = (320.0, 260.0)) -> Scenario:
    """Timber loading with rod and slew waypoints tracked by the operator, one 26 s cycle per
    log; each log is a payload step at the tip when grabbed and back to 0 when released."""
    pile, bunk = -0.8, 0.8
    rods: list[list[tuple[float, float]]] = [[] for _ in range(NC)]
    slew: list[tuple[float, float]] = []
    steps: list[tuple[float, float]] = []

    def at(t: float, angle: float, s: tuple[float, float, float]) -> None:
        slew.append((t, angle))
        for k in range(NC):
            rods[k].append((t, s[k]))

    t = 0.0
    at(0.0, 0.0, UP)
    for mass in logs_kg:
        if t + 26.0 > duration_s + 1e-9:
            break
        at(t + 5.0, pile, UP)          # swing to the pile
        at(t + 8.0, pile, DOWN)        # lower the grapple
        steps.append((t + 9.0, mass))      # grab
        at(t + 10.0, pile, DOWN)
        at(t + 13.0, pile, UP)         # lift
        at(t + 18.0, bunk, UP)         # swing to the load space
        at(t + 21.0, bunk, DOWN)       # lower
        steps.append((t + 22.0, 0.0))      # release
        at(t + 23.0, bunk, DOWN)
        at(t + 26.0, bunk, UP)         # raise the empty grapple
        t += 26.0
    closed = np.array([c.closed_m for c in p.cyl])

    def commands(t: float, x: F64) -> tuple[F64, float]:
        s = cylinder_lengths(p, x[SQ]) - closed
        ref = np.array([_min_jerk(t, rods[k])[0] for k in range(NC)])
        rate = np.array([_min_jerk(t, rods[k])[1] for k in range(NC)])
        u = 80.0 * (ref - s) + 25.0 * rate
        sref, srate = _min_jerk(t, slew)
        return u, _slew_pd(float(x[SQ][0]), float(x[SQD][0]), sref, srate)

    q0 = joints_from_rods(p, np.array(UP))
    return Scenario("log-cycle", duration_s, holding_state(p, q0, 0.0), commands,
                    payload0_kg=0.0, payload_steps=tuple(steps))
