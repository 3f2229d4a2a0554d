"""Bandwidth of the wire format: UDP payload bytes per sample on a given signal."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from cranetwin.protocol.data import decode_data, encode_data, on_grid
from cranetwin.protocol.wire import IP_UDP_OVERHEAD_V4, MAX_DATAGRAM, MachineKey

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class WireStats:
    """Measured size of a stream of data datagrams.

    Attributes:
        samples: Samples (rows of all channels) sent.
        datagrams: Data datagrams.
        payload_bytes: Sum of UDP payload bytes (our headers and HMAC tags included).
        bytes_per_sample: payload_bytes / samples.
        ip_udp_bytes_per_sample: IPv4 + UDP header bytes per sample (28 per datagram),
            reported separately, not included above.
        max_datagram_bytes: Largest datagram [bytes].
        lossless: Every decoded value equals the input snapped to the sensor grid (NaN where NaN).
    """

    samples: int
    datagrams: int
    payload_bytes: int
    bytes_per_sample: float
    ip_udp_bytes_per_sample: float
    max_datagram_bytes: int
    lossless: bool


def measure_bytes_per_sample(key: MachineKey, values: F64, period_ns: int, *,
                             batch_samples: int = 50, t0_ns: int = 0,
                             max_datagram: int = MAX_DATAGRAM) -> WireStats:
    """Encode ``values`` in batches as the :class:`~cranetwin.protocol.Sender` does, decode them
    back, and count bytes.

    Args:
        key: Machine key (layout of ``values``).
        values: Samples, shape (n, c), layout column order [channel units]; NaN = missing.
        period_ns: Sample period [ns].
        batch_samples: Samples per datagram (halved until a datagram fits ``max_datagram``).
        t0_ns: Time of the first sample [ns].
        max_datagram: Datagram size limit [bytes].
    """
    v = np.asarray(values, dtype=np.float64)
    sizes: list[int] = []
    ok = True
    seq = 0
    grid = on_grid(v, key.layout.resolutions)
    stack = [(i, min(i + batch_samples, v.shape[0])) for i in range(0, v.shape[0], batch_samples)]
    stack.reverse()
    while stack:
        a, b = stack.pop()
        dg = encode_data(key, seq, t0_ns + a * period_ns, period_ns, v[a:b])
        if len(dg) > max_datagram and b - a > 1:
            m = (a + b) // 2
            stack += [(m, b), (a, m)]
            continue
        seq += 1
        sizes.append(len(dg))
        back = decode_data(dg, key).values
        ok = ok and bool(np.array_equal(back, grid[a:b], equal_nan=True))
    n = v.shape[0]
    total = sum(sizes)
    return WireStats(samples=n, datagrams=len(sizes), payload_bytes=total,
                     bytes_per_sample=total / n if n else float("nan"),
                     ip_udp_bytes_per_sample=IP_UDP_OVERHEAD_V4 * len(sizes) / n if n else 0.0,
                     max_datagram_bytes=max(sizes, default=0), lossless=ok)
