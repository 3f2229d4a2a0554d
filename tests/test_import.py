"""cranetwin.importer: a simulated recording written out as a user's logger would (other units,
pin-to-pin lengths, other time formats, CSV / Parquet / MDF4), imported and read back equal
within each channel's resolution; bad rows refused with row and column; idempotent storage."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from cranetwin.importer import (
    ImportFileError,
    check_rod_positions,
    import_file,
    mapping_from_dict,
    read_file,
)
from cranetwin.model import Machine, load_machine
from cranetwin.samples import SampleArrays

pytestmark = pytest.mark.timeout(120)

T0 = 1_767_225_600.0  # 2026-01-01T00:00:00Z
PSI = 6894.757293168361


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load_machine("patu655")


@pytest.fixture(scope="module")
def rec(machine: Machine) -> SampleArrays:
    from cranetwin.sim import builtin_scenario, simulate

    r = simulate(machine, builtin_scenario("fig3", duration_s=6.0), wrenches=False)
    s = r.samples
    return SampleArrays("m1", s.t_s + T0, s.channels, s.values)


def _same(machine: Machine, got: SampleArrays, want: SampleArrays) -> None:
    """Equal within half a resolution step per channel (NaN where NaN), same times to 1 µs."""
    assert got.values.shape == want.values.shape
    np.testing.assert_allclose(got.t_s, want.t_s, rtol=0, atol=1e-6)
    for name in want.channels:
        g, w = got.column(name), want.column(name)
        np.testing.assert_array_equal(np.isnan(g), np.isnan(w), err_msg=name)
        ok = ~np.isnan(w)
        res = machine.channel(name).resolution
        err = np.max(np.abs(g[ok] - w[ok]), initial=0.0)
        assert err <= res / 2 + 1e-9 * np.abs(w[ok]).max(initial=0.0), name


def _write_csv(path: Path, header: list[str], cols: list[np.ndarray]) -> None:
    rows = [",".join(header)]
    for i in range(len(cols[0])):
        rows.append(",".join("" if isinstance(c[i], float) and np.isnan(c[i]) else str(c[i])
                             for c in cols))
    path.write_text("\n".join(rows) + "\n", encoding="utf-8")


def test_default_csv_in_channel_units_reads_back_equal(tmp_path: Path, machine: Machine,
                                                       rec: SampleArrays) -> None:
    p = tmp_path / "rec.csv"
    _write_csv(p, ["t_s", *rec.channels], [rec.t_s, *rec.values.T])
    got = read_file(p, machine, machine_id="m1")
    assert got.report.rows_refused == 0 and got.report.runs == 1
    assert got.samples.period_ns == 10_000_000
    _same(machine, got.samples, rec)


def test_csv_bar_mm_deg_pin_to_pin_iso_time(tmp_path: Path, machine: Machine,
                                            rec: SampleArrays) -> None:
    """Pressures in bar, pin-to-pin lengths in mm (offset given for one, the machine's closed
    length for the other), torque in kN·m, slew angle in degrees, ISO 8601 times."""
    cyl = {c.name: c for c in machine.cylinders}
    iso = [dt.datetime.fromtimestamp(t, dt.UTC).strftime("%Y-%m-%dT%H:%M:%S.%f") + "Z"
           for t in rec.t_s]
    header, cols = ["when"], [np.asarray(iso, dtype=object)]
    spec: dict[str, dict[str, object]] = {}
    for name in rec.channels:
        ch = machine.channel(name)
        v = rec.column(name)
        col = f"X {name}"
        if ch.quantity.startswith("pressure"):
            spec[name] = {"column": col, "unit": "bar"}
            v = v / 1e5
        elif ch.quantity == "position" and name == "lift_s":
            spec[name] = {"column": col, "unit": "mm", "convention": "pin_to_pin",
                          "offset": 820.0}
            v = (v + 0.82) * 1000.0
        elif ch.quantity == "position" and name == "jib_s":
            spec[name] = {"column": col, "unit": "mm", "convention": "pin_to_pin"}
            v = (v + cyl["jib"].closed_length_m) * 1000.0
        elif ch.quantity == "position":
            spec[name] = {"column": col, "unit": "mm"}
            v = v * 1000.0
        elif ch.quantity == "torque":
            spec[name] = {"column": col, "unit": "kN*m"}
            v = v / 1000.0
        else:
            spec[name] = {"column": col, "unit": "deg"}
            v = np.degrees(v)
        header.append(col)
        cols.append(v)
    p = tmp_path / "logger.csv"
    _write_csv(p, header, cols)
    m = mapping_from_dict({"time": {"column": "when", "format": "iso8601"}, "channels": spec},
                          machine)
    got = read_file(p, machine, m, machine_id="m1")
    assert got.report.rows_refused == 0, got.report.summary()
    _same(machine, got.samples, rec)


def test_parquet_psi_mpa_timestamp_and_epoch_ns(tmp_path: Path, machine: Machine,
                                                rec: SampleArrays) -> None:
    pa = pytest.importorskip("pyarrow")
    pq = pytest.importorskip("pyarrow.parquet")
    t_ns = np.rint(rec.t_s * 1e9).astype(np.int64)
    data = {}
    spec = {}
    for name in rec.channels:
        v = rec.column(name)
        if name.endswith("pA"):
            data[name] = v / PSI
            spec[name] = {"unit": "psi"}
        elif name.endswith("pB"):
            data[name] = v / 1e6
            spec[name] = {"unit": "MPa"}
        else:
            data[name] = v
    stamps = t_ns.astype("datetime64[ns]")
    utc_us = pa.array(stamps.astype("datetime64[us]"), pa.timestamp("us", "UTC"))
    for kind, tcol, fmt in (("timestamp", pa.array(stamps), "iso8601"),
                            ("timestamp-utc", utc_us, "epoch_s"),  # typed: a time, any format
                            ("ns", pa.array(t_ns), "epoch_ns")):
        p = tmp_path / f"rec_{kind}.parquet"
        pq.write_table(pa.table({"stamp": tcol, **{k: pa.array(v) for k, v in data.items()}}), p)
        m = mapping_from_dict({"time": {"column": "stamp", "format": fmt}, "channels": spec},
                              machine)
        got = read_file(p, machine, m, machine_id="m1")
        assert got.report.rows_refused == 0, got.report.summary()
        _same(machine, got.samples, rec)


def test_mdf4_relative_time_from_header_start(tmp_path: Path, machine: Machine,
                                              rec: SampleArrays) -> None:
    asammdf = pytest.importorskip("asammdf")
    mdf = asammdf.MDF(version="4.10")
    mdf.header.start_time = dt.datetime.fromtimestamp(T0, dt.UTC)
    t_rel = rec.t_s - T0
    mdf.append([asammdf.Signal(rec.column(n), t_rel, name=n) for n in rec.channels])
    p = tmp_path / "rec.mf4"
    mdf.save(p, overwrite=True)
    mdf.close()
    got = read_file(p, machine, machine_id="m1")
    assert got.report.rows_refused == 0, got.report.summary()
    _same(machine, got.samples, rec)


def test_bad_rows_refused_with_row_and_column_never_clipped(tmp_path: Path, machine: Machine,
                                                            rec: SampleArrays) -> None:
    p = tmp_path / "bad.csv"
    _write_csv(p, ["t_s", *rec.channels], [rec.t_s, *rec.values.T])
    lines = p.read_text().splitlines()
    # lines[k] is data row k, file line k + 1 (line 1 is the header)
    f = lines[10].split(",")
    f[1] = "oops"  # row 10: text
    lines[10] = ",".join(f)
    lines[20] = ",".join(lines[20].split(",")[:3])  # row 20: too few fields
    f = lines[30].split(",")
    f[1] = "3.0e7"  # row 30: lift_pA 300 bar, beyond the sensor's 250 bar
    lines[30] = ",".join(f)
    f = lines[40].split(",")
    f[0] = repr(rec.t_s[5])  # row 40: time goes back
    lines[40] = ",".join(f)
    p.write_text("\n".join(lines) + "\n")
    got = read_file(p, machine, machine_id="m1")
    rep = got.report
    assert rep.rows_read == rec.t_s.size and rep.rows_refused == 4
    found = {(r.row, r.column) for r in rep.first_refusals}
    assert found == {(10, "lift_pA"), (20, "(row)"), (30, "lift_pA"), (40, "t_s")}
    assert {r.line for r in rep.first_refusals} == {11, 21, 31, 41}
    assert "outside the channel's range" in rep.summary() and "row 30" in rep.summary()
    # the refused rows are gone (a gap), not clipped; everything else is imported
    kept = np.setdiff1d(np.arange(rec.t_s.size), [9, 19, 29, 39])
    want = SampleArrays("m1", rec.t_s[kept], rec.channels, rec.values[kept])
    _same(machine, got.samples, want)
    assert np.nanmax(got.samples.column("lift_pA")) < 2.5e7
    assert rep.runs == 5  # four gaps split the run


def test_gaps_and_jitter_split_into_regular_runs(tmp_path: Path, machine: Machine,
                                                 rec: SampleArrays) -> None:
    rng = np.random.default_rng(1)
    keep = np.r_[0:200, 260:rec.t_s.size]  # a 0.6 s dropout
    t = rec.t_s[keep] + rng.uniform(-1e-3, 1e-3, keep.size)  # ±1 ms logger jitter
    p = tmp_path / "gappy.csv"
    _write_csv(p, ["t_s", *rec.channels], [t, *rec.values[keep].T])
    got = read_file(p, machine, machine_id="m1")
    assert got.report.runs == 2 and got.report.rows_refused == 0
    assert got.report.max_time_shift_ns <= 2_000_000
    np.testing.assert_allclose(got.samples.t_s, t, atol=2.5e-3, rtol=0)
    assert got.samples.t_ns is not None
    assert np.all(np.diff(got.samples.t_ns[:200]) == got.report.period_ns)
    np.testing.assert_allclose(got.samples.values, rec.values[keep], atol=5e3, rtol=0)


def test_pin_to_pin_given_as_stroke_is_refused_loudly(tmp_path: Path, machine: Machine,
                                                      rec: SampleArrays) -> None:
    v = rec.values.copy()
    j = rec.channels.index("lift_s")
    v[:, j] += machine.cylinder("lift").closed_length_m  # pin-to-pin, undeclared
    p = tmp_path / "p2p.csv"
    _write_csv(p, ["t_s", *rec.channels], [rec.t_s, *v.T])
    with pytest.raises(ImportFileError, match=r"lift_s.*pin-to-pin.*convention = \"pin_to_pin\""):
        read_file(p, machine, machine_id="m1")
    from cranetwin.storage import Store

    with Store.open(f"sqlite:///{tmp_path / 'db.sqlite'}") as store:
        store.add_machine("m1", 1, b"k" * 32)
        with pytest.raises(ImportFileError, match="pin-to-pin"):
            import_file(p, machine, store, "m1")
        assert store.stats("m1").samples == 0  # nothing stored
    msgs = check_rod_positions(SampleArrays("m1", rec.t_s, rec.channels, v), machine)
    assert len(msgs) == 1 and "pin-to-pin" in msgs[0]
    assert check_rod_positions(rec, machine) == []
    v[:, j] = rec.values[:, j] * 1000.0  # millimetres, undeclared
    msgs = check_rod_positions(SampleArrays("m1", rec.t_s, rec.channels, v), machine)
    assert len(msgs) == 1 and 'unit = "mm"' in msgs[0]


def test_missing_channel_and_bad_mapping_name_the_problem(tmp_path: Path, machine: Machine,
                                                          rec: SampleArrays) -> None:
    p = tmp_path / "short.csv"
    _write_csv(p, ["t_s", *rec.channels[1:]], [rec.t_s, *rec.values[:, 1:].T])
    with pytest.raises(ImportFileError, match="lacks required channel.*lift_pA"):
        read_file(p, machine)
    with pytest.raises(ImportFileError, match="unknown unit 'furlong'"):
        mapping_from_dict({"channels": {"lift_s": {"unit": "furlong"}}}, machine)
    with pytest.raises(ImportFileError, match="is a pressure"):
        mapping_from_dict({"channels": {"lift_s": {"unit": "bar"}}}, machine)
    with pytest.raises(ImportFileError, match="no channel 'boom'"):
        mapping_from_dict({"channels": {"boom": {"unit": "bar"}}}, machine)
    # the optional slew angle may be absent
    q = tmp_path / "noangle.csv"
    _write_csv(q, ["t_s", *rec.channels[:-1]], [rec.t_s, *rec.values[:, :-1].T])
    assert read_file(q, machine).report.absent == ("slew_angle",)


def test_import_into_storage_twice_stores_once(tmp_path: Path, machine: Machine,
                                               rec: SampleArrays) -> None:
    from cranetwin.storage import Store

    p = tmp_path / "rec.csv"
    _write_csv(p, ["t_s", *rec.channels], [rec.t_s, *rec.values.T])
    with Store.open(f"sqlite:///{tmp_path / 'db.sqlite'}") as store:
        store.add_machine("m1", 1, b"k" * 32)
        first = import_file(p, machine, store, "m1")
        again = import_file(p, machine, store, "m1")
        assert first.stored == first.report.blocks >= 1 and first.duplicate == 0
        assert again.stored == 0 and again.duplicate == first.stored and not again.refused
        assert store.stats("m1").samples == rec.t_s.size
        back = store.read_samples("m1", rec.t_s[0], rec.t_s[-1] + 1)
    _same(machine, back, rec)


def test_cli_import_exit_status_and_summary(tmp_path: Path, rec: SampleArrays) -> None:
    from cranetwin.cli import app
    from cranetwin.storage import Store

    url = f"sqlite:///{tmp_path / 'db.sqlite'}"
    with Store.open(url) as store:
        store.add_machine("m1", 1, b"k" * 32)
    p = tmp_path / "rec.csv"
    v = rec.values.copy()
    v[3, 0] = 9e9  # row 4 out of range
    _write_csv(p, ["t_s", *rec.channels], [rec.t_s, *v.T])
    r = CliRunner().invoke(app, ["import", str(p), "--machine", "m1", "--db", url, "-q"])
    assert r.exit_code == 1, r.output
    assert "1 refused" in r.output and "row 4" in r.output and "lift_pA" in r.output
    r = CliRunner().invoke(app, ["import", str(p), "--machine", "m1", "--db", url, "--json"])
    assert r.exit_code == 1 and '"blocks_stored": 0' in r.output


def test_iso_times_with_zones() -> None:
    from cranetwin.importer.mapping import mapping_from_dict as mfd
    from cranetwin.importer.pipeline import raw_time_ns as _time_ns

    m = mfd({"time": {"format": "iso8601"}}, load_machine("patu655"))
    raw = np.array(["2026-01-01T02:00:00.010+02:00", "2026-01-01T00:00:00.020Z",
                    "2026-01-01 00:00:00.030", "yesterday"])
    t, bad = _time_ns(raw, m, None)
    assert bad.tolist() == [False, False, False, True]
    assert (t[:3] - 1_767_225_600_000_000_000).tolist() == [10_000_000, 20_000_000, 30_000_000]


def test_blank_and_comment_lines_are_skipped_rows_keep_their_numbers(
        tmp_path: Path, machine: Machine, rec: SampleArrays) -> None:
    p = tmp_path / "c.csv"
    _write_csv(p, ["t_s", *rec.channels], [rec.t_s, *rec.values.T])
    lines = p.read_text().splitlines()
    f = lines[50].split(",")
    f[3] = "x"  # row 50, lift_s
    lines[50] = ",".join(f)
    lines.insert(20, "# logger restarted")  # before row 20
    lines.insert(10, "")  # before row 10
    p.write_text("# exported by a logger\n" + "\n".join(lines) + "\n")
    rep = read_file(p, machine).report
    assert rep.rows_read == rec.t_s.size and rep.rows_refused == 1
    (r,) = rep.first_refusals
    assert (r.row, r.column, r.line) == (50, "lift_s", 54)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), p_unit=st.sampled_from(["Pa", "bar", "psi", "MPa"]),
       s_unit=st.sampled_from(["m", "mm", "in"]), pin=st.booleans(),
       tol=st.sampled_from([0.0, 0.013]))
def test_range_refusals_are_exactly_the_values_outside_after_conversion(
        machine: Machine, seed: int, p_unit: str, s_unit: str, pin: bool, tol: float) -> None:
    """Values a float step inside and outside each channel's accepted range, in other units
    and pin-to-pin: a row is refused iff one of its converted values lies outside, whether the
    chunk's extremes already decide it or not."""
    from cranetwin.importer import read_columns
    from cranetwin.importer.pipeline import Pipeline

    spec: dict[str, dict[str, object]] = {
        c.name: {"unit": p_unit} for c in machine.channels if c.quantity == "pressure"}
    spec.update({c.name: {"unit": s_unit, "convention": "pin_to_pin" if pin else "stroke"}
                 for c in machine.channels if c.name in ("lift_s", "jib_s")})
    m = mapping_from_dict({"channels": spec, "checks": {"range_tolerance": tol}}, machine)
    pipe = Pipeline(machine, m, "m", 1, list(m.channels))
    rng = np.random.default_rng(seed)
    n, c = 400, len(m.channels)
    lo_raw = (pipe.lo - pipe.shift) / pipe.scale  # the accepted range in the file's units
    hi_raw = (pipe.hi - pipe.shift) / pipe.scale
    finite = np.isfinite(lo_raw) & np.isfinite(hi_raw)
    raw = lo_raw + rng.random((n, c)) * np.where(finite, hi_raw - lo_raw, 1.0)
    raw[:, ~finite] = rng.normal(size=(n, (~finite).sum()))
    edge = rng.random((n, c)) < (0.02 if rng.random() < 0.5 else 0.0)  # sometimes none
    for j in np.flatnonzero(finite):
        for i in np.flatnonzero(edge[:, j]):
            b = lo_raw[j] if rng.random() < 0.5 else hi_raw[j]
            raw[i, j] = np.nextafter(b, rng.choice([-np.inf, np.inf])) if rng.random() < 0.7 \
                else b
    conv = raw * pipe.scale + pipe.shift
    outside = ((conv < pipe.lo) | (conv > pipe.hi)).any(axis=1)
    cols = {cm.column: raw[:, j] for j, cm in enumerate(m.channels)}
    cols["t_s"] = T0 + np.arange(n) / 100
    if outside.all():
        with pytest.raises(ImportFileError):
            read_columns(cols, machine, m)
        return
    got = read_columns(cols, machine, m)
    assert got.report.rows_refused == int(outside.sum())
    assert got.samples.values.shape[0] == n - int(outside.sum())
    refused_rows = {r.row for r in got.report.first_refusals}
    assert refused_rows <= set((np.flatnonzero(outside) + 1).tolist())


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), cuts=st.lists(st.integers(1, 299), max_size=8),
       block=st.integers(1, 40))
