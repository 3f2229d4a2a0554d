"""Calibration of cylinder friction and the carried mass from a recording (the paper's future
work: model validation).

For cylinder c driving joint j, Eq. 1–2 and inverse dynamics give, at every instant::

    pA·A1 − pB·A2 − tau_0,j/s'_j = m·g_j/s'_j + Fc_c·tanh(v_c/vc_c) + b_c·v_c

(s' = ds/dq the moment arm; tau_0 the inverse dynamics with the machine file's tool mass and no
payload; g the joint loads per kg at the load point). For fixed Coulomb velocities vc this is
linear in the extra mass m (payload plus any tool-mass error), in every (Fc, b) and in one
constant force offset per cylinder (the constant pressure-transducer biases, A1·δpA − A2·δpB,
which otherwise leak into b): one least squares over all cylinders. vc enters nonlinearly and is
found per cylinder by a coarse logarithmic grid then a bounded 1-D minimisation (coordinate
search, the other parameters re-solved at each point; a grid-step resolution of vc moved b by
up to 15 %). Residuals are reported before (machine-file friction, no extra mass, no offset)
and after, as RMS force [N].

Velocity noise and vc: the rod velocity is the Savitzky–Golay derivative of noisy positions,
v = v_true + e with e of standard deviation σ_v = σ_s·‖h'‖/Δt (σ_s the position noise the
replay estimated, h' the derivative filter). The low-pass below averages e out of every column,
so a column tanh(v/vc) tends to E_e[tanh((v_true + e)/vc)]: tanh blurred by the noise, wider
than tanh(v_true/vc), and the fit narrowed vc to compensate (the extension, vc = 3 mm/s with
σ_v ≈ 1.1 mm/s: −6 … −16 % on simulated 10-minute runs; with the true velocity +0.5 %). The
Coulomb column is therefore the deconvolved ψ(v) = tanh(u) + r²·tanh(u)·sech²(u), u = v/vc,
r = σ_v/vc, whose noise average is tanh(v_true/vc) to O(r⁴) (first term of the inverse heat
operator, ψ = f − (σ_v²/2)·f''); r is capped at ``MAX_NOISE_RATIO`` (ψ is monotone only for
r < 1/√2, and the series soon diverges). The smoothing error of the velocity itself (the
filter's bias at reversals, no noise) is not corrected: on those runs it moves vc by ≈ −3 %.

Both sides are low-passed by the same filter: the accelerations in tau_0 are smoothed, the
pressures are not, and their fast hydraulic oscillations would otherwise leak into the fit. The
fit first uses one moving average of the derivative-smoothing window (it keeps the sharp force
step at each reversal that determines vc). If that leaves more than ``WIDE_FILTER_RATIO`` of
the force unexplained (hydraulic oscillations the smoothed accelerations miss), the whole fit,
vc search included, is repeated with two passes of a moving average twice that window (on
simulated 10-minute runs the lift's residual drops from ~110 N to ~15 N, and b moved from up
to +28 % to within 9 %).

Excitation: b is the slope of force over speed. With white pressure noise (the sensor model's
12.5 kPa) the standard error of the lift's b on a 10-minute ``random`` run is ~5 %, so 10 % is
about 2σ and may be missed on some sensor seeds whatever the estimator (docs/ACCURACY.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.optimize import minimize_scalar

from cranetwin import physics
from cranetwin.errors import TwinError
from cranetwin.model import Cylinder, Machine
from cranetwin.samples import SampleArrays
from cranetwin.signal import nominal_period
from cranetwin.signal.savgol import sg_filter
from cranetwin.twin.channels import ChannelMap
from cranetwin.twin.options import ReplayOptions
from cranetwin.twin.replay import replay
from cranetwin.twin.result import TwinResult
from cranetwin.twin.stages import derivative_filter

F64 = npt.NDArray[np.float64]

VC_GRID = np.geomspace(5e-4, 0.05, 25)
# low-pass filters on both sides of the fit: (moving-average passes, width as a multiple of the
# derivative-smoothing window). The narrow one keeps the sharp force step at each reversal that
# determines vc; the wide one removes the hydraulic oscillations that the smoothed accelerations
# miss, and is used when the narrow fit leaves more than WIDE_FILTER_RATIO of the force (RMS
# after / before) unexplained (simulated runs with hydraulics: 2.7–5.7 %; a rigid synthetic
# recording: 0.1–0.2 %, where the wide filter blurs the reversals and loses vc)
NARROW_FILTER = (1, 1.0)
WIDE_FILTER = (2, 2.0)
WIDE_FILTER_RATIO = 0.01
# largest velocity-noise / vc ratio the Coulomb column is corrected for (module docstring)
MAX_NOISE_RATIO = 0.5


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
        extra_mass_std_kg: Its statistical standard error [kg]: residuals' correlation
            time and a jackknife over time blocks taken into account, model error not (on
            simulated 10-minute runs the error was 0.1–0.3 kg against a stated 0.02 kg).
        tool_mass_file_kg: The machine file's tool mass [kg].
        samples_used: Instants in the fit.
        offsets_n: Constant force offset per cylinder (pressure-transducer bias), in
            ``machine.cylinders`` order [N].
        filter_passes_width: The low-pass used: moving-average passes and width [instants].
        velocity_noise_mps: Standard deviation of each cylinder's velocity noise that the
            Coulomb column was corrected for, in ``machine.cylinders`` order [m/s].
    """

    cylinders: tuple[CylinderFit, ...]
    extra_mass_kg: float
    extra_mass_std_kg: float
    tool_mass_file_kg: float
    samples_used: int
    offsets_n: tuple[float, ...] = ()
    filter_passes_width: tuple[int, int] = (1, 1)
    velocity_noise_mps: tuple[float, ...] = ()


