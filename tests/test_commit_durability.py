"""The twin worker's connections commit without waiting for the disk flush (derived data is
replayed again if a server crash loses it); every other connection keeps durable commits."""

from __future__ import annotations

import pytest
from sqlalchemy import text

from cranetwin.storage.engine import make_engine, relax_commit_durability


@pytest.mark.postgres
@pytest.mark.timeout(60)
def test_only_the_relaxed_engine_commits_asynchronously(pg_url: str) -> None:
    durable, relaxed = make_engine(pg_url), make_engine(pg_url)
    try:
        with relaxed.connect() as c:  # a pooled connection from before: replaced
            c.execute(text("SELECT 1"))
        relax_commit_durability(relaxed)
        for _ in range(3):  # every connection of the pool, not just the first
            with relaxed.connect() as c, durable.connect() as d:
                assert c.execute(text("SHOW synchronous_commit")).scalar() == "off"
                assert d.execute(text("SHOW synchronous_commit")).scalar() == "on"
    finally:
        durable.dispose()
        relaxed.dispose()


@pytest.mark.timeout(60)
def test_sqlite_is_left_as_it_is(sqlite_url: str) -> None:
    engine = make_engine(sqlite_url)
    relax_commit_durability(engine)
    with engine.connect() as c:
        assert c.execute(text("SELECT 1")).scalar() == 1
    engine.dispose()
