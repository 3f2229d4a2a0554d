"""Signal processing for the twin: natural cubic splines, Newton-formula differentiation,
Savitzky–Golay smoothing with automatic window, regularisation, noise injection, NRMSE and
coarse quantisation (lattice detection and reconstruction).

Only numpy and scipy (plus the machine model for channel ranges)."""

from __future__ import annotations

import cranetwin.jitcache  # noqa: F401  (first: drops stale numba caches)
from cranetwin.signal.differentiate import newton_derivative
from cranetwin.signal.ici import ICI_WINDOWS, ici_select, ici_smooth, ici_smooth_pair
from cranetwin.signal.noise import NOISY_QUANTITIES, inject_uniform_noise, nrmse
from cranetwin.signal.noise_level import estimate_noise_std
from cranetwin.signal.quantisation import Lattice, detect_lattice, reconstruct, single_level
from cranetwin.signal.resample import Regular, nominal_period, regularize, uniform_grid
from cranetwin.signal.savgol import centre_weight, savgol_bank, savgol_smooth, sg_filter
from cranetwin.signal.spline import NaturalCubicSpline, knot_pieces, natural_pieces
from cranetwin.signal.window import SmoothingChoice, choose_derivative_window, choose_window

__all__ = [
    "ICI_WINDOWS",
    "Lattice",
    "NOISY_QUANTITIES",
    "NaturalCubicSpline",
    "knot_pieces",
    "natural_pieces",
    "Regular",
    "SmoothingChoice",
    "centre_weight",
    "choose_derivative_window",
    "choose_window",
    "detect_lattice",
    "single_level",
    "estimate_noise_std",
    "ici_select",
    "ici_smooth",
    "ici_smooth_pair",
    "inject_uniform_noise",
    "newton_derivative",
    "nominal_period",
    "nrmse",
    "reconstruct",
    "regularize",
    "savgol_bank",
    "savgol_smooth",
    "sg_filter",
    "uniform_grid",
]
