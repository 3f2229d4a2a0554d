"""A known payload as a time series, in the replay's inverse dynamics.

A user's log may weigh the load (a load cell, a scale's log; the import mapping's ``[payload]``
column, docs/IMPORT.md). :func:`cranetwin.twin.replay` takes such a series at the sample
times, shape (n,) [kg], NaN where it is not known. Where it is known it is the payload of
every load the replay computes (RNEA joint loads, residual, wrenches, the Eq. 3/4 correction,
the model-based forces, the slewing inertia of an integrated slew); where it is NaN the
sliding-window estimate (:mod:`cranetwin.twin.payload`) is used as without a series.
``TwinResult.payload_kg`` is the payload used and ``payload_std_kg`` is 0 where it was known,
as with a constant known payload.

The replay works on the regular sample instants t_k = origin + k·period; the series is
carried there by :func:`at_instants`: linear between the two samples around t_k when both are
known and at most ``max_gap_s`` apart (exactly the sample's value at a sample time), else NaN.
A grab is a step in the series: between two consecutive samples it becomes a ramp one sample
period long (the grid interpolates the payload linearly between samples), and a step inside a
dropout longer than ``max_gap_s`` is not smeared over it — the estimate fills the dropout.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]

SAME_INSTANT_S = 1e-6
"""An instant this close to a sample time [s] is that sample's instant (:func:`at_instants`)."""


def at_instants(t_s: F64, sample_t_s: F64, known_kg: F64, max_gap_s: float) -> F64:
    """The known payload at the instants ``t_s`` (module docstring).

    Args:
        t_s: Instants [s], shape (m,).
        sample_t_s: Sample times [s], shape (n,), increasing.
        known_kg: Known payload at the samples [kg], shape (n,); NaN = not known.
        max_gap_s: Longest spacing of two samples interpolated across [s].

    Returns:
        Shape (m,) [kg]; NaN where not known. An instant within ``SAME_INSTANT_S`` of a
        sample time takes that sample's value (a regular instant computed as origin + k·period
        may miss the sample's float time by rounding; epoch seconds resolve 0.24 µs).
    """
    out = np.full(t_s.shape, np.nan)
    n = sample_t_s.shape[0]
    if n == 0 or t_s.shape[0] == 0:
        return out
    hi = np.clip(np.searchsorted(sample_t_s, t_s), 0, n - 1)
    lo = np.clip(hi - 1, 0, n - 1)
    near = np.where(np.abs(sample_t_s[hi] - t_s) <= np.abs(t_s - sample_t_s[lo]), hi, lo)
    same = np.abs(sample_t_s[near] - t_s) <= SAME_INSTANT_S
    out[same] = known_kg[near[same]]
    between = ~same & (t_s > sample_t_s[0]) & (t_s < sample_t_s[-1])
    b = hi[between]
    t0, t1 = sample_t_s[b - 1], sample_t_s[b]
    y0, y1 = known_kg[b - 1], known_kg[b]
    val = y0 + (t_s[between] - t0) / (t1 - t0) * (y1 - y0)
    val[~(t1 - t0 <= max_gap_s)] = np.nan  # NaN y0 or y1 already gives NaN
    out[between] = val
    return out


def with_known(known_kg: F64 | None, mass_kg: F64, std_kg: F64) -> tuple[F64, F64]:
    """The payload and its standard error where known: ``known_kg`` with σ 0 where finite,
    the estimate ``mass_kg`` ± ``std_kg`` elsewhere; all shape (m,) [kg]. ``known_kg`` None:
    the estimate unchanged."""
    if known_kg is None:
        return mass_kg, std_kg
    ok = np.isfinite(known_kg)
    return np.where(ok, known_kg, mass_kg), np.where(ok, 0.0, std_kg)


def fully_known(known_kg: F64 | None) -> bool:
    """Every instant has a known payload (no estimate is needed)."""
    return known_kg is not None and bool(np.isfinite(known_kg).all())


__all__ = ["SAME_INSTANT_S", "at_instants", "fully_known", "with_known"]