def _lowpass(x: F64, width: int, passes: int) -> F64:
    """``passes`` moving averages of ``width`` along axis 0, 'valid' part only."""
    for _ in range(passes):
        x = _moving_average(x, width)
    return x


def _moving_average(x: F64, width: int) -> F64:
    """Moving average along axis 0, 'valid' part only: shape (n − width + 1, …)."""
    if width <= 1:
        return x
    c = np.cumsum(np.concatenate([np.zeros((1,) + x.shape[1:]), x]), axis=0)
    out: F64 = (c[width:] - c[:-width]) / width
    return out


def coulomb_column(v: F64, vc: float, sigma_v: float) -> F64:
    """Coulomb regressor of Eq. 2 at a noisy velocity: ψ(v) = tanh(u) + r²·tanh(u)·sech²(u),
    u = v/vc, r = min(σ_v/vc, ``MAX_NOISE_RATIO``), whose average over Gaussian velocity noise
    of standard deviation σ_v is tanh(v_true/vc) to O(r⁴) (module docstring).

    Args:
        v: Measured velocities [m/s].
        vc: Coulomb velocity [m/s].
        sigma_v: Velocity noise standard deviation [m/s]; 0 gives tanh(v/vc).
    """
    t = np.tanh(v / vc)
    r2 = min(sigma_v / vc, MAX_NOISE_RATIO) ** 2
    out: F64 = t + r2 * t * (1.0 - t * t) if r2 > 0.0 else t
    return out


def velocity_noise_std(res: TwinResult, samples: SampleArrays, machine: Machine) -> F64:
    """Standard deviation of each cylinder's rod-velocity noise in a replay [m/s]:
    σ_s·‖h'‖/Δt, with σ_s the position noise the replay estimated and h' the Savitzky–Golay
    derivative filter it used (:func:`cranetwin.twin.stages.derivative_filter`). The spline
    onto the grid is not counted (the fit's instants fall 1 ms after the samples; on simulated
    runs this matched the measured velocity error of the sensor noise to 1 %)."""
    cmap = ChannelMap.build(machine, samples.channels)
    dt = 1.0 / sample_rate(samples)
    out = np.zeros(len(machine.cylinders))
    for c, j in enumerate(cmap.s):
        name = cmap.names[j]
        pos, der = res.smoothing.get(name), res.smoothing.get(name + "'")
        if pos is None or der is None or not pos.sigma > 0.0:
            continue
        w, p = derivative_filter(der)
        out[c] = pos.sigma * float(np.linalg.norm(sg_filter(w, p, 1))) / dt
    return out


