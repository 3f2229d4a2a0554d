"""Synthetic recordings with exactly known truth, for tests, calibration checks and benchmarks.

Joint motion q(t) is a sum of smooth sinusoids inside the PATU 655's joint ranges (slew starting
at rest); the rod positions come from the kinematics, the chamber pressures from inverse
dynamics through Eq. 1–2 inverted with a chosen rod-side pressure, and the slewing torque from
inverse dynamics plus the drive friction. Unlike the simulator this has no hydraulic dynamics:
it checks the twin's algebra, not the sensor model.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from cranetwin import physics
from cranetwin.model import Friction, Machine
from cranetwin.samples import SampleArrays

F64 = npt.NDArray[np.float64]
Payload = float | Callable[[F64], F64]


@dataclass(frozen=True)
class Synthetic:
    """Samples and truth of a synthetic run.

    Attributes:
        samples: Sensor channels at the sample rate.
        t: Truth times, shape (n,) [s]; q, qd, qdd (n, 4); s, v, force (n, 3) [m, m/s, N];
            tau: inverse-dynamics joint loads (n, 4); payload (n,) [kg].
    """

    samples: SampleArrays
    t: F64
    q: F64
    qd: F64
    qdd: F64
    s: F64
    v: F64
    force: F64
    tau: F64
    payload: F64


def motion(t: F64, scale: float = 1.0) -> tuple[F64, F64, F64]:
    """Smooth joint motion [theta0, theta1, theta2, L], shapes (n, 4) [rad or m, per s, per s²].

    Args:
        t: Times, shape (n,) [s].
        scale: Multiplies the frequencies (slower or faster motion).
    """
    amp = np.array([0.8, 0.35, 0.5, 0.3])
    mid = np.array([0.0, 0.5, -1.2, 0.5])
    w = np.array([0.31, 0.53, 0.41, 0.37]) * 2 * np.pi * scale
    ph = np.array([np.pi / 2, 0.4, 1.1, 2.0])  # theta0 starts at rest
    arg = w[None, :] * t[:, None] + ph[None, :]
    q = mid + amp * np.sin(arg)
    qd = amp * w * np.cos(arg)
    qdd = -amp * w**2 * np.sin(arg)
    return q, qd, qdd


def _channels(machine: Machine, t: F64, payload: Payload, p_b: float,
              friction: Mapping[str, Friction], scale: float) -> dict[str, F64]:
    q, qd, qdd = motion(t, scale)
    pay = np.broadcast_to(np.asarray(payload(t) if callable(payload) else payload, dtype=float),
                          t.shape).copy()
    tau = physics.joint_torques(machine, q, qd, qdd, pay)
    s, arm = physics.cylinder_kinematics(machine, q)
    cj = [machine.joint_index(c.joint) for c in machine.cylinders]
    v = arm * qd[:, cj]
    force = tau[:, cj] / arm
    pa = np.empty_like(s)
    pb = np.full_like(s, p_b)
    for c, cyl in enumerate(machine.cylinders):
        fr = physics.friction_force(v[:, c], friction.get(cyl.name, cyl.friction))
        pa[:, c] = (force[:, c] + fr + p_b * cyl.area_b_m2) / cyl.area_a_m2
    drive = machine.torque_drives[0]
    slew = tau[:, 0] + physics.friction_force(qd[:, 0], drive.friction)
    return {"q": q, "qd": qd, "qdd": qdd, "s": s, "v": v, "force": force, "tau": tau,
            "pa": pa, "pb": pb, "slew": slew, "payload": pay}


def make(machine: Machine, duration_s: float = 12.0, rate_hz: float = 100.0,
         payload: Payload = 150.0, fine_hz: float | None = 1000.0, p_b: float = 2.0e6,
         with_angle: bool = False, friction: Mapping[str, Friction] | None = None,
         scale: float = 1.0, quantize: bool = False) -> Synthetic:
    """Sample the analytic motion at ``rate_hz``; truth at ``fine_hz`` (sample times if None).

    Args:
        machine: Machine (PATU 655 channel names).
        duration_s: Length [s].
        rate_hz: Sample rate [Hz].
        payload: Payload [kg], constant or a function of time.
        fine_hz: Truth grid rate [Hz], or None for truth at the samples only.
        p_b: Rod-side pressure of every cylinder [Pa] (pA follows from the force).
        with_angle: Also send the slew-angle channel.
        friction: Cylinder friction actually present, by cylinder name (default: the
            machine's), e.g. to test calibration against a machine file that is wrong.
        scale: Frequency scale of the motion.
        quantize: Round the channels to the machine's sensor resolution.
    """
    fr = dict(friction or {})
    ts = np.arange(int(round(duration_s * rate_hz)) + 1) / rate_hz
    d = _channels(machine, ts, payload, p_b, fr, scale)
    cols = {"lift_pA": d["pa"][:, 0], "lift_pB": d["pb"][:, 0], "lift_s": d["s"][:, 0],
            "jib_pA": d["pa"][:, 1], "jib_pB": d["pb"][:, 1], "jib_s": d["s"][:, 1],
            "ext_pA": d["pa"][:, 2], "ext_pB": d["pb"][:, 2], "ext_s": d["s"][:, 2],
            "slew_torque": d["slew"]}
    if with_angle:
        cols["slew_angle"] = d["q"][:, 0]
    if quantize:
        cols = {k: np.round(v / machine.channel(k).resolution) * machine.channel(k).resolution
                for k, v in cols.items()}
    samples = SampleArrays("synthetic", ts, tuple(cols), np.column_stack(list(cols.values())))
    if fine_hz is None:
        f = d
        tf = ts
    else:
        tf = np.arange(int(round(duration_s * fine_hz)) + 1) / fine_hz
        f = _channels(machine, tf, payload, p_b, fr, scale)
    return Synthetic(samples, tf, f["q"], f["qd"], f["qdd"], f["s"], f["v"], f["force"],
                     f["tau"], f["payload"])
