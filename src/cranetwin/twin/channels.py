"""Which sensor channel feeds which actuator, and how each is smoothed."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
import numpy.typing as npt

from cranetwin.errors import TwinError
from cranetwin.model import Machine
from cranetwin.signal import (
    ICI_WINDOWS,
    SmoothingChoice,
    choose_derivative_window,
    choose_window,
    estimate_noise_std,
)
from cranetwin.signal.quantisation import detect_lattice, reconstruct, single_level
from cranetwin.signal.split_risk import ici_or_fixed
from cranetwin.twin.force_model import smoothed_range, wants_model
from cranetwin.twin.observability import stated_force_sigma

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class ChannelMap:
    """Column indices of the channels the twin reads, in ``machine.cylinders`` order.

    Attributes:
        names: Channel names in the twin's working order: per cylinder pA, pB, s, then per
            torque drive (``machine.torque_drives`` order) its torque and its joint's angle,
            each if sent.
        p_a: Working-order indices of the pA channels, one per cylinder.
        p_b: Working-order indices of the pB channels.
        s: Working-order indices of the rod position channels.
        torques: Per torque drive, the index of its torque channel or None.
        angles: Per torque drive, the index of its joint's angle channel or None.
        resolution: Quantisation step per working channel (0 if unknown).
    """

    names: tuple[str, ...]
    p_a: tuple[int, ...]
    p_b: tuple[int, ...]
    s: tuple[int, ...]
    torques: tuple[int | None, ...]
    angles: tuple[int | None, ...]
    resolution: tuple[float, ...]

    @property
    def torque(self) -> int | None:
        """The first torque drive's torque channel (None if none is sent)."""
        return self.torques[0] if self.torques else None

    @property
    def angle(self) -> int | None:
        """The first torque drive's angle channel (None if none is sent)."""
        return self.angles[0] if self.angles else None

    @property
    def derivative_channels(self) -> tuple[int, ...]:
        """Working indices of the channels whose rates the twin needs (rod positions, then
        the angles sent, in drive order)."""
        return self.s + tuple(a for a in self.angles if a is not None)

    @property
    def choice_names(self) -> tuple[str, ...]:
        """Names of the smoothing choices: every channel, then ``name'`` for the windows used
        to differentiate the position channels."""
        return self.names + tuple(self.names[j] + "'" for j in self.derivative_channels)

    @staticmethod
    def build(machine: Machine, available: tuple[str, ...]) -> ChannelMap:
        """Map a machine's channels onto the columns present in a recording.

        Raises:
            TwinError: A cylinder lacks its pA, pB or s channel among ``available``.
        """
        by_key = {(c.source, c.quantity): c for c in machine.channels if c.name in available}
        names: list[str] = []
        res: list[float] = []
        idx: dict[str, list[int]] = {"pressure_a": [], "pressure_b": [], "position": []}
        for cyl in machine.cylinders:
            for q in ("pressure_a", "pressure_b", "position"):
                ch = by_key.get((cyl.name, q))
                if ch is None:
                    raise TwinError(f"cylinder {cyl.name!r} needs a {q} channel; the recording has "
                                    f"{list(available)}")
                idx[q].append(len(names))
                names.append(ch.name)
                res.append(ch.resolution)
        torques: list[int | None] = []
        angles: list[int | None] = []
        for drive in machine.torque_drives:
            for ch, into in ((by_key.get((drive.name, "torque")), torques),
                             (by_key.get((drive.joint, "angle")), angles)):
                into.append(None if ch is None else len(names))
                if ch is not None:
                    names.append(ch.name)
                    res.append(ch.resolution)
        return ChannelMap(tuple(names), tuple(idx["pressure_a"]), tuple(idx["pressure_b"]),
                          tuple(idx["position"]), tuple(torques), tuple(angles), tuple(res))