def _design(vc: F64, v: F64, g: F64, width: int, passes: int, sigma_v: F64) -> F64:
    """Columns [m, Fc_0, b_0, off_0, Fc_1, b_1, off_1, …] stacked over cylinders, each
    low-passed by :func:`_lowpass`: shape (n'·nc, 1 + 3nc). The Coulomb columns are
    :func:`coulomb_column` with the velocity noise ``sigma_v`` [m/s] per cylinder."""
    n, nc = v.shape
    m = n - passes * (max(width, 1) - 1)
    a = np.zeros((m * nc, 1 + 3 * nc))
    for c in range(nc):
        rows = slice(c * m, (c + 1) * m)
        a[rows, 0] = _lowpass(g[:, c], width, passes)
        a[rows, 1 + 3 * c] = _lowpass(coulomb_column(v[:, c], float(vc[c]), float(sigma_v[c])),
                                      width, passes)
        a[rows, 2 + 3 * c] = _lowpass(v[:, c], width, passes)
        a[rows, 3 + 3 * c] = 1.0
    return a


def res_rate(res: TwinResult) -> float:
    """Grid rate of a replay result [Hz]."""
    return 1.0 / nominal_period(res.t_s[:100])


def sample_rate(samples: SampleArrays) -> float:
    """Nominal sample rate [Hz]: the period the samples carry, estimated only if they carry
    none."""
    return 1.0 / nominal_period(samples.t_s, samples.period_ns)


def _before(y: F64, v: F64, cyls: list[Cylinder], c: int, width: int, passes: int) -> F64:
    """Low-passed force residual of cylinder ``c`` with the file's friction, no extra mass [N]."""
    return _lowpass(y[:, c] - physics.friction_force(v[:, c], cyls[c].friction), width, passes)


def _fit(y: F64, g: F64, v: F64, vc0: F64, width: int, passes: int,
         sigma_v: F64) -> tuple[F64, F64, F64]:
    """Least squares for fixed vc inside a coordinate search over each cylinder's vc (coarse
    logarithmic grid, then a bounded 1-D minimisation; a second sweep refines locally).

    Returns:
        (parameters [m, Fc_0, b_0, off_0, …], low-passed residual stacked over cylinders [N],
        vc per cylinder [m/s]).
    """
    yv = _lowpass(y, width, passes).T.reshape(-1)

    def solve(vc: F64) -> tuple[F64, F64]:
        a = _design(vc, v, g, width, passes, sigma_v)
        x = np.asarray(np.linalg.solve(a.T @ a, a.T @ yv), dtype=np.float64)
        return x, yv - a @ x

    def sse(vc: F64, c: int, log_vc: float) -> float:
        trial = vc.copy()
        trial[c] = np.exp(log_vc)
        _, r = solve(trial)
        return float(np.dot(r, r))

    vc = vc0.copy()
    log_step = float(np.log(VC_GRID[1] / VC_GRID[0]))
    for sweep in range(2):
        for c in range(v.shape[1]):
            if sweep == 0:   # coarse grid, then refine between the neighbours of the best
                vals = [sse(vc, c, float(np.log(x))) for x in VC_GRID]
                centre = float(np.log(VC_GRID[int(np.argmin(vals))]))
            else:
                centre = float(np.log(vc[c]))
            found = minimize_scalar(lambda lv, c=c: sse(vc, c, lv), method="bounded",
                                    bounds=(centre - log_step, centre + log_step),
                                    options={"xatol": 1e-4})
            vc[c] = float(np.exp(found.x))
    x, r = solve(vc)
    return x, r, vc


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
    unit = wd * res_rate(res) / decimate / sample_rate(samples)
    filters = [(p, max(1, int(round(k * unit)))) for p, k in (NARROW_FILTER, WIDE_FILTER)]
    if v.shape[0] - max(p * (w - 1) for p, w in filters) < 50:
        raise TwinError(f"calibration needs a longer recording ({v.shape[0]} instants for "
                        f"filters of {filters})")
    vc0 = np.array([c.friction.coulomb_velocity for c in cyls])
    passes, width = filters[0]
    sigma_v = velocity_noise_std(res, samples, machine)
    x, r, vc = _fit(y, g, v, vc0, width, passes, sigma_v)
    n = v.shape[0] - passes * (width - 1)
    before = np.column_stack([_before(y, v, cyls, c, width, passes) for c in range(nc)])
    ratio = max(float(np.sqrt(np.mean(r[c * n:(c + 1) * n] ** 2) / np.mean(before[:, c] ** 2)))
                for c in range(nc))
    if ratio > WIDE_FILTER_RATIO:   # hydraulic oscillations left: refit with the wide filter
        passes, width = filters[1]
        x, r, vc = _fit(y, g, v, vc, width, passes, sigma_v)
    a = _design(vc, v, g, width, passes, sigma_v)
    n = v.shape[0] - passes * (width - 1)
    dof = max(a.shape[0] - a.shape[1], 1)
    sigma2 = float(np.dot(r, r)) / dof
    # the residuals are low-passed (smoothing, then the moving averages above): neighbours are
    # correlated, so the independent-errors covariance is scaled by the residuals' integrated
    # autocorrelation time (the number of instants per independent error); errors that drift
    # over the recording (model mismatch) show in a delete-one-block jackknife over time
    # instead: the larger of the two is reported
    tau = max(correlation_time(r[c * n : (c + 1) * n]) for c in range(nc))
    try:
        cov = sigma2 * tau * np.linalg.inv(a.T @ a)
        mass_std = max(float(np.sqrt(cov[0, 0])),
                       _jackknife_std(a, _lowpass(y, width, passes).T.reshape(-1), n, nc))
    except np.linalg.LinAlgError as exc:
        raise TwinError("the recording does not determine the friction and mass "
                        "(no motion of some cylinder?)") from exc
    fits = []
    for c, cyl in enumerate(cyls):
        fr = cyl.friction
        before = _before(y, v, cyls, c, width, passes)
        after = r[c * n : (c + 1) * n]
        fits.append(CylinderFit(
            name=cyl.name, coulomb_file=fr.coulomb, coulomb=float(x[1 + 3 * c]),
            coulomb_velocity_file=fr.coulomb_velocity, coulomb_velocity=float(vc[c]),
            viscous_file=fr.viscous, viscous=float(x[2 + 3 * c]),
            rms_before_n=float(np.sqrt(np.mean(before**2))),
            rms_after_n=float(np.sqrt(np.mean(after**2)))))
    return Calibration(tuple(fits), float(x[0]), mass_std, machine.load_point.tool_mass_kg, n,
                       tuple(float(x[3 + 3 * c]) for c in range(nc)), (passes, width),
                       tuple(float(sv) for sv in sigma_v))


