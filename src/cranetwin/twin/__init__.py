"""The twin: replay of sensor samples through the machine's physics (``replay``, ``TwinStream``),
payload estimation, and calibration of friction and masses."""

from __future__ import annotations

import cranetwin.jitcache  # noqa: F401  (first: drops stale numba caches)
from cranetwin.twin.options import ReplayOptions
from cranetwin.twin.replay import TwinStream, iter_replay, replay
from cranetwin.twin.result import TwinResult

__all__ = ["ReplayOptions", "TwinResult", "TwinStream", "iter_replay", "replay"]
