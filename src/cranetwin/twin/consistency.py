"""Do the pressures and the motion agree? The replay's residual against what sensor noise explains.

The twin computes every actuated joint's load twice: from the cylinder's pressures,
τ_act = F·ds/dq with F = A_A·p_A − A_B·p_B − friction (Eq. 1–2), and from the measured motion
through the inverse dynamics, τ_id (:class:`cranetwin.twin.result.TwinResult`). Their
difference, the residual, divided by the moment arm ds/dq is a force [N] per cylinder::

    r = residual_j / (ds/dq) = F − F_id

With a machine file and a mapping that describe the crane, r is sensor noise, the hydraulic
transients the smoothed accelerations miss and what the payload estimate does not absorb. A
wrong bore, friction, pin offset or swapped chambers add a systematic part that follows the
motion and the pressures. Sensor noise averages out, a model error does not: r is averaged over
consecutive blocks of ``BLOCK_S`` (1 s), and the median |block mean| (a model error persists
over the window; the payload estimate's lag at a grab or release does not) is compared with

* what noise leaves in a block mean, σ_F/√(samples per block) (σ_F the per-sample force error
  of the pressures, estimated or stated, :func:`cranetwin.twin.observability.force_sigma`; a
  stated accuracy is mostly offset and gain and is not divided), and
* the RMS of the force the motion needs, F_id.

A cylinder is **inconsistent** with the machine file or the mapping when that median exceeds
``SHARE_LIMIT`` of the RMS force **and** ``NOISE_FACTOR`` × the noise allowance
(docs/ACCURACY.md, "Model consistency": the limits and how often they are wrong).

One likely cause is named: r regressed on the two chamber forces, r ≈ c_A·A_A·p_A −
c_B·A_B·p_B. An area error gives c = 1 − A_true/A_file < 1; swapped chambers give
c_A = 1 + A_B/A_A and c_B = 1 + A_A/A_B, both above 1, which no area error can. The hint is
given only when the fit explains most of r (``HINT_R2``). The coefficients are reported, but
no "area" hint: a pressure sensor's offset and a wrong pin offset on another cylinder gave the
same pattern on the test data (docs/ACCURACY.md, "Model consistency").

Shapes: m grid instants, n_c cylinders; SI units (N, m, Pa).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt

from cranetwin.model import Machine
from cranetwin.signal import SmoothingChoice
from cranetwin.twin.observability import channel_steps, force_sigma, stated_force_sigma

F64 = npt.NDArray[np.float64]

BLOCK_S = 1.0
"""Length of the blocks the residual is averaged over [s]."""
SHARE_LIMIT = 0.10
"""Inconsistent when the residual's median |block mean| exceeds this share of RMS F_id …"""
NOISE_FACTOR = 3.0
"""… and this many times what sensor noise leaves in a block mean."""
HINT_R2 = 0.8
"""A cause is hinted only when the pressure fit explains this share of the residual's energy."""
SWAP_C = 1.0
"""Both pressure coefficients above this: swapped chambers (an area error gives c < 1)."""


