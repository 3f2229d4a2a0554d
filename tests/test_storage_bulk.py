"""The bulk insert's PostgreSQL arrays: encoded here in the binary format for numeric, text and
bytea columns, a column that is not all of its type left to psycopg; what is stored is what
was given."""

from __future__ import annotations

import math

import numpy as np
import pytest
from sqlalchemy import text

from cranetwin.storage import Store
from cranetwin.storage import analytics_windows as _aw  # noqa: F401  (its table mapped)
from cranetwin.storage.bulk import insert_rows, pg_binary_array

pytestmark = pytest.mark.timeout(120)


def test_binary_arrays_refuse_what_they_cannot_carry() -> None:
    assert pg_binary_array([1, 2.5], int) is None  # never truncated
    assert pg_binary_array([1.0, None], float) is None  # NULL is not NaN
    assert pg_binary_array(["a", 3], str) is None
    assert pg_binary_array([True, False], int) is None
    assert pg_binary_array([1, 2], bool) is None
    assert pg_binary_array([2**63], int) is None  # beyond int8: never wrapped
    assert pg_binary_array(np.array([1, 2], dtype=np.uint64), int) is None
    assert pg_binary_array([1, 2], int) is not None
    assert pg_binary_array(np.array([1.0, math.nan]), float) is not None
    assert pg_binary_array([], float) is not None


@pytest.mark.postgres
def test_rows_stored_through_binary_arrays_read_back_equal(pg_url: str) -> None:
    store = Store.open(pg_url)
    store.add_machine("m", 1, b"k" * 32)
    with store.engine.connect() as c:
        pk = c.execute(text("SELECT id FROM machines")).scalar_one()
    rng = np.random.default_rng(0)
    vals = rng.standard_normal(50) * 1e6
    vals[3] = math.nan
    rows = [(pk, f"chän-{i % 7}", 1, 10**12 + i, i, float(vals[i]), 2.0 * i, 0)
            for i in range(50)]  # an int (0) in a float column
    summ_cols = ("machine_pk", "channel", "level_s", "bucket_s", "n", "vmin", "vmax", "vsum")
    parts = [("m", 60, 10**18 + i, 10**18 + i + 1, i, bytes([i, 0, 255]) * i, 1.5, 0.0)
             for i in range(5)]
    part_cols = ("machine_id", "level_s", "t0_ns", "t1_ns", "n", "data", "operating_s", "idle_s")
    with store.engine.begin() as c:
        insert_rows(c, "summaries", summ_cols, rows)
        insert_rows(c, "analytics_windows", part_cols, parts)
        insert_rows(c, "analytics_windows", part_cols, [])
    with store.engine.connect() as c:
        got = c.execute(text(f"SELECT {', '.join(summ_cols)} FROM summaries ORDER BY bucket_s"))
        back = [tuple(r) for r in got]
        pgot = c.execute(text(f"SELECT {', '.join(part_cols)} FROM analytics_windows "
                              "ORDER BY t0_ns"))
        pback = [tuple(bytes(x) if isinstance(x, memoryview) else x for x in r) for r in pgot]
    assert len(back) == 50
    for want, have in zip(rows, back, strict=True):
        assert want[:5] == have[:5]
        assert (math.isnan(have[5]) if math.isnan(want[5]) else want[5] == have[5])
        assert want[6:] == have[6:]
    assert pback == parts
    store.close()