def test_blocks_do_not_depend_on_how_the_file_is_chunked(machine: Machine, seed: int,
                                                         cuts: list[int], block: int) -> None:
    """Rows fed in any chunks (gaps, dropouts, refused rows included) give the blocks and the
    report of one chunk: streaming = batch."""
    from cranetwin.importer.pipeline import Pipeline
    from cranetwin.importer.readers import Chunk

    rng = np.random.default_rng(seed)
    n = 300
    m = mapping_from_dict({}, machine)
    chans = [machine.channel(cm.channel) for cm in m.channels]
    lo = np.array([c.min for c in chans])
    hi = np.array([c.max for c in chans])
    v = lo + rng.random((n, len(chans))) * (hi - lo)
    v[rng.random(v.shape) < 0.05] = np.nan
    v[rng.integers(n), 0] = hi[0] * 2  # one row refused (out of range)
    dt_s = np.where(rng.random(n) < 0.03, 0.5, 0.01)  # gaps start new runs
    t = T0 + np.cumsum(dt_s)
    cols = {cm.column: v[:, j] for j, cm in enumerate(m.channels)}

    def run(bounds: list[int]) -> tuple[list[tuple[object, ...]], str]:
        pipe = Pipeline(machine, m, "m", 5, list(m.channels), block_samples=block)
        out = []
        for a, b in zip(bounds[:-1], bounds[1:], strict=True):
            if b > a:
                out += pipe.feed(Chunk(a + 1, t[a:b], {c: x[a:b] for c, x in cols.items()},
                                       np.zeros(b - a, dtype=bool), [], None, b, n))
        out += pipe.finish()
        return [(b.seq, b.t0_ns, b.period_ns, b.steps.tobytes(), np.isnan(b.values).tobytes())
                for b in out], pipe.report.summary()

    assert run(sorted({0, n, *cuts})) == run([0, n])