class ModelConsistency(NamedTuple):
    """Whether one cylinder's pressures agree with the motion's inverse dynamics.

    Attributes:
        cylinder: Cylinder name.
        typical_n: Median |block mean| of the force residual over 1 s blocks [N] (a model
            error persists; the payload estimate's lag at a grab or release does not).
        residual_rms_n: RMS of the force residual's 1 s block means [N].
        raw_rms_n: RMS of the force residual per sample [N].
        range_n: Range of the inverse-dynamics force's block means [N].
        level_n: RMS of the inverse-dynamics force F_id [N].
        share: typical_n / level_n (inf for a zero force).
        noise_n: What sensor noise leaves in a block mean [N] (module docstring).
        noise_ratio: typical_n / noise_n (inf without noise).
        consistent: Not (share > ``SHARE_LIMIT`` and noise_ratio > ``NOISE_FACTOR``).
        c_a, c_b: Coefficients of the residual on A_A·p_A and −A_B·p_B (NaN: no fit).
        r2: Share of the residual's energy the pressure fit explains.
        hint: A likely cause ("swapped chambers …") or "".
    """

    cylinder: str
    typical_n: float
    residual_rms_n: float
    raw_rms_n: float
    range_n: float
    level_n: float
    share: float
    noise_n: float
    noise_ratio: float
    consistent: bool
    c_a: float = math.nan
    c_b: float = math.nan
    r2: float = math.nan
    hint: str = ""

    def message(self) -> str:
        """One line naming the cylinder and the numbers."""
        verdict = ("consistent" if self.consistent else
                   "INCONSISTENT with the machine file, the mapping or the pressure "
                   "sensors' calibration")
        text = (f"cylinder {self.cylinder!r}: pressures and motion {verdict}: force "
                f"residual {self.typical_n:.0f} N (median over {BLOCK_S:g} s means; RMS "
                f"{self.raw_rms_n:.0f} N) = {100 * self.share:.0f} % of the force the motion "
                f"needs ({self.level_n:.0f} N RMS; limit {100 * SHARE_LIMIT:.0f} %) and "
                f"{self.noise_ratio:.1f}× what sensor noise explains (±{self.noise_n:.0f} N; "
                f"limit {NOISE_FACTOR:g}×)")
        if self.hint:
            text += (f"; likely {self.hint} (residual ≈ {self.c_a:+.2f}·A_A·p_A "
                     f"{-self.c_b:+.2f}·A_B·p_B, R² {self.r2:.2f})")
        return text

    def as_json(self) -> dict[str, Any]:
        """Plain numbers for the API (non-finite → None)."""
        def num(x: float, digits: int = 4) -> float | None:
            return round(x, digits) if math.isfinite(x) else None
        return {"cylinder": self.cylinder, "typical_n": num(self.typical_n, 1),
                "residual_rms_n": num(self.residual_rms_n, 1),
                "raw_rms_n": num(self.raw_rms_n, 1), "range_n": num(self.range_n, 1),
                "level_n": num(self.level_n, 1),
                "share": num(self.share), "noise_n": num(self.noise_n, 1),
                "noise_ratio": num(self.noise_ratio, 2), "consistent": self.consistent,
                "c_a": num(self.c_a), "c_b": num(self.c_b), "r2": num(self.r2),
                "hint": self.hint or None}


