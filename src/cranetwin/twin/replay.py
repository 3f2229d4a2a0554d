"""Replay: sparse, noisy sensor samples in; motion and loads of the machine on a fine grid out.

Pipeline (paper Sect. 2, with the steps it leaves open made explicit)::

    samples ─ regularise (irregular times, dropouts) ─ Savitzky–Golay (window from noise level)
      ─ natural cubic spline to the grid (values, rate, acceleration)
      ─ kinematics: theta1, theta2, L from the rod positions; theta0 from the slew-angle channel
        or by integrating the slewing dynamics from the pillar torque
      ─ cylinder forces, Eq. 1–2 (or, where the pressures cannot resolve a force, the
        inverse dynamics corrected by the smoothed pressure residual,
        :mod:`cranetwin.twin.force_model`) ─ actuator joint loads F·ds/dq
      ─ payload by sliding-window least squares (where not known: a constant, or a series
        with NaN where not known, :mod:`cranetwin.twin.known_payload`) ─ inverse dynamics
        (RNEA): joint loads, residual, joint reaction wrenches

Everything runs per *chunk* of samples with enough overlap that every output instant sees the
same data as a whole-recording computation would: Savitzky–Golay is a finite filter, the
natural spline's dependence on far knots decays by ≈ 0.27 per knot (``settle_samples`` knots of
margin leave < 1e-20 of it), the payload window is centred, and so is the model-based
forces' residual smoothing (its range reaching a whole window at the recording's ends). So the
streaming form (:class:`TwinStream`, fed block by block as datagrams arrive) equals the batch form
(:func:`replay`), which is the stream fed everything at once — seams included.

Where the work is done: :class:`TwinStream` only buffers samples and keeps indices; the
stages are pure functions of the plan (:mod:`cranetwin.twin.plan`) and arrays. At the 100 Hz
instants: smoothing and the cylinder states (:mod:`cranetwin.twin.stages`), the payload
regression (:mod:`cranetwin.twin.payload`), the free-joint integration
(:mod:`cranetwin.twin.slew`); per chunk, :func:`cranetwin.twin.chunk.chunk` (splines, the
payload and mass matrices at the samples) and :func:`cranetwin.twin.gridpass.grid_pass`
(table-driven inverse kinematics, Eq. 1–2, the machine's batch RNEA, the Eq. 3/4
correction, the wrenches) at every grid instant. Free
joints (no cylinder drives them): each one with a torque drive takes its angle from its angle
channel, or, without one, integrates it from its torque (:mod:`cranetwin.twin.slew`, in drive
order; the first starts at ``theta0_initial``, any other at 0); a passive joint (no
actuator) is held at its ``fixed_value``. The kinematics tables (quintic Hermite pieces of the
exact inverse, 2048 cells per stroke) agree with the exact inverse to 1e-11 in q and ds/dq
and 1e-8 of the largest d²s/dq²; M_DD⁻¹ is interpolated between samples (agreement with the
exact M(q) at every instant: 1.5e-5 of the wrench range). ``tests/test_twin_gridpass.py``
recomputes every output through the separate physics functions.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import numpy.typing as npt

from cranetwin.errors import TwinError
from cranetwin.model import Machine
from cranetwin.model.positions import rod_position_problem
from cranetwin.samples import SampleArrays
from cranetwin.signal import SmoothingChoice, nominal_period, regularize
from cranetwin.twin import force_model
from cranetwin.twin.buffer import RowBuffer
from cranetwin.twin.channels import choose_smoothing
from cranetwin.twin.chunk import ChunkRows, PayloadSetting, Timing, chunk
from cranetwin.twin.known_payload import at_instants, fully_known
from cranetwin.twin.model_choice import choose_model
from cranetwin.twin.options import END_STOP_MARGIN_M, HasSamples, ReplayOptions
from cranetwin.twin.plan import ReplayPlan
from cranetwin.twin.result import TwinResult
from cranetwin.twin.slew import SlewState, integrate_free_joints
from cranetwin.twin.stages import (
    derivative_filter,
    estimate_payload,
    margins,
    payload_weights,
    sample_states,
    smooth_rows,
)

F64 = npt.NDArray[np.float64]

ROD_CHECK_SAMPLES = 200
"""Samples the rod-position convention check looks at (:meth:`TwinStream._check_rods`)."""

__all__ = ["END_STOP_MARGIN_M", "HasSamples", "ReplayOptions", "TwinStream",
           "derivative_filter", "iter_replay", "replay"]


class TwinStream:
    """Replay fed block by block; yields results for every instant that can no longer change.

    Holds the buffers (raw, regularised, gap flags, smoothed rows, cylinder states) and how
    far each stage has got; the stages themselves are pure functions (module docstring).

    Args:
        machine: Machine description.
        channels: Column names of the sample arrays that will be pushed.
        options: Replay settings.
        payload: Known constant payload [kg], or None to estimate it from the pressures
            (where a known payload series pushed with the samples, :meth:`push`, is NaN or
            absent).
    """

    def __init__(self, machine: Machine, channels: tuple[str, ...],
                 options: ReplayOptions | None = None, payload: float | None = None) -> None:
        self.machine = machine
        self.opt = options or ReplayOptions()
        self.payload = payload
        self.plan = ReplayPlan.of(machine, channels, self.opt)
        self.cmap = self.plan.cmap
        nch = self.plan.nch
        self._raw_t = np.empty(0)
        self._raw_v = np.empty((0, nch))
        # a known payload series: at the raw samples (NaN: not known), at the regular
        # instants (twin.known_payload); None until a series is pushed
        self._raw_k: F64 | None = None
        self._known: RowBuffer | None = None
        self._origin: float | None = None
        self._period: float | None = self.opt.sample_period_s
        self._r = 0
        self._choices: tuple[SmoothingChoice, ...] | None = self.opt.smoothing
        n_choice = len(self.cmap.choice_names)
        if self._choices is not None and len(self._choices) != n_choice:
            raise TwinError(f"smoothing: expected {n_choice} choices {self.cmap.choice_names}, "
                            f"got {len(self._choices)}")
        self._reg = RowBuffer(nch)
        self._gap = RowBuffer(1)
        self._sm = RowBuffer(self.plan.width)  # smoothed rows (twin.plan layout)
        self._sm_valid = 0  # smoothed rows [.., _sm_valid) have final values
        self._theta_done = 0  # integrated angles final in rows [.., _theta_done)
        # cylinder states rows at the samples (twin.stages.cylinder_states) as the integration
        # computed them, reused by the chunks when plan.use_cs
        self._cs = RowBuffer(5 * len(machine.cylinders))
        self._out_done = 0
        # the first integrated joint (the slew) starts at theta0_initial, any other at 0
        self._slew = [SlewState(theta0=self.opt.theta0_initial if i == 0 else 0.0)
                      for i in range(self.plan.n_int)]
        self._pw_cache: tuple[tuple[SmoothingChoice, ...], F64, F64, F64, F64] | None = None
        self._finished = False
        self._rods_checked = False

    # -- geometry of the margins -------------------------------------------------------------
    def _margins(self) -> tuple[int, int, int]:
        assert self._period is not None
        return margins(self._choices, self.plan.nch, self._period, self.opt.payload_window_s)

    @property
    def _hw(self) -> int:
        return self._margins()[0] if self._choices is not None else 0

    @property
    def _wh(self) -> int:
        """Samples the payload estimate at an instant reaches on each side."""
        _, half, pf = self._margins()
        return half + pf // 2

    @property
    def _fh(self) -> int:
        """Samples the model-based forces' residual smoothing reaches on each side
        (:mod:`cranetwin.twin.force_model`; 0 when no force is model-based)."""
        return force_model.model_half(self.plan, self._choices)

    @property
    def _fc(self) -> int:
        """Samples of context on each side of the residual's range that its raw pressures'
        reconstruction needs (:func:`cranetwin.twin.force_model.raw_context`)."""
        return force_model.raw_context(self.plan, self._choices)

    def _payload_setting(self) -> PayloadSetting:
        assert self._choices is not None
        hit = self._pw_cache
        if hit is None or hit[0] is not self._choices:
            hit = (self._choices, *payload_weights(self.plan, self._choices))
            self._pw_cache = hit
        _, half, pf = self._margins()
        return PayloadSetting(self.payload, hit[1], hit[2], pf // 2, half, hit[3], hit[4])

    # -- public API ----------------------------------------------------------------------------
    def set_smoothing(self, choices: tuple[SmoothingChoice, ...]) -> None:
        """Fix the smoothing choices (``cmap.choice_names`` order) before the first push."""
        if len(choices) != len(self.cmap.choice_names):
            raise TwinError(f"smoothing: expected {len(self.cmap.choice_names)} choices")
        if self._reg.end:
            raise TwinError("smoothing can only be set before data are pushed")
        self._choices = tuple(choices)

    def push(self, samples: SampleArrays, payload_kg: F64 | None = None) -> TwinResult | None:
        """Add samples (in time order, after those pushed before); return what became final.

        ``payload_kg``: a known payload at these samples, shape (n,) [kg], NaN where not known
        (:mod:`cranetwin.twin.known_payload`); None: not known (NaN) at these samples.
        Not with a constant ``payload``."""
        parts = list(self.push_iter(samples, payload_kg))
        return TwinResult.concat(parts) if parts else None

    def flush(self) -> TwinResult | None:
        """End of the stream: return everything not yet returned."""
        parts = list(self.flush_iter())
        return TwinResult.concat(parts) if parts else None

    def push_iter(self, samples: SampleArrays,
                  payload_kg: F64 | None = None) -> Iterator[TwinResult]:
        """Like :meth:`push`, one chunk at a time (bounded memory for long recordings)."""
        if self._finished:
            raise TwinError("stream already flushed")
        t = np.asarray(samples.t_s, dtype=np.float64)
        if t.shape[0] == 0:
            return
        if self._raw_t.shape[0] and not t[0] > self._raw_t[-1]:
            raise TwinError("pushed samples must come after the samples pushed before")
        self._push_known(t.shape[0], payload_kg)
        vals = np.asarray(samples.values, dtype=np.float64)
        if self.plan.cols != list(range(vals.shape[1])):
            vals = vals[:, self.plan.cols]
        if self._period is None and samples.period_ns is not None:
            self._period = nominal_period(t, samples.period_ns)
        self._raw_t = np.concatenate([self._raw_t, t])
        self._raw_v = np.concatenate([self._raw_v, vals])
        if self._raw_t.shape[0] >= ROD_CHECK_SAMPLES:
            self._check_rods()
        yield from self._advance(final=False)

    def _push_known(self, n: int, payload_kg: F64 | None) -> None:
        """Keep a known payload series with the raw samples (NaN where none was pushed)."""
        if payload_kg is not None:
            k = np.asarray(payload_kg, dtype=np.float64)
            if k.shape != (n,):
                raise TwinError(f"known payload has shape {k.shape}; the samples ({n},)")
            if self.payload is not None:
                raise TwinError("a known payload series and a constant payload: give one")
            if self._raw_k is None:  # the samples pushed before: not known
                self._raw_k = np.full(self._raw_t.shape[0], np.nan)
                self._known = RowBuffer(1)
                self._known.base = self._reg.base
                if self._reg.end > self._reg.base:
                    self._known.append(np.full((self._reg.end - self._reg.base, 1), np.nan))
        elif self._raw_k is None:
            return
        else:
            k = np.full(n, np.nan)
        assert self._raw_k is not None
        self._raw_k = np.concatenate([self._raw_k, k])

    def _known_rows(self, k0: int, k1: int) -> F64 | None:
        """The known payload at regular samples [k0, k1) [kg] (NaN: not known), or None
        when no series was pushed."""
        return None if self._known is None else self._known.get(k0, k1)[:, 0]

    def _check_rods(self) -> None:
        """Refuse rod positions that are no stroke positions (:mod:`cranetwin.model.positions`),
        once, on the first ``ROD_CHECK_SAMPLES`` samples (or all, if the stream is shorter):
        nearly all of them outside the stroke is a convention or unit mix-up, which clipping
        would hide."""
        if self._rods_checked:
            return
        self._rods_checked = True
        for k, cyl in enumerate(self.machine.cylinders):
            col = self.plan.cmap.s[k]
            problem = rod_position_problem(self.plan.cmap.names[col], self._raw_v[:, col],
                                           cyl.stroke_m, cyl.closed_length_m, min_share=0.9)
            if problem is not None:
                raise TwinError(problem.message + "; the twin needs stroke positions "
                                "(s = pin-to-pin length − closed length, in metres)")

    def flush_iter(self) -> Iterator[TwinResult]:
        """Like :meth:`flush`, one chunk at a time."""
        if self._finished:
            return
        if self._raw_t.shape[0]:
            self._check_rods()
        yield from self._advance(final=True)
        self._finished = True

    # -- stages ----------------------------------------------------------------------------------
    def _advance(self, final: bool) -> Iterator[TwinResult]:
        if self._raw_t.shape[0] < 2 and not final:
            return
        if self._raw_t.shape[0] < 4:
            if final and self._raw_t.shape[0] == 0:
                return
            if final:
                raise TwinError(f"replay needs at least 4 samples, got {self._raw_t.shape[0]}")
            return
        if self._period is None:
            self._period = nominal_period(self._raw_t)
        if self._origin is None:
            self._origin = float(self._raw_t[0])
        r = self.opt.grid_hz * self._period
        if abs(r - round(r)) > 1e-3 * r or round(r) < 1:
            raise TwinError(f"grid_hz {self.opt.grid_hz} must be an integer multiple of the "
                            f"sample rate {1 / self._period:g} Hz")
        self._r = int(round(r))
        self._stage_regular(final)
        if self._choices is None:
            have = self._reg.end * self._period
            if not final and have < self.opt.choose_after_s:
                return
            self._choices = self._choose(self._reg.arr)
        self._stage_smooth(final)
        if self.plan.integrated:
            self._stage_integrate(final)
        yield from self._stage_output(final)
        self._trim()

    def _choose(self, raw: F64) -> tuple[SmoothingChoice, ...]:
        """The smoothing choices of the choice span's regularised rows ``raw`` (n, nch)
        (:func:`cranetwin.twin.channels.choose_smoothing`); with ``model_forces="auto"`` each
        cylinder's model-based or pressure-only force then checked by the split risk
        (:mod:`cranetwin.twin.model_choice`)."""
        choices = choose_smoothing(self.machine, self.cmap, raw, self.opt.smooth,
                                   self.opt.adaptive_pressures, self.opt.model_forces)
        if self.opt.model_forces != "auto" or not self.opt.smooth:
            return choices
        period = self._period if self._period is not None else self.opt.sample_period_s
        assert period is not None
        return choose_model(self.plan, choices, raw, period, self.payload)

    def _stage_regular(self, final: bool) -> None:
        assert self._period is not None and self._origin is not None
        p = self._period
        look = 50 * p if self.opt.lookahead_s is None else self.opt.lookahead_s
        t_last = float(self._raw_t[-1])
        horizon = t_last if final else t_last - look
        k_hi = int(np.floor((horizon - self._origin) / p + 1e-9))  # inclusive
        k0 = self._reg.end
        if k_hi < k0:
            return
        reg = regularize(self._raw_t, self._raw_v, period=p, max_gap_s=self.opt.max_gap_s,
                         origin=self._origin)
        kr0 = int(round((reg.t[0] - self._origin) / p))
        if kr0 > k0:
            raise TwinError("internal: regularised samples do not continue the stream")
        self._reg.append(reg.values[k0 - kr0 : k_hi - kr0 + 1])
        self._gap.append(np.any(reg.gap, axis=1)[k0 - kr0 : k_hi - kr0 + 1].astype(float))
        if self._known is not None and k_hi >= k0:
            assert self._raw_k is not None
            limit = 5.0 * p if self.opt.max_gap_s is None else self.opt.max_gap_s
            self._known.append(at_instants(reg.t[k0 - kr0 : k_hi - kr0 + 1], self._raw_t,
                                           self._raw_k, limit)[:, None])
        # keep raw samples that the next regularisation needs (lookahead of context)
        keep_t = self._origin + (k_hi + 1) * p - look - 2 * p
        keep = int(np.searchsorted(self._raw_t, keep_t))
        keep = min(keep, self._raw_t.shape[0] - 2)
        if keep > 0:
            self._raw_t = self._raw_t[keep:]
            self._raw_v = self._raw_v[keep:]
            if self._raw_k is not None:
                self._raw_k = self._raw_k[keep:]

    def _stage_smooth(self, final: bool) -> None:
        assert self._choices is not None and self._period is not None
        hw = self._hw
        n_reg = self._reg.end
        k_hi = n_reg if final else n_reg - hw  # exclusive
        k0 = self._sm_valid
        if k_hi <= k0:
            return
        lo = max(self._reg.base, k0 - hw)
        hi = n_reg if final else min(n_reg, k_hi + hw)
        if not final and hi - lo < self._longest_window():
            return  # the stream's start, shorter than a window: wait for more (or the end)
        # the end fits only where the kept block reaches within a window of the data's ends
        out = smooth_rows(self.plan, self._choices, self._reg.get(lo, hi), self._period,
                          (k0 - lo < hw, hi - k_hi < hw))
        if self._sm.end != k0:
            raise TwinError("internal: smoothing does not continue the stream")
        self._sm.append(out[k0 - lo : k_hi - lo])
        self._sm_valid = k_hi

    def _longest_window(self) -> int:
        """Longest fixed smoothing window of the channels [samples] (what
        :func:`cranetwin.twin.stages.smooth_rows` needs at least)."""
        assert self._choices is not None
        return max([1] + [c.window for c in self._choices[: self.plan.nch] if not c.adaptive])

    def _stage_integrate(self, final: bool) -> None:
        """The integrated free joints' angles at the samples whose payload window is final."""
        assert self._period is not None
        plan = self.plan
        wh = self._wh
        avail = self._sm_valid
        edge = 4  # two nested 5-point Newton derivatives
        k_hi = avail if final else avail - wh - edge
        k0 = self._theta_done
        if k_hi <= k0:
            return
        lo = max(self._sm.base, k0 - wh - edge)
        hi = avail if final else min(avail, k_hi + wh + edge)
        q, qd, qdd, f, arm, cs = sample_states(plan, self._sm.get(lo, hi))
        if plan.use_cs and hi > self._cs.end:
            a = self._cs.end - lo
            if a < 0:
                raise TwinError("internal: cylinder states do not continue the stream")
            self._cs.append(cs[a:])
        known = self._known_rows(lo, hi)
        if self.payload is not None:
            mass = np.full(q.shape[0], float(self.payload))
        elif fully_known(known):
            assert known is not None
            mass = np.nan_to_num(np.maximum(known, 0.0))
        else:
            ps = self._payload_setting()
            est, _ = estimate_payload(plan, (q, qd, qdd), f, arm,
                                      (ps.weights, ps.frac, ps.prefilter_half, ps.half_window,
                                       ps.noise, ps.systematic))
            if known is not None:
                est = np.where(np.isfinite(known), known, est)
            mass = np.nan_to_num(np.maximum(est, 0.0))
        sl = slice(k0 - lo, k_hi - lo)
        nj = self.machine.n_joints
        mm = np.empty((k_hi - k0, nj, nj))
        plan.kernels.mass_matrix(np.ascontiguousarray(q[sl]), np.ascontiguousarray(mass[sl]), mm)
        rows = self._sm.get(k0, k_hi)
        torques = np.zeros((k_hi - k0, plan.n_int))
        for i, d in enumerate(plan.integrated):
            tc = self.cmap.torques[d]
            if tc is not None:
                torques[:, i] = rows[:, tc]
        theta = integrate_free_joints(plan, self._period, (q[sl], qd[sl]), mm, torques,
                                      self._slew)
        b = self._sm.base
        self._sm.arr[k0 - b : k_hi - b, plan.nch : plan.nch + plan.n_int] = theta
        self._theta_done = k_hi

    def _stage_output(self, final: bool) -> Iterator[TwinResult]:
        ready = self._theta_done if self.plan.integrated else self._sm_valid
        n_total = self._sm_valid
        fh = self._fh
        margin = self._wh + fh + self.opt.settle_samples
        k_end = n_total if final else ready - margin
        if not final and self._out_done < fh and k_end < fh:
            return  # the first chunk's residuals must reach a whole window (residual_range)
        while self._out_done < k_end:
            ka = self._out_done
            kb = min(k_end, ka + self.opt.chunk_samples)
            last = final and kb == n_total
            yield self._chunk(ka, kb, last, ready, final)
            self._out_done = kb

    def _trim(self) -> None:
        need = self._out_done - self._wh - 2 * self._fh - self.opt.settle_samples - 4
        need = min(need, self._sm_valid - 2 * self._hw - 8)
        if self.plan.integrated:
            need = min(need, self._theta_done - self._wh - 8)
        if need > 0:
            self._sm.trim(min(need, self._sm.end))
            self._reg.trim(min(need, self._reg.end))
            self._gap.trim(min(need, self._gap.end))
            self._cs.trim(min(need, self._cs.end))
            if self._known is not None:
                self._known.trim(min(need, self._known.end))

    def _chunk(self, ka: int, kb: int, last: bool, ready: int, final: bool) -> TwinResult:
        """Outputs at samples [ka, kb): the rows :func:`cranetwin.twin.chunk.chunk` needs.

        The payload, its regression and the mass matrices run at the sample instants of an
        extended range (the payload window reaches ``_wh`` samples on each side, beyond the
        model-based forces' residual range, :func:`cranetwin.twin.force_model.residual_range`),
        the splines over ``settle_samples`` more on each side."""
        assert self._period is not None and self._origin is not None and self._choices is not None
        wh = self._wh
        n_total = self._sm_valid if last else ready  # rows with every column final
        at_end = final and n_total == self._sm_valid
        r0, r1 = force_model.residual_range(ka, kb, self._fh, n_total, at_end)
        e0 = max(0, r0 - wh)
        e1 = min(n_total - 1, r1 + wh)  # inclusive
        f0 = max(self._sm.base, e0 - self.opt.settle_samples)
        f1 = min(n_total - 1, e1 + self.opt.settle_samples)  # inclusive
        cached = self.plan.use_cs and e1 < f1 and self._cs.base <= e0 and e1 < self._cs.end
        rows = ChunkRows(ka, kb, last, f0, e0, e1, self._sm.get(f0, f1 + 1),
                         self._cs.get(e0, e1 + 1) if cached else None,
                         self._gap.get(ka, kb)[:, 0], r0, self._raw_pressures(r0, r1),
                         self._known_rows(e0, e1 + 1))
        return chunk(self.plan, rows, Timing(self._period, self._origin, self._r),
                     self._payload_setting(), self._choices)


    def _raw_pressures(self, r0: int, r1: int) -> F64:
        """Regularised pressures at samples r0 … r1 (pA then pB per cylinder, (m, 2·n_c)
        [Pa]; a quantised one reconstructed, :func:`cranetwin.twin.force_model.raw_pressures`)
        when a force is model-based, else (0, 2·n_c)."""
        assert self._choices is not None
        cols = list(self.cmap.p_a) + list(self.cmap.p_b)
        if not self._fh:
            return np.empty((0, len(cols)))
        # the context (≤ fh) lies within the rows _trim keeps (2·fh before the next output)
        # and those the smoothing waits for (hw ≥ fc after the smoothed rows)
        fc = self._fc
        lo, hi = max(0, r0 - fc), min(self._reg.end, r1 + 1 + fc)
        return force_model.raw_pressures(self.plan, self._choices,
                                         self._reg.get(lo, hi)[:, cols], r0 - lo, r1 + 1 - r0)


