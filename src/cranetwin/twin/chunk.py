"""The replay's chunk stage: every output at the grid instants of samples [ka, kb).

Per chunk, as a pure function of the plan and the buffered rows the stream hands over:
natural splines of the smoothed rows (values, rates, accelerations; :func:`splines`), the
state at the sample instants of an extended range (the payload window reaches ``wh`` samples
on each side), the payload estimate and mass matrices there, then every grid quantity by
:func:`cranetwin.twin.gridpass.grid_pass`. Shapes: n grid rows, n_j joints, n_c cylinders.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from cranetwin.errors import TwinError
from cranetwin.signal import SmoothingChoice, knot_pieces, natural_pieces, newton_derivative
from cranetwin.twin import force_model, gridpass
from cranetwin.twin.known_payload import fully_known, with_known
from cranetwin.twin.plan import ReplayPlan
from cranetwin.twin.result import TwinResult
from cranetwin.twin.stages import (
    clip_rods,
    eq12,
    estimate_payload,
    joint_motion,
    payload_regressors,
    unpack_states,
)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]


class ChunkRows(NamedTuple):
    """What the stream's buffers hold for one chunk.

    Attributes:
        ka, kb: Output samples [ka, kb) (through kb − 1 … the end if ``last``).
        last: The stream's last chunk.
        f0: Index of the first smoothed row (the splines' first knot).
        e0, e1: Sample instants (inclusive) of the payload and mass-matrix stage.
        sm: Smoothed rows f0 … (:mod:`cranetwin.twin.plan` layout).
        cs: Cylinder states rows e0 … e1 the integration computed, or None.
        gap: Rows ka … kb − 1 of the gap flags, (kb − ka,) > 0 inside a bridged dropout.
        r0: First sample of the model-based forces' residuals
            (:func:`cranetwin.twin.force_model.residual_range`).
        raw: The regularised, unsmoothed pressures at samples r0 … (pA then pB per cylinder,
            (m, 2·n_c) [Pa]), a quantised channel reconstructed as the smoothing does
            (:func:`cranetwin.twin.force_model.raw_pressures`); m = 0 when no force is
            model-based.
        known: A known payload series at samples e0 … e1, (e1 − e0 + 1,) [kg], NaN where not
            known (:mod:`cranetwin.twin.known_payload`); None: none.
    """

    ka: int
    kb: int
    last: bool
    f0: int
    e0: int
    e1: int
    sm: F64
    cs: F64 | None
    gap: F64
    r0: int
    raw: F64
    known: F64 | None = None


class Timing(NamedTuple):
    """Sample period [s], time of sample 0 [s], grid points per sample."""

    period: float
    origin: float
    r: int


class PayloadSetting(NamedTuple):
    """A constant known payload [kg] (or None: estimated where no series is known,
    :attr:`ChunkRows.known`) and the regression's weights (n_c,),
    independent fractions (n_c,), prefilter half and half window [samples], raw force noise
    per cylinder (n_c,) [N], systematic force error per cylinder (n_c,) [N]
    (:func:`cranetwin.twin.stages.payload_weights`)."""

    known: float | None
    weights: F64
    frac: F64
    prefilter_half: int
    half_window: int
    noise: F64
    systematic: F64


def splines(plan: ReplayPlan, knots_t: F64, sm: F64, r: int) -> tuple[F64, I64, I64]:
    """One natural spline over every column the grid needs and the quantity table
    (:mod:`cranetwin.twin.gridpass`) saying which column (and derivative) is what.

    Rates and accelerations are the Savitzky–Golay derivative filters at the samples, splined
    (``velocity="spline"``); or Newton's divided differences of the smoothed positions,
    splined, and that spline's derivative (``"newton"``, the paper's way). An integrated
    angle takes its rate and acceleration from its own spline. With one grid row per sample
    (r = 1, the worker's grid) the grid reads the splines at their knots only: only the
    columns read with a derivative are solved for (:func:`cranetwin.signal.knot_pieces`).
    """
    pos_cols, cols, src, der = plan.layout
    data = sm[:, cols]
    if plan.opt.velocity == "newton":
        extra = newton_derivative(knots_t, sm[:, pos_cols], 2 if sm.shape[0] >= 5 else 1)
        data = np.concatenate([data, extra], axis=1)
    if r == 1:
        splined = sorted({int(c) for c, d in zip(src, der, strict=True) if c >= 0 and d > 0})
        return knot_pieces(knots_t, data, splined), src, der
    return natural_pieces(knots_t, data), src, der


def chunk(plan: ReplayPlan, rows: ChunkRows, timing: Timing, payload: PayloadSetting,
          choices: tuple[SmoothingChoice, ...]) -> TwinResult:
    """Outputs at samples [ka, kb) of ``rows`` (module docstring)."""
    m = plan.machine
    ka, kb, last, f0, e0, e1 = rows.ka, rows.kb, rows.last, rows.f0, rows.e0, rows.e1
    r, p = timing.r, timing.period
    nc = len(m.cylinders)
    nj = m.n_joints
    nfree = len(plan.free)
    qi = plan.qi
    knots_t: F64 = np.arange(f0, f0 + rows.sm.shape[0], dtype=np.float64) * p
    coef, src, der = splines(plan, knots_t, rows.sm, r)
    h0 = float(knots_t[1] - knots_t[0])
    h_last = float(knots_t[-1] - knots_t[-2])
    # -- the sample instants e0 … e1: state, actuator loads, payload --------------------------
    ne = e1 - e0 + 1
    # free joints whose angle the splines carry (from a channel or integrated)
    thetas = [f for f in range(nfree) if src[qi.free + 3 * f] >= 0]
    rod_v, rod_a = slice(qi.v, qi.v + nc), slice(qi.a, qi.a + nc)
    # the spline at a knot is the knot's value, except the end knot (last piece at h_last)
    at_samples = gridpass.Splines(coef, e0 - f0, 1, h0, h_last, src, der, qi)
    free_q = slice(qi.free, qi.free + 3 * nfree)
    f_s: F64 | None = None
    if rows.cs is not None:  # cylinder joints' motion, arms and forces as integrated
        theta = np.empty((ne, 3 * nfree))  # only the free joints' angles from the spline
        gridpass.spline_points(at_samples._replace(src=src[free_q], der=der[free_q]), ne,
                               theta)
        q_s = np.empty((ne, nj))
        qd_s = np.empty((ne, nj))
        qdd_s = np.empty((ne, nj))
        arm_s = np.empty((ne, nc))
        f_s = np.empty((ne, nc))
        unpack_states(rows.cs, plan.cyl_joint, theta[:, 0], plan.free[0] if thetas else -1,
                      q_s, qd_s, qdd_s, arm_s, f_s)
        smp = theta
    else:
        smp = np.empty((ne, src.shape[0]))
        gridpass.spline_points(at_samples, ne, smp)
        theta = smp[:, free_q]  # per free joint: angle, rate, acceleration
        q_other = np.tile(plan.free_joints.hold, (ne, 1))
        for f in thetas:
            q_other[:, f] = theta[:, 3 * f]
        q_s, qd_s, qdd_s, arm_s = joint_motion(plan, clip_rods(plan, smp[:, qi.s : qi.s + nc]),
                                               smp[:, rod_v], smp[:, rod_a], q_other)
    for f in thetas:
        qd_s[:, plan.free[f]] = theta[:, 3 * f + 1]
        qdd_s[:, plan.free[f]] = theta[:, 3 * f + 2]
    ks = slice(ka - e0, min(kb - e0 + 1, ne))  # samples ka … kb (if there)
    n_ks = ks.stop - ks.start
    use = force_model.model_cylinders(plan, choices)
    modelled = bool(use.any()) and rows.raw.shape[0] > 0
    known = rows.known if payload.known is None else np.full(ne, float(payload.known))
    estimated = not fully_known(known)
    regs = (payload_regressors(plan, (q_s, qd_s, qdd_s))
            if modelled or estimated else None)
    if f_s is None and (modelled or estimated):
        f_s = eq12(plan, smp[:, qi.pa : qi.pa + nc], smp[:, qi.pb : qi.pb + nc],
                   smp[:, rod_v])
    if not estimated:
        assert known is not None
        m_all = known
        mk = np.ascontiguousarray(known[ks])
        sk = np.zeros(n_ks)
        bk = np.zeros(n_ks)
    else:
        assert f_s is not None
        b_all = np.empty(ne)
        m_all, s_all = with_known(known, *estimate_payload(
            plan, (q_s, qd_s, qdd_s), f_s, arm_s,
            (payload.weights, payload.frac, payload.prefilter_half, payload.half_window,
             payload.noise, payload.systematic), regs, b_all))
        _, b_all = with_known(known, m_all, b_all)
        mk, sk = np.ascontiguousarray(m_all[ks]), np.ascontiguousarray(s_all[ks])
        bk = b_all[ks]
    dynamic = plan.opt.wrench_acceleration == "dynamic"
    # the joints whose loads are measured: every cylinder's, every drive's with a torque
    full = sorted(plan.cyl_joint.tolist()
                  + [j for j, t in zip(plan.drive_joints, plan.cmap.torques, strict=True)
                     if t is not None])
    if dynamic:
        mm = np.empty((n_ks, nj, nj))
        plan.kernels.mass_matrix(np.ascontiguousarray(q_s[ks]),
                                 np.nan_to_num(np.maximum(mk, 0.0)), mm)
        minv = np.empty((mm.shape[0], len(full), len(full)))
        minv_ok = np.empty(mm.shape[0], dtype=bool)
        gridpass.dd_inverse_batch(mm, np.array(full, dtype=np.int64), minv, minv_ok)
    else:
        mm = np.zeros((1, nj, nj))
        minv = np.zeros((1, len(full), len(full)))
        minv_ok = np.zeros(1, dtype=bool)
    # -- the grid ---------------------------------------------------------------------------
    n = (kb - 1 - ka) * r + 1 if last else (kb - ka) * r
    gap = rows.gap > 0
    gap_g = np.repeat(gap, r)[:n] if r > 1 else gap[:n]
    if gap_g.shape[0] < n:
        gap_g = np.concatenate([gap_g, np.zeros(n - gap_g.shape[0], dtype=bool)])
    out = gridpass.GridOut.empty(n, nj, nc, np.ascontiguousarray(gap_g))
    # one grid row per sample: the cylinder states the integration computed at the samples
    # are the grid's (same arithmetic on the same smoothed values)
    pre = (rows.cs[ka - e0 : ka - e0 + n] if r == 1 and rows.cs is not None
           else np.empty((0, 5 * nc)))
    model = None
    if modelled:
        assert regs is not None and f_s is not None
        model = (use, _model_residual(plan, rows, e0, (regs, m_all, arm_s, f_s), choices,
                                      (r, n)))
    bad = gridpass.grid_pass(
        gridpass.Splines(coef, ka - f0, r, h0, h_last, src, der, qi), plan.cylinders,
        plan.free_joints, gridpass.SampleState(mk, sk, mm, minv, minv_ok, len(full), dynamic),
        out, plan.kernels, pre, model)
    if bad:
        bad_rows = ~np.all(np.isfinite(out.q), axis=1)
        joint_motion(plan, out.rod_s[bad_rows], out.rod_v[bad_rows], out.rod_v[bad_rows],
                     np.tile(plan.free_joints.hold, (int(bad_rows.sum()), 1)))
        raise TwinError(f"rod positions do not fit the machine geometry at {bad} instants")
    t = np.arange(n, dtype=np.float64)  # origin + (ka + g/r)·p, in place
    t /= r
    t += ka
    t *= p
    t += timing.origin
    return TwinResult(
        t_s=t, q=out.q, qd=out.qd, qdd=out.qdd, rod_s=out.rod_s, rod_v=out.rod_v,
        p_a=out.pa, p_b=out.pb, cyl_force=out.force, actuator_torque=out.tau_act,
        id_torque=out.tau_id, residual=out.resid, joint_wrench=out.wrench,
        payload_kg=out.mass, payload_std_kg=out.std,
        payload_sys_std_kg=_at_grid(bk, r, n), gap=gap_g,
        smoothing=dict(zip(plan.cmap.choice_names, choices, strict=True)),
    )


def _at_grid(at_samples: F64, r: int, n: int) -> F64:
    """A per-sample series (samples ka … , (ns,)) at the chunk's n grid rows, linear between
    samples as the grid pass carries the payload and its σ (row g: sample g // r, fraction
    (g mod r)/r; past the last sample its value)."""
    if r == 1:
        return np.array(at_samples[:n], dtype=np.float64)
    g = np.arange(n)
    s0 = g // r
    fr = (g - s0 * r) / r
    u1 = np.minimum(s0 + 1, at_samples.shape[0] - 1)
    a: F64 = at_samples[s0]
    out: F64 = a + fr * (at_samples[u1] - a)
    return out


def _model_residual(plan: ReplayPlan, rows: ChunkRows, e0: int,
                    at_samples: tuple[tuple[F64, F64], F64, F64, F64],
                    choices: tuple[SmoothingChoice, ...], grid: tuple[int, int]) -> F64:
    """The smoothed residual F_raw − F_model (:mod:`cranetwin.twin.force_model`) at the n
    grid rows of the chunk, (n, n_c) [N]; at_samples = ((t0, t1) payload regressors, payload
    estimate, moment arms, pressure-smoothed forces) at samples e0 … (the residual range
    rows.r0 … lies within), grid = (rows per sample, n)."""
    (t0, t1), mass, arm, f_s = at_samples
    r, n = grid
    col = plan.sample_cols
    nc = len(plan.machine.cylinders)
    a, b = rows.r0 - e0, rows.r0 - e0 + rows.raw.shape[0]
    sm = rows.sm[rows.r0 - rows.f0 : rows.r0 - rows.f0 + rows.raw.shape[0]]
    v = sm[:, col.v0 : col.v0 + nc]
    pl = np.nan_to_num(np.maximum(mass[a:b], 0.0))
    tau = t0[a:b] + pl[:, None] * (t1[a:b] - t0[a:b])
    f_model = force_model.model_forces(plan, tau, arm[a:b], sm[:, col.s], f_s[a:b])
    raw_f = eq12(plan, np.ascontiguousarray(rows.raw[:, :nc]),
                 np.ascontiguousarray(rows.raw[:, nc:]), np.ascontiguousarray(v))
    sigma = np.array([choices[i].sigma for i in plan.cmap.p_a])
    corr = force_model.residual_correction(raw_f, f_model, sigma,
                                           force_model.model_cylinders(plan, choices))
    return force_model.interpolate(corr[rows.ka - rows.r0 :], r, n)
