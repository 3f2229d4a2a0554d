"""Export of raw and derived series (CSV and Parquet, streamed), the bulk sample reader behind
it, and the paged, filtered events and machines lists.

Data: exact kinematic samples (:func:`cranetwin.testing.blocks.kinematic_samples`) written
through the store's write path and processed by the twin worker, as in tests/test_api.py.
"""

from __future__ import annotations

import io
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session

from cranetwin.api import create_app
from cranetwin.api.services import Services
from cranetwin.model import load_machine
from cranetwin.samples import SampleArrays, SampleBlock
from cranetwin.service import export as ex
from cranetwin.service.timerange import TimeRange
from cranetwin.service.worker import TwinWorker
from cranetwin.settings import Settings
from cranetwin.storage import Event, Store
from cranetwin.storage.bulkread import read_samples_bulk
from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

pa = pytest.importorskip("pyarrow")
pq = pytest.importorskip("pyarrow.parquet")
pacsv = pytest.importorskip("pyarrow.csv")

pytestmark = pytest.mark.timeout(300)

T0 = 1795420800.0  # 2026-11-23T08:00:00Z
SPAN = 240.0
MID = "crane-1"


# --- the bulk reader equals Store.read_samples ----------------------------------------------
def _random_blocks(rng: np.random.Generator, machine_id: str) -> list[SampleBlock]:
    """Blocks with two channel layouts, two periods, NaN samples, overlaps and gaps."""
    out = []
    t = int(T0 * 1e9)
    layouts = [(("a", "b", "c"), (0.5, 1e-4, 1000.0)), (("b", "d"), (1e-4, 0.01))]
    for seq in range(120):
        chans, res = layouts[int(rng.integers(0, 2))]
        n = int(rng.integers(1, 60))
        period = int(rng.choice([10_000_000, 5_000_000]))
        steps = rng.integers(-30000, 30000, size=(n, len(chans)))
        if rng.random() < 0.5:  # wide values: other byte widths
            steps = steps * int(rng.choice([1, 1000, 10**9]))
        vals = steps * np.asarray(res)
        vals[rng.random(vals.shape) < 0.05] = np.nan
        out.append(SampleBlock(machine_id, seq, t, period, chans, res, vals))
        t += n * period + int(rng.choice([0, 0, period, 10**9]))
        if rng.random() < 0.15:  # the next block overlaps this one
            t -= (n // 2) * period + int(rng.integers(0, 3)) * 1000
    return out


@pytest.mark.timeout(120)
def test_bulk_read_equals_read_samples(db_url: str) -> None:
    store = Store.open(db_url)
    store.add_machine("m", wire_id=1, secret=b"s" * 32)
    rng = np.random.default_rng(7)
    res = store.write_batch(_random_blocks(rng, "m"))
    assert len(res.new) > 60
    lo, hi = store.data_range("m") or (0.0, 0.0)
    bounds = [(lo - 1, hi + 1), (lo, hi), (lo + 0.0137, hi - 3.3)]
    bounds += [tuple(sorted(rng.uniform(lo, hi, 2))) for _ in range(20)]
    with Session(store.engine) as s:
        for t0, t1 in bounds:
            ref = store.read_samples("m", t0, t1)
            got = read_samples_bulk(s, "m", t0, t1)
            assert got.channels == ref.channels
            assert got.period_ns == ref.period_ns
            assert got.t_ns is not None and ref.t_ns is not None
            np.testing.assert_array_equal(got.t_ns, ref.t_ns)
            np.testing.assert_array_equal(got.t_s, ref.t_s)
            np.testing.assert_array_equal(got.values, ref.values)  # NaN where NaN
    store.close()


# --- API on a populated store ----------------------------------------------------------------
@dataclass
class Ctx:
    client: TestClient
    services: Services
    keys: dict[str, str]

    def get(self, path: str, role: str = "fleet", **params: Any) -> Any:
        return self.client.get(path, params=params, headers={"X-API-Key": self.keys[role]})


@pytest.fixture(scope="module")
def ctx(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Ctx]:
    url = f"sqlite:///{tmp_path_factory.mktemp('export') / 'api.db'}"
    app = create_app(Settings(database_url=url, worker_in_process=False))
    machine = load_machine("patu655")
    with TestClient(app) as client:
        services: Services = app.state.services
        keys = {r: services.backend.create_key(r, f"test {r}")[1]
                for r in ("viewer", "fleet", "admin")}
        c = Ctx(client, services, keys)
        for mid, lat, lon in [(MID, 62.24, 25.75), ("crane-2", 60.17, 24.94),
                              ("crane-3", 62.30, 25.70), ("crane-4", None, None)]:
            body: dict[str, Any] = {"machine_id": mid, "model": "patu655"}
            if lat is not None:
                body["location"] = {"lat": lat, "lon": lon}
            r = client.post("/api/v1/machines", headers={"X-API-Key": keys["admin"]}, json=body)
            assert r.status_code == 201, r.text
        base = kinematic_samples(machine, 120.0)
        services.backend.store.write_blocks(list(tiled_blocks(MID, machine, T0, SPAN, 1.0,
                                                              base=base)))
        worker = TwinWorker(services.backend, services.settings, services.metrics,
                            services.fleet.replayer)
        worker.catch_up(services.backend.machine(MID))
        services.backend.store.add_events(
            [Event(MID, T0 + 1.0 + k, kind, sev, {"value": float(k), "limit": 1.0, "unit": "kg",
                                                   "component": "boom"})
             for k, (kind, sev) in enumerate([("x_over", "critical"), ("x_speed", "warning"),
                                              ("x_over", "critical"), ("x_stop", "info"),
                                              ("x_over", "warning")] * 3)])
        yield c


def _read(body: bytes, fmt: str) -> Any:
    if fmt == "csv":
        return pacsv.read_csv(io.BytesIO(body))
    return pq.read_table(io.BytesIO(body))


@pytest.mark.parametrize("fmt", ["csv", "parquet"])
def test_export_raw_equals_stored_samples(ctx: Ctx, fmt: str,
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ex, "CHUNK_SAMPLES", 997)  # many chunks, boundaries mid-block
    t0, t1 = T0 + 3.337, T0 + 171.01
    r = ctx.get(f"/api/v1/machines/{MID}/export", series="raw", format=fmt,
                **{"from": t0, "to": t1})
    assert r.status_code == 200, r.text
    assert r.headers["content-type"].startswith(ex.MEDIA_TYPES[fmt])
    assert f"{MID}-raw-" in r.headers["content-disposition"]
    tab = _read(r.content, fmt)
    ref = ctx.services.backend.read_samples(MID, t0, t1)
    machine = load_machine("patu655")
    assert tab.column_names == ["t_ns", "t_s"] + [c.name for c in machine.channels]
    assert tab.num_rows == ref.t_s.shape[0] > 16000
    assert ref.t_ns is not None
    np.testing.assert_array_equal(tab["t_ns"].to_numpy(), ref.t_ns)
    np.testing.assert_array_equal(tab["t_s"].to_numpy(), ref.t_s)
    for j, c in enumerate(ref.channels):
        col = tab[c].to_numpy(zero_copy_only=False).astype(np.float64)
        np.testing.assert_array_equal(col, ref.values[:, j])  # bit for bit
    if fmt == "parquet":
        assert pq.ParquetFile(io.BytesIO(r.content)).num_row_groups > 10  # one per chunk


def test_export_raw_nan_and_empty_range(ctx: Ctx) -> None:
    machine = load_machine("patu655")
    names = [c.name for c in machine.channels]
    arr = SampleArrays("x", np.array([0.0, 0.01]), tuple(names),
                       np.array([[np.nan] * len(names), [1.0] * len(names)]))
    chunk = {"t_ns": np.array([0, 10_000_000]), "t_s": arr.t_s,
             **{n: arr.values[:, j] for j, n in enumerate(names)}}
    sch = ex.schema("raw", machine)
    for fmt in ("csv", "parquet"):
        tab = _read(b"".join(ex.encode(iter([chunk]), sch, fmt)), fmt)
        assert tab[names[0]].null_count == 1
        empty = _read(b"".join(ex.encode(iter([]), sch, fmt)), fmt)
        assert empty.num_rows == 0 and empty.column_names == sch.names
    r = ctx.get(f"/api/v1/machines/{MID}/export", series="raw", format="csv",
                **{"from": T0 - 500, "to": T0 - 100})
    assert r.status_code == 200 and r.text.startswith('"t_ns","t_s"') and r.text.count("\n") == 1


@pytest.mark.timeout(30)
def test_csv_writes_integral_columns_as_ints_with_pyarrows_float_text() -> None:
    """Whole-number columns are written as int64 for speed: the text must be what pyarrow
    writes for the float64 values (so a pyarrow upgrade that changes either fails here)."""
    sch = pa.schema([("t_ns", pa.int64()), ("ints", pa.float64()), ("gaps", pa.float64()),
                     ("big", pa.float64()), ("negzero", pa.float64()),
                     ("fraction", pa.float64())])
    n = 8
    ints = np.array([0, -1, 4_560_000, 999_999_999, -999_999_999, 7, 12, 2_000_000],
                    dtype=np.float64)
    cols = {"t_ns": np.arange(n, dtype=np.int64), "ints": ints,
            "gaps": np.where(np.arange(n) % 3 == 0, np.nan, ints),
            "big": np.full(n, 1e10), "negzero": np.r_[-0.0, ints[1:]],
            "fraction": ints + 0.5}
    fast = ex._table(cols, sch, csv=True)
    assert [str(t) for t in fast.schema.types] == \
        ["int64", "int64", "int64", "double", "double", "double"]  # the fast path was taken
    assert fast["gaps"].null_count == 3
    text = b"".join(ex.encode(iter([cols]), sch, "csv"))
    floats = io.BytesIO()
    pacsv.write_csv(ex._table(cols, sch), floats)
    assert text == floats.getvalue()
    assert b"-0," in text and b"1e+10," in text and b"4560000," in text  # pyarrow's own forms


@pytest.mark.timeout(120)
def test_export_does_not_import_pandas() -> None:
    """pyarrow's ``pa.array`` imports pandas (0.3–0.5 s) to check its argument; the export
    builds its arrays from buffers so that a CLI run and a server's first export do not pay it."""
    import subprocess
    import sys

    code = """
import sys
import numpy as np
from cranetwin.model import load_machine
from cranetwin.service import export as ex
m = load_machine("patu655")
sch = ex.schema("raw", m)
n = 50
chunk = {"t_ns": np.arange(n, dtype=np.int64), "t_s": np.arange(n) / 100.0,
         **{c.name: np.where(np.arange(n) == 3, np.nan, np.arange(n) * 0.25) for c in m.channels}}
for fmt in ("csv", "parquet"):
    assert b"".join(ex.encode(iter([chunk]), sch, fmt))
print("pandas" in sys.modules)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=100)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"


@pytest.mark.parametrize("series", ["forces", "payload", "joint_loads"])
def test_export_twin_series_equal_minute_replays(ctx: Ctx, series: str) -> None:
    """A twin series is the replay of each minute with the worker's margin (values inside the
    range), across minute boundaries."""
    from cranetwin.importer.replay import result_columns
    from cranetwin.service.replayer import sample_rate_hz

    t0, t1 = T0 + 45.0, T0 + 75.0
    r = ctx.get(f"/api/v1/machines/{MID}/export", series=series, format="parquet",
                **{"from": t0, "to": t1})
    assert r.status_code == 200, r.text
    tab = pq.read_table(io.BytesIO(r.content))
    machine = load_machine("patu655")
    names = ex.twin_columns(series, machine)
    assert tab.column_names == names
    t = tab["t_s"].to_numpy()
    assert t[0] >= t0 and t[-1] < t1 and np.all(np.diff(t) > 0)
    assert abs(t.shape[0] - 30 * 100) <= 2
    b, m = ctx.services.backend, ctx.services.settings.twin_margin_s
    s = b.read_samples(MID, T0 + 60 - m, T0 + 120 + m)  # the second minute, as replayed
    res = ctx.services.fleet.replayer.replay(MID, machine, s, sample_rate_hz(s))
    cols = result_columns(res, machine)
    keep = (cols["t_s"] >= T0 + 60) & (cols["t_s"] < t1)
    got = t >= T0 + 60
    np.testing.assert_array_equal(t[got], cols["t_s"][keep])
    for n in names[1:]:
        np.testing.assert_allclose(tab[n].to_numpy()[got], cols[n][keep], rtol=1e-9, atol=1e-6)
    if series == "payload":  # the stored motion carries 400 kg in the second half-minute
        kg = tab["payload_kg"].to_numpy()
        assert np.nanmax(kg) > 300


def test_export_cycles_and_events(ctx: Ctx) -> None:
    from cranetwin.service.analytics import analytics_report

    rng = TimeRange(T0, T0 + 180.0)
    rep = analytics_report(ctx.services.backend, ctx.services.fleet.replayer,
                           load_machine("patu655"), MID, rng)
    r = ctx.get(f"/api/v1/machines/{MID}/export", series="cycles", format="csv",
                **{"from": rng.t0_s, "to": rng.t1_s})
    assert r.status_code == 200, r.text
    tab = _read(r.content, "csv")
    assert tab.num_rows == len(rep.cycles) > 0
    np.testing.assert_array_equal(tab["t_grab"].to_numpy(), [c.t_grab for c in rep.cycles])
    np.testing.assert_array_equal(tab["payload_kg"].to_numpy(),
                                  [c.payload_kg for c in rep.cycles])
    r = ctx.get(f"/api/v1/machines/{MID}/export", series="events", format="parquet",
                **{"from": T0, "to": T0 + SPAN})
    tab = _read(r.content, "parquet")
    listed = ctx.get(f"/api/v1/machines/{MID}/events", **{"from": T0, "to": T0 + SPAN}).json()
    assert tab.num_rows == len(listed) >= 15
    assert tab["kind"].to_pylist() == [e["kind"] for e in listed]
    assert tab["t_s"].to_pylist() == [e["t"] for e in listed]


@pytest.mark.parametrize("params", [{"series": "bogus"}, {"format": "xlsx"}])
def test_export_refuses_bad_series_or_format(ctx: Ctx, params: dict[str, str]) -> None:
    r = ctx.get(f"/api/v1/machines/{MID}/export", **{"from": T0, "to": T0 + 10}, **params)
    assert r.status_code == 422
    assert ctx.get(f"/api/v1/machines/{MID}/export", role="viewer",
                   **{"from": T0, "to": T0 + 10}).status_code == 403


# --- events: filters and paging ---------------------------------------------------------------
def test_events_filters_and_paging(ctx: Ctx) -> None:
    path = f"/api/v1/machines/{MID}/events"
    rng = {"from": T0, "to": T0 + SPAN}
    everything = ctx.get(path, "viewer", **rng).json()
    mine = [e for e in everything if e["kind"].startswith("x_")]
    assert len(mine) == 15
    crit = ctx.get(path, "viewer", severity="critical", **rng).json()
    assert [e["t"] for e in crit] == [e["t"] for e in everything if e["severity"] == "critical"]
    kinds = ctx.get(path, "viewer", kind="x_over,x_stop", severity="warning,info",
                    **rng).json()
    assert {(e["kind"], e["severity"]) for e in kinds} == {("x_over", "warning"),
                                                           ("x_stop", "info")}
    assert len(kinds) == 6
    timed = ctx.get(path, "viewer", kind="x_over,x_speed,x_stop",
                    **{"from": T0 + 3.0, "to": T0 + 6.0}).json()
    assert [e["t"] for e in timed] == [T0 + 3.0, T0 + 4.0, T0 + 5.0]
    # paging: follow Link until it ends; pages are disjoint and in order
    got: list[float] = []
    r = ctx.get(path, "viewer", limit=4, **rng)
    pages = 0
    while True:
        assert r.status_code == 200 and len(r.json()) <= 4
        got += [e["t"] for e in r.json()]
        pages += 1
        link = r.headers.get("link")
        if link is None:
            break
        url = link.split(";")[0].strip("<>")
        r = ctx.client.get(url, headers={"X-API-Key": ctx.keys["viewer"]})
    assert got == [e["t"] for e in everything] and pages == -(-len(everything) // 4)
    assert ctx.get(path, "viewer", severity="fatal", **rng).status_code == 422
    assert ctx.get(path, "viewer", cursor="x", **rng).status_code == 422


# --- machines: filters and paging -------------------------------------------------------------
def test_machines_paging_and_filters(ctx: Ctx) -> None:
    path = "/api/v1/machines"
    ids = [m["machine_id"] for m in ctx.get(path, "viewer").json()]
    assert ids == ["crane-1", "crane-2", "crane-3", "crane-4"]
    r = ctx.get(path, "viewer", limit=3)
    assert [m["machine_id"] for m in r.json()] == ids[:3]
    assert r.headers["x-total-count"] == "4"
    nxt = r.headers["link"].split(";")[0].strip("<>")
    r2 = ctx.client.get(nxt, headers={"X-API-Key": ctx.keys["viewer"]})
    assert [m["machine_id"] for m in r2.json()] == ids[3:] and "link" not in r2.headers
    assert [m["machine_id"] for m in ctx.get(path, "viewer", limit=2, offset=1).json()] \
        == ids[1:3]
    assert [m["machine_id"] for m in ctx.get(path, "viewer", cursor="crane-2").json()] \
        == ids[2:]
    box = ctx.get(path, "viewer", bbox="25.0,62.0,26.0,62.5").json()
    assert [m["machine_id"] for m in box] == ["crane-1", "crane-3"]
    assert ctx.get(path, "viewer", model="excavator").json() == []
    assert len(ctx.get(path, "viewer", model="patu655").json()) == 4
    # statuses: every machine is offline (old sample times) — a live filter keeps none
    statuses = {m["machine_id"]: m["status"] for m in ctx.get(path, "viewer").json()}
    for st in ("live", "idle", "offline"):
        want = [i for i in ids if statuses[i] == st]
        got = ctx.get(path, "viewer", status=st).json()
        assert [m["machine_id"] for m in got] == want
    two = ctx.get(path, "viewer", status="offline,idle,live", limit=2)
    assert len(two.json()) == 2 and "x-total-count" not in two.headers
    for bad in ({"status": "sleeping"}, {"bbox": "1,2,3"}, {"bbox": "30,0,20,1"},
                {"limit": 0}):
        assert ctx.get(path, "viewer", **bad).status_code == 422, bad


# --- streaming: the read-ahead thread ---------------------------------------------------------
@pytest.mark.timeout(30)
def test_prefetch_stops_when_the_consumer_goes_away() -> None:
    import threading

    made: list[int] = []

    def endless() -> Iterator[dict[str, Any]]:
        k = 0
        while True:
            made.append(k)
            yield {"t_s": np.array([float(k)])}
            k += 1

    before = threading.active_count()
    it = ex.prefetched(endless(), depth=2)
    assert [next(it)["t_s"][0] for _ in range(3)] == [0.0, 1.0, 2.0]
    it.close()  # what the server does when a client disconnects
    assert threading.active_count() == before
    n = len(made)
    assert n <= 3 + 2 + 1  # read ahead at most ``depth`` (+1 in hand), then stopped
    assert len(made) == n


@pytest.mark.timeout(30)
def test_prefetch_hands_on_a_producer_error() -> None:
    def failing() -> Iterator[dict[str, Any]]:
        yield {"t_s": np.zeros(1)}
        raise ValueError("disk gone")

    it = ex.prefetched(failing())
    next(it)
    with pytest.raises(ValueError, match="disk gone"):
        next(it)


# --- CLI --------------------------------------------------------------------------------------
def test_cli_export_writes_the_same_file(ctx: Ctx, tmp_path: Any,
                                         monkeypatch: pytest.MonkeyPatch) -> None:
    from typer.testing import CliRunner

    from cranetwin.cli import app

    monkeypatch.setenv("CRANETWIN_DATABASE_URL", ctx.services.settings.database_url)
    out = tmp_path / "raw.parquet"
    args = ["export", "--machine", MID, "--from", str(T0 + 1.5), "--to", str(T0 + 100.0),
            "--out", str(out), "-q"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    tab = pq.read_table(out)
    ref = ctx.services.backend.read_samples(MID, T0 + 1.5, T0 + 100.0)
    np.testing.assert_array_equal(tab["t_ns"].to_numpy(), ref.t_ns)
    np.testing.assert_array_equal(tab["lift_pA"].to_numpy(), ref.column("lift_pA"))
    bad = CliRunner().invoke(app, [*args[:-3], "--out", str(tmp_path / "x.xlsx")])
    assert bad.exit_code != 0 and not (tmp_path / "x.xlsx").exists()
    missing = CliRunner().invoke(app, [*args[:-3], "--out", str(tmp_path / "no" / "x.csv")])
    assert missing.exit_code != 0
