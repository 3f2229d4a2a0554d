"""A known payload column imported into storage (``cranetwin import`` with the mapping's
[payload]) and used by every replay of a stored range: the twin worker and the service's
replayer (the API's twin routes), and ``cranetwin replay --machine``. Without a stored series
they estimate the payload as before."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import func, select
from sqlalchemy.orm import Session
from typer.testing import CliRunner

from cranetwin.importer import import_file, read_file
from cranetwin.model import Machine, load_machine
from cranetwin.samples import SampleArrays
from cranetwin.storage import Store
from cranetwin.storage.payloads import PayloadRunRow

T0 = 1_767_225_600.0  # a whole minute: the worker's first window is [T0, T0 + 60)
MAP = '[payload]\ncolumn = "hook_t"\nunit = "t"\n'
SECRET = b"0123456789abcdef0123456789abcdef"


@dataclass(frozen=True)
class Logged:
    """A 100 s log-loading recording as a logger CSV with the known payload in tonnes (lifts
    9–23 s, 36–50 s, 63–77 s, 90–100 s), its mapping, the sample times and the true payload."""

    csv: Path
    mapping: Path
    t_s: np.ndarray
    truth_kg: np.ndarray


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load_machine("patu655")


@pytest.fixture(scope="module")
def logged(machine: Machine, tmp_path_factory: pytest.TempPathFactory) -> Logged:
    from cranetwin.sim import builtin_scenario, simulate

    rec = simulate(machine, builtin_scenario("log-loading", duration_s=100.0), wrenches=False)
    s = rec.samples
    truth = np.interp(s.t_s, rec.truth.t_s, rec.truth.payload_kg)
    d = tmp_path_factory.mktemp("payload_store")
    f = d / "logger.csv"
    np.savetxt(f, np.column_stack([s.t_s + T0, s.values, truth / 1000.0]), delimiter=",",
               fmt=["%.6f", *["%.10g"] * (len(s.channels) + 1)],
               header=",".join(["t_s", *s.channels, "hook_t"]), comments="")
    m = d / "map.toml"
    m.write_text(MAP)
    return Logged(f, m, s.t_s + T0, truth)


def _runs(store: Store) -> int:
    with Session(store.engine) as s:
        return int(s.scalar(select(func.count()).select_from(PayloadRunRow)) or 0)


@pytest.mark.timeout(300)
def test_import_stores_the_payload_column_once(db_url: str, machine: Machine,
                                               logged: Logged) -> None:
    with Store.open(db_url) as store:
        store.add_machine("known", 1, SECRET)
        first = import_file(logged.csv, machine, store, "known", logged.mapping)
        assert first.stored > 1 and first.payload_runs_stored == first.stored
        assert first.report.payload_rows == logged.t_s.size and first.report.payload_refused == 0
        file = read_file(logged.csv, machine, logged.mapping)
        assert file.payload_kg is not None
        got = store.read_payload("known", T0 - 1.0, T0 + 200.0)
        # the stored series is the file's, at the stored samples' times exactly
        assert np.array_equal(got.t_ns, file.samples.t_ns)
        assert np.array_equal(got.payload_kg, file.payload_kg, equal_nan=True)
        np.testing.assert_allclose(got.payload_kg, logged.truth_kg, rtol=1e-9, atol=1e-6)
        runs = _runs(store)
        again = import_file(logged.csv, machine, store, "known", logged.mapping)
        assert (again.stored, again.duplicate) == (0, first.stored)
        assert (again.payload_runs_stored, again.payload_runs_duplicate,
                again.payload_runs_differing) == (0, first.stored, 0)
        assert _runs(store) == runs  # stored once
        # samples imported without the column first: importing with it adds the series
        store.add_machine("later", 2, SECRET[::-1])
        plain = import_file(logged.csv, machine, store, "later")
        assert plain.payload_runs_stored == 0 and store.read_payload("later", 0, 4e9).n == 0
        added = import_file(logged.csv, machine, store, "later", logged.mapping)
        assert added.stored == 0 and added.duplicate == plain.stored
        assert added.payload_runs_stored == plain.stored
        assert np.array_equal(store.read_payload("later", 0, 4e9).payload_kg, file.payload_kg,
                              equal_nan=True)


@pytest.mark.timeout(300)
def test_payload_out_of_range_is_refused_with_row_and_column(machine: Machine, logged: Logged,
                                                             tmp_path: Path) -> None:
    """A negative payload and one above 3 × the largest rated payload (3000 kg for the
    PATU 655's chart) are refused, never clipped: named by row and column, not known there
    (NaN stored), while their rows' samples are imported; exit status 1."""
    from cranetwin.cli import app

    rows = logged.csv.read_text().splitlines()
    for row, val in ((5, "-0.2"), (700, "99")):  # data rows (row 1 = the first after the header)
        rows[row] = rows[row].rsplit(",", 1)[0] + "," + val
    f = tmp_path / "bad.csv"
    f.write_text("\n".join(rows) + "\n")
    db = f"sqlite:///{tmp_path / 'c.db'}"
    with Store.open(db) as store:
        store.add_machine("known", 1, SECRET)
    r = CliRunner().invoke(app, ["import", str(f), "--machine", "known", "--mapping",
                                 str(logged.mapping), "--db", db, "-q"])
    assert r.exit_code == 1, r.output
    assert "row 5 (line 6), column 'hook_t': -0.2 t: negative payload" in r.output, r.output
    assert ("row 700 (line 701), column 'hook_t': 99 t: payload above the largest accepted, "
            "3000 kg") in r.output, r.output
    assert f"{logged.t_s.size} rows read, {logged.t_s.size} accepted, 0 refused" in r.output
    assert "2 value(s) refused" in r.output
    with Store.open(db) as store:
        got = store.read_payload("known", T0 - 1.0, T0 + 200.0)
        assert got.n == logged.t_s.size
        assert np.isnan(got.payload_kg[[4, 699]]).all()
        ok = np.ones(got.n, dtype=bool)
        ok[[4, 699]] = False
        np.testing.assert_allclose(got.payload_kg[ok], logged.truth_kg[ok], rtol=1e-9, atol=1e-6)


@pytest.mark.timeout(300)
def test_a_load_cells_zero_offset_within_the_tolerance_is_read_as_zero(
        machine: Machine, logged: Logged, tmp_path: Path) -> None:
    """With ``[checks] range_tolerance = 0.01`` (30 kg of the 3000 kg accepted), −20 kg at an
    empty hook is read as 0 kg and counted, −50 kg is refused as before; the exit status says
    only the refusal."""
    from cranetwin.cli import app

    rows = logged.csv.read_text().splitlines()
    for row, val in ((3, "-0.02"), (4, "-0.05")):
        rows[row] = rows[row].rsplit(",", 1)[0] + "," + val
    f = tmp_path / "zero.csv"
    f.write_text("\n".join(rows) + "\n")
    mapping = tmp_path / "tol.toml"
    mapping.write_text(MAP + "\n[checks]\nrange_tolerance = 0.01\n")
    db = f"sqlite:///{tmp_path / 'z.db'}"
    with Store.open(db) as store:
        store.add_machine("known", 1, SECRET)
    r = CliRunner().invoke(app, ["import", str(f), "--machine", "known", "--mapping",
                                 str(mapping), "--db", db, "-q"])
    assert r.exit_code == 1, r.output
    assert "1 value(s) refused (not known there), 1 below zero within the tolerance read as " \
           "0 kg" in r.output, r.output
    assert "row 4 (line 5), column 'hook_t': -0.05 t: negative payload, beyond −30 kg" \
           in r.output, r.output
    with Store.open(db) as store:
        got = store.read_payload("known", T0 - 1.0, T0 + 200.0)
    assert got.payload_kg[2] == 0.0 and np.isnan(got.payload_kg[3])


@pytest.fixture(scope="module")
def imported(machine: Machine, logged: Logged,
             tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A SQLite store with the recording imported twice: machine ``known`` with the payload
    column, machine ``plain`` without."""
    db = f"sqlite:///{tmp_path_factory.mktemp('imported') / 'c.db'}"
    with Store.open(db) as store:
        store.add_machine("known", 1, SECRET)
        store.add_machine("plain", 2, SECRET[::-1])
        import_file(logged.csv, machine, store, "known", logged.mapping)
        import_file(logged.csv, machine, store, "plain")
    yield db


@pytest.mark.timeout(300)
def test_payload_of_blocks_storage_refuses_is_not_kept(machine: Machine, logged: Logged,
                                                       tmp_path: Path) -> None:
    """Samples stored without a payload; another file over the same times (other bytes: its
    blocks overlap and are refused) brings a payload column: its runs, written before the
    blocks, are deleted again, and the stored samples keep no payload."""
    db = f"sqlite:///{tmp_path / 'c.db'}"
    other = tmp_path / "other.csv"
    other.write_text(logged.csv.read_text().replace("\n", "\r\n"))  # same rows, other bytes
    with Store.open(db) as store:
        store.add_machine("known", 1, SECRET)
        first = import_file(logged.csv, machine, store, "known")
        got = import_file(other, machine, store, "known", logged.mapping)
        assert got.stored == 0 and got.refused["overlap"] == first.stored
        assert got.payload_runs_stored == 0 and _runs(store) == 0
        assert store.read_payload("known", 0.0, 4e9).n == 0


@pytest.mark.timeout(600)
def test_worker_and_replayer_use_the_stored_payload(db_url: str, machine: Machine,
                                                    logged: Logged) -> None:
    """The twin worker's window and the service's replays of a stored range take the stored
    payload where known (σ 0, the known value); a machine without one gets the estimate, which
    differs from it."""
    from cranetwin.service.backend import Backend
    from cranetwin.service.replayer import Replayer
    from cranetwin.service.worker import TwinWorker
    from cranetwin.settings import Settings

    b = Backend.open(db_url)
    try:
        b.store.add_machine("known", 1, SECRET)
        b.store.add_machine("plain", 2, SECRET[::-1])
        import_file(logged.csv, machine, b.store, "known", logged.mapping)
        import_file(logged.csv, machine, b.store, "plain")
        worker = TwinWorker(b, Settings(database_url="unused", worker_in_process=False))
        # a pass (its reads know which machines have payload runs, and where: on PostgreSQL
        # the plain machine's window reads none)
        asked: list[str] = []
        read = worker.replayer.payload_of
        assert read is not None
        worker.replayer.payload_of = lambda m, a, z: (asked.append(m), read(m, a, z))[1]
        assert worker.run_once() == 2
        assert asked == (["known"] if "postgresql" in db_url else ["known", "plain"])
        sec = np.floor(logged.t_s - T0).astype(int)
        inside = sec < 60
        truth_mean = np.bincount(sec[inside], logged.truth_kg[inside]) / np.bincount(sec[inside])
        per: dict[str, np.ndarray] = {}
        for mid in ("known", "plain"):
            sm = b.store.summaries(mid, ["payload"], T0, T0 + 60.0, max_points=60)
            assert sm.bucket_s == 1 and sm.t_s.shape == (60,)
            per[mid] = sm.mean[:, 0]
        # the worker's window: the known payload, second by second
        np.testing.assert_allclose(per["known"], truth_mean, rtol=0, atol=1e-3)
        assert np.max(np.abs(per["plain"] - truth_mean)) > 20.0  # the estimate lags grabs

        samples = b.read_samples("known", T0 + 5.0, T0 + 45.0)
        with_store = Replayer(b.store.read_payload)
        res = with_store.replay("known", b.model_of(b.machine("known")), samples, 100.0)
        t_res = np.round((res.t_s - T0) * 100.0).astype(int)
        truth = logged.truth_kg[t_res]
        assert np.all(res.payload_std_kg == 0.0)
        np.testing.assert_allclose(res.payload_kg, truth, rtol=1e-9, atol=1e-6)
        est = Replayer().replay("known", b.model_of(b.machine("known")), samples, 100.0)
        assert np.all(est.payload_std_kg > 0.0)
        assert np.max(np.abs(est.payload_kg - truth)) > 20.0
        # no stored series: the same replay as without a reader
        plain = b.read_samples("plain", T0 + 5.0, T0 + 45.0)
        a = with_store.replay("plain", b.model_of(b.machine("plain")), plain, 100.0)
        np.testing.assert_array_equal(a.payload_kg, est.payload_kg)
        np.testing.assert_array_equal(a.id_torque, est.id_torque)
    finally:
        b.close()


@pytest.mark.timeout(600)
def test_cli_replay_of_a_stored_range_uses_the_stored_payload(imported: str, logged: Logged,
                                                              tmp_path: Path) -> None:
    from cranetwin.cli import app

    def run(mid: str) -> tuple[str, dict[str, np.ndarray]]:
        out = tmp_path / f"{mid}.csv"
        r = CliRunner().invoke(app, ["replay", "--machine", mid, "--from", str(T0 + 5.0),
                                     "--to", str(T0 + 45.0), "--db", imported, "--out",
                                     str(out), "-q"])
        assert r.exit_code == 0, r.output
        names = out.read_text().split("\n", 1)[0].split(",")
        data = np.loadtxt(out, delimiter=",", skiprows=1)
        return r.output, {n: data[:, i] for i, n in enumerate(names)}

    said, known = run("known")
    assert ("known payload (stored with the samples) used in the inverse dynamics at "
            "100.0 % of the samples") in said, said
    i = 500 + np.arange(known["t_s"].shape[0])  # one row per sample from T0 + 5 s (the CSV
    assert i[-1] == 4499  # keeps 10 digits of t_s: whole seconds)
    np.testing.assert_allclose(known["payload_kg"], logged.truth_kg[i], rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(known["payload_known_kg"], logged.truth_kg[i], rtol=1e-9,
                               atol=1e-6)
    assert np.all(known["payload_std_kg"] == 0.0)
    said, plain = run("plain")
    assert "known payload" not in said and "payload_known_kg" not in plain
    assert np.all(plain["payload_std_kg"] > 0.0)
    assert np.abs(known["torque_id.theta1"] - plain["torque_id.theta1"]).max() > 1e3


@pytest.mark.timeout(30)
def test_payload_limit_from_the_mapping_or_the_rated_chart(machine: Machine) -> None:
    from cranetwin.importer import ImportFileError, mapping_from_dict
    from cranetwin.importer.payload import PayloadCheck, payload_limit_kg

    assert payload_limit_kg(machine, None) == 3000.0  # 3 × 1000 kg, the chart's largest
    m = mapping_from_dict({"payload": {"column": "w", "unit": "t", "max": 2.5},
                           "checks": {"range_tolerance": 0.1}}, machine)
    assert m.payload_max_kg == 2500.0 and payload_limit_kg(machine, m.payload_max_kg) == 2500.0
    with pytest.raises(ImportFileError, match="payload.max must be a number > 0"):
        mapping_from_dict({"payload": {"column": "w", "max": -1}}, machine)
    check = PayloadCheck("w", "t", 1000.0, 2500.0, 0.1)
    kg = np.array([0.0, 2750.0, 2750.5, -250.5, np.nan, np.inf, -1e-3])
    out, neg, high, zeroed = check.apply(kg, np.arange(1, 8), None)
    assert [r.row for r in neg] == [4] and [r.row for r in high] == [3, 6]
    assert out[0] == 0.0 and out[1] == 2750.0 and np.isnan(out[2:6]).all()
    assert out[6] == 0.0 and zeroed == 1  # below zero within 0.1 × 2500 kg: read as 0
    unbounded = PayloadCheck("w", "kg", 1.0, None)
    out, neg, high, zeroed = unbounded.apply(np.array([1e9, -0.1]), np.arange(1, 3), None)
    assert out[0] == 1e9 and [r.row for r in neg] == [2] and not high and zeroed == 0


@pytest.mark.timeout(300)
def test_api_twin_route_gives_the_stored_payload(imported: str, logged: Logged) -> None:
    """GET /machines/{id}/twin: ``payload.kg`` is the stored known payload and ``std_kg`` 0
    where one was imported; the estimate (σ > 0) for a machine without one."""
    from fastapi.testclient import TestClient

    from cranetwin.api import create_app
    from cranetwin.settings import Settings

    app = create_app(Settings(database_url=imported, worker_in_process=False))
    with TestClient(app) as client:
        key = app.state.services.backend.create_key("viewer", "test")[1]

        def twin(mid: str) -> dict[str, list[float]]:
            r = client.get(f"/api/v1/machines/{mid}/twin", headers={"X-API-Key": key},
                           params={"from": T0 + 10.0, "to": T0 + 30.0, "rate_hz": 100})
            assert r.status_code == 200, r.text
            return dict(r.json()["payload"])

        known = twin("known")
        i = np.round((np.array(known["t"]) - T0) * 100.0).astype(int)
        assert i[0] == 1000 and 1900 < i.size <= 2000
        np.testing.assert_allclose(known["kg"], logged.truth_kg[i], rtol=0, atol=0.006)
        assert np.all(np.array(known["std_kg"]) == 0.0)
        plain = twin("plain")
        assert np.all(np.array(plain["std_kg"]) > 0.0)
        assert np.max(np.abs(np.array(plain["kg"]) - logged.truth_kg[i])) > 20.0


@pytest.mark.postgres
@pytest.mark.timeout(300)
def test_import_into_a_sharded_store_puts_the_payload_on_the_machines_shard(
        machine: Machine, logged: Logged) -> None:
    import uuid

    import psycopg

    from conftest import PG_URL, _pg_conninfo, pg_unreachable_reason
    from cranetwin.storage.sharding import partition_of
    from cranetwin.storage.shardmap import ShardMap
    from cranetwin.storage.shards import ShardedStore

    reason = pg_unreachable_reason()
    if reason:
        pytest.skip(reason)
    names = [f"t_{uuid.uuid4().hex[:12]}" for _ in range(2)]
    with psycopg.connect(_pg_conninfo(), autocommit=True) as conn:
        for n in names:
            conn.execute(f'CREATE SCHEMA "{n}"')
    sep = "&" if "?" in PG_URL else "?"
    urls = [f"{PG_URL}{sep}options=-csearch_path%3D{n}" for n in names]
    st = ShardedStore.open_map(ShardMap.parse({"0-1": urls[0], "2-3": urls[1]}, 4))
    try:
        mid = next(f"crane-{w}" for w in range(1, 99) if partition_of(f"crane-{w}", 4) >= 2)
        st.add_machine(mid, 7, SECRET)
        got = import_file(logged.csv, machine, st, mid, logged.mapping)
        assert got.stored > 1 and got.payload_runs_stored == got.stored
        assert [_runs(s) for s in st.shards] == [0, got.stored]  # the machine's shard only
        back = st.read_payload(mid, T0 - 1.0, T0 + 200.0)
        np.testing.assert_allclose(back.payload_kg, logged.truth_kg, rtol=1e-9, atol=1e-6)
    finally:
        st.close()
        with psycopg.connect(_pg_conninfo(), autocommit=True) as conn:
            for n in names:
                conn.execute(f'DROP SCHEMA "{n}" CASCADE')


@pytest.mark.timeout(120)
def test_cli_calibrate_of_a_stored_range_fits_with_the_stored_payload(
        imported: str, logged: Logged, monkeypatch: pytest.MonkeyPatch) -> None:
    """``cranetwin calibrate --machine ID --from --to``: the stored range's samples and the
    known payload stored with them go to the fit (``--payload-column compare``: not); without a
    stored series the fit estimates the mass."""
    import cranetwin.twin.calibration as calmod
    from cranetwin.cli import app
    from cranetwin.twin.calibration import Calibration

    seen: list[tuple[object, object]] = []

    def fake(samples: object, machine: object, **kw: object) -> Calibration:
        seen.append((samples, kw.get("payload_kg")))
        return Calibration((), 0.5, 0.1, 90.0, 1000, (), (1, 100),
                           payload_known=kw.get("payload_kg") is not None)

    monkeypatch.setattr(calmod, "calibrate", fake)

    def run(mid: str, *extra: str) -> str:
        r = CliRunner().invoke(app, ["calibrate", "--machine", mid, "--from", str(T0 + 5.0),
                                     "--to", str(T0 + 45.0), "--db", imported, *extra],
                               terminal_width=200)
        assert r.exit_code == 0, r.output
        return r.output

    said = run("known")
    samples, kg = seen[-1]
    assert isinstance(kg, np.ndarray) and isinstance(samples, SampleArrays)
    t = samples.t_s
    assert t.shape[0] == 4000 and t[0] == pytest.approx(T0 + 5.0)
    np.testing.assert_allclose(kg, logged.truth_kg[500:4500], rtol=1e-9, atol=1e-6)
    assert "Tool mass error" in said and f"known [{T0 + 5.0}" in said
    run("known", "--payload-column", "compare")
    assert seen[-1][1] is None
    run("plain")
    assert seen[-1][1] is None
    bad = CliRunner().invoke(app, ["calibrate", "--machine", "known", "--from", str(T0)])
    assert bad.exit_code != 0


# runs alone (`make test`'s serial part): the per-machine catch_up finds late data by the
# server-wide commit-order mark, which another session's open transaction holds back
@pytest.mark.serial
@pytest.mark.timeout(600)
def test_cli_import_list_and_delete_of_a_payload_behind_the_worker(
        db_url: str, machine: Machine, logged: Logged) -> None:
    """``cranetwin import`` of the payload column for samples the worker has processed has
    their window processed again with it; ``cranetwin payload list`` shows the series and
    ``cranetwin payload delete`` removes it, after which the window is the estimate's again."""
    from cranetwin.cli import app
    from cranetwin.service.backend import Backend
    from cranetwin.service.worker import TwinWorker
    from cranetwin.settings import Settings

    def cli(*args: str) -> str:
        r = CliRunner().invoke(app, [*args, "--db", db_url])
        assert r.exit_code == 0, r.output
        return r.output

    sec = np.floor(logged.t_s - T0).astype(int)
    inside = sec < 60
    truth_mean = np.bincount(sec[inside], logged.truth_kg[inside]) / np.bincount(sec[inside])
    b = Backend.open(db_url)
    try:
        b.store.add_machine("known", 1, SECRET)
        import_file(logged.csv, machine, b.store, "known")  # the samples, without the column
        worker = TwinWorker(b, Settings(database_url="unused", worker_in_process=False),
                            clock=lambda: 0.0)
        rec = b.machine("known")

        def window() -> np.ndarray:
            sm = b.store.summaries("known", ["payload"], T0, T0 + 60.0, max_points=60)
            return np.asarray(sm.mean[:, 0])

        assert worker.catch_up(rec) == 1
        estimate = window()
        assert np.max(np.abs(estimate - truth_mean)) > 20.0
        said = cli("import", str(logged.csv), "--machine", "known", "--mapping",
                   str(logged.mapping), "-q")
        assert "known payload:" in said and "run(s) stored" in said, said
        assert worker.catch_up(rec) == 1  # the processed window, with the known payload
        np.testing.assert_allclose(window(), truth_mean, rtol=0, atol=1e-3)
        assert worker.catch_up(rec) == 0

        listed = cli("payload", "list", "--machine", "known")
        lines = listed.strip().splitlines()
        assert len(lines) == 1 and "2026-01-01T00:00:00.000Z – 2026-01-01T00:01:40.000Z" in \
            lines[0] and f"{logged.t_s.size} value(s), {logged.t_s.size} known" in lines[0], \
            listed
        import json

        js = json.loads(cli("payload", "list", "--machine", "known", "--json"))
        assert js[0]["max_kg"] == pytest.approx(logged.truth_kg.max(), abs=1e-6)

        said = cli("payload", "delete", "--machine", "known", "--from", str(T0 + 50.0),
                   "--to", "2026-01-01T00:01:10", "--json")
        got = json.loads(said)
        assert got["values_deleted"] == 2000 and got["runs_cut"] >= 1, got
        kept = b.store.read_payload("known", T0, T0 + 200.0)
        assert kept.n == logged.t_s.size - 2000
        assert not np.any((kept.t_s >= T0 + 50.0) & (kept.t_s < T0 + 70.0))
        assert worker.catch_up(rec) == 1  # the window: estimated from 50 s on again
        w = window()
        np.testing.assert_allclose(w[:48], truth_mean[:48], rtol=0, atol=1e-3)
        np.testing.assert_allclose(w[52:], estimate[52:], rtol=0, atol=1e-3)

        said = cli("payload", "delete", "--machine", "known", "--all")
        assert f"{logged.t_s.size - 2000} value(s) deleted" in said, said
        assert b.store.read_payload("known", 0.0, 4e9).n == 0
        assert "no known payload stored" in cli("payload", "list", "--machine", "known")
        assert worker.catch_up(rec) == 1
        np.testing.assert_allclose(window(), estimate, rtol=0, atol=1e-6)
        r = CliRunner().invoke(app, ["payload", "delete", "--machine", "known", "--from",
                                     str(T0), "--db", db_url])
        assert r.exit_code != 0 and "--all" in str(r.exception), r.output  # (main(): status 2)
    finally:
        b.close()
