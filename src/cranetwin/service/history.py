"""Analytics of any range from stored, mergeable parts (no HTTP here).

The twin worker stores, per machine and minute window, the :class:`AnalyticsPart` of the window's
load history (:func:`store_part`) and rolls complete hours and days up into one part each
(:func:`roll_up`). A ``[from, to)`` request folds the largest stored windows that lie inside it
(days, then hours, then minutes) and replays only what has no stored part — the partial minutes
at the edges and minutes not processed yet — exactly as the worker replays a minute
(:func:`window_history`). Folding parts equals folding the windows' histories
(tests/test_history_merge.py), so the result is that of a direct analysis of the range.
"""

from __future__ import annotations

import math
import pickle
import zlib
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt

from cranetwin.analytics import AnalyticsConfig, AnalyticsPart, AnalyticsState, LoadHistory
from cranetwin.analytics.runs import Run
from cranetwin.errors import AnalyticsError, CraneTwinError
from cranetwin.model import Machine
from cranetwin.storage import analytics_windows as aw

PART_MAGIC = b"cranetwin-analytics-part-2\n"  # 2: loaded stretches carry steady columns
PART_MAGIC_1 = b"cranetwin-analytics-part-1\n"  # every instant steady (read, upgraded)
MINUTE_S = 60
LEVELS = (86400, 3600, MINUTE_S)


def dump_part(part: AnalyticsPart) -> bytes:
    """Bytes of a part (pickle behind a version tag, zlib): written and read by the service
    only, never from an untrusted source."""
    return PART_MAGIC + zlib.compress(pickle.dumps(part, protocol=pickle.HIGHEST_PROTOCOL), 1)


def load_part(data: bytes) -> AnalyticsPart:
    """A part written by :func:`dump_part`.

    Raises:
        AnalyticsError: Not a part of this version.
    """
    old = data.startswith(PART_MAGIC_1)
    if not (old or data.startswith(PART_MAGIC)):
        raise AnalyticsError("not an analytics part of this version")
    part = pickle.loads(zlib.decompress(data[len(PART_MAGIC):]))
    if not isinstance(part, AnalyticsPart):
        raise AnalyticsError(f"expected an AnalyticsPart, got {type(part).__name__}")
    if old and part.productivity.loaded is not None:
        part.productivity.loaded.runs = [_steady_everywhere(r)
                                         for r in part.productivity.loaded.runs]
    return part


def _steady_everywhere(r: Run) -> Run:
    """A loaded stretch of a version-1 part (payload, ratio, reach, slew, rise) with the
    steady columns of every instant steady (what version 1 averaged over)."""
    def pad(x: Any) -> Any:
        return np.concatenate([x, [1.0, x[0], x[1]]])
    return Run(r.t_start, r.t_end, r.n, pad(r.first), pad(r.last), pad(r.vmax), pad(r.vmin),
               np.concatenate([r.vsum, [float(r.n), r.vsum[0], r.vsum[1]]]), r.t_peak,
               pad(r.at_peak))


def window_rows(res: Any, w0: float, w1: float) -> npt.NDArray[np.bool_]:
    """The instants of a replay (:class:`cranetwin.twin.TwinResult`) that window [w0, w1) [s]
    keeps: inside it and not bridged across a dropout (``res.gap``: values made up between
    samples further apart than the replay's ``max_gap_s``). A stored window or span therefore
    counts, summarises and analyses only instants that samples support, whether the machine
    was off between two windows or inside one. Shape (m,) for the replay's m instants."""
    t = res.t_s
    keep: npt.NDArray[np.bool_] = (t >= w0) & (t < w1) & ~np.asarray(res.gap, dtype=bool)
    return keep


def window_history(backend: Any, replayer: Any, machine: Machine, machine_id: str, w0: float,
                   w1: float, margin_s: float, theta0: float = 0.0) -> LoadHistory | None:
    """The load history of the minute window [w0, w1), replayed as the twin worker does (the
    window with ``margin_s`` of samples either side); None without enough samples."""
    from cranetwin.service.analytics import load_history
    from cranetwin.service.replayer import sample_rate_hz

    samples = backend.read_samples(machine_id, w0 - margin_s, w1 + margin_s)
    n_in = int(np.count_nonzero((samples.t_s >= w0) & (samples.t_s < w1)))
    if n_in < 8:
        return None
    try:
        res = replayer.replay(machine_id, machine, samples, sample_rate_hz(samples),
                              theta0_initial=theta0)
    except CraneTwinError:
        return None
    keep = window_rows(res, w0, w1)
    if int(np.count_nonzero(keep)) < 2:
        return None
    h: LoadHistory = load_history(machine, res, keep)
    return h


def part_row(machine: Machine, machine_id: str, w0: float, w1: float, h: LoadHistory,
             operating_s: float = 0.0, idle_s: float = 0.0,
             ) -> tuple[AnalyticsPart, dict[str, Any]] | None:
    """The part of minute window [w0, w1) and its row (with the worker's operating and idle
    time of the window [s]; :func:`cranetwin.storage.analytics_windows.put_rows` stores or
    replaces it), or None when the history makes no part."""
    part = AnalyticsState(machine).part(h)
    if part is None:
        return None
    return part, aw.window_row(machine_id, MINUTE_S, w0, w1, part.n, dump_part(part),
                               operating_s, idle_s)