def choose_smoothing(machine: Machine, cmap: ChannelMap, values: F64,
                     enabled: bool = True,
                     adaptive: bool | Literal["choose"] = "choose",
                     model: Literal["auto", "on", "off"] = "auto") -> tuple[SmoothingChoice, ...]:
    """Savitzky–Golay choices, from regularly sampled data, in ``cmap.choice_names`` order.

    Pressures pA and pB of a cylinder share their windows, chosen on the hydraulic force
    A1·pA − A2·pB (Eq. 1 without friction), the quantity the twin needs from them; the window
    adapts sample by sample (LPA-ICI, :func:`cranetwin.signal.ici_select`) because valve steps
    make the pressures jump: long windows in between, short ones at the jumps. Where the force
    is slow under heavy noise one long fixed window does better; by default (``"choose"``) each
    cylinder takes whichever of the two predicts held-out samples of its force better.

    Args:
        machine: Machine (cylinder areas).
        cmap: Channel map.
        values: Regular samples in working order, shape (n, len(cmap.names)), finite.
        enabled: If False every channel gets window 1 (no smoothing).
        adaptive: Pressures by LPA-ICI (True), by the fixed SURE window (False), or
            ``"choose"``: per cylinder whichever of the two predicts held-out samples of the
            force better (the two-fold split risk,
            :func:`cranetwin.signal.split_risk.ici_or_fixed`).
        model: Which cylinders' forces are model-based (``model_based`` on the pressure
            pair's choices; :mod:`cranetwin.twin.force_model`): ``"auto"`` those whose force
            error σ_F (the larger of the stated accuracy's and the estimated noise, as the
            observability flag) exceeds 20 % (``force_model.MODEL_SHARE``) of the range of
            the force smoothed over the fixed window (``force_model.smoothed_range``);
            ``"on"`` all; ``"off"`` none. (The replay then revisits the ``"auto"`` choice
            by a split risk, :mod:`cranetwin.twin.model_choice`: it needs the inverse
            dynamics.)

    Position channels get a second window for their derivatives (rod velocity and
    acceleration), chosen by Lepski's rule (:func:`cranetwin.signal.choose_derivative_window`):
    a second derivative needs far more smoothing than the values.

    A channel whose samples lie on a lattice coarser than its declared resolution
    (:func:`detected_steps`) carries the step in its choice (``step``) and every window is
    chosen on its reconstruction (:func:`cranetwin.signal.quantisation.reconstruct`), which
    :func:`cranetwin.twin.stages.smooth_rows` smooths; half the step bounds its error
    (:func:`cranetwin.twin.observability.effective_accuracy`). A channel that read one value
    throughout (:func:`cranetwin.signal.quantisation.single_level`) is marked ``flat``.
    """
    none = SmoothingChoice(1, 0, 0.0, 0.0)
    out = [none] * len(cmap.choice_names)
    if not enabled:
        return tuple(out)
    cols = np.ascontiguousarray(np.asarray(values, dtype=np.float64).T)  # one pass, not ten
    steps = detected_steps(cols, cmap.resolution)
    flat = [single_level(col) for col in cols]  # no lattice: a single level has none
    for j, h in enumerate(steps):
        if h > 0:  # windows chosen on what smooth_rows will smooth: the reconstruction
            cols[j] = reconstruct(cols[j], h)
    named = dict(zip(cmap.names, steps, strict=True))
    sigma: dict[int, float] = {}  # noise of each derivative channel, estimated once
    for i, j in enumerate(cmap.derivative_channels):
        sigma[j] = estimate_noise_std(cols[j], cmap.resolution[j])
        out[len(cmap.names) + i] = choose_derivative_window(cols[j], sigma=sigma[j])
    for c, cyl in enumerate(machine.cylinders):
        ia, ib = cmap.p_a[c], cmap.p_b[c]
        force = cyl.area_a_m2 * cols[ia] - cyl.area_b_m2 * cols[ib]
        res = float(np.hypot(cyl.area_a_m2 * cmap.resolution[ia],
                             cyl.area_b_m2 * cmap.resolution[ib]))
        ch = choose_window(force, resolution=res)
        # pressures: window adapted per sample (LPA-ICI) on the force, up to the longest
        # candidate, or the fixed SURE window; sigma and the fixed window's risk kept for the
        # payload weights either way
        ici = adaptive is True or (adaptive == "choose" and ici_or_fixed(
            force, ch.sigma, ch.window, ch.polyorder, ICI_WINDOWS, 3).adaptive)
        pair = (SmoothingChoice(max(ICI_WINDOWS), 3, ch.sigma, ch.risk, adaptive=True)
                if ici else ch)
        if model == "on" or (model == "auto" and wants_model(
                max(stated_force_sigma(machine, c, named), ch.sigma),
                smoothed_range(force, ch.window))):
            pair = replace(pair, model_based=True)
        out[ia], out[ib] = replace(pair, step=steps[ia]), replace(pair, step=steps[ib])
        js = cmap.s[c]
        out[js] = choose_window(cols[js], sigma=sigma.get(js),
                                resolution=cmap.resolution[js])
    for opt in cmap.torques + cmap.angles:
        if opt is not None:
            out[opt] = choose_window(cols[opt], sigma=sigma.get(opt),
                                     resolution=cmap.resolution[opt])
    return tuple(replace(c, step=steps[j], flat=flat[j])
                 if j < len(steps) and (c.step != steps[j] or c.flat != flat[j]) else c
                 for j, c in enumerate(out))


COARSER = 1.5
"""A lattice counts as a coarse quantisation when its step exceeds the channel's declared
resolution (``Channel.resolution``) by this factor: at least twice it (an integer multiple),
with room for the step's rounding."""


def detected_steps(cols: F64, resolution: tuple[float, ...]) -> tuple[float, ...]:
    """The coarse quantisation step of each channel [channel unit]: (c, n) columns and their
    declared resolutions (c,) in, one step per column out, 0 where the samples are not on a
    lattice (:func:`cranetwin.signal.quantisation.detect_lattice`) or on one no coarser than
    the declared resolution (the sensor as the machine file describes it: its noise estimate
    is already floored at resolution/√12)."""
    out = []
    for col, res in zip(cols, resolution, strict=True):
        lat = detect_lattice(col)
        out.append(0.0 if lat is None or not lat.step > COARSER * res else lat.step)
    return tuple(out)