def iter_replay(samples: SampleArrays | HasSamples, machine: Machine, grid_hz: float = 1000.0,
                payload: float | F64 | None = None, options: ReplayOptions | None = None,
                block_samples: int = 6000) -> Iterator[TwinResult]:
    """Replay a whole recording chunk by chunk (bounded memory); see :func:`replay`.

    The smoothing windows are chosen on the whole recording first; the samples are then fed
    to a :class:`TwinStream` ``block_samples`` at a time, so memory does not grow with the
    recording's length (the stream's seams equal the whole-recording result).
    """
    if not isinstance(samples, SampleArrays):  # a sim Recording (or anything with .samples)
        inner = getattr(samples, "samples", None)
        if not isinstance(inner, SampleArrays):
            raise TwinError("replay needs SampleArrays or a Recording with .samples")
        samples = inner
    opt = options or ReplayOptions()
    if opt.grid_hz != grid_hz:
        opt = ReplayOptions(**{**opt.__dict__, "grid_hz": grid_hz})
    n = samples.t_s.shape[0]
    if opt.sample_period_s is None and n >= 2:
        opt = ReplayOptions(**{**opt.__dict__,
                               "sample_period_s": nominal_period(samples.t_s,
                                                                 samples.period_ns)})
    series: F64 | None = None
    if payload is not None and np.ndim(payload) > 0:
        series = np.asarray(payload, dtype=np.float64)
        if series.shape != (n,):
            raise TwinError(f"known payload series has shape {series.shape}; the samples "
                            f"({n},)")
    stream = TwinStream(machine, samples.channels, opt,
                        None if payload is None or series is not None else float(payload))
    if opt.smoothing is None and n >= 4 and opt.sample_period_s is not None:
        cols = [samples.channels.index(c) for c in stream.cmap.names]
        # (gathered even when no column moves: the gather yields a column-major copy that the
        # window choice then transposes for free; skipping it only moves that cost there)
        reg = regularize(samples.t_s, samples.values[:, cols], period=opt.sample_period_s,
                         max_gap_s=opt.max_gap_s)
        stream.set_smoothing(stream._choose(reg.values))
        del reg
    for i in range(0, n, block_samples):
        j = min(n, i + block_samples)
        yield from stream.push_iter(samples.take(slice(i, j)),
                                    None if series is None else series[i:j])
    yield from stream.flush_iter()


def replay(samples: SampleArrays | HasSamples, machine: Machine, grid_hz: float = 1000.0,
           payload: float | F64 | None = None, options: ReplayOptions | None = None
           ) -> TwinResult:
    """Reconstruct the machine's motion and loads from its sensor samples.

    Args:
        samples: Sensor samples (pA, pB, s per cylinder, slewing torque, optional slew angle),
            or a simulator ``Recording`` (its ``.samples`` are used); irregular times and NaN
            dropouts are allowed.
        machine: Machine description.
        grid_hz: Output grid rate [Hz], an integer multiple of the sample rate.
        payload: Known payload [kg]: a constant, or a series at the sample times, shape
            (n,), NaN where not known (the estimate there; :mod:`cranetwin.twin.known_payload`);
            None to estimate it everywhere (sliding-window least squares). Where known,
            ``payload_kg`` is it and ``payload_std_kg`` 0.
        options: Further settings (:class:`ReplayOptions`).

    Returns:
        :class:`TwinResult` from the first to the last sample time.

    Raises:
        TwinError: Missing channels, too few samples, rod positions outside the geometry.
    """
    return TwinResult.concat(list(iter_replay(samples, machine, grid_hz, payload, options)))
