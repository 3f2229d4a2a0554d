"""Smoothing's former single module: its names, now in one module per concept.

:mod:`cranetwin.signal.noise_level` (σ from higher differences),
:mod:`cranetwin.signal.savgol` (Savitzky–Golay filters), :mod:`cranetwin.signal.window`
(automatic window choice), :mod:`cranetwin.signal.ici` and
:mod:`cranetwin.signal.ici_kernels` (LPA-ICI). Kept so that existing imports keep working.
"""

from __future__ import annotations

from cranetwin.signal.ici import ICI_GAMMA, ICI_WINDOWS, ici_select, ici_smooth, ici_smooth_pair
from cranetwin.signal.noise_level import _median, _rank_pair, _rank_value, estimate_noise_std
from cranetwin.signal.savgol import (
    FFT_MIN_WINDOW,
    centre_weight,
    savgol_bank,
    savgol_columns,
    savgol_smooth,
    sg_filter,
)
from cranetwin.signal.window import (
    DEFAULT_POLYORDERS,
    DEFAULT_WINDOWS,
    SmoothingChoice,
    choose_derivative_window,
    choose_window,
)

__all__ = [
    "DEFAULT_POLYORDERS",
    "DEFAULT_WINDOWS",
    "FFT_MIN_WINDOW",
    "ICI_GAMMA",
    "ICI_WINDOWS",
    "SmoothingChoice",
    "_median",
    "_rank_pair",
    "_rank_value",
    "centre_weight",
    "choose_derivative_window",
    "choose_window",
    "estimate_noise_std",
    "ici_select",
    "ici_smooth",
    "ici_smooth_pair",
    "savgol_bank",
    "savgol_columns",
    "savgol_smooth",
    "sg_filter",
]
