"""The API's replay cache and the known payload: a twin window replayed and cached by one API
process is replayed again after the machine's known payload is stored or deleted by another
process (a store of its own on the same database; ``cranetwin payload delete``), and still
served from the cache while the payload is unchanged (the key holds the payload's version,
``cranetwin.storage.payload_version``)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from typer.testing import CliRunner

from cranetwin.api import create_app
from cranetwin.api.services import Services
from cranetwin.model import load_machine
from cranetwin.samples import SampleArrays
from cranetwin.settings import Settings
from cranetwin.storage import open_store
from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

T0 = 1795420800.0  # a whole minute
MID = "crane-c"
MACHINE = load_machine("patu655")
KNOWN_KG = 2500.0
"""The known payload stored for the window (the samples' own: 400 kg)."""
WINDOW = {"from": T0 + 95.0, "to": T0 + 105.0, "rate_hz": 10}
"""A window in the second half of a minute: 400 kg lifted in the samples."""


@pytest.fixture(scope="module")
def base() -> SampleArrays:
    return kinematic_samples(MACHINE, 120.0)


@pytest.fixture
def api(db_url: str, base: SampleArrays) -> Iterator[tuple[TestClient, Services, str]]:
    """An API process on a database holding 4 minutes of samples; (client, services, key)."""
    with open_store(db_url) as store:
        store.add_machine(MID, wire_id=7, secret=b"k" * 32)
        store.write_blocks(list(tiled_blocks(MID, MACHINE, T0, 240.0, 1.0, base=base,
                                             origin_s=T0)))
    app = create_app(Settings(database_url=db_url, worker_in_process=False, warm_up=False,
                              heavy_processes=0))
    with TestClient(app) as client:
        services: Services = app.state.services
        yield client, services, services.backend.create_key("viewer", "test")[1]


def _twin(client: TestClient, key: str) -> tuple[bytes, Any]:
    r = client.get(f"/api/v1/machines/{MID}/twin", params=WINDOW, headers={"X-API-Key": key})
    assert r.status_code == 200, r.text
    return r.content, np.asarray(r.json()["payload"]["kg"], dtype=float)


def test_twin_cache_follows_a_payload_stored_and_deleted_by_another_process(
        api: tuple[TestClient, Services, str], db_url: str) -> None:
    from cranetwin.cli import app as cli_app

    client, services, key = api
    cache = services.fleet.twin_cache
    estimated, kg = _twin(client, key)
    assert np.all(np.abs(kg - 400.0) < 50.0)  # the estimate: the samples' own payload
    hits = cache.hits
    assert _twin(client, key)[0] == estimated and cache.hits == hits + 1  # cached

    t_ns = round((T0 + 60.0) * 1e9) + np.arange(6000, dtype=np.int64) * 10**7  # 60 s, 100 Hz
    with open_store(db_url) as other:  # not the API's store: what an import does
        assert other.write_payload(MID, np.full(t_ns.shape, KNOWN_KG), t_ns=t_ns).stored >= 1
    known, kg = _twin(client, key)
    assert known != estimated and np.all(np.abs(kg - KNOWN_KG) < 1.0), kg
    hits = cache.hits
    assert _twin(client, key)[0] == known and cache.hits == hits + 1  # cached again

    # deleted by the command (a process of its own: its own store)
    r = CliRunner().invoke(cli_app, ["payload", "delete", "--machine", MID, "--all",
                                     "--db", db_url])
    assert r.exit_code == 0, r.output
    back, kg = _twin(client, key)
    assert back == estimated  # the same replay as before the payload was stored
    with open_store(db_url) as other:  # a delete that removes nothing changes nothing
        assert other.delete_payload(MID, T0, T0 + 240.0).runs_deleted == 0
    hits = cache.hits
    assert _twin(client, key)[0] == estimated and cache.hits == hits + 1


def test_payload_version_is_raised_by_every_change_and_only_by_a_change(db_url: str) -> None:
    with open_store(db_url) as a, open_store(db_url) as b:
        a.add_machine(MID, wire_id=7, secret=b"k" * 32)
        a.add_machine("other", wire_id=8, secret=b"k" * 32)
        assert a.payload_version(MID) == 0
        t_ns = round(T0 * 1e9) + np.arange(100, dtype=np.int64) * 10**7
        assert a.write_payload(MID, np.full(100, 300.0), t_ns=t_ns).stored == 1
        assert b.payload_version(MID) == 1 and b.payload_version("other") == 0
        assert b.write_payload(MID, np.full(100, 300.0), t_ns=t_ns).stored == 0  # duplicate
        assert a.payload_version(MID) == 1
        assert a.write_payload(MID, np.full(100, np.nan), t_ns=t_ns + 10**9).stored == 1
        assert b.payload_version(MID) == 2  # not known values: still a change of the series
        cut = b.delete_payload(MID, T0 + 0.5, T0 + 0.6)
        assert cut.runs_cut == 1 and a.payload_version(MID) == 3
        assert b.delete_payload(MID, T0 + 0.5, T0 + 0.6).values_deleted == 0
        assert a.payload_version(MID) == 3
        starts = [r.t_first_ns for r in a.payload_stretches(MID)]
        assert b.delete_payload_runs(MID, starts[:1]) == 1 and a.payload_version(MID) == 4
        assert a.payload_version("other") == 0
        # read with the machine (the API's per-request read), not in listings
        assert a.get_machine(MID).payload_version == 4
        assert a.get_machine("other").payload_version == 0
        assert {m.payload_version for m in a.machines()} == {None}


def _key(key: Any) -> Any:
    assert key is not None  # a window that ends in stored data is cached
    return key


def test_twin_key_holds_the_version_read_with_the_record_else_reads_it(
        db_url: str, base: SampleArrays) -> None:
    from cranetwin.service.backend import Backend
    from cranetwin.service.fleet import FleetService
    from cranetwin.service.timerange import TimeRange

    b = Backend.open(db_url)
    b.store.add_machine(MID, wire_id=7, secret=b"k" * 32)
    b.store.write_blocks(list(tiled_blocks(MID, MACHINE, T0, 30.0, 1.0, base=base,
                                           origin_s=T0)))
    fleet = FleetService(Settings(database_url=db_url, worker_in_process=False), b)
    rng = TimeRange(T0, T0 + 10.0)
    t_ns = round(T0 * 1e9) + np.arange(10, dtype=np.int64) * 10**8
    b.store.write_payload(MID, np.full(10, 300.0), t_ns=t_ns)
    listed = next(r for r in b.list_machines() if r.machine_id == MID)
    assert listed.payload_version is None
    assert _key(fleet.twin_key(listed, rng, 10.0))[1] == 1  # read
    assert _key(fleet.twin_key(b.machine(MID), rng, 10.0))[1] == 1  # with the record
    b.store.delete_payload(MID, T0, T0 + 10.0)
    assert (_key(fleet.twin_key(listed, rng, 10.0))[1]
            == _key(fleet.twin_key(b.machine(MID), rng, 10.0))[1] == 2)
    b.close()


def test_two_api_processes_side_by_side_both_replay_after_a_payload_change(
        api: tuple[TestClient, Services, str], db_url: str) -> None:
    """Two API processes on one database (stateless, each with its own replay cache): both
    cached the window; the payload stored elsewhere, both give the known payload."""
    client_a, _, key = api  # the key is stored in the database: the second process knows it
    app_b = create_app(Settings(database_url=db_url, worker_in_process=False, warm_up=False,
                                heavy_processes=0))
    with TestClient(app_b) as client_b:
        before = _twin(client_a, key)[0]
        assert _twin(client_b, key)[0] == before
        assert app_b.state.services.fleet.twin_cache.hits == 0
        assert _twin(client_b, key)[0] == before
        assert app_b.state.services.fleet.twin_cache.hits == 1
        t_ns = round((T0 + 60.0) * 1e9) + np.arange(6000, dtype=np.int64) * 10**7
        with open_store(db_url) as other:
            other.write_payload(MID, np.full(t_ns.shape, KNOWN_KG), t_ns=t_ns)
        for client in (client_a, client_b):
            body, kg = _twin(client, key)
            assert body != before and np.all(np.abs(kg - KNOWN_KG) < 1.0)
