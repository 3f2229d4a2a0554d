"""The API's replay cache and the stored blocks of a past window: samples that arrive late into
a cached window (a machine retransmitting its journal after an outage, stored by another
process), blocks committed out of order and retention dropping the window's partition are
replayed at the next call, while a live machine's blocks appended in time order leave past
windows cached (the key holds the late-data version, ``cranetwin.storage.late_version``)."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import delete
from sqlalchemy.orm import Session

from cranetwin.api import create_app
from cranetwin.api.services import Services
from cranetwin.model import load_machine
from cranetwin.samples import SampleArrays, SampleBlock
from cranetwin.settings import Settings
from cranetwin.storage import Store, open_store, writes
from cranetwin.storage import late_version as lv
from cranetwin.storage.analytics_windows import AnalyticsWindowRow
from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

T0 = 1795420800.0  # 2026-11-23 08:00 UTC, a whole minute
DAY = 86400.0
MID = "crane-l"
MACHINE = load_machine("patu655")
WINDOW = {"from": T0 + 95.0, "to": T0 + 105.0, "rate_hz": 10}
GAP = (T0 + 98.0, T0 + 101.0)
"""Blocks starting in here are missing at first (the machine was offline)."""

pytestmark = [pytest.mark.timeout(120)]


@pytest.fixture(scope="module")
def base() -> SampleArrays:
    return kinematic_samples(MACHINE, 120.0)


def _blocks(base: SampleArrays, start_s: float, duration_s: float,
            seq0: int = 0) -> list[SampleBlock]:
    return list(tiled_blocks(MID, MACHINE, start_s, duration_s, 1.0, base=base, seq0=seq0,
                             origin_s=T0))


def _in_gap(b: SampleBlock) -> bool:
    return GAP[0] <= b.t0_ns / 1e9 < GAP[1]


@pytest.fixture
def api(db_url: str, base: SampleArrays) -> Iterator[tuple[TestClient, Services, str]]:
    """An API process on a database holding 4 minutes of samples with 3 s missing inside
    :data:`WINDOW`; (client, services, key)."""
    with open_store(db_url) as store:
        store.add_machine(MID, wire_id=7, secret=b"k" * 32)
        store.write_blocks([b for b in _blocks(base, T0, 240.0) if not _in_gap(b)])
    app = create_app(Settings(database_url=db_url, worker_in_process=False, warm_up=False,
                              heavy_processes=0))
    with TestClient(app) as client:
        services: Services = app.state.services
        yield client, services, services.backend.create_key("viewer", "test")[1]


def _twin(client: TestClient, key: str, window: dict[str, float] = WINDOW) -> bytes:
    r = client.get(f"/api/v1/machines/{MID}/twin", params=window, headers={"X-API-Key": key})
    assert r.status_code == 200, r.text
    return r.content


def _hit(api: tuple[TestClient, Services, str], window: dict[str, float] = WINDOW
         ) -> tuple[bytes, bool]:
    """The window's body and whether the cache answered it."""
    client, services, key = api
    hits = services.fleet.twin_cache.hits
    body = _twin(client, key, window)
    return body, services.fleet.twin_cache.hits == hits + 1


def _fresh(api: tuple[TestClient, Services, str]) -> bytes:
    """The window replayed from what is stored now (the cache emptied first)."""
    api[1].fleet.twin_cache.clear()
    body, hit = _hit(api)
    assert not hit
    return body


def test_samples_arriving_late_into_a_cached_window_are_replayed(
        api: tuple[TestClient, Services, str], db_url: str, base: SampleArrays) -> None:
    gap, hit = _hit(api)
    assert not hit
    assert _hit(api) == (gap, True)  # cached, with the gap
    late = [b for b in _blocks(base, T0, 240.0) if _in_gap(b)]
    assert len(late) == 3
    with open_store(db_url) as daemon:  # another process's store (the ingest daemon's)
        assert daemon.write_blocks(late) == 3
    body, hit = _hit(api)
    assert not hit and body != gap  # replayed with the late samples
    assert _hit(api) == (body, True)  # and cached again
    assert _fresh(api) == body  # what a replay of the stored data gives


def test_blocks_committed_out_of_order_are_replayed(
        api: tuple[TestClient, Services, str], db_url: str, base: SampleArrays) -> None:
    """A writer commits newer blocks first (the window becomes cacheable without its middle),
    another the older ones afterwards, in one batch with newer blocks of its own."""
    tail = _blocks(base, T0 + 240.0, 20.0, seq0=240)
    with open_store(db_url) as a:
        a.write_blocks(tail[10:])
    gap, hit = _hit(api)
    assert not hit and _hit(api) == (gap, True)
    late = [b for b in _blocks(base, T0, 240.0) if _in_gap(b)]
    with open_store(db_url) as b:
        assert b.write_blocks(tail[:10] + late) == 13
    body, hit = _hit(api)
    assert not hit and body != gap and body == _fresh(api)