def store_part(engine: Any, machine: Machine, machine_id: str, w0: float, w1: float,
               h: LoadHistory, operating_s: float = 0.0, idle_s: float = 0.0) -> None:
    """Store the part of minute window [w0, w1) (replacing one stored before), with the
    worker's operating and idle time of the window [s]."""
    from sqlalchemy.orm import Session

    got = part_row(machine, machine_id, w0, w1, h, operating_s, idle_s)
    if got is not None:
        with Session(engine) as s, s.begin():
            aw.put_rows(s, [got[1]])


def roll_up(engine: Any, machine: Machine, machine_id: str, t0_s: float, t1_s: float) -> int:
    """Merge the stored parts of every whole hour, then day, in [t0_s, t1_s) (all processed)
    into one part each (those stored already are left). Returns parts written. Parts too
    short to merge (a fraction of a second) leave their hour to the minutes."""
    done = 0
    proto = AnalyticsState(machine)
    for level, sub in ((3600, MINUTE_S), (86400, 3600)):
        a = math.ceil(t0_s / level) * level
        have = set(aw.window_starts(engine, machine_id, level, a, t1_s))
        while a + level <= t1_s:
            if a not in have:
                rows = aw.windows(engine, machine_id, sub, a, a + level)
                if rows and (level == 3600 or len(rows) == 24
                             or _all_hours_without_gaps(engine, machine_id, a, rows)):
                    try:
                        part = load_part(rows[0][3])
                        for r in rows[1:]:
                            part = proto.merge_parts(part, load_part(r[3]))
                    except AnalyticsError:
                        a += level
                        continue
                    aw.put_window(engine, machine_id, level, a, a + level, part.n,
                                  dump_part(part))
                    done += 1
            a += level
    return done


def _all_hours_without_gaps(engine: Any, machine_id: str, day0: float,
                            hours: list[tuple[float, float, int, bytes]]) -> bool:
    """A day rolls up from hour parts only if no hour of it has minute parts but no hour part
    (an hour that could not be merged)."""
    starts = {r[0] for r in hours}
    minutes = aw.window_starts(engine, machine_id, MINUTE_S, day0, day0 + 86400)
    return all(math.floor(m / 3600) * 3600 in starts for m in minutes)


EdgeFn = Callable[[float, float], LoadHistory | None]


def range_state(engine: Any, machine: Machine, machine_id: str, t0_s: float, t1_s: float,
                edge: EdgeFn, stored_until_s: float | None,
                max_replay_s: float | None = None,
                config: AnalyticsConfig | None = None,
                next_sample: Callable[[float], float | None] | None = None) -> AnalyticsState:
    """The analytics state of [t0_s, t1_s): stored parts where they exist, else ``edge(w0, w1)``
    (the load history of minute window [w0, w1), cut to the range by this function).

    Args:
        stored_until_s: The worker's progress mark: minutes before it without a part hold no
            data (or could not be replayed), so they are not replayed again; None: replay every
            minute without a part.
    """
    state = AnalyticsState(machine, config)
    use_parts = config is None or config == AnalyticsConfig()
    starts = {lv: set(aw.window_starts(engine, machine_id, lv, t0_s, t1_s)) if use_parts
              else set() for lv in LEVELS}
    plan: list[tuple[str, int, float, float]] = []
    a = float(math.floor(t0_s / MINUTE_S) * MINUTE_S)
    while a < t1_s:
        for lv in LEVELS:
            if a >= t0_s and a in starts[lv] and a + lv <= t1_s:
                plan.append(("part", lv, a, a + lv))
                a += lv
                break
        else:
            b = a + MINUTE_S
            whole_done = use_parts and a >= t0_s and b <= t1_s \
                and stored_until_s is not None and b <= stored_until_s
            if not whole_done and next_sample is not None and (
                    stored_until_s is None or a >= stored_until_s or not use_parts):
                nxt = next_sample(a)
                if nxt is None or nxt >= t1_s:
                    break
                if nxt >= b:  # nothing stored in this minute: step to the next sample
                    a = float(math.floor(nxt / MINUTE_S) * MINUTE_S)
                    continue
            if not whole_done:
                plan.append(("replay", MINUTE_S, a, b))
            a = b
    n_replay = sum(p[0] == "replay" for p in plan)
    if max_replay_s is not None and n_replay * MINUTE_S > max_replay_s:
        from cranetwin.service.errors import InvalidRequestError

        raise InvalidRequestError(
            "Range not processed yet", f"{n_replay} minutes of the range have no stored "
            f"analytics (the twin worker has not processed them); at most {max_replay_s:.6g} s "
            "are replayed per request")
    data: dict[tuple[int, float], bytes] = {}
    for lv in LEVELS:
        need = [p for p in plan if p[0] == "part" and p[1] == lv]
        if need:
            for r in aw.windows(engine, machine_id, lv, need[0][2], need[-1][3]):
                data[(lv, r[0])] = r[3]
    for kind, lv, w0, w1 in plan:
        if kind == "part":
            state.apply(load_part(data[(lv, w0)]))
            continue
        h = edge(w0, w1)
        if h is None:
            continue
        i, j = np.searchsorted(h.t_s, [t0_s, t1_s])
        if j > i:
            state.update(h.slice(int(i), int(j)))
    return state


