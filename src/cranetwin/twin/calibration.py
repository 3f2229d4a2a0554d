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

A known payload series (a logger's load cell, the import mapping's ``[payload]`` column) at
the sample times: the mass at the load point is then the known payload plus one constant tool-
mass error. Its joint loads (known·g) are moved to the left-hand side and one mass column
(shared by the whole run, no segments) is fitted: ``extra_mass_kg`` is the tool-mass error
alone. Instants where the series is not known (NaN) and within 1 s of a change of it are left
out; the replay behind the fit uses the series too (:mod:`cranetwin.twin.known_payload`). The
residual "before" then has the known payload in it (file friction, no tool-mass error); the
choice of the low-pass below still compares with the force the whole mass makes, as without a
series (else the smaller "before" alone sent a 240 s synthetic run to the wide filter, where
the lift's Fc was lost).

Excitation: b is the slope of force over speed. With white pressure noise (the sensor model's
12.5 kPa) the standard error of the lift's b on a 10-minute ``random`` run is ~5 %, so 10 % is
about 2σ and may be missed on some sensor seeds whatever the estimator (docs/ACCURACY.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from cranetwin import physics
from cranetwin.errors import TwinError
from cranetwin.model import Machine
from cranetwin.samples import SampleArrays
from cranetwin.twin.calibration_data import (
    correlation_time,
    jackknife_std,
    known_payload_changes,
    payload_segments,
    res_rate,
    sample_rate,
    velocity_noise_std,
)
from cranetwin.twin.calibration_fit import (
    VC_GRID,
    Fixed,
    Layout,
    design,
    fit_friction,
    good_rows,
    log_dist,
    lowpass,
    residual_before,
    vc_rises,
)
from cranetwin.twin.known_payload import at_instants
from cranetwin.twin.options import END_STOP_MARGIN_M, ReplayOptions
from cranetwin.twin.replay import replay

F64 = npt.NDArray[np.float64]

# low-pass filters on both sides of the fit: (moving-average passes, width as a multiple of the
# derivative-smoothing window). The narrow one keeps the sharp force step at each reversal that
# determines vc; the wide one removes the hydraulic oscillations that the smoothed accelerations
# miss, and is used when the narrow fit leaves more than WIDE_FILTER_RATIO of the force (RMS
# after / before) unexplained (simulated runs with hydraulics: 2.7–5.7 %; a rigid synthetic
# recording: 0.1–0.2 %, where the wide filter blurs the reversals and loses vc)
NARROW_FILTER = (1, 1.0)
WIDE_FILTER = (2, 2.0)
WIDE_FILTER_RATIO = 0.01
# a friction parameter is identified when its standard error is at most this share of its value
# (the value at least two standard errors from zero)
REL_SE_MAX = 0.5
# rod positions within this share of the stroke (and at least END_STOP_MARGIN_M) of either end
# count as end-stop contact: the stop takes a force Eq. 1–2 does not know
END_STOP_SHARE = 0.01


@dataclass(frozen=True)
class CylinderFit:
    """Friction of one cylinder: file values and estimates (Eq. 2).

    A parameter the data do not identify (standard error above ``REL_SE_MAX`` of its value, a
    value ≤ 0, or for vc a flat residual between vc/2 and 2·vc) keeps the file's value; it
    is listed in ``prior`` and the reason in ``notes``. ``*_std`` are standard errors (NaN
    where the prior was kept; vc has none: its identification is a residual test).
    """

    name: str
    coulomb_file: float
    coulomb: float
    coulomb_velocity_file: float
    coulomb_velocity: float
    viscous_file: float
    viscous: float
    rms_before_n: float
    rms_after_n: float
    coulomb_std: float = float("nan")
    viscous_std: float = float("nan")
    prior: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()


@dataclass(frozen=True)
class MassSegment:
    """A stretch of constant carried mass between payload changes (grab, release).

    Attributes:
        t0_s, t1_s: Its start and end [s] (transitions left out of the fit).
        extra_mass_kg: Mass beyond the file's tool mass there [kg].
        std_kg: Its standard error [kg].
        identified: The total (tool + extra) is physical (≥ 0) and determined.
        note: Why not, when not.
    """

    t0_s: float
    t1_s: float
    extra_mass_kg: float
    std_kg: float
    identified: bool
    note: str = ""


@dataclass(frozen=True)
class Calibration:
    """Result of :func:`calibrate`.

    Attributes:
        cylinders: Friction fits, in ``machine.cylinders`` order.
        extra_mass_kg: Mass at the load point beyond the file's tool mass (payload + tool error)
            of the longest constant-mass segment (``segments``; one when the payload did not
            change) [kg]; NaN when that mass is not identified (``mass_note`` says why). With
            a known payload series: beyond the tool mass and that payload, i.e. the tool-mass
            error (one segment).
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
        segments: The constant-mass segments the payload changes split the run into.
        excluded_s: Seconds left out, by reason (``"end stop"``, ``"payload change"``,
            ``"dropout"``; with a known payload series also ``"payload not known"``).
        mass_note: Why ``extra_mass_kg`` is NaN, else "".
        payload_known: A known payload series was given (``extra_mass_kg`` is the tool-mass
            error).
    """

    cylinders: tuple[CylinderFit, ...]
    extra_mass_kg: float
    extra_mass_std_kg: float
    tool_mass_file_kg: float
    samples_used: int
    offsets_n: tuple[float, ...] = ()
    filter_passes_width: tuple[int, int] = (1, 1)
    velocity_noise_mps: tuple[float, ...] = ()
    segments: tuple[MassSegment, ...] = ()
    excluded_s: dict[str, float] = field(default_factory=dict)
    mass_note: str = ""
    payload_known: bool = False


def calibrate(samples: SampleArrays, machine: Machine, trim_s: float = 1.0,
              decimate: int = 10, payload_kg: F64 | None = None) -> Calibration:
    """Estimate friction (Fc, vc, b per cylinder) and the carried mass by least squares.

    Before the fit, instants are left out where a rod touches an end stop (within
    ``END_STOP_SHARE`` of its stroke: the stop takes a force Eq. 1–2 does not know), where a
    dropout was bridged, and around payload changes; a run whose payload changes (grab,
    release) is split into constant-mass segments, each with its own mass, friction shared.
    After the fit, a friction parameter the data do not identify (:class:`CylinderFit`) and
    any negative Fc, vc or b keeps the file's value and the rest is fitted again; a segment
    whose total mass (tool + extra) comes out negative is reported as not identified, never
    as a mass.

    Args:
        samples: A recording with motion of every cylinder through zero velocity.
        machine: The machine file being calibrated.
        trim_s: Seconds dropped at each end (spline end effects) [s].
        decimate: Use every ``decimate``-th grid instant (1 kHz grid).
        payload_kg: A known payload series at the sample times, shape (n,) [kg], NaN where
            not known (module docstring), or None: the carried mass is fitted per segment.

    Returns:
        :class:`Calibration`.

    Raises:
        TwinError: Too little usable data, or data that does not determine the parameters.
    """
    # motion from the replay (payload estimated there only for the slewing inertia when theta0
    # is integrated from torque); the fit itself uses the raw Eq. 1 force and inverse dynamics.
    # Pressures by fixed (linear) windows: the adaptive ICI choice is nonlinear and biased the
    # viscous coefficient by ~10 % in tests.
    window_s = 4.0
    res = replay(samples, machine, grid_hz=1000.0, payload=payload_kg,
                 options=ReplayOptions(payload_window_s=window_s, adaptive_pressures=False))
    keep = (res.t_s >= res.t_s[0] + trim_s) & (res.t_s <= res.t_s[-1] - trim_s)
    idx = np.flatnonzero(keep)[::decimate]
    if idx.shape[0] < 50:
        raise TwinError(f"calibration needs a longer recording (only {idx.shape[0]} instants)")
    cyls = machine.cylinders
    nc = len(cyls)
    t = res.t_s[idx]
    dt_i = float(np.median(np.diff(t)))
    stroke = np.array([c.stroke_m for c in cyls])
    margin = np.maximum(END_STOP_SHARE * stroke, END_STOP_MARGIN_M)
    rod = res.rod_s[idx]
    stop = np.any((rod <= margin) | (rod >= stroke - margin), axis=1)
    gap = res.gap[idx]
    known = None
    if payload_kg is None:
        seg, n_seg, near, changes = payload_segments(res, t, 1.0 / sample_rate(samples),
                                                     window_s)
        unknown = np.zeros(t.shape[0], dtype=bool)
    else:  # one mass column, the tool-mass error: the known payload's loads move to y
        known = at_instants(t, samples.t_s, np.asarray(payload_kg, dtype=np.float64),
                            5.0 / sample_rate(samples))
        near, _ = known_payload_changes(t, known)
        seg, n_seg, changes = np.zeros(t.shape[0], dtype=np.int64), 1, []
        unknown = ~np.isfinite(known)
    ok = ~(stop | near | gap | unknown)
    excluded = {"end stop": float(stop.sum() * dt_i),
                "payload change": float((near & ~stop).sum() * dt_i),
                "dropout": float((gap & ~stop & ~near).sum() * dt_i)}
    if known is not None:
        excluded["payload not known"] = float((unknown & ~stop & ~near & ~gap).sum() * dt_i)
    q, qd, qdd = res.q[idx], res.qd[idx], res.qdd[idx]
    tau0 = physics.joint_torques(machine, q, qd, qdd, 0.0)
    g_all = physics.joint_torques(machine, q, qd, qdd, 1.0) - tau0
    _, arm = physics.cylinder_kinematics(machine, q)
    cj = [machine.joint_index(c.joint) for c in cyls]
    hyd = np.column_stack([res.p_a[idx, c] * cyl.area_a_m2 - res.p_b[idx, c] * cyl.area_b_m2
                           for c, cyl in enumerate(cyls)])
    y = hyd - tau0[:, cj] / arm  # what friction and the extra mass must explain [N]
    g = g_all[:, cj] / arm
    y_all = y  # the force with the whole carried mass in it (the filter choice's reference)
    if known is not None:  # (0 where not known: those instants are left out, and a NaN
        y = y - np.nan_to_num(known)[:, None] * g  # would spread through the moving sums)
    v = res.rod_v[idx]
    # "filter both sides": the accelerations come smoothed over the derivative window, the
    # pressures carry the fast hydraulic oscillations they miss; the same moving average on
    # the force and on every regressor removes that mismatch without biasing the parameters
    wd = max((c.window for k, c in res.smoothing.items() if k.endswith("'")), default=1)
    unit = wd * res_rate(res) / decimate / sample_rate(samples)
    filters = [(p, max(1, int(round(k * unit)))) for p, k in (NARROW_FILTER, WIDE_FILTER)]
    lay = Layout(seg, n_seg, ok)
    usable = [int(good_rows(lay, w_, p_, 1).sum()) for p_, w_ in filters]
    if usable[0] < 50:
        w_ = filters[0][1]
        raise TwinError(
            f"calibration needs more usable data: {usable[0]} instants left for filters of "
            f"{w_} instants after leaving out {excluded['end stop']:.1f} s of end-stop "
            f"contact, {excluded['payload change']:.1f} s around payload changes, "
            f"{excluded['dropout']:.1f} s of dropouts"
            + (f" and {excluded['payload not known']:.1f} s where the known payload is not "
               "known" if known is not None else ""))
    vc0 = np.array([c.friction.coulomb_velocity for c in cyls])
    sigma_v = velocity_noise_std(res, samples, machine)
    no_fix = Fixed({}, np.zeros(nc, dtype=bool))
    filt = filters[0]
    try:
        x, r, vc, _ = fit_friction(y, g, v, vc0, filt, sigma_v, lay, no_fix)
        before = [residual_before(y_all, v, cyls, c, filt[1], filt[0], lay)
                  for c in range(nc)]
        n = before[0].shape[0]
        ratio = max(float(np.sqrt(np.mean(r[c * n:(c + 1) * n] ** 2) / np.mean(before[c] ** 2)))
                    for c in range(nc))
        if ratio > WIDE_FILTER_RATIO and usable[1] >= 50:  # oscillations left: the wide filter
            filt = filters[1]
            x, r, vc, _ = fit_friction(y, g, v, vc, filt, sigma_v, lay, no_fix)
        fixed, notes = _identify(x, r, vc, (y, g, v, sigma_v), filt, lay, machine)
        if fixed.cols or fixed.vc.any():
            vc = np.where(fixed.vc, vc0, vc)
            x, r, vc, _ = fit_friction(y, g, v, vc, filt, sigma_v, lay, fixed)
        passes, width = filt
        rows = good_rows(lay, width, passes, nc)
        n = int(rows.sum()) // nc
        a = design(vc, v, g, width, passes, sigma_v, lay)[rows]
        dof = max(a.shape[0] - a.shape[1] + len(fixed.cols), 1)
        sigma2 = float(np.dot(r, r)) / dof
        # the residuals are low-passed (smoothing, then the moving averages above): neighbours
        # are correlated, so the independent-errors covariance is scaled by the residuals'
        # integrated autocorrelation time; errors that drift over the recording (model
        # mismatch) show in a delete-one-block jackknife over time instead: the larger of the
        # two is reported for the mass
        tau = max(correlation_time(r[c * n : (c + 1) * n]) for c in range(nc))
        free = [k for k in range(a.shape[1]) if k not in fixed.cols]
        cov = np.full((a.shape[1], a.shape[1]), np.nan)
        cov[np.ix_(free, free)] = sigma2 * tau * np.linalg.inv(a[:, free].T @ a[:, free])
        yv = lowpass(y, width, passes).T.reshape(-1)[rows]
        fix_idx = sorted(fixed.cols)
        rhs = yv - a[:, fix_idx] @ np.array([fixed.cols[k] for k in fix_idx]) if fix_idx else yv
        jack = jackknife_std(a[:, free], rhs, n, nc) if n_seg == 1 else 0.0
    except np.linalg.LinAlgError as exc:
        raise TwinError("the recording does not determine the friction and mass "
                        "(no motion of some cylinder?)") from exc
    se = np.sqrt(np.diag(cov))
    segs = _mass_segments(x, se, jack, t, seg, n_seg, changes, machine.load_point.tool_mass_kg)
    main = max(range(n_seg), key=lambda k: int(np.sum((seg == k) & ok)))
    fits = []
    for c, cyl in enumerate(cyls):
        fr = cyl.friction
        b0 = residual_before(y, v, cyls, c, width, passes, lay)
        after = r[c * n : (c + 1) * n]
        k0 = n_seg + 3 * c
        prior = tuple(name for name, col in (("Fc", k0), ("b", k0 + 1)) if col in fixed.cols)
        prior += ("vc",) if fixed.vc[c] else ()
        fits.append(CylinderFit(
            name=cyl.name, coulomb_file=fr.coulomb, coulomb=float(x[k0]),
            coulomb_velocity_file=fr.coulomb_velocity, coulomb_velocity=float(vc[c]),
            viscous_file=fr.viscous, viscous=float(x[k0 + 1]),
            rms_before_n=float(np.sqrt(np.mean(b0**2))),
            rms_after_n=float(np.sqrt(np.mean(after**2))),
            coulomb_std=float(se[k0]), viscous_std=float(se[k0 + 1]), prior=prior,
            notes=tuple(notes[c])))
    ms = segs[main]
    return Calibration(tuple(fits), ms.extra_mass_kg if ms.identified else float("nan"),
                       ms.std_kg, machine.load_point.tool_mass_kg, n,
                       tuple(float(x[n_seg + 2 + 3 * c]) for c in range(nc)), (passes, width),
                       tuple(float(sv) for sv in sigma_v), tuple(segs), excluded,
                       "" if ms.identified else ms.note, known is not None)


def _identify(x: F64, r: F64, vc: F64, data: tuple[F64, F64, F64, F64],
              filt: tuple[int, int], lay: Layout,
              machine: Machine) -> tuple[Fixed, list[list[str]]]:
    """Which friction parameters keep the file's value (:class:`CylinderFit`), and why."""
    y, g, v, sigma_v = data
    cyls = machine.cylinders
    nc = len(cyls)
    passes, width = filt
    rows = good_rows(lay, width, passes, nc)
    n = int(rows.sum()) // nc
    a = design(vc, v, g, width, passes, sigma_v, lay)[rows]
    dof = max(a.shape[0] - a.shape[1], 1)
    sigma2 = float(np.dot(r, r)) / dof
    tau = max(correlation_time(r[c * n : (c + 1) * n]) for c in range(nc))
    try:
        se = np.sqrt(np.abs(np.diag(sigma2 * tau * np.linalg.pinv(a.T @ a))))
        cond = float(np.linalg.cond(a / np.maximum(np.linalg.norm(a, axis=0), 1e-300)))
    except np.linalg.LinAlgError:
        se = np.full(a.shape[1], np.inf)
        cond = np.inf
    cols: dict[int, float] = {}
    hold_vc = np.zeros(nc, dtype=bool)
    notes: list[list[str]] = [[] for _ in range(nc)]
    for c, cyl in enumerate(cyls):
        k0 = lay.n_seg + 3 * c
        for name, k, prior in (("Fc", k0, cyl.friction.coulomb),
                               ("b", k0 + 1, cyl.friction.viscous)):
            val, err = float(x[k]), float(se[k])
            if not val > 0.0:
                cols[k] = prior
                notes[c].append(f"{name} came out {val:.4g} (≤ 0, not physical): file value "
                                f"{prior:g} kept")
            elif not err <= REL_SE_MAX * val:
                cols[k] = prior
                notes[c].append(f"{name} = {val:.4g} ± {err:.2g} not determined by the data "
                                f"(standard error > {100 * REL_SE_MAX:.0f} %; condition "
                                f"number {cond:.2g}): file value {prior:g} kept")
        vc_file = cyl.friction.coulomb_velocity
        if k0 in cols:
            hold_vc[c] = True
            notes[c].append("vc: file value kept (Fc not determined)")
            continue
        # a likelihood-ratio test: one standard error of vc raises the residual sum of
        # squares by σ²·τ (τ: the residuals' correlation time)
        half, double = vc_rises(y, g, v, vc, filt, sigma_v, lay, c,
                                 (0.5 * vc[c], 2.0 * vc[c]))
        unit = sigma2 * tau
        edge = log_dist(vc[c]) < float(np.log(VC_GRID[1] / VC_GRID[0]))
        # the standard errors here come out several times the actual errors on simulated runs
        # (the residuals are mostly smoothing error, not noise), and holding a weakly
        # determined vc at a wrong file value biased b by 10 %: so only a vc at the end of the
        # search range (no minimum inside it) keeps the file value; a flat one is reported
        if edge:
            hold_vc[c] = True
            notes[c].append(f"vc = {1e3 * vc[c]:.3g} mm/s not determined (at the end of the "
                            f"search range, {1e3 * VC_GRID[0]:g}–{1e3 * VC_GRID[-1]:g} mm/s): "
                            f"file value {1e3 * vc_file:.3g} mm/s kept")
        elif min(half, double) < unit:
            notes[c].append(f"vc = {1e3 * vc[c]:.3g} mm/s weakly determined (vc/2 or 2·vc "
                            "within one standard error)")
    return Fixed(cols, hold_vc), notes


def _mass_segments(x: F64, se: F64, jack: float, t: F64, seg: npt.NDArray[np.int64],
                   n_seg: int, changes: list[float], tool_kg: float) -> list[MassSegment]:
    """One :class:`MassSegment` per constant-mass stretch; a negative total is no answer."""
    bounds = [float(t[0]), *changes, float(t[-1])]
    out = []
    for k in range(n_seg):
        m, s = float(x[k]), max(float(se[k]), jack)
        total = tool_kg + m
        if not np.isfinite(m):
            out.append(MassSegment(bounds[k], bounds[k + 1], m, s, False,
                                   "not determined (no usable instants)"))
        elif total < 0.0:
            out.append(MassSegment(bounds[k], bounds[k + 1], m, s, False,
                                   f"the fit gives a total mass of {total:.1f} kg at the load "
                                   f"point (tool {tool_kg:g} kg {m:+.1f} kg), which is not "
                                   "physical: the run does not determine it (too little "
                                   "motion of the boom, or a model error)"))
        else:
            out.append(MassSegment(bounds[k], bounds[k + 1], m, s, True))
    return out

