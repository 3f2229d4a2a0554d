"""Twin output → public JSON: resampling to the requested rate, poses, pins, forces, wrenches,
the estimated tool force.

Pure functions of (machine, arrays); the fleet service, the warm-up and the live stream call them.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from cranetwin.model import Machine
from cranetwin.physics import body_poses, cylinder_force, cylinder_pins, joints_from_cylinders
from cranetwin.physics.actuator import actuator_torques
from cranetwin.twin.result import TwinResult
from cranetwin.twin.toolload import tool_force

F64 = npt.NDArray[np.float64]


def _r(a: F64, digits: int = 6) -> F64:
    """Rounded C-contiguous copy (JSON size; orjson serialises it, NaN as null)."""
    return np.ascontiguousarray(np.round(np.asarray(a, dtype=np.float64), digits))


def relief_forces(machine: Machine) -> F64:
    """Largest push force of each cylinder: relief pressure × piston area, shape (n_cyl,) [N]."""
    p = machine.hydraulics.relief_pressure_pa if machine.hydraulics else 2.0e7
    return np.array([p * c.area_a_m2 for c in machine.cylinders], dtype=np.float64)


def poses_json(machine: Machine, poses: F64) -> dict[str, F64]:
    """Per body: (n, 16) column-major 4x4 world poses, from poses (n, n_joints, 4, 4)."""
    cm = np.swapaxes(poses, -1, -2).reshape(poses.shape[0], poses.shape[1], 16)
    return {j.child: _r(cm[:, i]) for i, j in enumerate(machine.joints)}


def pins_json(machine: Machine, q: F64) -> dict[str, F64]:
    """Per cylinder: (n, 6) base pin xyz then rod pin xyz in the world [m]."""
    pins = cylinder_pins(machine, q)
    both = np.concatenate([pins.base, pins.rod], axis=2)
    return {c.name: _r(both[:, k]) for k, c in enumerate(machine.cylinders)}


def tool_force_json(machine: Machine, q: F64, residual: F64) -> dict[str, F64] | None:
    """The estimated tool force (:func:`cranetwin.twin.toolload.tool_force`) of the twin's
    residual at the output instants, or None for a machine whose working arm cannot resolve one
    (fewer than two cylinder joints up to the load body).

    ``n`` is the force on the tool at the load point, world axes, (m, 3) [N] (NaN → null near a
    singular arm pose); ``sigma_min_m`` the arm's shortest lever for it, (m,) [m]. It is the
    force the pressures imply beyond the model — gravity, inertia and the payload *estimate* —
    so while the tool is in the ground the payload estimate takes up part of it (a vertical
    force at the load point and a payload differ only by the payload's inertia): the vertical
    tool force and the payload are to be read together (F_z − max(m̂, 0)·g: the dynamics use
    a negative estimate as no payload), the horizontal component alone.
    """
    try:
        est = tool_force(machine, q, residual)
    except ValueError:
        return None
    return {"n": _r(est.force_n, 1), "sigma_min_m": _r(est.sigma_min_m, 4)}


def twin_json(machine: Machine, res: TwinResult, t0_s: float, t1_s: float,
              rate_hz: float) -> dict[str, Any]:
    """The contract's twin object for [t0_s, t1_s) at ``rate_hz`` from a replay result.

    The replay's grid is sampled at the nearest grid instant to each output time (the replay is
    run at ``rate_hz`` or a multiple of it, so this is exact up to rounding); instants bridged
    across a dropout (``res.gap``) are left out, so a silence shows as a step in ``t`` (the 3D
    view says "no data" there instead of drawing the spline across it). Wrenches are rotated
    from the child body frame to world axes.
    """
    grid = res.t_s
    if res.n == 0:
        idx = np.zeros(0, dtype=np.int64)
    else:
        n_out = int(np.floor((t1_s - t0_s) * rate_hz - 1e-9)) + 1
        t_out = t0_s + np.arange(max(n_out, 0)) / rate_hz
        t_out = t_out[(t_out >= grid[0] - 0.5 / rate_hz) & (t_out <= grid[-1] + 0.5 / rate_hz)]
        idx = np.clip(np.searchsorted(grid, t_out - 0.5 / rate_hz), 0, res.n - 1)
        nxt = np.clip(idx + 1, 0, res.n - 1)
        idx = np.where(np.abs(grid[nxt] - t_out) < np.abs(grid[idx] - t_out), nxt, idx)
        idx = np.unique(idx)
        idx = idx[(grid[idx] >= t0_s - 0.5 / rate_hz) & (grid[idx] < t1_s) & ~res.gap[idx]]
    q = res.q[idx]
    poses = body_poses(machine, q) if len(idx) else np.zeros((0, machine.n_joints, 4, 4))
    rot = poses[:, :, :3, :3]
    w = res.joint_wrench[idx]
    w_world = np.concatenate([np.einsum("nkij,nkj->nki", rot, w[..., :3]),
                              np.einsum("nkij,nkj->nki", rot, w[..., 3:])], axis=2)
    lp = machine.load_point
    body_i = [j.child for j in machine.joints].index(lp.body)
    tip = (np.einsum("nij,j->ni", poses[:, body_i, :3, :3], np.asarray(lp.point_m))
           + poses[:, body_i, :3, 3])
    forces = res.cyl_force[idx]
    util = np.abs(forces) / relief_forces(machine)
    t = res.t_s[idx]
    return {
        "t": _r(t, 4),
        "q": _r(q),
        "tip": _r(tip, 5),
        "poses": poses_json(machine, poses),
        "cylinder_pins": pins_json(machine, q) if len(idx) else
        {c.name: np.zeros((0, 6)) for c in machine.cylinders},
        "cylinder_forces": {c.name: _r(forces[:, k], 1) for k, c in enumerate(machine.cylinders)},
        "utilisation": {c.name: _r(util[:, k], 4) for k, c in enumerate(machine.cylinders)},
        "joint_torques": _r(res.id_torque[idx], 2),
        "wrenches": _r(w_world, 2),
        "payload": {"t": _r(t, 4), "kg": _r(res.payload_kg[idx], 2),
                    "std_kg": _r(res.payload_std_kg[idx], 2)},
        "tool_force": tool_force_json(machine, q, res.residual[idx]) if len(idx) else None,
        "force_observability": [v.as_json() for v in res.force_observability(machine)],
        "model_consistency": [v.as_json() for v in res.model_consistency(machine)],
    }


class LiveKinematics:
    """Per-sample state for the live stream, from raw channel values (no smoothing, no lag).

    q from the rod positions (and slew angle if sent) through the inverse kinematics; forces
    from Eq. 1–2 with the rod velocity by backward difference over the last two samples; joint
    torques (``joint_torques`` {joint: N·m or N}) of the actuators, τ = F·ds/dq plus the measured
    drive torques (the live counterpart of the stored ``torque:<joint>`` channel, without the
    inertia and payload terms of the inverse dynamics).

    Args:
        machine: Machine description.
        channels: Channel names of the sample columns.
    """

    def __init__(self, machine: Machine, channels: tuple[str, ...]) -> None:
        self.machine = machine
        self.channels = channels
        by_source: dict[tuple[str, str], int] = {}
        for i, name in enumerate(channels):
            try:
                ch = machine.channel(name)
            except KeyError:
                continue
            by_source[(ch.quantity, ch.source)] = i
        cyl = machine.cylinders
        self.i_pa = [by_source.get(("pressure_a", c.name)) for c in cyl]
        self.i_pb = [by_source.get(("pressure_b", c.name)) for c in cyl]
        self.i_s = [by_source.get(("position", c.name)) for c in cyl]
        driven = {c.joint for c in cyl}
        self.free = [j.name for j in machine.joints if j.name not in driven]
        self.i_angle = [by_source.get(("angle", j)) for j in self.free]
        self.i_drive = [by_source.get(("torque", d.name), by_source.get(("torque", d.joint)))
                        for d in machine.torque_drives]
        self.pressure_cols = [(name, i) for i, name in enumerate(channels)
                              if name in {c.name for c in machine.channels
                                          if c.quantity in ("pressure_a", "pressure_b")}]
        self.relief = relief_forces(machine)

    def usable(self) -> bool:
        """Whether every cylinder's rod position is sent."""
        return all(i is not None for i in self.i_s)

    def frames(self, t_s: F64, values: F64, prev: F64 | None,
               prev_t_s: float | None = None) -> list[dict[str, Any]]:
        """Live frames for samples ``values`` (n, n_channels) at ``t_s`` (n,).

        Args:
            t_s: Sample times [s].
            values: Samples in channel units.
            prev: The sample row before ``values[0]`` (for the first velocity), or None (the
                first velocity is then 0).
            prev_t_s: Time of ``prev`` [s]; required with ``prev``.
        """
        n = len(t_s)
        if n == 0 or not self.usable():
            return []
        s = np.column_stack([values[:, i] for i in self.i_s if i is not None])
        s = np.nan_to_num(s, nan=0.0)
        if self.free:
            qo = np.column_stack([values[:, i] if i is not None else np.zeros(n)
                                  for i in self.i_angle])
            qo = np.nan_to_num(qo, nan=0.0)
        else:
            qo = None
        m = self.machine
        lo = np.zeros(len(m.cylinders))
        hi = np.array([c.stroke_m for c in m.cylinders])
        q = joints_from_cylinders(m, np.clip(s, lo, hi), qo)
        if prev is None:
            s_prev, t_prev = s[:1], float(t_s[0]) - 1.0  # zero first velocity, any dt
        else:
            if prev_t_s is None:
                raise ValueError("prev_t_s is required with prev (the time of the previous row)")
            s_prev = np.nan_to_num(np.array([[prev[i] for i in self.i_s if i is not None]]),
                                   nan=0.0)
            t_prev = prev_t_s
        dt = np.diff(np.concatenate([[t_prev], t_s]))
        v = np.diff(np.vstack([s_prev, s]), axis=0) / np.maximum(dt, 1e-6)[:, None]
        forces = np.zeros((n, len(m.cylinders)))
        for k, c in enumerate(m.cylinders):
            ia, ib = self.i_pa[k], self.i_pb[k]
            pa = values[:, ia] if ia is not None else np.zeros(n)
            pb = values[:, ib] if ib is not None else np.zeros(n)
            forces[:, k] = cylinder_force(np.nan_to_num(pa), np.nan_to_num(pb), v[:, k], c)
        poses = body_poses(m, q)
        cm = np.swapaxes(poses, -1, -2).reshape(n, m.n_joints, 16)
        pins = cylinder_pins(m, q)
        util = np.abs(forces) / self.relief
        drives = np.column_stack([np.nan_to_num(values[:, i]) if i is not None else np.zeros(n)
                                  for i in self.i_drive]) if self.i_drive else None
        tau = actuator_torques(m, q, forces, drives)
        out = []
        for i in range(n):
            out.append({
                "t": round(float(t_s[i]), 4),
                "q": np.round(q[i], 6).tolist(),
                "poses": {j.child: np.round(cm[i, b], 5).tolist()
                          for b, j in enumerate(m.joints)},
                "cylinder_pins": {c.name: np.round(np.concatenate(
                    [pins.base[i, k], pins.rod[i, k]]), 5).tolist()
                    for k, c in enumerate(m.cylinders)},
                "cylinder_forces": {c.name: round(float(forces[i, k]), 1)
                                    for k, c in enumerate(m.cylinders)},
                "utilisation": {c.name: round(float(util[i, k]), 4)
                                for k, c in enumerate(m.cylinders)},
                "pressures": {name: _num(values[i, j]) for name, j in self.pressure_cols},
                "joint_torques": {j.name: round(float(tau[i, b]), 1)
                                  for b, j in enumerate(m.joints)},
            })
        return out


def _num(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None
