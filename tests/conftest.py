"""Shared fixtures: ``db_url`` runs a test on SQLite (a temporary file) and on PostgreSQL.

PostgreSQL is ``postgresql+psycopg://postgres@127.0.0.1:5432/test`` (override with
``CRANETWIN_TEST_PG``); each test gets its own schema (dropped afterwards) through the URL's
``search_path``, so tests never see each other's rows. The PostgreSQL parameter is skipped, with
the reason, only when no server answers.
"""

from __future__ import annotations

import asyncio
import os
import threading
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from functools import cache
from pathlib import Path
from typing import Any

import pytest

PG_URL = os.environ.get("CRANETWIN_TEST_PG", "postgresql+psycopg://postgres@127.0.0.1:5432/test")


def _pg_conninfo() -> str:
    return PG_URL.replace("postgresql+psycopg://", "postgresql://", 1)


@cache
def pg_unreachable_reason() -> str | None:
    """None if the test PostgreSQL server answers, else why not."""
    try:
        import psycopg

        with psycopg.connect(_pg_conninfo(), connect_timeout=3) as conn:
            conn.execute("SELECT 1")
    except Exception as exc:  # any failure means: no usable server here
        return f"no PostgreSQL server reachable at {PG_URL}: {exc}"
    return None


@contextmanager
def fresh_pg_schema() -> Iterator[str]:
    """A PostgreSQL URL whose search_path is a fresh, empty schema, dropped on exit (the
    server must be reachable)."""
    import psycopg

    schema = f"t_{uuid.uuid4().hex[:12]}"
    with psycopg.connect(_pg_conninfo(), autocommit=True) as conn:
        conn.execute(f'CREATE SCHEMA "{schema}"')
    sep = "&" if "?" in PG_URL else "?"
    try:
        yield f"{PG_URL}{sep}options=-csearch_path%3D{schema}"
    finally:
        with psycopg.connect(_pg_conninfo(), autocommit=True) as conn:
            conn.execute(f'DROP SCHEMA "{schema}" CASCADE')


@pytest.fixture
def pg_url() -> Iterator[str]:
    """A PostgreSQL URL whose search_path is a fresh, empty schema (dropped afterwards)."""
    reason = pg_unreachable_reason()
    if reason:
        pytest.skip(reason)
    with fresh_pg_schema() as url:
        yield url


@pytest.fixture
def sqlite_url(tmp_path: Path) -> str:
    """A SQLite URL of a fresh file in the test's temporary directory."""
    return f"sqlite:///{tmp_path / 'cranetwin.db'}"


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def db_url(request: pytest.FixtureRequest) -> str:
    """The same test on SQLite and on PostgreSQL."""
    name = "pg_url" if request.param == "postgresql" else "sqlite_url"
    return str(request.getfixturevalue(name))


# --- ingest helpers -----------------------------------------------------------------------------
SECRET = b"test-secret-0123456789abcdef"


@contextmanager
def running_daemon(store: Any, bus: Any = None, **config: Any) -> Iterator[Any]:
    """An :class:`IngestDaemon` serving on a free loopback port in a background thread."""
    from cranetwin.ingest.daemon import DaemonConfig, IngestDaemon, new_event_loop

    cfg = DaemonConfig(**{"port": 0, "batch_wait_s": 0.01, "metrics_interval_s": 0.2,
                          **config})
    daemon = IngestDaemon(store, cfg, bus)
    errors: list[BaseException] = []

    def run() -> None:
        try:
            with asyncio.Runner(loop_factory=new_event_loop) as r:
                r.run(daemon.serve(install_signal_handlers=False))
        except BaseException as exc:  # surfaced by the test below
            errors.append(exc)

    t = threading.Thread(target=run, name="test-daemon", daemon=True)
    t.start()
    assert daemon.ready.wait(20), f"daemon did not start: {errors}"
    try:
        yield daemon
    finally:
        daemon.stop()
        t.join(60)
        assert not t.is_alive(), "daemon did not shut down"
        assert not errors, errors


