"""Replay: sparse, noisy sensor samples in; motion and loads of the machine on a fine grid out.

Pipeline (paper Sect. 2, with the steps it leaves open made explicit)::

    samples ─ regularise (irregular times, dropouts) ─ Savitzky–Golay (window from noise level)
      ─ natural cubic spline to the grid (values, rate, acceleration)
      ─ kinematics: theta1, theta2, L from the rod positions; theta0 from the slew-angle channel
        or by integrating the slewing dynamics from the pillar torque
      ─ cylinder forces, Eq. 1–2 ─ actuator joint loads F·ds/dq
      ─ payload by sliding-window least squares (if not given) ─ inverse dynamics (RNEA):
        joint loads, residual, joint reaction wrenches

Everything runs per *chunk* of samples with enough overlap that every output instant sees the
same data as a whole-recording computation would: Savitzky–Golay is a finite filter, the
natural spline's dependence on far knots decays by ≈ 0.27 per knot (``settle_samples`` knots of
margin leave < 1e-20 of it), and the payload window is centred. So the streaming form
(:class:`TwinStream`, fed block by block as datagrams arrive) equals the batch form
(:func:`replay`), which is the stream fed everything at once — seams included.

Where the work is done: the sample-rate stages (smoothing, the payload regression, the slew
integration, mass matrices) run at the 100 Hz instants; every grid-rate quantity is computed
per chunk by :func:`cranetwin.twin.gridpass.grid_pass` (splines, table-driven inverse
kinematics, Eq. 1–2, the machine's batch RNEA, the Eq. 3/4 correction, the wrenches). Free
joints (no cylinder drives them): the one with a torque drive takes its angle from the angle
channel, or integrates it from the torque (:mod:`cranetwin.twin.slew`); a free joint with
neither is held at 0 (the reference pose). The kinematics tables (quintic Hermite pieces of
the exact inverse, 2048 cells per stroke) agree with the exact inverse to 1e-11 in q and ds/dq
and 1e-8 of the largest d²s/dq²; M_DD⁻¹ is interpolated between samples (agreement with the
exact M(q) at every instant: 1.5e-5 of the wrench range). ``tests/test_twin_gridpass.py``
recomputes every output through the separate physics functions.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import numpy.typing as npt

from cranetwin import physics
from cranetwin.errors import PhysicsError, TwinError
from cranetwin.model import Machine
from cranetwin.physics import actuator
from cranetwin.physics.chain import compile_chain
from cranetwin.physics.dynamics import batch_kernels
from cranetwin.samples import SampleArrays
from cranetwin.signal import (
    ICI_WINDOWS,
    SmoothingChoice,
    centre_weight,
    ici_smooth_pair,
    natural_pieces,
    newton_derivative,
    nominal_period,
    regularize,
    savgol_smooth,
)
from cranetwin.signal.savgol import savgol_columns
from cranetwin.twin import gridpass, kintable
from cranetwin.twin.buffer import RowBuffer
from cranetwin.twin.channels import ChannelMap, choose_smoothing
from cranetwin.twin.options import END_STOP_MARGIN_M, HasSamples, ReplayOptions
from cranetwin.twin.payload import regression_payload
from cranetwin.twin.result import TwinResult
from cranetwin.twin.slew import SlewState, integrate_slew
from cranetwin.twin.stages import (
    SampleColumns,
    cylinder_states,
    derivative_filter,
    spline_layout,
    unpack_states,
)

F64 = npt.NDArray[np.float64]

__all__ = ["END_STOP_MARGIN_M", "HasSamples", "ReplayOptions", "TwinStream",
           "derivative_filter", "iter_replay", "replay"]
B = npt.NDArray[np.bool_]





def _h0(choice: SmoothingChoice) -> float:
    return centre_weight(choice.window, choice.polyorder)


class TwinStream:
    """Replay fed block by block; yields results for every instant that can no longer change.

    Args:
        machine: Machine description.
        channels: Column names of the sample arrays that will be pushed.
        options: Replay settings.
        payload: Known payload [kg] (scalar) or None to estimate it from the pressures.
    """

    def __init__(self, machine: Machine, channels: tuple[str, ...],
                 options: ReplayOptions | None = None, payload: float | None = None) -> None:
        self.machine = machine
        self.opt = options or ReplayOptions()
        self.payload = payload
        self.cmap = ChannelMap.build(machine, channels)
        self._cols = [channels.index(n) for n in self.cmap.names]
        self._nch = len(self.cmap.names)
        self._raw_t = np.empty(0)
        self._raw_v = np.empty((0, self._nch))
        self._origin: float | None = None
        self._period: float | None = self.opt.sample_period_s
        self._r = 0
        self._choices: tuple[SmoothingChoice, ...] | None = self.opt.smoothing
        self._dcols = list(self.cmap.derivative_channels)
        n_choice = len(self.cmap.choice_names)
        if self._choices is not None and len(self._choices) != n_choice:
            raise TwinError(f"smoothing: expected {n_choice} choices {self.cmap.choice_names}, "
                            f"got {len(self._choices)}")
        self._reg = RowBuffer(self._nch)
        self._gap = RowBuffer(1)
        # smoothed channels | integrated theta0 | rates | accelerations of the position channels
        self._nd = len(self.cmap.derivative_channels)
        self._sm = RowBuffer(self._nch + 1 + 2 * self._nd)
        self._sm_valid = 0  # smoothed rows [.., _sm_valid) have final values
        self._theta_done = 0
        # cylinder states at the samples (q, qd, qdd of the cylinder joints, moment arms,
        # forces; 5 blocks of n_cylinders) as the slew stage computed them, reused by the
        # chunks: the same rows from the same smoothed samples (only with the rates taken from
        # the smoothed samples, velocity="spline"; the Newton rates differ)
        self._cs = RowBuffer(5 * len(machine.cylinders))
        self._out_done = 0
        self._slew = SlewState(theta0=self.opt.theta0_initial)
        # free joints (no cylinder drives them) have torque drives: a drive's joint takes its
        # angle from its angle channel; the first one without an angle channel integrates it
        # from its torque (twin.slew: a vertical axis); any other is held at 0
        drives = machine.torque_drives
        self._drive_joints = [machine.joint_index(d.joint) for d in drives]
        no_angle = [d for d, a in enumerate(self.cmap.angles) if a is None]
        self._integrated = no_angle[0] if no_angle else None  # drive index
        self._integrate = self._integrated is not None
        self._drive = drives[self._integrated] if self._integrated is not None else None
        self._slew_joint = (self._drive_joints[self._integrated]
                            if self._integrated is not None else None)
        self._cyl_joint = [machine.joint_index(c.joint) for c in machine.cylinders]
        self._cyl_joint_arr = np.array(self._cyl_joint, dtype=np.int64)
        self._s_cols = np.array(self.cmap.s, dtype=np.int64)
        self._pa_cols = np.array(self.cmap.p_a, dtype=np.int64)
        self._pb_cols = np.array(self.cmap.p_b, dtype=np.int64)
        self._pw_cache: tuple[tuple[SmoothingChoice, ...], F64, F64] | None = None
        self._layout: tuple[list[int], list[int], npt.NDArray[np.int64],
                            npt.NDArray[np.int64]] | None = None
        self._free = [j for j in range(machine.n_joints) if j not in self._cyl_joint]
        self._stroke = np.array([c.stroke_m for c in machine.cylinders])
        self._finished = False
        params = compile_chain(machine)
        self._cyl = params.cyl
        self._fpar = actuator.cylinder_params(machine)
        self._kernels = batch_kernels(params, self.opt.generated_kernels)
        self._mass_matrix = self._kernels.mass_matrix
        self._table = np.empty((len(machine.cylinders), kintable.KIN_TABLE_NODES - 1, 6))
        self._table_ok = kintable.kinematics_table(params.cyl, self._stroke,
                                                   kintable.KIN_TABLE_NODES, self._table)
        self._qi = gridpass.Quantities.of(len(machine.cylinders), len(self._free))
        drive_friction = np.zeros((len(self._free), 3))
        drive_friction[:, 1] = 1.0
        for d in machine.torque_drives:
            f = d.friction
            drive_friction[self._free.index(machine.joint_index(d.joint))] = (
                f.coulomb, f.coulomb_velocity, f.viscous)
        self._free_joints = gridpass.FreeJoints(np.array(self._free, dtype=np.int64),
                                                drive_friction)
        self._cylinders = gridpass.Cylinders(params.cyl, self._table, self._table_ok,
                                             self._fpar, self._stroke, self._cyl_joint_arr,
                                             END_STOP_MARGIN_M)
        # each drive's index among the free joints (its angle and torque quantities)
        self._drive_free = [self._free.index(j) for j in self._drive_joints]
        # the sample-rate states of the slew stage serve the chunks when the integrated angle
        # is the only free joint
        self._use_cs = (self._integrate and self.opt.velocity == "spline"
                        and len(self._free) == 1)

    # -- geometry of the margins -------------------------------------------------------------
    @property
    def _hw(self) -> int:
        if self._choices is None:
            return 0
        return max(c.window // 2 for c in self._choices)

    @property
    def _payload_half(self) -> int:
        assert self._period is not None
        return max(1, int(round(self.opt.payload_window_s / self._period / 2)))

    @property
    def _prefilter(self) -> int:
        """Width [samples] of the moving average applied to the payload regression's force and
        regressor alike: the longest derivative window. The accelerations are smoothed over
        it, the pressures are not; low-passing both removes the mismatch ("filter both
        sides"), which otherwise biases the estimate by tens of kg in fast motion."""
        if self._choices is None:
            return 1
        return max([1] + [c.window for c in self._choices[self._nch :]])

    @property
    def _wh(self) -> int:
        """Samples the payload estimate at an instant reaches on each side."""
        return self._payload_half + self._prefilter // 2

    # -- public API ----------------------------------------------------------------------------
    def set_smoothing(self, choices: tuple[SmoothingChoice, ...]) -> None:
        """Fix the smoothing choices (``cmap.choice_names`` order) before the first push."""
        if len(choices) != len(self.cmap.choice_names):
            raise TwinError(f"smoothing: expected {len(self.cmap.choice_names)} choices")
        if self._reg.end:
            raise TwinError("smoothing can only be set before data are pushed")
        self._choices = tuple(choices)

    def push(self, samples: SampleArrays) -> TwinResult | None:
        """Add samples (in time order, after those pushed before); return what became final."""
        parts = list(self.push_iter(samples))
        return TwinResult.concat(parts) if parts else None

    def flush(self) -> TwinResult | None:
        """End of the stream: return everything not yet returned."""
        parts = list(self.flush_iter())
        return TwinResult.concat(parts) if parts else None

    def push_iter(self, samples: SampleArrays) -> Iterator[TwinResult]:
        """Like :meth:`push`, one chunk at a time (bounded memory for long recordings)."""
        if self._finished:
            raise TwinError("stream already flushed")
        t = np.asarray(samples.t_s, dtype=np.float64)
        if t.shape[0] == 0:
            return
        if self._raw_t.shape[0] and not t[0] > self._raw_t[-1]:
            raise TwinError("pushed samples must come after the samples pushed before")
        vals = np.asarray(samples.values, dtype=np.float64)
        if self._cols != list(range(vals.shape[1])):
            vals = vals[:, self._cols]
        if self._period is None and samples.period_ns is not None:
            self._period = nominal_period(t, samples.period_ns)
        self._raw_t = np.concatenate([self._raw_t, t])
        self._raw_v = np.concatenate([self._raw_v, vals])
        yield from self._advance(final=False)

    def flush_iter(self) -> Iterator[TwinResult]:
        """Like :meth:`flush`, one chunk at a time."""
        if self._finished:
            return
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
            self._choices = choose_smoothing(self.machine, self.cmap, self._reg.arr,
                                             self.opt.smooth, self.opt.adaptive_pressures)
        self._stage_smooth(final)
        if self._integrate:
            self._stage_slew(final)
        yield from self._stage_output(final)
        self._trim()

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
        # keep raw samples that the next regularisation needs (lookahead of context)
        keep_t = self._origin + (k_hi + 1) * p - look - 2 * p
        keep = int(np.searchsorted(self._raw_t, keep_t))
        keep = min(keep, self._raw_t.shape[0] - 2)
        if keep > 0:
            self._raw_t = self._raw_t[keep:]
            self._raw_v = self._raw_v[keep:]

    def _stage_smooth(self, final: bool) -> None:
        assert self._choices is not None
        hw = self._hw
        n_reg = self._reg.end
        k_hi = n_reg if final else n_reg - hw  # exclusive
        k0 = self._sm_valid
        if k_hi <= k0:
            return
        lo = max(self._reg.base, k0 - hw)
        hi = n_reg if final else min(n_reg, k_hi + hw)
        raw = self._reg.get(lo, hi)
        nd = self._nd
        out = np.empty((raw.shape[0], self._nch + 1 + 2 * nd))
        written: set[int] = set()  # the rest is NaN (the integrated slew angle's column)
        groups: dict[tuple[int, int], list[int]] = {}
        in_bank = set(self._dcols)  # position channels: value and rates from one filter bank
        for j, choice in enumerate(self._choices[: self._nch]):
            if choice.adaptive:
                continue
            if choice.window > 1 and raw.shape[0] < choice.window:
                raise TwinError(f"{raw.shape[0]} samples are fewer than the smoothing window "
                                f"{choice.window}")
            if j not in in_bank:
                groups.setdefault((choice.window, choice.polyorder), []).append(j)
        for ci, cyl in enumerate(self.machine.cylinders):
            ia, ib = self.cmap.p_a[ci], self.cmap.p_b[ci]
            ch = self._choices[ia]
            if ch.adaptive:
                out[:, [ia, ib]] = self._ici_pressures(raw[:, ia], raw[:, ib], cyl.area_a_m2,
                                                       cyl.area_b_m2, ch)
                written.update((ia, ib))
        for (w, p), cols in groups.items():
            out[:, cols] = savgol_smooth(raw[:, cols], w, p)
            written.update(cols)
        dt = self._period
        assert dt is not None
        bank: list[list[tuple[int, int, int]]] = []
        for i, j in enumerate(self._dcols):
            c = self._choices[self._nch + i]
            w, p = derivative_filter(c, raw.shape[0])
            cv = self._choices[j]
            bank.append([(cv.window, cv.polyorder, 0), (w, p, 1), (w, p, 2)])
        if bank:  # every position channel's value, rate and acceleration: one batched FFT
            # the end fits only where the kept block reaches within a window of the data's ends
            outs = savgol_columns(raw[:, self._dcols], bank, delta=dt,
                                  edges=(k0 - lo < hw, hi - k_hi < hw))
            for i, j in enumerate(self._dcols):
                out[:, j], out[:, self._nch + 1 + i], out[:, self._nch + 1 + nd + i] = outs[i]
                written.update((j, self._nch + 1 + i, self._nch + 1 + nd + i))
        unset = [c for c in range(out.shape[1]) if c not in written]
        if unset:
            out[:, unset] = np.nan
        block = out[k0 - lo : k_hi - lo]
        if self._sm.end != k0:
            raise TwinError("internal: smoothing does not continue the stream")
        self._sm.append(block)
        self._sm_valid = k_hi

    @staticmethod
    def _ici_pressures(pa: F64, pb: F64, a1: float, a2: float,
                       ch: SmoothingChoice) -> F64:
        ws = tuple(w for w in ICI_WINDOWS if w <= ch.window)
        return ici_smooth_pair(pa, pb, a1, a2, ch.sigma, ws, ch.polyorder)

    def _sample_state(self, k0: int, k1: int) -> tuple[F64, F64, F64, F64, F64, F64]:
        """q, qd, qdd (the slew joint at 0), cylinder forces, moment arms and the cylinder
        states rows (:func:`_cylinder_states`) at samples [k0, k1) from the smoothed
        channels, in one compiled pass."""
        sm = self._sm.get(k0, k1)
        n = sm.shape[0]
        nj = self.machine.n_joints
        nc = len(self.machine.cylinders)
        q = np.zeros((n, nj))
        qd = np.zeros((n, nj))
        qdd = np.zeros((n, nj))
        cs = np.empty((n, 5 * nc))
        cols = SampleColumns(self._s_cols, self._pa_cols, self._pb_cols, self._nch + 1,
                             self._nch + 1 + self._nd)
        bad = cylinder_states(sm, cols, self._cylinders, q, qd, qdd, cs)
        if bad:  # the descriptive error
            self._joint_motion(self._clip_s(sm[:, self._s_cols]),
                               sm[:, self._nch + 1 : self._nch + 1 + nc],
                               sm[:, self._nch + 1 + self._nd : self._nch + 1 + self._nd + nc],
                               np.zeros((n, nj - nc)))
            raise TwinError("rod positions do not fit the machine geometry")
        return q, qd, qdd, cs[:, 4 * nc :], cs[:, 3 * nc : 4 * nc], cs

    def _stage_slew(self, final: bool) -> None:
        assert self._period is not None and self._drive is not None
        wh = self._wh
        avail = self._sm_valid
        edge = 4  # two nested 5-point Newton derivatives
        k_hi = avail if final else avail - wh - edge
        k0 = self._theta_done
        if k_hi <= k0:
            return
        lo = max(self._sm.base, k0 - wh - edge)
        hi = avail if final else min(avail, k_hi + wh + edge)
        q, qd, qdd, f, arm, cs = self._sample_state(lo, hi)
        if self._use_cs and hi > self._cs.end:
            a = self._cs.end - lo
            if a < 0:
                raise TwinError("internal: cylinder states do not continue the stream")
            self._cs.append(cs[a:])
        if self.payload is not None:
            mass = np.full(q.shape[0], float(self.payload))
        else:
            mass, _ = self._estimate_payload(q, qd, qdd, f, arm)
            mass = np.nan_to_num(np.maximum(mass, 0.0))
        sl = slice(k0 - lo, k_hi - lo)
        j0 = self._slew_joint
        assert j0 is not None
        # column j0 of M (= row j0, M symmetric), from the compiled mass matrix (cheaper than
        # the two inverse-dynamics passes of M·e_j0 = tau(q, 0, e_j0) − tau(q, 0, 0))
        mm = np.empty((k_hi - k0, self.machine.n_joints, self.machine.n_joints))
        self._mass_matrix(np.ascontiguousarray(q[sl]), np.ascontiguousarray(mass[sl]), mm)
        row = mm[:, :, j0]
        m00 = row[:, j0]
        others = [j for j in range(self.machine.n_joints) if j != j0]
        coupling = np.einsum("nj,nj->n", row[:, others], qd[sl][:, others])
        tc = self.cmap.torques[self._integrated] if self._integrated is not None else None
        if tc is None:
            torque = np.zeros(m00.shape[0])
        else:
            torque = self._sm.get(k0, k_hi)[:, tc]
        fr = self._drive.friction
        theta, _ = integrate_slew(self._period, torque, m00, coupling, fr.coulomb,
                                  fr.coulomb_velocity, fr.viscous, self._slew)
        self._sm.arr[k0 - self._sm.base : k_hi - self._sm.base, self._nch] = theta
        self._theta_done = k_hi

    def _stage_output(self, final: bool) -> Iterator[TwinResult]:
        ready = self._theta_done if self._integrate else self._sm_valid
        n_total = self._sm_valid
        margin = self._wh + self.opt.settle_samples
        k_end = n_total if final else ready - margin
        while self._out_done < k_end:
            ka = self._out_done
            kb = min(k_end, ka + self.opt.chunk_samples)
            last = final and kb == n_total
            yield self._chunk(ka, kb, last, ready)
            self._out_done = kb

    def _trim(self) -> None:
        need = self._out_done - self._wh - self.opt.settle_samples - 4
        need = min(need, self._sm_valid - 2 * self._hw - 8)
        if self._integrate:
            need = min(need, self._theta_done - self._wh - 8)
        if need > 0:
            self._sm.trim(min(need, self._sm.end))
            self._reg.trim(min(need, self._reg.end))
            self._gap.trim(min(need, self._gap.end))
            self._cs.trim(min(need, self._cs.end))

    # -- physics helpers -----------------------------------------------------------------------
    def _clip_s(self, s: F64) -> F64:
        """Rod positions clipped to [0, stroke], as a new C-contiguous array."""
        out: F64 = np.maximum(s, 0.0)
        np.minimum(out, self._stroke, out=out)
        return out

    def _joint_motion(self, s: F64, v: F64, a: F64,
                      q_other: F64) -> tuple[F64, F64, F64, F64]:
        """q, qd, qdd (n, n_joints) and moment arms ds/dq (n, n_cylinders), one fused pass
        through the kinematics tables (:func:`cranetwin.twin.kintable.kinematics_table`;
        s within the strokes)."""
        n = s.shape[0]
        nj = self.machine.n_joints
        q = np.zeros((n, nj))
        qd = np.zeros((n, nj))
        qdd = np.zeros((n, nj))
        if q_other.shape[1]:
            q[:, self._free] = q_other
        arm = np.empty((n, len(self.machine.cylinders)))
        kintable.table_motion_batch(self._table, self._table_ok, self._cyl,
                                    np.ascontiguousarray(s), np.ascontiguousarray(v),
                                    np.ascontiguousarray(a), q, qd, qdd, arm)
        if not np.all(np.isfinite(q[:, self._cyl_joint])):
            try:  # the descriptive error
                physics.joint_motion_and_arms(self.machine, s, v, a,
                                              q_other if q_other.shape[1] else None)
            except PhysicsError as exc:
                raise TwinError(f"rod positions do not fit the machine geometry: {exc}") from exc
            raise TwinError("rod positions do not fit the machine geometry")
        return q, qd, qdd, arm

    def _eq12(self, pa: F64, pb: F64, v: F64) -> F64:
        """Eq. 1–2 for every cylinder, (n, n_cylinders) [N] (as physics.cylinder_forces)."""
        out = np.empty(v.shape)
        actuator.cylinder_forces_into(pa, pb, v, self._fpar, out)
        return out

    def _payload_weights(self) -> tuple[F64, F64]:
        """Weights 1/σ² per cylinder joint and the independent errors per sample of each,
        from the smoothing choices (cached with them)."""
        assert self._choices is not None
        hit = self._pw_cache
        if hit is not None and hit[0] is self._choices:
            return hit[1], hit[2]
        m = self.machine
        weights = np.empty(len(m.cylinders))
        frac = np.empty(len(m.cylinders))
        for c, cyl in enumerate(m.cylinders):
            ch = self._choices[self.cmap.p_a[c]]
            weights[c] = 1.0 / (max(ch.risk, 0.0) + cyl.friction.coulomb ** 2)
            # independent errors per sample ≈ the smoother's variance gain, risk/σ²
            frac[c] = float(np.clip(ch.risk / ch.sigma**2, 1e-3, 1.0)) if ch.sigma > 0 else 1.0
        self._pw_cache = (self._choices, weights, frac)
        return weights, frac

    def _estimate_payload(self, q: F64, qd: F64, qdd: F64, f: F64, arm: F64) -> tuple[F64, F64]:
        """Payload and its standard error at every instant of q (windows cut at its ends) from
        the cylinder forces f and moment arms (the actuator loads F·ds/dq)."""
        nj = self.machine.n_joints
        t0 = np.empty((q.shape[0], nj))  # joint loads without payload
        t1 = np.empty((q.shape[0], nj))  # and with 1 kg at the load point
        c = np.ascontiguousarray
        self._kernels.rnea_payload(c(q), c(qd), c(qdd), t0, t1)
        weights, frac = self._payload_weights()
        return regression_payload(t0, t1, f, arm, self._cyl_joint_arr, weights,
                                  self._prefilter // 2, self._payload_half, frac)

    # -- one chunk ------------------------------------------------------------------------------
    def _splines(self, knots_t: F64, sm: F64) -> tuple[F64, npt.NDArray[np.int64],
                                                       npt.NDArray[np.int64]]:
        """One natural spline over every column the grid needs and the quantity table
        (:mod:`cranetwin.twin.gridpass`) saying which column (and derivative) is what.

        Rates and accelerations are the Savitzky–Golay derivative filters at the samples,
        splined (``velocity="spline"``); or Newton's divided differences of the smoothed
        positions, splined, and that spline's derivative (``"newton"``, the paper's way). An
        integrated slew angle takes its rate and acceleration from its own spline.
        """
        if self._layout is None:
            self._layout = spline_layout(self.cmap, self._nch, self.opt.velocity,
                                         self._integrated, self._qi, self._drive_free)
        pos_cols, cols, src, der = self._layout
        data = sm[:, cols]
        if self.opt.velocity == "newton":
            extra = newton_derivative(knots_t, sm[:, pos_cols], 2 if sm.shape[0] >= 5 else 1)
            data = np.concatenate([data, extra], axis=1)
        return natural_pieces(knots_t, data), src, der

    def _chunk(self, ka: int, kb: int, last: bool, ready: int) -> TwinResult:
        """Outputs at samples [ka, kb) (through kb − 1 … the end on the ``last`` chunk).

        Payload, its regression and the mass matrices run at the sample instants of an
        extended range (the payload window reaches ``_wh`` samples on each side); every grid
        quantity is then computed by :func:`cranetwin.twin.gridpass.grid_pass`.
        """
        assert self._period is not None and self._origin is not None and self._choices is not None
        m = self.machine
        r = self._r
        p = self._period
        wh = self._wh
        nc = len(m.cylinders)
        nj = m.n_joints
        qi = self._qi
        n_total = self._sm_valid if last else ready  # rows with every column final
        e0 = max(0, ka - wh)
        e1 = min(n_total - 1, kb + wh)  # inclusive
        f0 = max(self._sm.base, e0 - self.opt.settle_samples)
        f1 = min(n_total - 1, e1 + self.opt.settle_samples)  # inclusive
        knots_t: F64 = np.arange(f0, f1 + 1, dtype=np.float64) * p
        coef, src, der = self._splines(knots_t, self._sm.get(f0, f1 + 1))
        h0 = float(knots_t[1] - knots_t[0])
        h_last = float(knots_t[-1] - knots_t[-2])
        # -- the sample instants e0 … e1: state, actuator loads, payload ----------------------
        ne = e1 - e0 + 1
        # free joints whose angle the splines carry (from a channel or integrated)
        thetas = [f for f in range(len(self._free)) if src[qi.free + 3 * f] >= 0]
        rod_v, rod_a = slice(qi.v, qi.v + nc), slice(qi.a, qi.a + nc)
        # the spline at a knot is the knot's value, except the end knot (last piece at h_last)
        cached = self._use_cs and e1 < f1 and self._cs.base <= e0 and e1 < self._cs.end
        at_samples = gridpass.Splines(coef, e0 - f0, 1, h0, h_last, src, der, qi)
        free_q = slice(qi.free, qi.free + 3 * len(self._free))
        if cached:  # only the slew angle, its rate and acceleration are needed from the spline
            smp = np.empty((ne, 3 * len(self._free)))
            gridpass.spline_points(at_samples._replace(src=src[free_q], der=der[free_q]), ne,
                                   smp)
            theta = smp
        else:
            smp = np.empty((ne, src.shape[0]))
            gridpass.spline_points(at_samples, ne, smp)
            theta = smp[:, free_q]  # per free joint: angle, rate, acceleration
        f_s: F64 | None = None
        if cached:  # cylinder joints' motion, arms and forces as the slew stage found them
            q_s = np.empty((ne, nj))
            qd_s = np.empty((ne, nj))
            qdd_s = np.empty((ne, nj))
            arm_s = np.empty((ne, nc))
            f_s = np.empty((ne, nc))
            unpack_states(self._cs.get(e0, e1 + 1), self._cyl_joint_arr, theta[:, 0],
                          self._free[0] if thetas else -1, q_s, qd_s, qdd_s, arm_s, f_s)
        else:
            s_s = self._clip_s(smp[:, qi.s : qi.s + nc])
            q_other = np.zeros((ne, nj - nc))
            for f in thetas:
                q_other[:, f] = theta[:, 3 * f]
            q_s, qd_s, qdd_s, arm_s = self._joint_motion(s_s, smp[:, rod_v], smp[:, rod_a],
                                                         q_other)
        for f in thetas:
            qd_s[:, self._free[f]] = theta[:, 3 * f + 1]
            qdd_s[:, self._free[f]] = theta[:, 3 * f + 2]
        ks = slice(ka - e0, min(kb - e0 + 1, ne))  # samples ka … kb (if there)
        n_ks = ks.stop - ks.start
        if self.payload is not None:
            mk = np.full(n_ks, float(self.payload))
            sk = np.zeros(n_ks)
        else:
            if f_s is None:
                f_s = self._eq12(smp[:, qi.pa : qi.pa + nc], smp[:, qi.pb : qi.pb + nc],
                                 smp[:, rod_v])
            mk, sk = self._estimate_payload(q_s, qd_s, qdd_s, f_s, arm_s)
            mk, sk = np.ascontiguousarray(mk[ks]), np.ascontiguousarray(sk[ks])
        dynamic = self.opt.wrench_acceleration == "dynamic"
        # the joints whose loads are measured: every cylinder's, every drive's with a torque
        full = sorted(self._cyl_joint + [j for j, t in zip(self._drive_joints, self.cmap.torques,
                                                           strict=True) if t is not None])
        if dynamic:
            mm = np.empty((n_ks, nj, nj))
            self._mass_matrix(np.ascontiguousarray(q_s[ks]), np.nan_to_num(np.maximum(mk, 0.0)),
                              mm)
            minv = np.empty((mm.shape[0], len(full), len(full)))
            minv_ok = np.empty(mm.shape[0], dtype=bool)
            gridpass.dd_inverse_batch(mm, np.array(full, dtype=np.int64), minv, minv_ok)
        else:
            mm = np.zeros((1, nj, nj))
            minv = np.zeros((1, len(full), len(full)))
            minv_ok = np.zeros(1, dtype=bool)
        # -- the grid -------------------------------------------------------------------------
        n = (kb - 1 - ka) * r + 1 if last else (kb - ka) * r
        gap = self._gap.get(ka, kb)[:, 0] > 0
        gap_g = np.repeat(gap, r)[:n] if r > 1 else gap[:n]
        if gap_g.shape[0] < n:
            gap_g = np.concatenate([gap_g, np.zeros(n - gap_g.shape[0], dtype=bool)])
        out = gridpass.GridOut.empty(n, nj, nc, np.ascontiguousarray(gap_g))
        bad = gridpass.grid_pass(
            gridpass.Splines(coef, ka - f0, r, h0, h_last, src, der, qi), self._cylinders,
            self._free_joints, gridpass.SampleState(mk, sk, mm, minv, minv_ok, len(full), dynamic),
            out, self._kernels)
        if bad:
            rows = ~np.all(np.isfinite(out.q), axis=1)
            self._joint_motion(out.rod_s[rows], out.rod_v[rows], out.rod_v[rows],
                               np.zeros((int(rows.sum()), nj - nc)))
            raise TwinError(f"rod positions do not fit the machine geometry at {bad} instants")
        t = np.arange(n, dtype=np.float64)  # origin + (ka + g/r)·p, in place
        t /= r
        t += ka
        t *= p
        t += self._origin
        return TwinResult(
            t_s=t, q=out.q, qd=out.qd, qdd=out.qdd, rod_s=out.rod_s, rod_v=out.rod_v,
            p_a=out.pa, p_b=out.pb, cyl_force=out.force, actuator_torque=out.tau_act,
            id_torque=out.tau_id, residual=out.resid, joint_wrench=out.wrench,
            payload_kg=out.mass, payload_std_kg=out.std, gap=gap_g,
            smoothing=dict(zip(self.cmap.choice_names, self._choices, strict=True)),
        )


def iter_replay(samples: SampleArrays | HasSamples, machine: Machine, grid_hz: float = 1000.0,
                payload: float | None = None, options: ReplayOptions | None = None,
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
    stream = TwinStream(machine, samples.channels, opt, payload)
    if opt.smoothing is None and n >= 4 and opt.sample_period_s is not None:
        cols = [samples.channels.index(c) for c in stream.cmap.names]
        # (gathered even when no column moves: the gather yields a column-major copy that the
        # window choice then transposes for free; skipping it only moves that cost there)
        reg = regularize(samples.t_s, samples.values[:, cols], period=opt.sample_period_s,
                         max_gap_s=opt.max_gap_s)
        stream.set_smoothing(choose_smoothing(machine, stream.cmap, reg.values, opt.smooth,
                                              opt.adaptive_pressures))
        del reg
    for i in range(0, n, block_samples):
        j = min(n, i + block_samples)
        yield from stream.push_iter(samples.take(slice(i, j)))
    yield from stream.flush_iter()


def replay(samples: SampleArrays | HasSamples, machine: Machine, grid_hz: float = 1000.0,
           payload: float | None = None, options: ReplayOptions | None = None) -> TwinResult:
    """Reconstruct the machine's motion and loads from its sensor samples.

    Args:
        samples: Sensor samples (pA, pB, s per cylinder, slewing torque, optional slew angle),
            or a simulator ``Recording`` (its ``.samples`` are used); irregular times and NaN
            dropouts are allowed.
        machine: Machine description.
        grid_hz: Output grid rate [Hz], an integer multiple of the sample rate.
        payload: Known payload [kg], or None to estimate it (sliding-window least squares).
        options: Further settings (:class:`ReplayOptions`).

    Returns:
        :class:`TwinResult` from the first to the last sample time.

    Raises:
        TwinError: Missing channels, too few samples, rod positions outside the geometry.
    """
    return TwinResult.concat(list(iter_replay(samples, machine, grid_hz, payload, options)))
