"""The twin worker: follows stored samples window by window and stores derived summaries.

It runs as its own process, ``cranetwin worker`` (:func:`cranetwin.cli.worker`), or inside
``cranetwin serve`` for the embedded demo (``CRANETWIN_WORKER_IN_PROCESS``).

For each machine, windows of ``worker_window_s`` (60 s, aligned to whole minutes so that the
storage's 1-min summary level stays exact) are replayed once samples exist a little past their
end (``worker_settle_s``). The window is replayed with ``twin_margin_s`` of samples either side
(so the spline, smoothing and payload window see the same data as a whole-day replay) and the
instants inside it are reduced to derived channels:

* ``force:<cylinder>`` — cylinder force (Eq. 1–2) [N];
* ``payload`` — payload estimate [kg];
* ``moment:<joint>`` — magnitude of the joint reaction moment (revolute joints) [N·m];
* ``torque:<joint>`` — inverse-dynamics joint torque/force [N·m or N];
* ``working`` — 1 while any joint moves (|qd| above 0.02 rad/s or 0.01 m/s), else 0.

A machine with several windows ready (a worker behind its machines, catch-up after downtime)
has them replayed and committed as one span, up to the next whole minute
(:meth:`TwinWorker._span_windows`): the per-window cost of reads, replay set-up and transactions
is then paid once per span, so a worker that falls behind catches up instead of falling further
behind. Late data redoes the stored span it falls in.

The summaries of a window and the machine's new progress row (watermark = end of the window,
cumulative counters) are committed in ONE transaction (with the other machines' spans of the
pass, :mod:`cranetwin.service.workercommit`), and derived summaries are written by
overwriting their buckets: a crash before the commit leaves the window unprocessed (it is done
again, once), a crash after it leaves it done. After downtime the worker starts from the
watermark and catches up; empty stretches (machine off) are skipped in one step. The commit is
conditional on the watermark the window started from, so a second worker on the same machine
(two processes by mistake, or during a hand-over) finds the window done and rolls its own
replay back instead of counting it twice.

Cost per machine and pass (what bounds the machines per worker core at short windows): the
pass reads the data ranges, progress rows, late-data marks, late blocks and stored known-payload
runs of all its machines, and each machine's first span of samples, in a few statements
(:mod:`cranetwin.service.workerpass`); the spans the pass replays (derived summaries, analytics
parts, lift seconds, events and progress of all its machines) are committed together, one
transaction of fixed statements per engine at the end of the pass or every 100 machines or 2 s
(:mod:`cranetwin.service.workercommit`: each machine's progress still moves only from the
watermark its span started from, in the transaction holding its results); the new late-data
marks are written in one statement at the end of the pass. A machine whose next window is not
ready yet (at the defaults, 59 passes in 60: 1-s polls at 60-s windows) is read no further
than its data range when it has neither late blocks behind its watermark nor redo requests,
which two statements check for all such machines every pass (:meth:`_idle`): it has no turn,
and late data or a redo request of it is found by the next pass, as before. Late data
(:meth:`_redo_late`) is redone and committed at once, before the machine's forward spans.
The worker keeps what only it writes while it owns a machine — the last analytics part it
committed (the next window's event look-back), the duty to date, and which blocks above its
late-data mark its last pass had seen (:class:`~cranetwin.storage.analytics_windows.Seen`)
— and drops them when its partitions change, when a commit finds the watermark moved and when
late data is redone. A span whose replay or analytics failed is passed (logged, counted) and
recorded (:mod:`cranetwin.storage.failed_windows`), so that a known payload or late data over
it later has it processed again like a span that has a part.

Scale-out: with an :class:`~cranetwin.service.ownership.Ownership` (``cranetwin worker
--partitions …``) a worker processes only the machines of the partitions it owns, re-checked
between machines at most every ``worker_interval_s`` (never inside a window), and reports per
partition the lag (newest sample − watermark, the largest of its machines) and the watermark age
(now − the oldest watermark). The worker owning partition 0 (or a worker without partitions)
also keeps the PostgreSQL time partitions of the raw samples: made ahead, and dropped by
retention once processed (``storage_*`` settings, :mod:`cranetwin.storage.partitions`).
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace as dc_replace
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from cranetwin.errors import CraneTwinError
from cranetwin.model import Machine
from cranetwin.service.derived import (
    MOVING_M_S,
    MOVING_RAD_S,
    derive,
    derived_channels,
    lift_seconds,
    update_counters,
)
from cranetwin.service.history import window_rows
from cranetwin.service.liftcount import seconds_row
from cranetwin.service.workercommit import LastPart
from cranetwin.storage.failed_windows import failed_row

if TYPE_CHECKING:
    from cranetwin.samples import SampleArrays
    from cranetwin.service.backend import Backend, MachineRecord, Progress
    from cranetwin.service.history import DutyToDate
    from cranetwin.service.metrics import Metrics
    from cranetwin.service.ownership import Ownership
    from cranetwin.service.replayer import Replayer
    from cranetwin.service.workercommit import PassCommit
    from cranetwin.service.workerpass import PassReads
    from cranetwin.settings import Settings
    from cranetwin.storage.analytics_windows import Seen

log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]

__all__ = ["MOVING_M_S", "MOVING_RAD_S", "TwinWorker", "derive", "derived_channels",
           "update_counters"]


class _TooFewSamples(CraneTwinError):
    """A span with too few samples to replay (not a failure to retry: no known payload
    changes it, late samples redo it anyway)."""


class TwinWorker:
    """Replays every machine's new samples into derived summaries (see module docstring).

    Runs as its own process (``cranetwin worker``: :meth:`run` in the main thread) or, for
    the embedded demo, as a task of ``cranetwin serve`` (:meth:`run_forever`). Every window is
    committed only from the watermark it started from (:meth:`Backend.commit_window`), so several
    workers on one database never count a window twice.

    Args:
        backend: Store adapter.
        settings: The settings of the process (``worker_*``, ``twin_margin_s``).
        metrics: Counters of windows, lag and errors (None: not counted).
        replayer: Replayer shared with the API in the same process (a new one when None).
        max_windows_per_pass: Windows of one machine per pass before the next machine's turn.
    """

    def __init__(self, backend: Backend, settings: Settings, metrics: Metrics | None = None,
                 replayer: Replayer | None = None, max_windows_per_pass: int = 30,
                 quiet_s: float = 60.0, clock: Callable[[], float] = time.monotonic,
                 ownership: Ownership | None = None, schedule_check_s: float = 60.0) -> None:
        from cranetwin.service.replayer import Replayer

        self.replayer = replayer if replayer is not None else Replayer(backend.store.read_payload)
        self.backend = backend
        self.settings = settings
        self.metrics = metrics
        self.max_windows_per_pass = max_windows_per_pass
        self.quiet_s = quiet_s
        """A machine whose newest sample has not changed for this long [s of ``clock``] is
        quiet: its last window is processed without samples past its end."""
        self.clock = clock
        self.ownership = ownership
        """Partitions owned (None: every machine)."""
        self._last_sample: dict[str, tuple[float, float]] = {}
        self._marks: dict[str, tuple[float, float]] = {}  # machine → (newest sample, watermark)
        self._next_upkeep = clock()
        self._next_rollup = clock()
        self.schedule_check_s = schedule_check_s
        """Least time between two checks of one machine's service schedules [s of ``clock``]
        (each merges its stored analytics when it has lift or damage items)."""
        self._next_schedule_check: dict[str, float] = {}
        self._last_part: dict[str, LastPart] = {}
        """Machine → the last analytics part this worker committed (the look-back of the next
        window's events, kept as made: not decoded again), kept while nothing else can have
        written its parts: dropped when the worker's partitions change, when the machine is not
        owned, when a commit finds the watermark moved, and when late data redoes windows."""
        self._seen: dict[str, tuple[int, Seen, float]] = {}
        """Machine → (the late-data mark of the pass that last committed its spans, what that
        pass saw, the watermark it committed): :func:`~cranetwin.service.workerpass.read_pass`
        leaves the blocks it saw out of the next pass's late data. Kept and dropped as
        :attr:`_last_part`."""
        self._known: dict[str, tuple[int, float]] = {}
        """Machine → (late-data mark below which its blocks have been checked, watermark this
        worker committed) after a pass that read the machine fully and stored its mark
        (PostgreSQL): lets later passes skip an idle machine's reads (:meth:`_idle`). Kept
        and dropped as :attr:`_last_part`, and dropped at the start of every turn."""
        self._duty: dict[str, DutyToDate] = {}
        """Machine → the duty to date this worker stored last (not read back while valid: kept
        and dropped as :attr:`_last_part`)."""
        self._owned: frozenset[int] | None = None
        self._pool: ThreadPoolExecutor | None = None
        self.stop_event = threading.Event()
        """Set to stop: checked between windows, so the window being replayed is finished and
        committed first (a second or so)."""

    def _forget(self, machine_id: str | None = None) -> None:
        """Drop what this worker keeps of a machine's stored rows (:attr:`_last_part`,
        :attr:`_duty`), of every machine when None: something else may have written them."""
        if machine_id is None:
            self._last_part.clear()
            self._duty.clear()
            self._seen.clear()
            self._known.clear()
        else:
            self._last_part.pop(machine_id, None)
            self._duty.pop(machine_id, None)
            self._seen.pop(machine_id, None)
            self._known.pop(machine_id, None)

    def _engine(self, rec: MachineRecord) -> Any:
        """The engine holding the machine's rows (its shard when storage is sharded)."""
        return self.backend.store.engine_for(rec.machine_id)

    def stop_requested(self) -> bool:
        """Whether :attr:`stop_event` is set."""
        return self.stop_event.is_set()

    async def run_forever(self) -> None:
        """Process passes until :attr:`stop_event` is set, sleeping when caught up (in-process
        mode: each pass runs in a thread, so the event loop keeps serving)."""
        while not self.stop_event.is_set():
            try:
                done = await asyncio.to_thread(self.run_once)
            except asyncio.CancelledError:
                raise
            except Exception:
                log.exception("twin worker pass failed")
                done = 0
            if done == 0:
                await asyncio.to_thread(self.stop_event.wait, self.settings.worker_interval_s)
            else:
                await asyncio.sleep(0)

    def run(self) -> int:
        """Process passes until :attr:`stop_event` is set (own-process mode); returns windows
        processed.

        The window being replayed when the event is set is finished and committed; if the
        process is killed instead, its transaction is rolled back and the next run does it
        again. Never raises for a failed pass (logged, retried after ``worker_interval_s``).
        """
        stop = self.stop_event
        total = 0
        while not stop.is_set():
            try:
                done = self.run_once()
            except CraneTwinError as exc:
                log.error("twin worker pass failed: %s", exc)
                done = 0
            except Exception:
                log.exception("twin worker pass failed")
                done = 0
            total += done
            if done == 0:
                stop.wait(self.settings.worker_interval_s)
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
        return total

    def run_once(self) -> int:
        """One pass over all machines: at most ``max_windows_per_pass`` windows each.

        With ``worker_threads`` > 1 the machines are caught up that many at a time (each
        machine by one thread at a time; their commits stay conditional on the watermark).

        Returns:
            Windows processed (0 = every machine is caught up).
        """
        try:
            return self._run_once()
        except BaseException:
            self._known.clear()  # a mark of the pass may not be stored: read fully next pass
            raise

    def _run_once(self) -> int:
        from cranetwin.service.workercommit import PassCommit
        from cranetwin.service.workerpass import flush_marks, read_pass

        total = 0
        own = self.ownership
        if own is not None:
            own.refresh()
            owned = frozenset(own.owned)
            if owned != self._owned:  # what another worker may have written meanwhile
                self._forget()
                self._owned = owned
        self._rollup()
        pool = self._thread_pool()
        machines = self.backend.list_machines()
        mine = [r.machine_id for r in machines if own is None or own.owns(r.machine_id)]
        got = self.backend.data_ranges(mine)
        idle = self._idle(got)
        reads: PassReads | None = read_pass(
            self.backend, [m for m in mine if m not in idle], self.settings.worker_window_s,
            self._first_span(self.max_windows_per_pass), dict(self._seen), got)
        batch = PassCommit(self.backend)
        try:
            total += self._pass(machines, reads, batch, pool, idle)
        finally:  # what the machines done so far replayed, also when one failed
            self._commit(batch)
        if reads is not None and reads.marks:
            flush_marks(self.backend, reads)
        self._partition_metrics()
        if own is None or 0 in own.owned:
            self._upkeep()
        return total

    def _idle(self, got: dict[str, tuple[int, tuple[float, float] | None]],
              ) -> dict[str, tuple[float, float]]:
        """The machines of this pass whose turn would do nothing (machine → (newest sample
        [s], watermark [s])): their next window is not ready (watermark + window + settle
        beyond the newest sample, not quiet: the first test of :meth:`_catch_up`), and they
        have no late blocks behind the watermark nor redo requests
        (:func:`~cranetwin.service.workerpass.idle_machines`, two statements for all of them).
        Only machines this worker read fully before and owns since (:attr:`_known`); on
        PostgreSQL. The pass reads nothing else of them and skips their turns: an idle
        machine then costs its data range and its share of those two statements, and late
        data or a redo request of it is still found by the next pass."""
        from cranetwin.service.workerpass import idle_machines

        s = self.settings
        cand: dict[str, tuple[int, float]] = {}
        for mid, (mark, wm) in self._known.items():
            dr = got.get(mid, (0, None))[1]
            if dr is None:
                continue
            if wm + s.worker_window_s + s.worker_settle_s > dr[1] and not (
                    self._quiet(mid, dr[1]) and wm <= dr[1]):
                cand[mid] = (mark, wm)
        if not cand:
            return {}
        ok = idle_machines(self.backend, got, cand, self._seen)
        out: dict[str, tuple[float, float]] = {}
        for mid in ok:
            self._known[mid] = cand[mid]  # its mark advanced: checked up to this pass
            dr = got[mid][1]
            assert dr is not None
            out[mid] = (dr[1], cand[mid][1])
        return out

    def _pass(self, machines: list[MachineRecord], reads: PassReads | None, batch: PassCommit,
              pool: ThreadPoolExecutor | None,
              idle: dict[str, tuple[float, float]] | None = None) -> int:
        """The machines' turns of :meth:`run_once`; returns windows processed. The ``idle``
        machines (:meth:`_idle`) have no turn, only their lag and schedules looked at."""
        own = self.ownership
        due = self.clock() + self.settings.worker_interval_s
        total = 0
        pending: list[Future[int]] = []
        failed: list[BaseException] = []

        def result(f: Future[int]) -> int:  # a failed machine fails the pass at its end
            exc = f.exception()
            if exc is not None:
                failed.append(exc)
                return 0
            return f.result()

        for rec in machines:
            if self.stop_requested():
                break
            if own is not None:
                if self.clock() >= due:  # between machines too: a joiner waits no whole pass
                    own.refresh()
                    due = self.clock() + self.settings.worker_interval_s
                    if frozenset(own.owned) != self._owned:  # the pass's reads are stale
                        reads = None
                        idle = None
                        self._forget()
                        self._owned = frozenset(own.owned)
                if not own.owns(rec.machine_id):
                    self._marks.pop(rec.machine_id, None)
                    self._forget(rec.machine_id)
                    continue
            if idle is not None and rec.machine_id in idle:
                newest, wm = idle[rec.machine_id]
                self._marks[rec.machine_id] = (newest, wm)
                if self.metrics is not None:
                    self.metrics.worker_lag.labels(rec.machine_id).set(max(0.0, newest - wm))
                self._check_schedules(rec)
                continue
            pre = reads if reads is not None and rec.machine_id in reads.ranges else None
            if batch.due():  # between turns: no machine adds to it meanwhile
                total += sum(result(f) for f in pending)
                pending.clear()
                self._commit(batch)
            if pool is None:
                total += self.catch_up(rec, self.max_windows_per_pass, pre, batch)
                continue
            pending.append(pool.submit(self.catch_up, rec, self.max_windows_per_pass, pre,
                                       batch))
            if len(pending) >= 2 * self.settings.worker_threads:  # ownership re-checked often
                total += result(pending.pop(0))
        total += sum(result(f) for f in pending)
        if failed:
            raise failed[0]  # after every machine of the pass had its turn
        return total

    def _commit(self, batch: PassCommit) -> None:
        """Commit the pass's collected spans (:mod:`cranetwin.service.workercommit`)."""
        try:
            won, lost, parts = batch.commit()
        except BaseException:
            self._forget()  # nothing of it stored: what was kept of those spans is not
            raise
        self._last_part.update(parts)
        for mid in sorted(lost):
            log.info("machine %s: span committed by another worker", mid)
            self._forget(mid)
        if self.metrics is not None:
            for mid, n in won.items():
                if n:
                    self.metrics.worker_windows.labels(mid).inc(n)

    def _rollup(self) -> None:
        """Roll the raw 1-min summaries up, at most every ``worker_rollup_s`` (0: never).

        The ingest daemon and the storage writers roll up every 30 s; this is for a service
        fed by another writer, so that long history queries are still answered from 1-min
        rows. It covers every machine's changed minutes, not only the owned ones: done at
        every pass by every worker, it cost more than the windows themselves (1000 machines'
        current minutes recomputed per pass and worker)."""
        every = self.settings.worker_rollup_s
        if every <= 0 or self.clock() < self._next_rollup:
            return
        self._next_rollup = self.clock() + every
        self.backend.store.rollup()

    def _thread_pool(self) -> ThreadPoolExecutor | None:
        """The threads of ``worker_threads`` > 1 (made on first use), else None."""
        n = self.settings.worker_threads
        if n <= 1:
            return None
        if self._pool is None:
            self._pool = ThreadPoolExecutor(n, thread_name_prefix="twin-worker")
        return self._pool

    def _partition_metrics(self) -> None:
        """Per owned partition: lag and watermark age (gauges), from this pass's machines."""
        own, m = self.ownership, self.metrics
        if own is None or m is None:
            return
        from cranetwin.storage.sharding import partition_of

        now = time.time()
        lag: dict[int, float] = dict.fromkeys(own.owned, 0.0)
        oldest: dict[int, float] = {}
        for mid, (newest, wm) in self._marks.items():
            p = partition_of(mid, own.spec.count)
            if p in lag:
                lag[p] = max(lag[p], newest - wm)
                oldest[p] = min(oldest.get(p, wm), wm)
        for p in range(own.spec.count):
            if p in lag:
                m.worker_partition_lag.labels(str(p)).set(max(0.0, lag[p]))
                m.worker_partition_age.labels(str(p)).set(max(0.0, now - oldest.get(p, now)))
            else:
                for g in (m.worker_partition_lag, m.worker_partition_age):
                    try:
                        g.remove(str(p))
                    except KeyError:
                        pass
        m.worker_partitions_owned.set(len(own.owned))

    def _upkeep(self) -> None:
        """Every ``storage_maintenance_interval_s``: time partitions ahead, and retention."""
        s = self.settings
        if self.clock() < self._next_upkeep:
            return
        self._next_upkeep = self.clock() + s.storage_maintenance_interval_s
        try:
            res = self.backend.store.maintain_partitions(
                time.time(), ahead=s.storage_partitions_ahead,
                interval=s.storage_partition_interval,
                keep_days=s.storage_retention_days or None, margin_s=s.twin_margin_s)
        except CraneTwinError as exc:
            log.warning("partition maintenance failed: %s", exc)
            return
        if res.dropped or res.kept:
            log.info("retention: dropped %s, kept %d expired partition(s) not yet processed",
                     res.dropped, len(res.kept))

    def catch_up(self, rec: MachineRecord, max_windows: int | None = None,
                 reads: PassReads | None = None, batch: PassCommit | None = None) -> int:
        """Process the ready windows of one machine, oldest first; returns how many.

        Stops early when :attr:`stop_requested`, or when another worker moved the machine's
        watermark (it is processing the same machine; the next pass re-reads the progress).

        Args:
            reads: The pass's reads holding this machine (:mod:`cranetwin.service.workerpass`;
                None: read them for this machine alone, the same way, and store its new
                late-data mark at the end of the turn, :meth:`_read_alone`).
            batch: Collect the spans for the pass's commit (:mod:`cranetwin.service.
                workercommit`; None: each span is committed at once).
        """
        from cranetwin.service.workerpass import flush_marks

        self._known.pop(rec.machine_id, None)  # set again once this turn is stored
        try:
            if reads is not None:
                return self._catch_up(rec, max_windows, reads, batch)
            alone = self._read_alone(rec.machine_id, max_windows)
            try:
                return self._catch_up(rec, max_windows, alone, batch)
            finally:  # the mark of what was redone (the redo is committed at once)
                if alone.marks:
                    flush_marks(self.backend, alone)
        except BaseException:
            self._forget(rec.machine_id)
            raise

    def _read_alone(self, machine_id: str, max_windows: int | None) -> PassReads:
        """The reads of a pass over this machine alone
        (:func:`~cranetwin.service.workerpass.read_pass`): a turn outside a pass (the benches,
        the tests, or a pass whose partitions changed under it) reads its late blocks, leaves
        out those its last turn saw (:class:`~cranetwin.storage.analytics_windows.Seen`) and
        stores its mark exactly as a pass does.

        Raises:
            UnknownMachineError: No such machine.
        """
        from cranetwin.service.workerpass import read_pass
        from cranetwin.storage.machines import UnknownMachineError

        seen = {machine_id: self._seen[machine_id]} if machine_id in self._seen else {}
        reads = read_pass(self.backend, [machine_id], self.settings.worker_window_s,
                          self._first_span(max_windows), seen)
        if machine_id not in reads.ranges:
            raise UnknownMachineError(machine_id)
        return reads

    def _catch_up(self, rec: MachineRecord, max_windows: int | None,
                  reads: PassReads, batch: PassCommit | None) -> int:
        from cranetwin.service.backend import Progress

        s = self.settings
        win = s.worker_window_s
        mid = rec.machine_id
        dr = reads.ranges[mid]
        stored = reads.progress.get(mid) if dr is not None else None
        if dr is None:
            return 0
        expected = stored.watermark_s if stored is not None else None
        prog = stored if stored is not None else Progress.empty(
            rec.machine_id, math.floor(dr[0] / win) * win)
        done = 0
        redone = self._redo_late(rec, prog, reads)  # the first pass only sets the block mark
        if redone is None:
            return 0
        prog, done = redone
        redid = done > 0  # the duty to date was dropped: rebuilt at the end of the turn
        start_wm = prog.watermark_s
        quiet = self._quiet(rec.machine_id, dr[1])
        while (max_windows is None or done < max_windows) and not self.stop_requested():
            w0 = prog.watermark_s
            if w0 + win + s.worker_settle_s > dr[1] and not (quiet and w0 <= dr[1]):
                break
            k = self._span_windows(w0, dr[1], quiet,
                                   None if max_windows is None else max_windows - done)
            a, z = w0 - s.twin_margin_s, w0 + k * win + s.twin_margin_s
            ahead = reads.samples.pop(mid, None)
            samples = (ahead[2] if ahead is not None and ahead[:2] == (a, z)
                       else self.backend.read_samples(mid, a, z))
            new: Progress | None
            if not np.any((samples.t_s >= w0) & (samples.t_s < w0 + win)):
                # no sample in the first window: where do the samples go on (a gap is
                # skipped in one step)? A sample in it answers that without asking
                nxt = self.backend.next_sample_time(mid, w0)
                if nxt is None:
                    break
                if nxt >= w0 + win:
                    new = dc_replace(prog, watermark_s=math.floor(nxt / win) * win)
                    if not self._save(new, expected, batch):
                        log.info("machine %s: watermark moved by another worker", mid)
                        self._forget(mid)
                        break
                    prog, expected = new, new.watermark_s
                    continue
            new = self.process_window(rec, prog, expected, until_s=w0 + k * win,
                                      samples=samples, reads=reads, batch=batch)
            if new is None:
                log.info("machine %s: window %.0f committed by another worker", mid, w0)
                break
            done += k
            prog, expected = new, new.watermark_s
        end_wm = prog.watermark_s

        snap = reads.snapshots.get(mid) if mid in reads.late else None
        top = reads.late[mid][1] if snap is not None else 0
        # the mark stored at the end of the pass (or of the turn alone)
        mark = reads.marks.get(mid, reads.late[mid][0]) if mid in reads.late else None

        def after_commit() -> None:  # what reads the stored parts: after the spans' commit
            if mark is not None:  # (a failed pass drops it: :meth:`run_once`)
                self._known[mid] = (mark, end_wm)
            if snap is not None and end_wm > start_wm:
                # every window reaching the blocks committed in the pass's snapshot that start
                # after start_wm + margin was replayed with them (read after it)
                from cranetwin.storage.analytics_windows import Seen

                self._seen[mid] = (top, Seen(snap, start_wm + s.twin_margin_s), end_wm)
            self._roll_up(rec, start_wm, end_wm)
            if done or end_wm != start_wm:
                # the duty to date folds every minute since its last update: once a minute of
                # data (or when the machine went quiet, or windows were redone) is enough, not
                # once per short window
                if (quiet or redid
                        or math.floor(end_wm / 60.0) != math.floor(start_wm / 60.0)):
                    self._update_duty(rec, dr[0], end_wm)
            self._check_schedules(rec)

        if batch is None:
            after_commit()
        else:
            batch.after(mid, after_commit)
        self._marks[rec.machine_id] = (dr[1], prog.watermark_s)
        if self.metrics is not None:
            self.metrics.worker_lag.labels(rec.machine_id).set(max(0.0, dr[1] - prog.watermark_s))
        return done

    def _save(self, prog: Progress, expected: float | None, batch: PassCommit | None,
              rows: list[dict[str, Any]] | None = None) -> bool:
        """Store progress without a replay's results (a skipped gap, a span not replayed),
        with ``rows`` of ``analytics_windows`` (a failed span's): into ``batch`` when given
        (True), else at once (False: another worker moved the watermark first)."""
        if batch is not None:
            batch.add(prog, expected, rows=rows)
            return True
        if not rows:
            return self.backend.save_progress(prog, expected)
        from cranetwin.storage import analytics_windows as aw

        return self.backend.commit_window(prog, expected, [], np.zeros(0), np.zeros((0, 0)),
                                          lambda session, _pk: aw.put_rows(session, rows))

    def _put_rows(self, rec: MachineRecord, rows: list[dict[str, Any]]) -> None:
        """Store (replace) rows of ``analytics_windows`` of the machine at once."""
        from sqlalchemy.orm import Session

        from cranetwin.storage import analytics_windows as aw

        with Session(self._engine(rec)) as s, s.begin():
            aw.put_rows(s, rows)

    def _first_span(self, budget: int | None,
                    ) -> Callable[[float, float], tuple[float, float] | None]:
        """(watermark ``w0``, newest sample ``newest_s``) → the sample range [from, to) [s] a
        machine's turn of at most ``budget`` windows (None: no limit) reads first (not quiet,
        nothing redone), or None when no window is ready
        (:func:`cranetwin.service.workerpass.read_pass` reads it ahead)."""
        s = self.settings
        win = s.worker_window_s

        def span(w0: float, newest_s: float) -> tuple[float, float] | None:
            if w0 + win + s.worker_settle_s > newest_s:
                return None
            k = self._span_windows(w0, newest_s, False, budget)
            return w0 - s.twin_margin_s, w0 + k * win + s.twin_margin_s

        return span

    def _span_windows(self, w0: float, newest_s: float, quiet: bool,
                      budget: int | None) -> int:
        """How many ready windows from ``w0`` to replay and commit as one span (≥ 1).

        A worker that is behind (a pass longer than a window, catch-up after downtime, many
        machines per core) finds several windows of a machine ready; replaying them as one span
        costs one read, one replay and one transaction instead of one each, so the per-window
        overhead (which at short windows is most of the cost) is paid once per span. A span
        never crosses a whole minute (the stored analytics parts stay inside the minute, hour
        and day they are rolled up into) and holds only ready windows: those ending at least
        ``worker_settle_s`` before the newest sample, or, for a quiet machine, the one holding
        its newest sample too.

        Args:
            w0: Start of the first window (the watermark) [s].
            newest_s: Newest stored sample of the machine [s].
            quiet: Whether the machine is quiet (:meth:`_quiet`).
            budget: Windows still allowed in this pass (None: no limit).
        """
        s = self.settings
        win = s.worker_window_s
        if quiet:
            ready = math.floor((newest_s - w0) / win) + 1
        else:
            ready = math.floor((newest_s - s.worker_settle_s - w0) / win + 1e-9)
        minute_end = (math.floor(w0 / 60.0 + 1e-9) + 1) * 60.0
        in_minute = math.floor((minute_end - w0) / win + 1e-9)
        k = min(ready, in_minute, budget if budget is not None else ready)
        return max(1, k)

    def _analytics(self, rec: MachineRecord, machine: Machine, res: object,
                   keep: npt.NDArray[np.bool_], w0: float, w1: float,
                   times: tuple[float, float] = (0.0, 0.0), batch: PassCommit | None = None,
                   reach: F64 | None = None,
                   ) -> tuple[dict[str, Any] | None, list[Any] | None, LastPart | None]:
        """The window's analytics part row (:mod:`cranetwin.service.history`: what any range's
        analytics merge from) and its events, stored with the window's commit: a redone
        window replaces its part and its events (storage keeps an event found again as it is
        stored: unique on machine, time, kind). Returns (part row or None, events or None when
        they could not be found: a redone window then keeps the events stored, the part as
        kept for the next window's look-back or None); (None, None, None) when the part could
        not be made (the span is recorded as failed: :mod:`cranetwin.storage.failed_windows`).
        ``reach``: the kept instants' horizontal reach [m], shape (k,), if already computed.

        The events are found the way a report merges parts: the previous minute's stored part
        is folded first (:meth:`_previous_part`), so the look-back detectors (force rates,
        end-stop entries) see the samples before the window, and a run that started before
        the window is not a new event here; then the window's own part's events (what a
        detector's ``update`` with the window's history computes). A window stores the events
        that start in it (a run still open at its end is stored as it stands; a report joins it
        with its continuation, same start)."""
        from cranetwin.analytics import EventDetector
        from cranetwin.service.analytics import load_history, stored_events
        from cranetwin.service.history import part_row

        if int(np.count_nonzero(keep)) < 2:
            return None, [], None
        try:
            h = load_history(machine, res, keep, reach)
            got = part_row(machine, rec.machine_id, w0, w1, h, *times)
        except CraneTwinError as exc:
            log.warning("machine %s: analytics of window %.0f failed: %s", rec.machine_id, w0,
                        exc)
            return None, None, None
        row = got[1] if got is not None else None
        made = LastPart(w0, w1, got[1]["data"], got[0]) if got is not None else None
        try:
            det = EventDetector(machine)
            prev = self._previous_part(rec, w0, batch)
            if prev is not None:
                part = prev.decoded()
                if part.t_last < float(h.t_s[0]):
                    det.apply(part.events)
            det.apply(got[0].events if got is not None else det.part(h))
            events = stored_events(rec.machine_id,
                                   [e for e in det.all_events() if e.t_start >= w0])
        except CraneTwinError as exc:
            log.warning("machine %s: analytics of window %.0f failed: %s", rec.machine_id, w0,
                        exc)
            return row, None, made
        return row, events, made

    def _previous_part(self, rec: MachineRecord, w0: float,
                       batch: PassCommit | None = None) -> LastPart | None:
        """The last stored minute part inside [w0 − 60 s, w0), or None: the one of the
        machine's span waiting in ``batch`` (not stored yet), else the one this worker
        committed last when it is still valid (:attr:`_last_part`: only windows processed
        forward set it, so it is the newest part before the watermark), else read."""
        from cranetwin.storage import analytics_windows as aw

        seen = batch.parts.get(rec.machine_id) if batch is not None else None
        if seen is None:
            seen = self._last_part.get(rec.machine_id)
        if seen is not None and seen.end_s <= w0:
            return seen if seen.start_s >= w0 - 60 else None
        prev = aw.windows(self._engine(rec), rec.machine_id, 60, w0 - 60, w0)
        if not prev:
            return None
        a, b, _, data = prev[-1]
        return LastPart(a, b, data)

    def _quiet(self, machine_id: str, last_sample_s: float) -> bool:
        """Whether the machine's newest sample has stayed the same for ``quiet_s`` of this
        worker's clock: its last window is then processed without waiting for samples past its
        end (samples arriving later into it are late data, redone by :meth:`_redo_late`)."""
        now = self.clock()
        seen = self._last_sample.get(machine_id)
        if seen is None or seen[0] != last_sample_s:
            self._last_sample[machine_id] = (last_sample_s, now)
            return False
        return now - seen[1] >= self.quiet_s

    def _redo_late(self, rec: MachineRecord, prog: Progress,
                   reads: PassReads) -> tuple[Progress, int] | None:
        """Redo the windows behind the watermark that received samples since the last pass
        (late data, backfills): blocks stored after the machine's block mark that start before
        the watermark mark their windows, and the windows whose replay margin reaches into
        them. Returns (progress, windows redone), None if another worker moved the watermark.
        Hour and day parts over redone windows are rolled up again.

        A known payload stored or deleted for processed samples is found the same way: its
        redo requests (:mod:`cranetwin.storage.redo`) mark their ranges like late blocks, and
        are deleted once their windows are redone (those ahead of the watermark at once: their
        windows are replayed with the payload when they come). An operator's request
        (``cranetwin worker redo``) marks every window of its range behind the watermark that
        holds stored samples, processed, failed or never processed (no margin), and is
        deleted the same way.

        Its redo requests come from the pass's ``reads``, and so do its mark and late blocks
        when they hold them (PostgreSQL: its new mark is stored at the end of the pass or of
        the turn, :mod:`cranetwin.service.workerpass`); elsewhere they are read here and the
        mark stored at once.
        """
        from cranetwin.service.history import drop_duty, roll_up
        from cranetwin.storage import analytics_windows as aw
        from cranetwin.storage import redo

        engine = self._engine(rec)
        win, m = self.settings.worker_window_s, self.settings.twin_margin_s
        mid = rec.machine_id
        got = reads.late.get(mid)
        top: int | None
        if got is not None:
            mark, top, late = got
        else:
            mark = aw.block_mark(engine, mid)
            top, late = aw.new_blocks_before(engine, mid, mark, prog.watermark_s)

        requests = reads.redo.get(mid, [])

        def set_mark(new_mark: int) -> None:
            if got is not None:
                reads.marks[mid] = new_mark
            else:
                aw.set_block_mark(engine, mid, new_mark)

        def windows_of(ranges: list[tuple[float, float]]) -> list[float]:
            grid: set[float] = set()
            for a, b in ranges:
                w = math.floor((a - m) / win) * win
                while w < min(b + m, prog.watermark_s):
                    grid.add(float(w))
                    w += win
            return sorted(grid)

        held, late_alone = self._held_spans(engine, mid, windows_of(late))
        spans = set(held) | {(w, w + win) for w in late_alone}
        grid = windows_of([r.span_s for r in requests if not r.whole])
        if grid:  # a known payload changes only windows already processed (failed ones too)
            spans.update(self._stored_spans(engine, mid, grid, only_stored=True))
        # an operator's request: every window of its range behind the watermark holding
        # samples; one inside no stored span was passed by the watermark with nothing stored
        # (redone like a span whose replay failed: its windows counted, no time)
        grid = sorted({w for r in requests if r.whole
                       for w in redo.sampled_windows(engine, mid, r.t0_ns, r.t1_ns, win)
                       if w + win <= prog.watermark_s})
        held, alone = self._held_spans(engine, mid, grid)
        spans.update(held)
        spans.update((w, w + win) for w in alone)
        passed = set(alone) - set(late_alone)  # (late samples there: counted as new)
        if not spans:  # nothing behind the watermark (requests ahead of it: nothing to redo)
            if top is not None and top != mark:
                set_mark(top)
            redo.done(engine, mid, requests)
            return prog, 0
        self._forget(mid)  # parts behind the watermark are written again
        done = 0
        for w0, w1 in sorted(spans):
            if self.stop_requested():
                return prog, done  # the mark stays: the rest is found again next pass
            new = self.process_window(rec, prog, prog.watermark_s, redo_w0=w0, until_s=w1,
                                      reads=reads, passed=w0 in passed)
            if new is None:
                return None
            prog = new
            done += 1
        recounted = self._recount_lifts(rec, prog)
        if recounted is None:
            return None
        prog = recounted
        lo, hi = min(spans)[0], max(spans)[1]
        aw.delete_windows(engine, rec.machine_id, lo, hi, levels=(3600, 86400))
        drop_duty(engine, rec.machine_id)  # rebuilt from the parts at the end of the pass
        try:
            roll_up(engine, self.backend.model_of(rec), rec.machine_id,
                    math.floor(lo / 86400) * 86400.0, prog.watermark_s)
        except CraneTwinError as exc:
            log.warning("machine %s: roll-up after late data failed: %s", rec.machine_id, exc)
        if top is not None:
            set_mark(top)
        redo.done(engine, mid, requests)
        log.info("machine %s: %d window(s) redone for late data, a known payload or an "
                 "operator's request", rec.machine_id, done)
        return prog, done

    def _stored_spans(self, engine: Any, machine_id: str, grid: list[float],
                      only_stored: bool = False) -> list[tuple[float, float]]:
        """The spans to redo for the windows starting at ``grid`` (sorted) [s]: the stored
        span holding a window (it was replayed as one, :meth:`_span_windows`; a span with a
        part, or one whose replay or analytics failed, :mod:`cranetwin.storage.failed_windows`)
        is redone whole, a window inside no stored span alone (left out with ``only_stored``:
        a known payload changes nothing of a window never processed). Returns ``(start, end)``
        pairs, sorted, distinct."""
        held, alone = self._held_spans(engine, machine_id, grid)
        win = self.settings.worker_window_s
        return sorted(set(held) | (set() if only_stored else {(w, w + win) for w in alone}))

    def _held_spans(self, engine: Any, machine_id: str, grid: list[float],
                    ) -> tuple[list[tuple[float, float]], list[float]]:
        """For the windows starting at ``grid`` (sorted) [s]: the stored spans holding any of
        them (:meth:`_stored_spans`), sorted and distinct, and the windows inside none."""
        from cranetwin.storage import analytics_windows as aw
        from cranetwin.storage.failed_windows import failed_spans

        if not grid:
            return [], []
        win = self.settings.worker_window_s
        reach = max(60.0, win)
        lo, hi = grid[0] - reach, grid[-1] + win + reach
        stored = sorted(set(aw.spans(engine, machine_id, 60, lo, hi))
                        | set(failed_spans(engine, machine_id, lo, hi)))
        held: set[tuple[float, float]] = set()
        alone: list[float] = []
        i = 0
        for w in grid:
            while i < len(stored) and stored[i][1] <= w:
                i += 1
            if i < len(stored) and stored[i][0] <= w < stored[i][1]:
                held.add((stored[i][0], stored[i][1]))
            else:
                alone.append(w)
        return sorted(held), alone

    def _recount_lifts(self, rec: MachineRecord, prog: Progress) -> Progress | None:
        """``prog`` with the lift counters folded again over the stored minutes
        (:func:`cranetwin.service.liftcount.recount`) and saved; None if another worker moved
        the watermark."""
        from cranetwin.service.liftcount import recount

        new = recount(self._engine(rec), self.backend.model_of(rec), prog,
                      self.settings.payload_lift_threshold_kg)
        if new is None:
            log.warning("machine %s: lift counters not recounted (minutes processed before "
                        "their lift seconds were stored)", rec.machine_id)
            return prog
        if new == prog:
            return prog
        return new if self.backend.save_progress(new, prog.watermark_s) else None

    def _update_duty(self, rec: MachineRecord, first_s: float, until_s: float) -> None:
        """Fold the new minutes into the machine's duty to date (AEMP's kp and design life
        used: :class:`cranetwin.service.history.DutyToDate`)."""
        from cranetwin.service.history import update_duty

        known = self._duty.pop(rec.machine_id, None)  # back only once it is stored
        try:
            self._duty[rec.machine_id] = update_duty(
                self._engine(rec), self.backend.model_of(rec), rec.machine_id, first_s,
                until_s, known)
        except CraneTwinError as exc:
            log.warning("machine %s: duty to date not updated: %s", rec.machine_id, exc)

    def _check_schedules(self, rec: MachineRecord) -> None:
        """Raise the ``service_due`` events of the machine's due items
        (:func:`cranetwin.service.schedules.check_due`), at most every ``schedule_check_s``."""
        from cranetwin.service.schedules import check_due

        now = self.clock()
        if now < self._next_schedule_check.get(rec.machine_id, -math.inf):
            return
        self._next_schedule_check[rec.machine_id] = now + self.schedule_check_s
        try:
            n = check_due(self.backend, rec.machine_id)
        except CraneTwinError as exc:
            log.warning("machine %s: service schedule not checked: %s", rec.machine_id, exc)
            return
        if n:
            log.info("machine %s: %d service item(s) due", rec.machine_id, n)

    def _roll_up(self, rec: MachineRecord, from_s: float, to_s: float) -> None:
        """Roll the minute parts of the hours (and days) the progress mark passed from
        ``from_s`` to ``to_s`` up into hour (and day) parts."""
        from cranetwin.service.history import roll_up

        if math.floor(from_s / 3600) == math.floor(to_s / 3600):
            return
        try:
            roll_up(self._engine(rec), self.backend.model_of(rec), rec.machine_id,
                    math.floor(from_s / 86400) * 86400.0, to_s)
        except CraneTwinError as exc:
            log.warning("machine %s: roll-up to %.0f failed: %s", rec.machine_id, to_s, exc)

    def process_window(self, rec: MachineRecord, prog: Progress,
                       expected_watermark_s: float | None,
                       redo_w0: float | None = None, until_s: float | None = None,
                       samples: SampleArrays | None = None,
                       reads: PassReads | None = None,
                       batch: PassCommit | None = None, passed: bool = False,
                       ) -> Progress | None:
        """Replay [watermark, until_s) (default: one window), commit its summaries and progress
        together.

        Args:
            rec: The machine.
            prog: Its progress before the window.
            expected_watermark_s: The stored watermark the commit is conditional on (None: no
                progress row stored yet).
            redo_w0: Redo the past window starting here instead (late data behind the
                watermark): the watermark stays; the window's derived summaries, analytics part,
                lift seconds and events are written again; its operating and idle time replace
                those counted for it before (if any); the lift counters are left to
                :meth:`_recount_lifts` after the redo.
            until_s: End of the span [s]: a whole number of windows after its start (one
                window when None); with ``redo_w0``, the end of the stored span redone.
            samples: The machine's samples of the span and its margins, if already read.
            reads: The pass's reads holding this machine (its stored known payload runs:
                a span outside them reads none).
            batch: Collect the span for the pass's commit instead of committing it now
                (forward spans only, not with ``redo_w0``); the new progress is returned as
                if committed (:mod:`cranetwin.service.workercommit`).
            passed: With ``redo_w0``: the span has neither a part nor a failed span, and the
                watermark passed it counting its windows and no time (an operator's redo of a
                window never processed, or whose replay failed before failed spans were
                recorded: :mod:`cranetwin.storage.redo`); its windows are not counted again.

        Returns:
            The new progress, or None when another worker committed the window first (nothing
            of this replay was stored).
        """
        from cranetwin.physics import horizontal_reach
        from cranetwin.service.replayer import sample_rate_hz

        expected = expected_watermark_s
        s = self.settings
        machine = self.backend.model_of(rec)
        w0 = prog.watermark_s if redo_w0 is None else redo_w0
        w1 = w0 + s.worker_window_s if until_s is None else until_s
        n_windows = max(1, round((w1 - w0) / s.worker_window_s))
        m = s.twin_margin_s
        if samples is None:
            samples = self.backend.read_samples(rec.machine_id, w0 - m, w1 + m)
        new = dc_replace(prog, watermark_s=w1, windows=prog.windows + n_windows)
        count = True
        old: tuple[float, float] | None = None
        if redo_w0 is not None:  # what the progress counted for the span: its part's times,
            from cranetwin.storage import analytics_windows as aw  # or a failed span's counts
            from cranetwin.storage import failed_windows

            engine = self._engine(rec)
            old = aw.window_times(engine, rec.machine_id, 60, w0)
            count = old is None
            if old is None and (got := failed_windows.counted(engine, rec.machine_id, w0)):
                count, old = got[0] == 0, got[1:]
            elif old is None and passed:
                count, old = False, (0.0, 0.0)
            new = prog if not count else dc_replace(prog, windows=prog.windows + n_windows)
        n_in = int(np.count_nonzero((samples.t_s >= w0) & (samples.t_s < w1)))
        try:
            if n_in < 8:
                raise _TooFewSamples(f"only {n_in} samples in the window")
            grid_hz = sample_rate_hz(samples)
            stored = reads is None or reads.payload_stored(  # a second more either side
                rec.machine_id, float(samples.t_s[0]) - 1.0, float(samples.t_s[-1]) + 1.0)
            res = self.replayer.replay(rec.machine_id, machine, samples, grid_hz,
                                       theta0_initial=prog.theta0_rad or 0.0,
                                       payload_stored=stored)
        except CraneTwinError as exc:
            log.warning("machine %s window %.0f–%.0f not replayed: %s", rec.machine_id, w0, w1,
                        exc)
            if self.metrics is not None:
                self.metrics.worker_errors.labels(rec.machine_id).inc()
            # retried when its input changes, with what the progress counts for it
            counted = n_windows if redo_w0 is None or not count else 0
            failure = [] if isinstance(exc, _TooFewSamples) else [
                failed_row(rec.machine_id, w0, w1, counted, *(old or (0.0, 0.0)))]
            if redo_w0 is not None:  # the progress stays as counted before
                if failure:
                    self._put_rows(rec, failure)
                return prog
            return new if self._save(new, expected, batch, failure) else None
        keep = window_rows(res, w0, w1)
        names, values = derive(machine, res, keep)
        t = res.t_s[keep]
        reach = horizontal_reach(machine, res.q[keep]) if t.size else np.zeros(0)
        times = (t.size / grid_hz, float(np.sum(values[:, -1] < 0.5)) / grid_hz)
        if redo_w0 is None:
            new = update_counters(new, machine, t, res.payload_kg[keep], reach, values[:, -1],
                                  1.0 / grid_hz, s.payload_lift_threshold_kg)
        else:  # a redone window replaces its share of the operating time; the lift counters
            o = old or (0.0, 0.0)  # are recounted after the redo (:meth:`_recount_lifts`)
            new = dc_replace(new, operating_s=new.operating_s - o[0] + times[0],
                             idle_s=new.idle_s - o[1] + times[1])
            finite = res.payload_kg[keep]
            finite = finite[np.isfinite(finite)]
            if w1 >= prog.watermark_s and finite.size:  # the newest processed span: the
                new = dc_replace(new, last_payload_kg=float(finite[-1]))  # last estimate
        rows: list[dict[str, Any]] = []
        events: list[Any] | None = []
        part: dict[str, Any] | None = None
        made: LastPart | None = None
        failed = False
        if t.size:
            if redo_w0 is None:
                new = dc_replace(new, theta0_rad=float(res.q[keep][-1, 0]))
            rows.append(seconds_row(rec.machine_id, w0, w1,
                                    *lift_seconds(machine, t, res.payload_kg[keep], reach)))
            part, events, made = self._analytics(rec, machine, res, keep, w0, w1, times,
                                                 batch, reach)
            if part is not None:
                rows.append(part)
            elif events is None:  # no part could be made: retried when its input changes
                failed = True
                rows.append(failed_row(rec.machine_id, w0, w1, n_windows, *times))
        if batch is not None and redo_w0 is None:
            batch.add(new, expected, names, t, values, rows, events, n_windows)
            if made is not None:  # (made exactly when the part row is)
                batch.parts[rec.machine_id] = made
            return new

        def also(session: Any, machine_pk: int) -> None:
            from cranetwin.analytics.events import KINDS
            from cranetwin.storage import analytics_windows as aw
            from cranetwin.storage import events as ev
            from cranetwin.storage import failed_windows

            if redo_w0 is not None and part is not None:  # a part again: no longer failed
                failed_windows.clear(session, rec.machine_id, w0)
            elif redo_w0 is not None and failed:  # the part made from the inputs before is
                aw.delete_window(session, rec.machine_id, 60, w0)  # not kept
            aw.put_rows(session, rows)
            if redo_w0 is not None and events is not None:  # the window's events replaced
                ev.replace_in(session, machine_pk, round(w0 * 1e9), round(w1 * 1e9), KINDS,
                              events)
            else:
                ev.add_in(session, machine_pk, events or [])

        if not self.backend.commit_window(new, expected, names, t, values,
                                          also if rows else None):
            self._forget(rec.machine_id)
            return None
        if made is not None and redo_w0 is None:
            self._last_part[rec.machine_id] = made
        if self.metrics is not None:
            self.metrics.worker_windows.labels(rec.machine_id).inc()
        return new