def offset_pressures(samples: Any, machine: Any, level: float, seed: int,
                     channels: tuple[str, ...] = ("lift_pA", "lift_pB", "jib_pA", "jib_pB",
                                                  "ext_pA", "ext_pB")) -> Any:
    """``samples`` with a constant offset per channel of ``channels``, uniform within
    ±``level`` × the channel's full range (seeded): a sensor's offset within its stated
    accuracy."""
    import dataclasses

    import numpy as np

    rng = np.random.default_rng(seed)
    vals = samples.values.copy()
    ranges = {c.name: c.full_range for c in machine.channels}
    for name in channels:
        r = ranges[name]
        assert r is not None
        vals[:, samples.channels.index(name)] += rng.uniform(-1.0, 1.0) * level * r
    return dataclasses.replace(samples, values=vals)


def assert_same_progress(a: Any, b: Any) -> None:
    """Two worker progress records (:class:`cranetwin.service.worker.Progress`) equal field by
    field, floats to 1e-9 relative (1e-6 absolute)."""
    from cranetwin.service.backend import Progress

    assert isinstance(a, Progress) and isinstance(b, Progress)
    for k in Progress.__dataclass_fields__:
        x, y = getattr(a, k), getattr(b, k)
        assert x == (pytest.approx(y, rel=1e-9, abs=1e-6) if isinstance(y, float) else y), k


def stream_in_random_chunks(samples: Any, machine: Any, opt: Any, seed: int,
                            payload: float | None = None) -> Any:
    """``samples`` replayed through :class:`cranetwin.twin.TwinStream` in chunks of 1–399
    samples (seeded), the chunks' results concatenated: what a stream gives, to compare with
    the batch replay."""
    import numpy as np

    from cranetwin.samples import SampleArrays
    from cranetwin.twin import TwinResult, TwinStream

    st = TwinStream(machine, samples.channels, opt, payload)
    rng = np.random.default_rng(seed)
    parts: list[Any] = []
    i, n = 0, samples.t_s.shape[0]
    while i < n:
        j = min(n, i + int(rng.integers(1, 400)))
        out = st.push(SampleArrays(samples.machine_id, samples.t_s[i:j], samples.channels,
                                   samples.values[i:j]))
        if out is not None:
            parts.append(out)
        i = j
    last = st.flush()
    if last is not None:
        parts.append(last)
    return TwinResult.concat(parts)


# The files whose tests take minutes, run first: `make test` spreads whole files over two
# processes (pytest-xdist, --dist loadfile --no-loadscope-reorder: in collection order, not by
# number of tests), so a long file collected last would run alone at the end. Measured with
# --durations on a clean clone (2026-12-03).
LONG_FILES = ("test_twin_calibration.py", "test_chaos.py", "test_analytics_bench.py",
              "test_fleet_bench.py", "test_api.py", "test_api_schemathesis.py",
              "test_web_e2e.py", "test_mqtt_ingest.py", "test_worker_partitions.py")


# The files whose PostgreSQL tests find late data by the server's commit-order mark
# (pg_snapshot_xmin): a transaction open in any other session holds it back, so these run alone
# (marked `serial`: `make test` runs them after the parallel part, in one process).
SERIAL_FILES = ("test_worker_late.py", "test_worker_pass.py", "test_worker_commit.py",
                "test_worker_idle.py", "test_api_worker_history.py", "test_payload_redo.py",
                "test_worker_redo.py", "test_service_schedules.py")


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Put the tests of :data:`LONG_FILES` first, in that order (the rest keep theirs), and
    mark those of :data:`SERIAL_FILES` ``serial``."""
    rank = {name: i for i, name in enumerate(LONG_FILES)}
    items.sort(key=lambda it: rank.get(it.path.name, len(LONG_FILES)))  # stable
    for it in items:
        if it.path.name in SERIAL_FILES:
            it.add_marker(pytest.mark.serial)
