"""CSV reading: pyarrow's parser gives exactly what numpy's (the fallback) gives — the same
times, values, missing cells, refused rows with the same row, line, column and message — on
varied files (random values and number spellings, empty cells, quoted fields, spaces, bad cells,
short rows, comment and blank lines, CRLF, three delimiters, three time kinds, any chunk size);
and the import of a file through either parser yields the same samples and summary."""

from __future__ import annotations

import datetime as dt
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cranetwin.importer import mapping_from_dict, read_file, readers
from cranetwin.importer.readers import Chunk, read_csv
from cranetwin.model import Machine, load_machine

pytestmark = [pytest.mark.timeout(120),
              pytest.mark.filterwarnings("ignore:loadtxt:UserWarning"),
              pytest.mark.filterwarnings("ignore:Input line:UserWarning")]
pytest.importorskip("pyarrow")

T0 = 1_767_225_600.0  # 2026-01-01T00:00:00Z


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load_machine("patu655")


def _number(rng: np.random.Generator, spaces: bool, quoted: bool) -> str:
    x = float(rng.normal() * 10.0 ** rng.integers(-8, 9))
    k = rng.integers(6)
    s = (repr(x), f"{x:.6g}", f"{x:.3e}", str(int(x)), f"{x:.2f}", "+" + repr(abs(x)))[k]
    if spaces and rng.random() < 0.2:
        s = f" {s} "
    if quoted and rng.random() < 0.2:
        s = f'"{s}"'
    return s


def _write(path: Path, rng: np.random.Generator, n: int, kind: str, delim: str, *,
           missing: bool, quoted: bool, spaces: bool, bad: bool, comments: bool,
           short: bool, crlf: bool) -> None:
    """A file with a time column ``t`` (epoch s, epoch ns or ISO 8601) and ``a``, ``b``, ``c``
    and an unused column ``note`` (free text)."""
    lines = [delim.join(["a", "t", "b", "note", "c"])]
    for i in range(n):
        sec = T0 + 0.01 * i
        t = (repr(sec) if kind == "float" else str(int(sec * 1e9)) if kind == "int" else
             dt.datetime.fromtimestamp(sec, dt.UTC).isoformat().replace("+00:00", "Z"))
        cells = [_number(rng, spaces, quoted) for _ in range(3)]
        for j in range(3):
            u = rng.random()
            if missing and u < 0.05:
                cells[j] = ""
            elif missing and u < 0.07:
                cells[j] = str(rng.choice(["nan", "NaN", "inf", "-inf"]))
            elif bad and u > 0.995:
                cells[j] = str(rng.choice(["x", "1.2.3", "NA", "null", "0x10", "1,5"]))
        if bad and rng.random() < 0.005:  # refused: no time
            t = ""
        if bad and rng.random() < 0.003:
            t = "later"
        note = str(rng.choice(["ok", "", '"a, b"', "NA", "x y"]))
        if short and rng.random() < 0.005:
            note = '"two\nlines"'  # one row to pyarrow, two to numpy (which refuses them)
        row = [cells[0], t, cells[1], note, cells[2]]
        if short and rng.random() < 0.005:
            row = row[: rng.integers(1, 4)]
        lines.append(delim.join(row))
        if comments and rng.random() < 0.01:
            lines.append(str(rng.choice(["# logger restarted", "", "  "])))
    end = "\r\n" if crlf else "\n"
    path.write_bytes((end.join(lines) + end).encode())


def _chunks(path: Path, kind: Any, delim: str, chunk_bytes: int, engine: Any,
            ) -> tuple[list[Chunk], int]:
    """All chunks, and how many pyarrow parsed."""
    used = 0
    make = readers._csv_arrow_parser

    def counting(*args: Any) -> Any:
        parse = make(*args)
        assert parse is not None

        def wrapped(data: bytes, n: int) -> Any:
            nonlocal used
            got = parse(data, n)
            used += got is not None
            return got
        return wrapped

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(readers, "_csv_arrow_parser", counting)
        out = list(read_csv(path, ["a", "b", "c"], "t", kind, delim, chunk_bytes, engine))
    return out, used


def _assert_same_chunks(got: list[Chunk], want: list[Chunk], kind: str) -> None:
    assert len(got) == len(want)
    for g, w in zip(got, want, strict=True):
        assert (g.first_row, g.n, g.done, g.total) == (w.first_row, w.n, w.done, w.total)
        assert g.lines is not None and w.lines is not None
        np.testing.assert_array_equal(g.lines, w.lines)
        np.testing.assert_array_equal(g.bad, w.bad)
        assert g.refusals == w.refusals
        assert g.time.dtype.kind == w.time.dtype.kind
        if kind == "str":  # the ISO text as the pipeline reads it (stripped)
            np.testing.assert_array_equal(np.char.strip(g.time), np.char.strip(w.time))
        else:
            np.testing.assert_array_equal(g.time, w.time)
        assert g.columns.keys() == w.columns.keys()
        for c in w.columns:
            assert g.columns[c].dtype == np.float64
            np.testing.assert_array_equal(g.columns[c], w.columns[c], err_msg=c)


