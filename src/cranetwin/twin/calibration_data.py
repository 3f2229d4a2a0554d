"""What :mod:`cranetwin.twin.calibration` needs to know about its data: sample and grid rates,
the rod-velocity noise the Coulomb column is corrected for, the constant-mass segments between
payload changes (of the estimate, or of a known payload series), and the statistics of
correlated residuals (integrated autocorrelation time, a delete-one-block jackknife).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from cranetwin.model import Machine
from cranetwin.samples import SampleArrays
from cranetwin.signal import nominal_period
from cranetwin.signal.savgol import sg_filter
from cranetwin.twin.channels import ChannelMap
from cranetwin.twin.result import TwinResult
from cranetwin.twin.stages import derivative_filter

F64 = npt.NDArray[np.float64]

# a payload step smaller than this is no payload change [kg]; larger than 5σ of the estimate
PAYLOAD_STEP_KG = 30.0


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


def res_rate(res: TwinResult) -> float:
    """Grid rate of a replay result [Hz]."""
    return 1.0 / nominal_period(res.t_s[:100])


def sample_rate(samples: SampleArrays) -> float:
    """Nominal sample rate [Hz]: the period the samples carry, estimated only if they carry
    none."""
    return 1.0 / nominal_period(samples.t_s, samples.period_ns)


def payload_segments(res: TwinResult, t: F64, sample_period: float,
              window_s: float) -> tuple[npt.NDArray[np.int64], int, npt.NDArray[np.bool_],
                                        list[float]]:
    """Constant-mass segments from the replay's payload estimate: (segment per instant of
    ``t``, count, instants near a payload change, change times [s]).

    A change is where the estimate crosses halfway between its low and high levels (10th and
    90th percentiles) when they differ by more than ``PAYLOAD_STEP_KG`` and 5σ; the smear of
    the estimate's window (:func:`cranetwin.twin.lifts.payload_smear_s`) and 1 s either side
    are left out."""
    from cranetwin.twin.lifts import lift_payloads, payload_smear_s

    m = np.nan_to_num(res.payload_kg)
    lo, hi = np.percentile(m, [10.0, 90.0])
    sig = float(np.median(res.payload_std_kg[np.isfinite(res.payload_std_kg)])) \
        if np.any(np.isfinite(res.payload_std_kg)) else 0.0
    seg = np.zeros(t.shape[0], dtype=np.int64)
    near = np.zeros(t.shape[0], dtype=bool)
    if hi - lo < max(PAYLOAD_STEP_KG, 5.0 * sig):
        return seg, 1, near, []
    smear = payload_smear_s(res, sample_period, window_s)
    lifts = lift_payloads(res.t_s, m - lo, np.ones_like(m), smear, (hi - lo) / 2.0)
    changes = sorted({x for lf in lifts for x in (lf.grab_s, lf.release_s)
                      if res.t_s[0] < x < res.t_s[-1]})
    for tc in changes:
        seg += (t > tc).astype(np.int64)
        near |= np.abs(t - tc) <= smear / 2.0 + 1.0
    return seg, len(changes) + 1, near, changes


def known_payload_changes(t: F64, known_kg: F64,
                          away_s: float = 1.0) -> tuple[npt.NDArray[np.bool_], list[float]]:
    """Instants of ``t`` [s] within ``away_s`` of a change of a known payload series
    ``known_kg`` (at those instants [kg], NaN where not known), and the change times [s].

    A change is a step of more than ``PAYLOAD_STEP_KG`` between neighbouring known instants
    (within ``away_s`` of each other); it is left out of the fit as the estimate's changes
    are (:func:`payload_segments`): a grab or release brings contact and swinging the
    model does not know, and the logger's timing of the step may be off by a sample."""
    near = np.zeros(t.shape[0], dtype=bool)
    ok = np.flatnonzero(np.isfinite(known_kg))
    if ok.shape[0] < 2:
        return near, []
    step = np.abs(np.diff(known_kg[ok])) > PAYLOAD_STEP_KG
    step &= np.diff(t[ok]) <= away_s
    changes = [float(0.5 * (t[ok[i]] + t[ok[i + 1]])) for i in np.flatnonzero(step)]
    for tc in changes:
        near |= np.abs(t - tc) <= away_s
    return near, changes


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


def jackknife_std(a: F64, yv: F64, n: int, nc: int, blocks: int = 10) -> float:
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
