"""The law of the protocol, for any interleaving: acked ⇒ stored exactly once, and everything the
sender journaled is eventually acked.

A hypothesis state machine drives the sans-IO :class:`Sender` and :class:`Receiver` with an
in-memory idempotent store (unique on (machine, epoch, seq), like the real one) through sends,
losses, duplicates, reorderings (any queued datagram may be delivered next), sender clock jumps,
server crashes (uncommitted writes and all
receiver state lost), sender crashes (``kill -9``: memory and unsynced journal entries lost) and
sender restarts that lost their journal (a new epoch over the same sequence numbers).

Out of the contract, hence not modelled: a journal restored from an old copy (its epoch would
reuse sequence numbers for new data). Storage refuses such a reuse when it reaches it
(``seq_reused``), but the receiver's durable set cannot tell it from a retransmission.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.stateful import (
    RuleBasedStateMachine,
    invariant,
    precondition,
    rule,
)

from cranetwin.protocol import (
    ChannelSpec,
    DatagramError,
    Layout,
    Limits,
    MachineKey,
    MemoryJournal,
    Receiver,
    RefusedError,
    ReplayedError,
    Sender,
    decode_data,
)
from cranetwin.samples import SampleBlock

LAYOUT = Layout((ChannelSpec("p", 0.0, 25e6, 5000.0), ChannelSpec("s", 0.0, 1.0, 1e-4)))
KEY = MachineKey(11, "m11", b"s" * 32, LAYOUT)
PERIOD = 10_000_000
MS = 1_000_000
T0 = 1_800_000_000 * 10**9


class CrashableJournal(MemoryJournal):
    """A MemoryJournal whose appends since the last sync vanish in a crash."""

    def crash(self) -> None:
        while self._end > max(self.synced_end, self._start):
            self._q.pop()
            self._end -= 1


class ProtocolMachine(RuleBasedStateMachine):
    def __init__(self) -> None:
        super().__init__()
        self.now = T0
        self.data_t = T0  # machine clock of the next sample
        self.rows = 0
        self.journal = CrashableJournal(epoch=1)
        self.journal_first = 0
        self.epochs = [1]
        self.sender = self._new_sender()
        self.rx = Receiver({KEY.wire_id: KEY}, Limits(max_past_s=10 * 86400.0,
                                                      max_future_s=10 * 86400.0))
        self.up: list[bytes] = []
        self.down: list[bytes] = []
        self.uncommitted: list[SampleBlock] = []
        self.store: dict[tuple[int, int], SampleBlock] = {}
        self.run = 0  # incarnation of the sender (a restored backup reuses (epoch, seq))
        self.sent: dict[tuple[int, int, int], SampleBlock] = {}  # (run, epoch, seq) → content
        self.acked: set[tuple[int, int, int]] = set()
        self.refused: set[tuple[int, int, int]] = set()
        self.lost_with_journal: set[tuple[int, int, int]] = set()

    def _new_sender(self) -> Sender:
        return Sender(KEY, PERIOD, journal=self.journal, batch_samples=5, max_unacked=6,
                      min_rto_ns=200 * MS, max_rto_ns=2000 * MS, max_burst=8)

    def _unacked(self) -> set[tuple[int, int, int]]:
        s = self.sender
        return {(self.run, s.epoch, q)
                for q in [*s.pending_seqs(), *range(s._loaded, self.journal.end)]}

    # --- the machine ----------------------------------------------------------------------------
    @rule(n=st.integers(1, 12), value=st.integers(0, 4000))
    def produce(self, n: int, value: int) -> None:
        v = np.column_stack([np.full(n, value * 5000.0), np.full(n, (value % 9000) * 1e-4)])
        self.sender.push(self.data_t, v)
        self.data_t += n * PERIOD
        self.rows += n

    @rule()
    def flush(self) -> None:
        self.sender.flush()

    @rule(jump_s=st.integers(-3600, 3600))
    def machine_clock_jumps(self, jump_s: int) -> None:
        self.sender.flush()
        self.data_t += jump_s * 10**9

    @rule(dt_ms=st.integers(0, 1500))
    def tick(self, dt_ms: int) -> None:
        self.now += dt_ms * MS
        for dg in self.sender.datagrams_to_send(self.now):
            block = decode_data(dg, KEY)
            # nothing leaves the sender before the journal made it durable
            assert block.epoch == self.journal.epoch and block.seq < self.journal.synced_end
            self.sent.setdefault((self.run, block.epoch, block.seq), block)
            self.up.append(dg)

    @rule()
    def sender_killed(self) -> None:
        """kill -9: memory and unsynced journal entries are gone; restart on the journal."""
        self.journal.crash()
        self.sender = self._new_sender()  # same journal, same (epoch, seq) → same content

    @rule(skip=st.integers(1, 50))
    def sender_restarts_losing_its_journal(self, skip: int) -> None:
        """The disk was wiped: a new epoch. What the old journal held unacked is lost (only a
        durable journal can keep that promise); nothing acked may be lost."""
        self.lost_with_journal |= self._unacked()
        self.journal_first = skip % 3
        self.journal = CrashableJournal(first_seq=self.journal_first)  # the same low seqs again
        self.epochs.append(self.journal.epoch)
        self.run += 1
        self.sender = self._new_sender()

    # --- the network ----------------------------------------------------------------------------
    @precondition(lambda self: self.up)
    @rule(i=st.integers(0, 10**6), copies=st.integers(0, 2))
    def deliver_up(self, i: int, copies: int) -> None:
        dg = self.up.pop(i % len(self.up))
        for _ in range(copies):  # 0 = lost, 2 = duplicated
            self._server_receive(dg)

    @precondition(lambda self: self.down)
    @rule(i=st.integers(0, 10**6), lost=st.booleans())
    def deliver_down(self, i: int, lost: bool) -> None:
        dg = self.down.pop(i % len(self.down))
        if not lost:
            self._sender_receive(dg)

    # --- the server -----------------------------------------------------------------------------
    def _server_receive(self, dg: bytes) -> None:
        try:
            item = self.rx.receive(dg, self.now)
        except ReplayedError as err:
            assert err.machine_id is not None
            self.down.append(self.rx.ack(err.machine_id, err.epoch, self.now))
            return
        except RefusedError as err:
            self.down.append(self.rx.refusal(err, self.now))
            return
        assert isinstance(item, SampleBlock)
        self.uncommitted.append(item)

    @rule()
    def commit(self) -> None:
        epochs = set()
        for b in self.uncommitted:
            k = (b.epoch, b.seq)
            old = self.store.setdefault(k, b)  # ON CONFLICT DO NOTHING
            if old.t0_ns != b.t0_ns or not np.array_equal(old.values, b.values):
                self.down.append(self.rx.refuse(b.machine_id, b.epoch, b.seq, "seq_reused",
                                                self.now))
                continue
            self.rx.mark_durable(b.machine_id, b.epoch, b.seq)
            epochs.add(b.epoch)
        self.uncommitted.clear()
        for e in epochs:
            self.down.append(self.rx.ack(KEY.machine_id, e, self.now))

    @rule()
    def server_crashes(self) -> None:
        self.uncommitted.clear()
        self.rx = Receiver({KEY.wire_id: KEY}, self.rx.limits)

    def _sender_receive(self, dg: bytes) -> None:
        before = self._unacked()
        rejected = len(self.journal.rejected)
        try:
            self.sender.receive(dg, self.now)
        except DatagramError:
            pytest.fail("a server datagram did not verify")
        refused = {(self.run, self.sender.epoch, q) for q, _, reason in
                   self.journal.rejected[rejected:]}
        assert all(r == "seq_reused" for _, _, r in self.journal.rejected)
        self.refused |= refused
        self.acked |= before - self._unacked() - refused

    # --- the laws -------------------------------------------------------------------------------
    @invariant()
    def acked_implies_stored_exactly_once(self) -> None:
        for k in self.acked:
            want = self.sent.get(k)
            assert want is not None, f"{k} acked but never sent"
            got = self.store.get(k[1:])
            assert got is not None, f"{k} acked but not stored"
            assert got.t0_ns == want.t0_ns and np.array_equal(got.values, want.values), \
                f"{k} acked but the store holds other data under its (epoch, seq)"
        assert not self.acked & self.refused

    def teardown(self) -> None:
        """A good network for long enough: everything journaled is acked and stored once."""
        self.sender.flush()
        for dg in self.up:  # stale copies still in flight arrive too
            self._server_receive(dg)
        self.up.clear()
        for _ in range(400):
            if self.sender.idle:
                break
            self.now += 100 * MS
            self.tick(0)
            for dg in self.up:
                self._server_receive(dg)
            self.up.clear()
            self.commit()
            while self.down:
                self._sender_receive(self.down.pop(0))
        assert self.sender.idle, "the sender never drained over a perfect network"
        self.acked_implies_stored_exactly_once()
        journaled = {(self.run, self.journal.epoch, s)
                     for s in range(self.journal_first, self.journal.synced_end)}
        assert journaled <= self.acked | self.refused
        for k in self.sent:  # everything sent was acked, refused or lost with its journal
            assert k in self.acked or k in self.refused or k in self.lost_with_journal


TestProtocol = ProtocolMachine.TestCase
TestProtocol.settings = settings(max_examples=150, stateful_step_count=60, deadline=None,
                                 suppress_health_check=[HealthCheck.too_slow])