def _blocks(x: F64, ok: npt.NDArray[np.bool_], size: int) -> tuple[F64, F64]:
    """(means, sample counts) of ``x`` over consecutive blocks of ``size`` rows, only the
    ``ok`` samples; x (m, n_c), ok (m, n_c); blocks without samples have count 0. A chunk
    shorter than a block is one block."""
    m = x.shape[0]
    nb = max(1, m // size)
    edges = np.linspace(0, m, nb + 1).astype(int)
    xs = np.where(ok, x, 0.0)
    cs = np.concatenate([np.zeros((1, x.shape[1])), np.cumsum(xs, axis=0)])
    cn = np.concatenate([np.zeros((1, x.shape[1])), np.cumsum(ok, axis=0)])
    sums = cs[edges[1:]] - cs[edges[:-1]]
    counts = cn[edges[1:]] - cn[edges[:-1]]
    with np.errstate(all="ignore"):
        means = np.where(counts > 0, sums / np.maximum(counts, 1), 0.0)
    return means, counts


@dataclass
class ResidualStats:
    """The force residual's sums per cylinder, collected over the chunks of a replay.

    Attributes:
        block_sq: Σ count·mean² of the residual's block means, (n_c,) [N²].
        raw_sq: Σ r² per sample, (n_c,) [N²].
        samples: Samples counted, (n_c,).
        blocks: Blocks with samples, (n_c,).
        id_lo, id_hi: Smallest and largest block mean of F_id, (n_c,) [N].
        xtx, xty: Normal equations of r on (A_A·p_A, −A_B·p_B), (n_c, 2, 2) and (n_c, 2).
    """

    block_sq: F64 = field(default_factory=lambda: np.zeros(0))
    raw_sq: F64 = field(default_factory=lambda: np.zeros(0))
    samples: F64 = field(default_factory=lambda: np.zeros(0))
    blocks: F64 = field(default_factory=lambda: np.zeros(0))
    id_lo: F64 = field(default_factory=lambda: np.zeros(0))
    id_hi: F64 = field(default_factory=lambda: np.zeros(0))
    id_sq: F64 = field(default_factory=lambda: np.zeros(0))
    block_means: list[F64] = field(default_factory=list)
    block_counts: list[F64] = field(default_factory=list)
    xtx: F64 = field(default_factory=lambda: np.zeros((0, 2, 2)))
    xty: F64 = field(default_factory=lambda: np.zeros((0, 2)))

    def add(self, machine: Machine, t_s: F64, q: F64, residual: F64, id_torque: F64,
            p_a: F64, p_b: F64, gap: npt.NDArray[np.bool_]) -> None:
        """Take in a chunk of a replay result (the :class:`TwinResult` arrays of that name:
        t_s (m,), q/residual/id_torque (m, n_joints), p_a/p_b (m, n_c), gap (m,))."""
        from cranetwin.physics import moment_arms

        m, nc = t_s.shape[0], len(machine.cylinders)
        if m == 0 or nc == 0:
            return
        if self.samples.shape[0] == 0:
            self.block_sq, self.raw_sq = np.zeros(nc), np.zeros(nc)
            self.samples, self.blocks = np.zeros(nc), np.zeros(nc)
            self.id_lo, self.id_hi = np.full(nc, np.inf), np.full(nc, -np.inf)
            self.id_sq = np.zeros(nc)
            self.xtx, self.xty = np.zeros((nc, 2, 2)), np.zeros((nc, 2))
        joints = [machine.joint_index(c.joint) for c in machine.cylinders]
        arm = moment_arms(machine, q)
        with np.errstate(all="ignore"):
            r = residual[:, joints] / arm
            f_id = id_torque[:, joints] / arm
        aa = np.array([c.area_a_m2 for c in machine.cylinders])
        ab = np.array([c.area_b_m2 for c in machine.cylinders])
        xa, xb = p_a * aa, -p_b * ab
        ok = (np.isfinite(r) & np.isfinite(f_id) & np.isfinite(xa) & np.isfinite(xb)
              & (np.abs(arm) > 1e-6) & ~gap[:, None])
        dt = float(np.median(np.diff(t_s))) if m > 1 else BLOCK_S
        size = max(1, int(round(BLOCK_S / dt))) if dt > 0 else m
        rm, cnt = _blocks(r, ok, size)
        fm, _ = _blocks(f_id, ok, size)
        self.block_sq += np.sum(cnt * rm**2, axis=0)
        self.blocks += np.sum(cnt > 0, axis=0)
        self.block_means.append(rm)
        self.block_counts.append(cnt)
        self.samples += np.sum(ok, axis=0)
        r0 = np.where(ok, r, 0.0)
        self.raw_sq += np.sum(r0**2, axis=0)
        self.id_sq += np.sum(np.where(ok, f_id, 0.0)**2, axis=0)
        has = cnt > 0
        self.id_lo = np.minimum(self.id_lo, np.where(has, fm, np.inf).min(axis=0))
        self.id_hi = np.maximum(self.id_hi, np.where(has, fm, -np.inf).max(axis=0))
        a0, b0 = np.where(ok, xa, 0.0), np.where(ok, xb, 0.0)
        self.xtx[:, 0, 0] += np.sum(a0 * a0, axis=0)
        self.xtx[:, 0, 1] += np.sum(a0 * b0, axis=0)
        self.xtx[:, 1, 0] += np.sum(a0 * b0, axis=0)
        self.xtx[:, 1, 1] += np.sum(b0 * b0, axis=0)
        self.xty[:, 0] += np.sum(a0 * r0, axis=0)
        self.xty[:, 1] += np.sum(b0 * r0, axis=0)

    def assess(self, machine: Machine,
               smoothing: Mapping[str, SmoothingChoice]) -> tuple[ModelConsistency, ...]:
        """One :class:`ModelConsistency` per cylinder (``machine.cylinders`` order; nothing
        added: none)."""
        if self.samples.shape[0] == 0:
            return ()
        means = np.concatenate(self.block_means) if self.block_means else np.zeros((0, 1))
        counts = np.concatenate(self.block_counts) if self.block_counts else np.zeros((0, 1))
        out = []
        for k, cyl in enumerate(machine.cylinders):
            n = float(self.samples[k])
            full = counts[:, k] >= 0.5 * counts[:, k].max() if counts.shape[0] else counts[:, 0]
            if n == 0 or not np.any(full):
                nan = math.nan
                out.append(ModelConsistency(cyl.name, nan, nan, nan, nan, nan, nan, nan, nan,
                                            True))
                continue
            typ = float(np.median(np.abs(means[full, k])))
            lp = math.sqrt(float(self.block_sq[k]) / n)
            raw = math.sqrt(float(self.raw_sq[k]) / n)
            span = float(self.id_hi[k] - self.id_lo[k])
            level = math.sqrt(float(self.id_sq[k]) / n)
            sigma, _ = force_sigma(machine, k, smoothing)
            stated = stated_force_sigma(machine, k, channel_steps(smoothing))
            est = sigma if sigma > stated else 0.0
            noise = math.hypot(est / math.sqrt(float(np.median(counts[full, k]))), stated)
            share = typ / level if level > 0 else (0.0 if typ == 0 else math.inf)
            ratio = typ / noise if noise > 0 else (0.0 if typ == 0 else math.inf)
            bad = share > SHARE_LIMIT and ratio > NOISE_FACTOR
            c_a, c_b, r2 = self._fit(k, raw**2 * n)
            out.append(ModelConsistency(cyl.name, typ, lp, raw, span, level, share, noise, ratio,
                                        not bad, c_a, c_b, r2,
                                        _hint(c_a, c_b, r2) if bad else ""))
        return tuple(out)

    def _fit(self, k: int, energy: float) -> tuple[float, float, float]:
        a, y = self.xtx[k], self.xty[k]
        if not np.all(np.isfinite(a)) or abs(float(np.linalg.det(a))) <= 1e-12 * float(
                np.trace(a)) ** 2 or energy <= 0:
            return math.nan, math.nan, math.nan
        c = np.linalg.solve(a, y)
        explained = float(c @ y)  # ‖X c‖² at the least-squares solution
        return float(c[0]), float(c[1]), explained / energy


def _hint(c_a: float, c_b: float, r2: float) -> str:
    """The likely cause from the pressure fit (module docstring), or ""."""
    if not (math.isfinite(r2) and r2 >= HINT_R2):
        return ""
    if c_a > SWAP_C and c_b > SWAP_C:
        return "swapped chambers (p_A and p_B exchanged)"
    return ""


def assess(machine: Machine, t_s: F64, q: F64, residual: F64, id_torque: F64, p_a: F64,
           p_b: F64, gap: npt.NDArray[np.bool_],
           smoothing: Mapping[str, SmoothingChoice]) -> tuple[ModelConsistency, ...]:
    """One :class:`ModelConsistency` per cylinder over one window (arrays as
    :meth:`ResidualStats.add`)."""
    st = ResidualStats()
    st.add(machine, t_s, q, residual, id_torque, p_a, p_b, gap)
    return st.assess(machine, smoothing)


def inconsistent(verdicts: tuple[ModelConsistency, ...]) -> list[str]:
    """The warning lines of the cylinders found inconsistent."""
    return [v.message() for v in verdicts if not v.consistent]
