"""Settings of a replay, and what a replay accepts as samples."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol

from cranetwin.samples import SampleArrays
from cranetwin.signal import SmoothingChoice

END_STOP_MARGIN_M = 0.002
"""Rod positions this close to either end of the stroke [m] count as in the end stop: the
wrench accelerations stay kinematic for that joint there (``wrench_acceleration``)."""


class HasSamples(Protocol):
    """Anything carrying sensor samples, e.g. :class:`cranetwin.sim.Recording`."""

    @property
    def samples(self) -> SampleArrays: ...


@dataclass(frozen=True)
class ReplayOptions:
    """Settings of a replay.

    Attributes:
        grid_hz: Output grid rate [Hz]; must be an integer multiple of the sample rate.
        smooth: Savitzky–Golay smoothing on (window chosen from the noise level) or off.
        adaptive_pressures: Pressure windows adapted per sample (LPA-ICI, True), the fixed
            window of least Stein risk (False), or per cylinder whichever of the two predicts
            held-out samples of its force better (``"choose"``,
            :func:`cranetwin.signal.split_risk.ici_or_fixed`).
        smoothing: Fixed smoothing choices per working channel (skips the automatic choice).
        velocity: Rod velocity from the derivative of the position spline (``"spline"``) or by
            Newton's divided-difference formula at the samples, then splined (``"newton"``).
        payload_window_s: Length of the payload least-squares window [s].
        chunk_samples: Samples per processing chunk (memory and cache size). Each chunk
            recomputes a margin of ``payload window / 2 + prefilter / 2 + settle_samples``
            samples on either side (≈ 200 at 100 Hz), so longer chunks waste less; 6000 (one
            minute at 100 Hz, ≈ 30 MB of 1 kHz outputs) matches iter_replay's blocks.
        settle_samples: Spline margin on each side of a chunk [samples].
        sample_period_s: Nominal sample period [s]; the median spacing of the first data if None.
        choose_after_s: Streaming: data collected before the smoothing windows are chosen [s].
        theta0_initial: Slew angle at the start when it is integrated from torque [rad] (the
            first integrated free joint; any other integrated joint starts at 0).
        max_gap_s: Dropouts longer than this are flagged in ``TwinResult.gap`` (5 periods if None).
        lookahead_s: Streaming: raw data held back for regularisation [s] (50 periods if None).
        wrench_acceleration: Joint accelerations behind ``joint_wrench``: ``"dynamic"`` =
            forward dynamics from the measured actuator loads, qdd = M⁻¹(tau_act − C·qd − g)
            (paper Eq. 3/4) on every joint whose load is measured (cylinder joints; the slew
            when the pillar torque is sent), keeping the hydraulic oscillations that the
            smoothed kinematic accelerations lose (docs/ACCURACY.md "Joint reaction loads":
            moment NRMSE 4–30× lower on fig3/log-loading at e = 0 and 2 %, fatigue damage of
            the bending moments 0.66–1.04× the truth's instead of 0.00–0.6×); ``"kinematic"``
            = the twice-differentiated positions (``qdd``). ``qdd``, ``id_torque`` and
            ``residual`` stay kinematic either way, and so does a cylinder joint while its
            rod is within ``END_STOP_MARGIN_M`` of an end of the stroke (the end stop takes
            a force the pressures do not show) and during bridged dropouts.
        model_forces: Cylinder forces from the inverse dynamics corrected by the pressures
            (:mod:`cranetwin.twin.force_model`): ``"auto"`` for the cylinders whose pressure
            error σ_F exceeds 20 % of the force range (decided with the smoothing windows),
            unless the two-fold split risk on the choice span shows the other force better by
            more than two standard errors (:mod:`cranetwin.twin.model_choice`),
            ``"on"`` for every cylinder, ``"off"`` for none (Eq. 1–2 of the smoothed
            pressures only). Needs smoothing on.
        generated_kernels: Inverse dynamics and mass matrices by the kernels generated for
            the machine (:func:`cranetwin.physics.dynamics.batch_kernels`); False: the
            generic ones (same results to rounding; the benchmark's baseline).
    """

    grid_hz: float = 1000.0
    smooth: bool = True
    adaptive_pressures: bool | Literal["choose"] = "choose"
    smoothing: tuple[SmoothingChoice, ...] | None = None
    velocity: Literal["spline", "newton"] = "spline"
    payload_window_s: float = 2.0
    chunk_samples: int = 6000
    settle_samples: int = 40
    sample_period_s: float | None = None
    choose_after_s: float = 10.0
    theta0_initial: float = 0.0
    max_gap_s: float | None = None
    lookahead_s: float | None = None
    wrench_acceleration: Literal["dynamic", "kinematic"] = "dynamic"
    model_forces: Literal["auto", "on", "off"] = "auto"
    generated_kernels: bool = True