def correlation_time(x: F64, max_lag_fraction: float = 0.1) -> float:
    """Integrated autocorrelation time τ = 1 + 2·Σ ρ_k of a series [samples], the sum stopped
    at the first negative ρ_k (or at ``max_lag_fraction`` of the length): the variance of a
    mean of n correlated values is τ·σ²/n. 1 for white noise."""
    xa = np.asarray(x, dtype=np.float64)
    xa = xa - xa.mean()
    n = xa.shape[0]
    if n < 4 or not np.any(xa):
        return 1.0
    size = 1 << int(np.ceil(np.log2(2 * n)))
    spec = np.fft.rfft(xa, size)
    acf = np.fft.irfft(spec * np.conj(spec), size)[:n]
    rho = acf / acf[0]
    lag_max = max(1, int(max_lag_fraction * n))
    neg = np.flatnonzero(rho[1 : lag_max + 1] < 0.0)
    stop = int(neg[0]) + 1 if neg.size else lag_max + 1
    return float(max(1.0, 1.0 + 2.0 * np.sum(rho[1:stop])))


def _jackknife_std(a: F64, yv: F64, n: int, nc: int, blocks: int = 10) -> float:
    """Delete-one-block jackknife standard error of the first parameter (the mass) of the
    stacked least squares a·x = yv, the blocks contiguous in time (the same instants removed
    from every cylinder's rows)."""
    edges = np.linspace(0, n, blocks + 1).astype(int)
    est = np.empty(blocks)
    for k in range(blocks):
        keep = np.ones(n, dtype=bool)
        keep[edges[k] : edges[k + 1]] = False
        rows = np.tile(keep, nc)
        ak = a[rows]
        est[k] = np.linalg.solve(ak.T @ ak, ak.T @ yv[rows])[0]
    return float(np.sqrt((blocks - 1) / blocks * np.sum((est - est.mean()) ** 2)))