DUTY_LEVEL = -1
"""``level_s`` of the row holding a machine's duty to date (:class:`DutyToDate`)."""


class DutyToDate:
    """The ISO 4301-1 / ISO 12482 duty of a machine's whole processed history: work cycles and
    Σ (P_i/P_max)³, from the same work-cycle detection as every report (the parts' loaded
    stretches folded by a :class:`~cranetwin.analytics.ProductivityTracker`), so AEMP, the API
    analytics and the CLI report give one kp and one design life used for the same range.

    Attributes:
        until_s: End of the last minute folded [s].
        cycles: Work cycles closed so far (the open one excluded).
        cube_sum: Σ ratio³ of those cycles.
    """

    def __init__(self, machine: Machine) -> None:
        self.tracker = AnalyticsState(machine).productivity
        self.until_s = -math.inf
        self.cycles = 0
        self.cube_sum = 0.0

    def _drain(self) -> None:
        for c in self.tracker.cycles:
            self.cycles += 1
            self.cube_sum += c.load_ratio ** 3
        self.tracker.cycles.clear()
        self.tracker.days.clear()  # per-day usage is not needed here (bounded memory)

    def fold(self, part: AnalyticsPart, until_s: float) -> None:
        """Fold the next part (ending at ``until_s``)."""
        self.tracker.apply(part.productivity)
        self._drain()
        self.until_s = until_s

    def totals(self) -> tuple[int, float]:
        """(work cycles, Σ ratio³) including the cycle open at the end (as a report closes
        it)."""
        open_cycles, _, _, _ = self.tracker.snapshot()
        return (self.cycles + len(open_cycles),
                self.cube_sum + sum(c.load_ratio ** 3 for c in open_cycles))


def update_duty(engine: Any, machine: Machine, machine_id: str, first_s: float,
                until_s: float, stored: DutyToDate | None = None) -> DutyToDate:
    """The machine's duty to date folded up to ``until_s`` (the worker's progress mark) and
    stored; built from the stored parts of [first minute, until_s) when none is stored (or it
    was dropped after late data).

    Args:
        stored: The duty this caller returned last time, when it knows nothing else has
            written or dropped it since (it is then not read back); it is folded on in place.
    """
    rows = [] if stored is not None else aw.windows(engine, machine_id, DUTY_LEVEL, -1e9, 1e9)
    duty: DutyToDate | None = stored
    if rows and rows[0][3].startswith(PART_MAGIC):  # another version: rebuilt
        try:
            obj = pickle.loads(zlib.decompress(rows[0][3][len(PART_MAGIC):]))
            duty = obj if isinstance(obj, DutyToDate) else None
        except Exception:  # a row of another version: rebuilt
            duty = None
    t0 = float(math.floor(first_s / MINUTE_S) * MINUTE_S)
    if duty is None:
        duty = DutyToDate(machine)
        if until_s > t0:
            state = range_state(engine, machine, machine_id, t0, until_s, lambda a, b: None,
                                until_s)
            duty.tracker = state.productivity
            duty._drain()
            duty.until_s = until_s
    elif until_s > duty.until_s:
        for _a, b, _n, data in aw.windows(engine, machine_id, MINUTE_S, duty.until_s, until_s):
            duty.fold(load_part(data), b)
        duty.until_s = until_s
    blob = PART_MAGIC + zlib.compress(pickle.dumps(duty, protocol=pickle.HIGHEST_PROTOCOL), 1)
    aw.put_window(engine, machine_id, DUTY_LEVEL, 0.0, 0.0, duty.cycles, blob)
    return duty


def stored_duty(engine: Any, machine_id: str) -> tuple[int, float, float] | None:
    """(work cycles, Σ ratio³, until s) of the stored duty to date, or None."""
    rows = aw.windows(engine, machine_id, DUTY_LEVEL, -1e9, 1e9)
    if not rows or not rows[0][3].startswith(PART_MAGIC):
        return None
    try:
        duty = pickle.loads(zlib.decompress(rows[0][3][len(PART_MAGIC):]))
    except Exception:
        return None
    if not isinstance(duty, DutyToDate):
        return None
    n, cube = duty.totals()
    return n, cube, duty.until_s


def drop_duty(engine: Any, machine_id: str) -> None:
    """Forget the duty to date (late data changed the past; rebuilt on the next update)."""
    aw.delete_windows(engine, machine_id, -1e9, 1e9, levels=(DUTY_LEVEL,))