@settings(max_examples=40, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**32 - 1), kind=st.sampled_from(["float", "int", "str"]),
       delim=st.sampled_from([",", ";", "\t"]), missing=st.booleans(), quoted=st.booleans(),
       spaces=st.booleans(), bad=st.booleans(), comments=st.booleans(), short=st.booleans(),
       crlf=st.booleans(), chunk_bytes=st.sampled_from([64, 300, 4096, 1 << 20]))
def test_pyarrow_chunks_equal_numpy_chunks(tmp_path: Path, seed: int, kind: str, delim: str,
                                           missing: bool, quoted: bool, spaces: bool,
                                           bad: bool, comments: bool, short: bool, crlf: bool,
                                           chunk_bytes: int) -> None:
    rng = np.random.default_rng(seed)
    p = tmp_path / f"f{seed}.csv"
    _write(p, rng, 400, kind, delim, missing=missing, quoted=quoted, spaces=spaces, bad=bad,
           comments=comments, short=short, crlf=crlf)
    got, used = _chunks(p, kind, delim, chunk_bytes, "auto")
    want = list(read_csv(p, ["a", "b", "c"], "t", kind, delim, chunk_bytes,  # type: ignore[arg-type]
                         "numpy"))
    _assert_same_chunks(got, want, kind)
    if not (bad or comments or short):  # rows pyarrow takes: it read every chunk
        assert used == len(got) > 0


def test_clean_chunks_of_a_dirty_file_go_through_pyarrow(tmp_path: Path) -> None:
    """Only the chunks with a bad row or a comment fall back; refusals keep their lines."""
    rng = np.random.default_rng(3)
    p = tmp_path / "d.csv"
    _write(p, rng, 2000, "float", ",", missing=True, quoted=True, spaces=True, bad=False,
           comments=False, short=False, crlf=False)
    lines = p.read_text().splitlines()
    lines[700] = lines[700].replace(lines[700].split(",")[0], "oops", 1)  # row 700, line 701
    lines.insert(1500, "# restart")  # data row 1499 is now on line 1501
    p.write_text("\n".join(lines) + "\n")
    got, used = _chunks(p, "float", ",", 8192, "auto")
    want = list(read_csv(p, ["a", "b", "c"], "t", "float", ",", 8192, "numpy"))
    _assert_same_chunks(got, want, "float")
    assert 2 <= len(got) - used <= 3  # the two chunks with the bad row and the comment
    refusals = [r for c in got for r in c.refusals]
    assert [str(r) for r in refusals] == ["row 700 (line 701), column 'a': 'oops' is not a number"]
    assert got[-1].lines is not None and int(got[-1].lines[-1]) == 2002


@settings(max_examples=8, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**32 - 1), iso=st.booleans(), delim=st.sampled_from([",", ";"]))
def test_import_through_either_parser_gives_the_same_samples_and_summary(
        tmp_path: Path, machine: Machine, seed: int, iso: bool, delim: str) -> None:
    rng = np.random.default_rng(seed)
    n = 3000
    chans = list(machine.channels)
    lo = np.array([c.min for c in chans])
    hi = np.array([c.max for c in chans])
    v = lo + rng.random((n, len(chans))) * (hi - lo) * 1.02  # some outside: refused
    t = T0 + 0.01 * np.arange(n)
    t[rng.random(n) < 0.002] -= 1.0  # time goes back: refused
    rows = [delim.join(["time", *(c.name for c in chans)])]
    for i in range(n):
        ts = (dt.datetime.fromtimestamp(float(t[i]), dt.UTC).isoformat() if iso
              else repr(float(t[i])))
        cells = ["" if rng.random() < 0.02 else repr(float(x)) for x in v[i]]
        if rng.random() < 0.002:
            cells[rng.integers(len(cells))] = "n/a"
        rows.append(delim.join([ts, *cells]))
    p = tmp_path / f"m{seed}.csv"
    p.write_text("\n".join(rows) + "\n")
    mapping = {"time": {"column": "time", "format": "iso8601" if iso else "epoch_s"},
               "csv": {"delimiter": delim}}
    m = mapping_from_dict(mapping, machine)
    new = read_file(p, machine, m)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(readers, "_csv_arrow_parser", lambda *a: None)
        old = read_file(p, machine, m)
    np.testing.assert_array_equal(new.samples.t_s, old.samples.t_s)
    np.testing.assert_array_equal(new.samples.values, old.samples.values)
    assert new.samples.channels == old.samples.channels
    assert new.report.summary() == old.report.summary()
    assert new.report.first_refusals == old.report.first_refusals
    assert new.report.rows_refused > 0
