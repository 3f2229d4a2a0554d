"""What the twin worker stores per window: derived channels of a replay and the machine's
cumulative counters (operating and idle time, lifts, payload totals, overloads).

Pure functions over numpy arrays (no storage, no I/O); :mod:`cranetwin.service.worker` calls them
for every window.
"""

from __future__ import annotations

from dataclasses import replace as dc_replace
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from cranetwin.model import Machine

if TYPE_CHECKING:
    from cranetwin.service.backend import Progress

F64 = npt.NDArray[np.float64]

MOVING_RAD_S = 0.02
MOVING_M_S = 0.01


def derived_channels(machine: Machine) -> list[str]:
    """Names of the derived channels the worker stores for ``machine``."""
    out = [f"force:{c.name}" for c in machine.cylinders]
    out.append("payload")
    out += [f"moment:{j.name}" for j in machine.joints if j.kind == "revolute"]
    out += [f"torque:{j.name}" for j in machine.joints]
    out.append("working")
    return out


def derive(machine: Machine, res: object, keep: npt.NDArray[np.bool_]) -> tuple[list[str], F64]:
    """Derived channel values at the kept instants of a replay result.

    Args:
        machine: Machine description.
        res: :class:`~cranetwin.twin.TwinResult`.
        keep: Which grid instants to use, shape (m,).

    Returns:
        (channel names, values of shape (k, n_channels)) in :func:`derived_channels` order.
    """
    from cranetwin.twin import TwinResult

    assert isinstance(res, TwinResult)
    cols: list[F64] = [res.cyl_force[keep, k] for k in range(len(machine.cylinders))]
    cols.append(res.payload_kg[keep])
    w = res.joint_wrench[keep]
    for i, j in enumerate(machine.joints):
        if j.kind == "revolute":
            cols.append(np.linalg.norm(w[:, i, 3:], axis=1))
    cols += [res.id_torque[keep, i] for i in range(machine.n_joints)]
    limits = np.array([MOVING_RAD_S if j.kind == "revolute" else MOVING_M_S
                       for j in machine.joints])
    moving = np.any(np.abs(res.qd[keep]) > limits, axis=1)
    cols.append(moving.astype(np.float64))
    return derived_channels(machine), np.column_stack(cols)


def lift_seconds(machine: Machine, t_s: F64, payload_kg: F64, reach_m: F64) -> tuple[F64, F64]:
    """What the lift counters see of a window: per whole second of ``t_s``, the mean payload
    (non-finite values as 0) [kg] and the rated load at the reach of its first instant [kg]."""
    if not len(t_s):
        return np.zeros(0), np.zeros(0)
    sec = np.floor(t_s).astype(np.int64)
    starts = np.concatenate(([0], np.flatnonzero(np.diff(sec)) + 1))
    pl = np.where(np.isfinite(payload_kg), payload_kg, 0.0)
    means = np.add.reduceat(pl, starts) / np.diff(np.append(starts, len(t_s)))
    rl = machine.rated_load  # no chart: ratios unknown (inf rating), see fold_lifts
    rated_at = (np.asarray(rl.payload_at(reach_m[starts]), dtype=np.float64) if rl is not None
                else np.full(starts.shape, np.inf))
    return means.astype(np.float64), rated_at


def rated_max_kg(machine: Machine) -> float | None:
    """The largest rated payload of the machine's chart [kg], None without a chart."""
    rl = machine.rated_load
    return float(max(rl.payload_kg)) if rl is not None else None


def fold_lifts(prog: Progress, means: F64, rated_at: F64, threshold_kg: float,
               rated_max_kg: float | None) -> Progress:
    """The lift counters after the seconds ``means`` / ``rated_at`` (:func:`lift_seconds`).

    A lift starts when a 1-s mean exceeds ``threshold_kg`` and ends below half of it; at its
    end it is counted, its peak added to the payload total, (peak/rated max)³ to the spectrum
    sum, and it is an overload when the peak exceeded the rated load at its reach. The counters
    of a history are this fold over its seconds in time order (a lift may span windows).
    Without a rated-load chart (``rated_max_kg`` None, ``rated_at`` inf) the ratio stays 0
    (the stored column has no null) and neither overloads nor the spectrum are counted."""
    in_lift, peak, ratio = prog.in_lift, prog.lift_peak_kg, prog.lift_peak_ratio
    count, total, cube, over = prog.load_count, prog.payload_total_kg, prog.load_cube_sum, \
        prog.overloads
    mx = prog.max_payload_kg
    for m, r in zip(means.tolist(), rated_at.tolist(), strict=True):
        if not in_lift and m > threshold_kg:
            in_lift, peak, ratio = True, m, m / r
        elif in_lift:
            if m > peak:
                peak = m
            ratio = max(ratio, m / r)
            if m < threshold_kg / 2:
                count += 1
                total += peak
                if rated_max_kg is not None:
                    cube += (peak / rated_max_kg) ** 3
                    over += int(ratio > 1.0)
                mx = max(mx, peak)
                in_lift, peak, ratio = False, 0.0, 0.0
    return dc_replace(prog, in_lift=in_lift, lift_peak_kg=peak, lift_peak_ratio=ratio,
                      load_count=count, payload_total_kg=total, load_cube_sum=cube,
                      overloads=over, max_payload_kg=mx)


def update_counters(prog: Progress, machine: Machine, t_s: F64, payload_kg: F64,
                    reach_m: F64, working: F64, period_s: float, threshold_kg: float) -> Progress:
    """Cumulative counters after one window.

    Operating time = samples × period; idle = the part with ``working`` = 0; lifts as
    :func:`fold_lifts` over the window's :func:`lift_seconds`.

    Args:
        prog: Progress before the window.
        machine: Machine description (rated-load chart).
        t_s: Grid times of the window, shape (k,) [s].
        payload_kg: Payload estimate, shape (k,) [kg].
        reach_m: Horizontal reach of the load point, shape (k,) [m].
        working: 1 moving / 0 still, shape (k,).
        period_s: Grid period [s].
        threshold_kg: Lift threshold [kg].
    """
    new = dc_replace(prog, operating_s=prog.operating_s + len(t_s) * period_s,
                     idle_s=prog.idle_s + float(np.sum(working < 0.5)) * period_s)
    if not len(t_s):
        return new
    means, rated_at = lift_seconds(machine, t_s, payload_kg, reach_m)
    new = fold_lifts(new, means, rated_at, threshold_kg, rated_max_kg(machine))
    finite = payload_kg[np.isfinite(payload_kg)]
    return new if not finite.size else dc_replace(new, last_payload_kg=float(finite[-1]))
