"""Live payload estimate: a replay of the newest stored samples gives the payload being held now
(synthetic samples with a known payload schedule), falls back to the twin worker's estimate, and
is shown as a non-negative number or null."""

from __future__ import annotations

import math

import pytest

from cranetwin.model import load_machine
from cranetwin.service.backend import Backend, Progress
from cranetwin.service.live_payload import LivePayload, public_kg
from cranetwin.service.replayer import Replayer
from cranetwin.testing.blocks import PAYLOAD_KG, kinematic_samples, tiled_blocks

T0 = 1795420800.0  # a whole minute; the payload is PAYLOAD_KG in [T0+30, T0+60), 0 after
MID = "crane-lp"
MACHINE = load_machine("patu655")


def _write(b: Backend, start: float, seconds: float, seq0: int) -> None:
    base = kinematic_samples(MACHINE, 120.0)
    b.store.write_blocks(list(tiled_blocks(MID, MACHINE, start, seconds, 1.0, base=base,
                                           seq0=seq0, origin_s=T0)))


def test_live_estimate_follows_the_held_payload(sqlite_url: str) -> None:
    b = Backend.open(sqlite_url)
    b.store.add_machine(MID, wire_id=8, secret=b"k" * 32)
    now = [0.0]
    lp = LivePayload(MID, MACHINE, b, Replayer(), clock=lambda: now[0])
    assert lp.value() is None  # nothing stored, no worker estimate
    lp.join()
    assert lp.kg is None
    _write(b, T0, 52.0, 0)  # newest sample at T0+52: holding PAYLOAD_KG
    now[0] = 1.0  # not due yet (every_s = 2 s since the first call at 0)
    assert lp.value() is None and lp.kg is None
    now[0] = 2.0  # due
    assert lp.value() is None
    lp.join()
    now[0] = 10.0
    assert lp.value() == pytest.approx(PAYLOAD_KG, rel=0.02)
    assert lp.t_s == pytest.approx(T0 + 50.0, abs=0.02)
    _write(b, T0 + 52.0, 28.0, 52)  # newest sample at T0+80: released at T0+60
    assert lp.refresh() == pytest.approx(0.0, abs=0.02 * PAYLOAD_KG)
    b.close()


def test_falls_back_to_the_worker_estimate(sqlite_url: str) -> None:
    b = Backend.open(sqlite_url)
    b.store.add_machine(MID, wire_id=8, secret=b"k" * 32)
    b.reset_progress(Progress.empty(MID, T0))
    b.reset_progress(Progress(**{**Progress.empty(MID, T0).__dict__, "last_payload_kg": 321.0}))
    lp = LivePayload(MID, MACHINE, b, Replayer())
    assert lp.refresh() is None  # no samples: no live estimate
    assert lp.value() == 321.0
    lp.join()
    b.close()


@pytest.mark.parametrize(("kg", "shown"), [(None, None), (math.nan, None), (-0.31, 0.0),
                                           (412.349, 412.3), (0.0, 0.0)])
def test_public_kg(kg: float | None, shown: float | None) -> None:
    assert public_kg(kg) == shown


def test_no_replay_when_nothing_new_is_stored(sqlite_url: str) -> None:
    b = Backend.open(sqlite_url)
    b.store.add_machine(MID, wire_id=8, secret=b"k" * 32)
    _write(b, T0, 52.0, 0)
    calls: list[int] = []

    class Counting(Replayer):
        def replay(self, *args, **kwargs):  # type: ignore[no-untyped-def]
            calls.append(1)
            return super().replay(*args, **kwargs)

    lp = LivePayload(MID, MACHINE, b, Counting())
    first = lp.refresh()
    assert first == pytest.approx(PAYLOAD_KG, rel=0.02)
    assert lp.refresh() == first and len(calls) == 1
    _write(b, T0 + 52.0, 28.0, 52)
    assert lp.refresh() == pytest.approx(0.0, abs=0.02 * PAYLOAD_KG) and len(calls) == 2
    b.close()


def test_machines_list_starts_a_live_estimate_before_the_worker_has_one(sqlite_url: str) -> None:
    import time

    from cranetwin.api.services import Services
    from cranetwin.settings import Settings

    services = Services.open(Settings(database_url=sqlite_url, worker_in_process=False,
                                      warm_up=False))
    b = services.backend
    b.store.add_machine(MID, wire_id=8, secret=b"k" * 32)
    start = float(int(time.time()) - 52)  # streaming now: holding PAYLOAD_KG since start+30
    base = kinematic_samples(MACHINE, 120.0)
    blocks = list(tiled_blocks(MID, MACHINE, start, 52.0, 1.0, base=base))
    b.store.write_blocks(blocks[-3:])  # the newest 3 s ("live"): too little for an estimate
    rec = b.machine(MID)
    first = services.machine_public(rec)
    assert first.payload_kg is None  # no worker estimate yet, no live one either
    services.fleet.live_payload[MID].join()
    services.fleet.live_payload[MID].every_s = 0.0  # (2 s between refreshes in service)
    b.store.write_blocks(blocks[:-3])  # the 49 s before them arrive (retransmitted)
    second = services.machine_public(rec)  # a later listing refreshes the estimate
    assert second.status == "live" and second.payload_kg is None
    services.fleet.live_payload[MID].join()
    assert services.machine_public(rec).payload_kg == pytest.approx(PAYLOAD_KG, rel=0.02)
    b.close()
