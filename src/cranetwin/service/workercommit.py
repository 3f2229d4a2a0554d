"""A twin worker pass's commit: the spans its machines replayed, committed together.

Each machine's span used to be one transaction of its own (derived summaries, analytics rows,
events and progress: five statements and a commit round trip per machine and pass, about a
third of a short span's cost). A pass instead collects them here and commits them in one
transaction per engine (:meth:`cranetwin.service.backend.Backend.commit_spans`): a fixed
number of statements for all the machines collected, at the end of the pass, or earlier once
``max_machines`` machines or ``max_age_s`` of work are waiting.

Exactly once, as before: every machine's progress moves only from the watermark its first
collected span started from, in the transaction that writes its results, so

* a crash (or an error) before the commit leaves every collected machine as it was: the next
  pass replays their spans again, nothing was written twice;
* a machine whose watermark another worker moved meanwhile (a hand-over) is left out of the
  commit with all of its spans (the others are committed); the worker forgets what it kept of
  it (:meth:`TwinWorker._forget`).

What a machine's turn does after its spans are stored (hour roll-ups, the duty to date,
service schedules: they read the stored parts) waits for the commit (:meth:`PassCommit.after`).
Two workers committing overlapping machines at once may deadlock in PostgreSQL; one of the
two transactions is then rolled back whole and its pass fails (logged, done again next pass).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, NamedTuple

if TYPE_CHECKING:
    from cranetwin.analytics import AnalyticsPart
    from cranetwin.samples import F64
    from cranetwin.service.backend import Backend, Progress, SpanCommit

MAX_MACHINES = 100
"""Machines collected before the pass commits (the statements per commit do not grow with
them; the rows do)."""
MAX_AGE_S = 2.0
"""Longest a collected span waits for its commit [s] (bounds the results' delay when spans
are long: 60-s windows of 100 Hz data)."""


class LastPart(NamedTuple):
    """A machine's last analytics part as the worker keeps it (the look-back of the events of
    its next span): the part's window [start_s, end_s) [s], its stored bytes, and the part
    itself when the worker made it (None: read from storage, decoded when used)."""

    start_s: float
    end_s: float
    data: bytes
    part: AnalyticsPart | None = None

    def decoded(self) -> AnalyticsPart:
        """The part (decoded from :attr:`data` when not kept).

        Raises:
            AnalyticsError: The data is not a part of this version.
        """
        from cranetwin.service.history import load_part

        return self.part if self.part is not None else load_part(self.data)


class PassCommit:
    """The spans of a pass waiting for their commit (module docstring); thread-safe.

    Args:
        backend: Store adapter.
        max_machines: Commit once this many machines wait (:meth:`due`).
        max_age_s: Commit once the oldest waiting span is this old [s] (:meth:`due`).
    """

    def __init__(self, backend: Backend, max_machines: int = MAX_MACHINES,
                 max_age_s: float = MAX_AGE_S) -> None:
        self.backend = backend
        self.max_machines = max_machines
        self.max_age_s = max_age_s
        self._lock = threading.Lock()
        self._pending: dict[str, SpanCommit] = {}
        self._replayed: dict[str, int] = {}
        self._after: dict[str, list[Callable[[], None]]] = {}
        self._since: float | None = None
        self.parts: dict[str, LastPart] = {}
        """Machine → the last analytics part of its spans waiting (the look-back of its next
        span's events; set by the worker)."""

    def __len__(self) -> int:
        """Machines waiting."""
        with self._lock:
            return len(self._pending)

    def add(self, prog: Progress, expected_watermark_s: float | None,
            channels: list[str] | None = None, t_s: F64 | None = None,
            values: F64 | None = None, rows: list[dict[str, Any]] | None = None,
            events: list[Any] | None = None, windows: int = 0) -> None:
        """Collect a span of ``prog.machine_id`` (or only its progress: a skipped gap, a span
        not replayed).

        Args:
            prog: The machine's progress after the span.
            expected_watermark_s: The stored watermark the span started from (used for the
                machine's first collected span only: the later ones start where it ended).
            channels: Derived channel names of ``values``.
            t_s: Grid times of the span, shape (k,) [s].
            values: Derived values, shape (k, c).
            rows: Analytics-window rows (part, lift seconds).
            events: Events found in the span.
            windows: Windows the span holds (0: no replay, only progress).
        """
        from cranetwin.service.backend import SpanCommit

        mid = prog.machine_id
        with self._lock:
            c = self._pending.get(mid)
            if c is None:
                c = self._pending[mid] = SpanCommit(prog, expected_watermark_s,
                                                    list(channels or []), [], [], [])
                if self._since is None:
                    self._since = time.monotonic()
            c.prog = prog
            if channels:
                c.channels = list(channels)
            if t_s is not None and values is not None and t_s.size:
                c.spans.append((t_s, values))
            c.rows += rows or []
            c.events += events or []
            c.windows += windows
            if windows:
                self._replayed[mid] = self._replayed.get(mid, 0) + 1

    def after(self, machine_id: str, step: Callable[[], None]) -> None:
        """Run ``step`` once the machine's collected spans are committed: now when none
        wait; never when another worker moved its watermark first."""
        with self._lock:
            if machine_id in self._pending:
                self._after.setdefault(machine_id, []).append(step)
                return
        step()

    def due(self) -> bool:
        """Whether enough waits to commit before the end of the pass."""
        with self._lock:
            return len(self._pending) >= self.max_machines or (
                self._since is not None and time.monotonic() - self._since >= self.max_age_s)

    def commit(self) -> tuple[dict[str, int], set[str], dict[str, LastPart]]:
        """Commit what waits (:meth:`Backend.commit_spans`) and run the committed machines'
        :meth:`after` steps. Call it while no machine's turn is running (between turns).

        Returns:
            (committed machine → spans replayed, machines another worker got first,
            committed machine → its last part as :attr:`parts` held it).

        Raises:
            Whatever the database raised: nothing waiting was committed (and it is dropped:
            the machines are replayed again next pass).
        """
        with self._lock:
            pending, self._pending = self._pending, {}
            replayed, self._replayed = self._replayed, {}
            after, self._after = self._after, {}
            parts, self.parts = self.parts, {}
            self._since = None
        if not pending:
            return {}, set(), {}
        won = self.backend.commit_spans(list(pending.values()))
        for mid in sorted(won):
            for step in after.get(mid, []):
                step()
        return ({m: replayed.get(m, 0) for m in won}, set(pending) - won,
                {m: p for m, p in parts.items() if m in won})
