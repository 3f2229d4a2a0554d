"""MDF4 files whose channels sit in several channel groups at different rates: put on the
fastest group's time base by linear interpolation, dropouts and edges missing (NaN)."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np
import pytest

from cranetwin.importer import read_file
from cranetwin.importer.mdf import align_to
from cranetwin.model import Machine, load_machine
from cranetwin.samples import SampleArrays

asammdf = pytest.importorskip("asammdf")

T0 = 1_767_225_600.0


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load_machine("patu655")


@pytest.fixture(scope="module")
def rec(machine: Machine) -> SampleArrays:
    from cranetwin.sim import builtin_scenario, simulate

    s = simulate(machine, builtin_scenario("fig3", duration_s=6.0), wrenches=False).samples
    return SampleArrays("m1", s.t_s + T0, s.channels, s.values)


def _write(path: Path, groups: list[tuple[np.ndarray, dict[str, np.ndarray]]]) -> Path:
    mdf = asammdf.MDF(version="4.10")
    mdf.header.start_time = dt.datetime.fromtimestamp(T0, dt.UTC)
    for t, cols in groups:
        mdf.append([asammdf.Signal(v, t, name=n) for n, v in cols.items()])
    mdf.save(path, overwrite=True)
    mdf.close()
    return path


def _slow(rec: SampleArrays) -> tuple[list[str], list[str]]:
    slow = [c for c in rec.channels if c.endswith("_s") or c.startswith("slew")]
    return [c for c in rec.channels if c not in slow], slow


@pytest.mark.timeout(300)
@pytest.mark.parametrize("fast_first", [True, False])
def test_two_groups_at_100_and_50_hz_on_one_time_base(tmp_path: Path, machine: Machine,
                                                      rec: SampleArrays,
                                                      fast_first: bool) -> None:
    """Pressures at 100 Hz in one group, positions and slew channels at 50 Hz in another
    (starting 0.1 s later): the 100 Hz master is the time base whichever group comes first;
    the 50 Hz channels equal their own samples where the times coincide and the linear
    interpolation between them elsewhere; before their first sample they are missing."""
    fast, slow = _slow(rec)
    t_rel = rec.t_s - T0
    k = np.arange(10, t_rel.size, 2)  # 50 Hz, from 0.1 s
    g_fast = (t_rel, {c: rec.column(c) for c in fast})
    g_slow = (t_rel[k], {c: rec.column(c)[k] for c in slow})
    groups = [g_fast, g_slow] if fast_first else [g_slow, g_fast]
    got = read_file(_write(tmp_path / "two.mf4", groups), machine, machine_id="m1")
    s = got.samples
    assert got.report.rows_refused == 0, got.report.summary()
    np.testing.assert_allclose(s.t_s, rec.t_s, rtol=0, atol=1e-6)
    for c in fast:
        res = machine.channel(c).resolution
        np.testing.assert_allclose(s.column(c), rec.column(c), rtol=0, atol=res / 2 + 1e-9)
    for c in slow:
        res = machine.channel(c).resolution
        want = np.interp(t_rel, t_rel[k], rec.column(c)[k])
        want[t_rel < t_rel[10] - 1e-9] = np.nan
        g = s.column(c)
        np.testing.assert_array_equal(np.isnan(g), np.isnan(want), err_msg=c)
        ok = ~np.isnan(want)
        assert np.max(np.abs(g[ok] - want[ok])) <= res / 2 + 1e-9 * np.abs(want[ok]).max(), c
        # on the shared instants the value is the channel's own sample, not a blend
        np.testing.assert_allclose(g[k], rec.column(c)[k], rtol=0, atol=res / 2 + 1e-9)


@pytest.mark.timeout(300)
def test_a_dropout_in_the_slow_group_is_missing_not_bridged(tmp_path: Path,
                                                            machine: Machine,
                                                            rec: SampleArrays) -> None:
    fast, slow = _slow(rec)
    t_rel = rec.t_s - T0
    k = np.arange(0, t_rel.size, 2)
    k = k[(t_rel[k] < 2.0) | (t_rel[k] > 2.5)]  # 0.5 s without the slow group
    got = read_file(_write(tmp_path / "gap.mf4", [
        (t_rel, {c: rec.column(c) for c in fast}),
        (t_rel[k], {c: rec.column(c)[k] for c in slow})]), machine, machine_id="m1")
    s = got.samples
    rel = s.t_s - T0
    inside = (rel > 1.98 + 1e-6) & (rel < 2.52 - 1e-6)  # between the gap's neighbours
    for c in slow:
        assert np.all(np.isnan(s.column(c)[inside])), c
        assert not np.any(np.isnan(s.column(c)[~inside & (rel < 5.9)])), c
    assert not np.any(np.isnan(s.column(fast[0])))


@pytest.mark.timeout(60)
def test_align_to_by_hand() -> None:
    t = np.array([0.0, 0.02, 0.04, 0.10, 0.12])
    v = np.array([0.0, 2.0, np.nan, 8.0, 10.0])
    base = np.array([-0.01, 0.0, 0.01, 0.02, 0.03, 0.07, 0.11, 0.12, 0.13])
    got = align_to(base, t, v, max_gap_s=0.03)
    want = np.array([np.nan, 0.0, 1.0, 2.0, np.nan, np.nan, 9.0, 10.0, np.nan])
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_allclose(got[~np.isnan(want)], want[~np.isnan(want)], rtol=0, atol=1e-12)