def test_a_live_machine_appending_in_order_keeps_past_windows_cached(
        api: tuple[TestClient, Services, str], db_url: str, base: SampleArrays) -> None:
    client, services, key = api
    past, hit = _hit(api)
    assert not hit and _hit(api) == (past, True)
    newest = {"from": T0 + 230.0, "to": T0 + 240.0, "rate_hz": 10}
    open_body, hit = _hit(api, newest)
    assert not hit and _hit(api, newest)[1] is False  # still growing: never cached
    version = services.backend.machine(MID).late_version
    with open_store(db_url) as daemon:
        for k in range(5):  # the live machine, block after block
            assert daemon.write_blocks(_blocks(base, T0 + 240.0 + k, 1.0, seq0=240 + k)) == 1
            assert daemon.write_blocks(_blocks(base, T0 + 240.0 + k, 1.0, seq0=240 + k)) == 0
    assert services.backend.machine(MID).late_version == version
    assert _hit(api) == (past, True)  # the past window: still the cached replay
    closed, hit = _hit(api, newest)  # now ends before the newest data: replayed, cached
    assert not hit and _hit(api, newest) == (closed, True)


@pytest.mark.postgres
def test_retention_dropping_a_cached_window_is_not_served_from_the_cache(
        pg_url: str, base: SampleArrays) -> None:
    from cranetwin.service.backend import Progress

    with open_store(pg_url) as store:
        store.add_machine(MID, wire_id=7, secret=b"k" * 32)
        store.write_blocks(_blocks(base, T0, 240.0))  # November
        store.write_blocks(_blocks(base, T0 + 30 * DAY, 5.0, seq0=1000))  # December
    app = create_app(Settings(database_url=pg_url, worker_in_process=False, warm_up=False,
                              heavy_processes=0))
    with TestClient(app) as client:
        services: Services = app.state.services
        api = (client, services, services.backend.create_key("viewer", "test")[1])
        stored, hit = _hit(api)
        assert not hit and _hit(api) == (stored, True)
        services.backend.reset_progress(Progress.empty(MID, T0 + 10 * DAY))
        with open_store(pg_url) as worker:  # the twin worker's process applies retention
            worker.rollup()
            res = worker.maintain_partitions(T0 + 100 * DAY, keep_days=80, margin_s=5.0)
            assert res.dropped == ["sample_blocks_p20261101"], res
        gone, hit = _hit(api)  # December still stored: the window stays cacheable
        assert not hit and gone != stored and gone == _fresh(api)
        assert _hit(api) == (gone, True)


def _version(store: Store) -> int:
    with Session(store.engine) as s:
        return lv.read(s, MID)


def test_late_version_is_raised_by_blocks_behind_the_newest_only(
        db_url: str, base: SampleArrays) -> None:
    blocks = _blocks(base, T0, 10.0)
    with open_store(db_url) as a, open_store(db_url) as b:
        a.add_machine(MID, wire_id=7, secret=b"k" * 32)
        a.add_machine("other", wire_id=8, secret=b"k" * 32)
        assert _version(a) == 0
        a.write_blocks(blocks[:3])  # the first blocks: the row is made (version 1)
        assert _version(b) == 1
        for blk in blocks[4:6]:  # in order, one by one and in a batch: no change
            b.write_blocks([blk])
        a.write_blocks(blocks[6:8])
        assert _version(b) == 1
        assert a.write_batch(blocks[6:8]).outcomes[0].status == "duplicate"
        assert _version(b) == 1  # a duplicate stores nothing
        b.write_blocks([blocks[3]])  # behind the newest: raised once
        assert _version(a) == 2
        a.write_blocks(blocks[8:])
        assert _version(a) == 2
        with Session(a.engine) as s:
            assert lv.read(s, "other") == 0

        # data stored before the version existed (its row missing): the mark is taken from
        # the stored blocks, so a block behind them still raises it
        with Session(a.engine) as s, s.begin():
            s.execute(delete(AnalyticsWindowRow).where(AnalyticsWindowRow.level_s == lv.LEVEL))
        more = _blocks(base, T0 + 10.0, 10.0, seq0=10)
        a.write_blocks([more[9]])
        with Session(a.engine) as s, s.begin():
            s.execute(delete(AnalyticsWindowRow).where(AnalyticsWindowRow.level_s == lv.LEVEL))
        a.write_blocks([more[2]])  # behind more[9]: the row is made
        assert _version(a) == 1
        a.write_blocks([more[5]])  # after more[2], behind more[9]
        assert _version(b) == 2


def test_a_block_waits_for_a_newer_uncommitted_one_and_counts_late(
        db_url: str, base: SampleArrays) -> None:
    """Two writers of one machine: the newer block's transaction has noted its blocks but not
    committed when an older block is written by another process. The older one is late for
    any reader that sees the newer: its writer waits for the newer one's commit and raises
    the version (read without waiting, it would find the old mark and not)."""
    blocks = _blocks(base, T0, 10.0)
    with open_store(db_url) as a, open_store(db_url) as b:
        a.add_machine(MID, wire_id=7, secret=b"k" * 32)
        a.write_blocks(blocks[:2])
        v0 = _version(a)
        noted, go = threading.Event(), threading.Event()

        class Held(Session):
            def commit(self) -> None:
                noted.set()
                assert go.wait(60)
                super().commit()

        errors: list[BaseException] = []

        def newer() -> None:
            try:
                pks = a._machine_pks({MID})
                writes.write(lambda: Held(a.engine), [blocks[9]], pks)
            except BaseException as exc:
                errors.append(exc)

        t = threading.Thread(target=newer)
        t.start()
        assert noted.wait(60)
        result: list[Any] = []
        w = threading.Thread(target=lambda: result.append(b.write_blocks([blocks[5]])))
        w.start()
        go.set()
        t.join(60)
        w.join(60)
        assert not errors and result == [1]
        assert _version(a) == v0 + 1
