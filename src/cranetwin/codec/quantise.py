"""Values in channel units ↔ integer steps of the channel's resolution.

A sensor reports multiples of its resolution; ``k = round(v / resolution)`` is exact for them and
``k · resolution`` (computed in float64 as ``float(k) * resolution``) gives back the very same
float. Both the wire encoder and storage's float path quantise here, and every decoder
dequantises here, so a value read from storage is bit-for-bit the value the wire decoder made.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
Mask = npt.NDArray[np.bool_]

EXACT_STEPS = 2.0**53
"""|k| below which float64 ↔ int64 is exact (the default limit of :func:`quantise`)."""


class QuantiseError(ValueError):
    """Values cannot be quantised (shape, resolution, infinite or too large)."""


def _res(resolution: Sequence[float] | npt.ArrayLike, c: int) -> F64:
    res = np.asarray(resolution, dtype=np.float64)
    if res.ndim != 1 or res.shape[0] != c:
        raise QuantiseError(f"values have {c} channels, {res.size} resolutions given")
    return res


def quantise(values: F64, resolution: Sequence[float] | npt.ArrayLike, *,
             limit: float = EXACT_STEPS) -> tuple[I64, Mask]:
    """Integer steps k = round(v / resolution) (half to even) and the missing mask.

    Args:
        values: Shape (n, c) [channel units]; NaN = missing.
        resolution: Step per channel, length c [channel units], finite and > 0.
        limit: Largest |k| accepted (exclusive) [steps].

    Returns:
        ``(k, missing)``, both shape (n, c); k is 0 where missing.

    Raises:
        QuantiseError: shapes disagree, a resolution is not finite and > 0, or a value is
            infinite or ``limit`` steps or more from zero.
    """
    v = np.asarray(values, dtype=np.float64)
    if v.ndim != 2:
        raise QuantiseError(f"values must be 2-D (samples × channels), got shape {v.shape}")
    res = _res(resolution, v.shape[1])
    if not np.all(np.isfinite(res) & (res > 0)):
        raise QuantiseError(f"resolutions must be finite and > 0, got {res.tolist()}")
    missing = np.isnan(v)
    q = v / res  # one array for every stage: rounded and checked in place
    if missing.any():
        np.copyto(q, 0.0, where=missing)
    np.rint(q, out=q)
    if q.size and not (-limit < q.min() and q.max() < limit):  # ±inf fail here too
        raise QuantiseError(f"values are infinite or beyond ±{limit:.0f} steps of their "
                            "resolution")
    return q.astype(np.int64), missing


def dequantise(k: I64, missing: Mask | None, resolution: Sequence[float] | npt.ArrayLike) -> F64:
    """Values ``float(k) · resolution`` [channel units], NaN where ``missing``.

    Args:
        k: Integer steps, shape (n, c).
        missing: Shape (n, c), or None for none missing.
        resolution: Step per channel, length c [channel units].
    """
    out: F64 = np.multiply(k, _res(resolution, k.shape[1]), dtype=np.float64)
    if missing is not None and missing.any():
        np.copyto(out, np.nan, where=missing)
    return out


def on_grid(values: F64, resolution: Sequence[float] | npt.ArrayLike) -> F64:
    """``values`` snapped to the grid exactly as a decoder returns them (k · resolution)."""
    k, missing = quantise(values, resolution)
    return dequantise(k, missing, resolution)
