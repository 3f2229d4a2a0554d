"""Calibration of cylinder friction and the carried mass from a recording (the paper's future
work: model validation).

For cylinder c driving joint j, Eq. 1–2 and inverse dynamics give, at every instant::

    pA·A1 − pB·A2 − tau_0,j/s'_j = m·g_j/s'_j + Fc_c·tanh(v_c/vc_c) + b_c·v_c

(s' = ds/dq the moment arm; tau_0 the inverse dynamics with the machine file's tool mass and no
payload; g the joint loads per kg at the load point). For fixed Coulomb velocities vc this is
linear in the extra mass m (payload plus any tool-mass error) and in every (Fc, b): one least
squares over all cylinders. vc enters nonlinearly and is searched on a 1-D logarithmic grid per
cylinder (coordinate search, the other parameters re-solved at each point). Residuals are
reported before (machine-file friction, no extra mass) and after, as RMS force [N].

Both sides are low-passed by the same moving average (the derivative-smoothing window): the
accelerations in tau_0 are smoothed, the pressures are not, and their fast hydraulic
oscillations would otherwise leak into the fit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from cranetwin import physics
from cranetwin.errors import TwinError
from cranetwin.model import Machine
from cranetwin.samples import SampleArrays
from cranetwin.twin.replay import ReplayOptions, replay
from cranetwin.twin.result import TwinResult

F64 = npt.NDArray[np.float64]

VC_GRID = np.geomspace(5e-4, 0.05, 25)


@dataclass(frozen=True)
class CylinderFit:
    """Friction of one cylinder: file values and estimates (Eq. 2)."""

    name: str
    coulomb_file: float
    coulomb: float
    coulomb_velocity_file: float
    coulomb_velocity: float
    viscous_file: float
    viscous: float
    rms_before_n: float
    rms_after_n: float


@dataclass(frozen=True)
class Calibration:
    """Result of :func:`calibrate`.

    Attributes:
        cylinders: Friction fits, in ``machine.cylinders`` order.
        extra_mass_kg: Mass at the load point beyond the file's tool mass (payload + tool error).
        extra_mass_std_kg: Its standard error [kg].
        tool_mass_file_kg: The machine file's tool mass [kg].
        samples_used: Instants in the fit.
    """

    cylinders: tuple[CylinderFit, ...]
    extra_mass_kg: float
    extra_mass_std_kg: float
    tool_mass_file_kg: float
    samples_used: int


def _moving_average(x: F64, width: int) -> F64:
    """Moving average along axis 0, 'valid' part only: shape (n − width + 1, …)."""
    if width <= 1:
        return x
    c = np.cumsum(np.concatenate([np.zeros((1,) + x.shape[1:]), x]), axis=0)
    out: F64 = (c[width:] - c[:-width]) / width
    return out


def _design(vc: F64, v: F64, g: F64, width: int) -> F64:
    """Columns [m, Fc_0, b_0, Fc_1, b_1, …] stacked over cylinders, each low-passed by a
    moving average of ``width`` instants: shape (n'·nc, 1 + 2nc)."""
    n, nc = v.shape
    m = n - max(width, 1) + 1
    a = np.zeros((m * nc, 1 + 2 * nc))
    for c in range(nc):
        rows = slice(c * m, (c + 1) * m)
        a[rows, 0] = _moving_average(g[:, c], width)
        a[rows, 1 + 2 * c] = _moving_average(np.tanh(v[:, c] / vc[c]), width)
        a[rows, 2 + 2 * c] = _moving_average(v[:, c], width)
    return a


def res_rate(res: TwinResult) -> float:
    """Grid rate of a replay result [Hz]."""
    return float(1.0 / np.median(np.diff(res.t_s[:100])))


def sample_rate(samples: SampleArrays) -> float:
    """Nominal sample rate [Hz]."""
    return float(1.0 / np.median(np.diff(samples.t_s)))


def calibrate(samples: SampleArrays, machine: Machine, trim_s: float = 1.0,
              decimate: int = 10) -> Calibration:
    """Estimate friction (Fc, vc, b per cylinder) and the carried mass by least squares.

    Args:
        samples: A recording with motion of every cylinder through zero velocity and a constant
            payload (the fit assumes one mass for the whole recording).
        machine: The machine file being calibrated.
        trim_s: Seconds dropped at each end (spline end effects) [s].
        decimate: Use every ``decimate``-th grid instant (1 kHz grid).

    Returns:
        :class:`Calibration`.

    Raises:
        TwinError: Too little data, or data that does not determine the parameters.
    """
    # motion from the replay (payload estimated there only for the slewing inertia when theta0
    # is integrated from torque); the fit itself uses the raw Eq. 1 force and inverse dynamics.
    # Pressures by fixed (linear) windows: the adaptive ICI choice is nonlinear and biased the
    # viscous coefficient by ~10 % in tests.
    res = replay(samples, machine, grid_hz=1000.0, payload=None,
                 options=ReplayOptions(payload_window_s=4.0, adaptive_pressures=False))
    keep = (res.t_s >= res.t_s[0] + trim_s) & (res.t_s <= res.t_s[-1] - trim_s)
    idx = np.flatnonzero(keep)[::decimate]
    if idx.shape[0] < 50:
        raise TwinError(f"calibration needs a longer recording (only {idx.shape[0]} instants)")
    q, qd, qdd = res.q[idx], res.qd[idx], res.qdd[idx]
    tau0 = physics.joint_torques(machine, q, qd, qdd, 0.0)
    g_all = physics.joint_torques(machine, q, qd, qdd, 1.0) - tau0
    _, arm = physics.cylinder_kinematics(machine, q)
    cj = [machine.joint_index(c.joint) for c in machine.cylinders]
    cyls = machine.cylinders
    nc = len(cyls)
    hyd = np.column_stack([res.p_a[idx, c] * cyl.area_a_m2 - res.p_b[idx, c] * cyl.area_b_m2
                           for c, cyl in enumerate(cyls)])
    y = hyd - tau0[:, cj] / arm  # what friction and the extra mass must explain [N]
    g = g_all[:, cj] / arm
    v = res.rod_v[idx]
    # "filter both sides": the accelerations come smoothed over the derivative window, the
    # pressures carry the fast hydraulic oscillations they miss; the same moving average on
    # the force and on every regressor removes that mismatch without biasing the parameters
    wd = max((c.window for k, c in res.smoothing.items() if k.endswith("'")), default=1)
    width = max(1, int(round(wd * res_rate(res) / decimate / sample_rate(samples))))
    yv = _moving_average(y, width).T.reshape(-1)

    def solve(vc: F64) -> tuple[F64, F64]:
        a = _design(vc, v, g, width)
        x = np.asarray(np.linalg.solve(a.T @ a, a.T @ yv), dtype=np.float64)
        return x, yv - a @ x

    def search(vc: F64, c: int, grid: F64) -> float:
        best = (np.inf, float(vc[c]))
        for cand in grid:
            trial = vc.copy()
            trial[c] = cand
            _, r = solve(trial)
            sse = float(np.dot(r, r))
            if sse < best[0]:
                best = (sse, float(cand))
        return best[1]

    vc = np.array([c.friction.coulomb_velocity for c in cyls])
    step = VC_GRID[1] / VC_GRID[0]
    for _ in range(2):  # coordinate search over each cylinder's vc, then a finer local grid
        for c in range(nc):
            vc[c] = search(vc, c, VC_GRID)
            vc[c] = search(vc, c, vc[c] * np.geomspace(1 / step, step, 13))
    x, r = solve(vc)
    a = _design(vc, v, g, width)
    n = v.shape[0] - width + 1
    dof = max(a.shape[0] - a.shape[1], 1)
    sigma2 = float(np.dot(r, r)) / dof
    try:
        cov = sigma2 * np.linalg.inv(a.T @ a)
        mass_std = float(np.sqrt(cov[0, 0]))
    except np.linalg.LinAlgError as exc:
        raise TwinError("the recording does not determine the friction and mass "
                        "(no motion of some cylinder?)") from exc
    fits = []
    for c, cyl in enumerate(cyls):
        fr = cyl.friction
        before = _moving_average(y[:, c] - fr.coulomb * np.tanh(v[:, c] / fr.coulomb_velocity)
                                 - fr.viscous * v[:, c], width)
        after = r[c * n : (c + 1) * n]
        fits.append(CylinderFit(
            name=cyl.name, coulomb_file=fr.coulomb, coulomb=float(x[1 + 2 * c]),
            coulomb_velocity_file=fr.coulomb_velocity, coulomb_velocity=float(vc[c]),
            viscous_file=fr.viscous, viscous=float(x[2 + 2 * c]),
            rms_before_n=float(np.sqrt(np.mean(before**2))),
            rms_after_n=float(np.sqrt(np.mean(after**2)))))
    return Calibration(tuple(fits), float(x[0]), mass_std, machine.load_point.tool_mass_kg, n)
