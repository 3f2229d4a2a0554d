"""Laws of the integer codec shared by the wire and storage: every stage inverts exactly, for any
resolution, missing samples and the extremes of int64."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from cranetwin import codec

INT64 = st.integers(-(2**63), 2**63 - 1)
RESOLUTIONS = st.one_of(st.sampled_from([1e-4, 3e-7, 0.1, 0.25, 1.0, 5.0, 5000.0]),
                        st.floats(1e-9, 1e6, allow_nan=False, allow_infinity=False))


def _steps(max_abs: int) -> st.SearchStrategy[np.ndarray]:
    edges = st.sampled_from([0, 1, -1, max_abs - 1, -(max_abs - 1)])
    return hnp.arrays(np.int64, hnp.array_shapes(min_dims=2, max_dims=2, max_side=12),
                      elements=st.one_of(edges, st.integers(-(max_abs - 1), max_abs - 1)))


@settings(max_examples=200, deadline=None)
@given(k=_steps(2**50), data=st.data())
def test_quantise_inverts_dequantise_for_any_resolution_and_gaps(k: np.ndarray,
                                                                  data: st.DataObject) -> None:
    res = data.draw(st.lists(RESOLUTIONS, min_size=k.shape[1], max_size=k.shape[1]))
    missing = data.draw(hnp.arrays(np.bool_, k.shape))
    k = np.where(missing, 0, k)
    v = codec.dequantise(k, missing, res)
    assert np.array_equal(np.isnan(v), missing)
    k2, m2 = codec.quantise(v, res)
    assert np.array_equal(k2, k) and np.array_equal(m2, missing)
    assert np.array_equal(codec.on_grid(v, res), v, equal_nan=True)


@pytest.mark.parametrize("bad", [np.inf, -np.inf, 2.0**53, -(2.0**60)])
def test_quantise_refuses_infinite_and_inexact_values(bad: float) -> None:
    with pytest.raises(codec.QuantiseError):
        codec.quantise(np.array([[1.0, bad]]), (1.0, 1.0))
    with pytest.raises(ValueError):  # QuantiseError is a ValueError
        codec.quantise(np.array([[1.0]]), (0.0,))


@given(v=INT64)
def test_zigzag_inverts_and_agrees_with_its_array_form(v: int) -> None:
    z = codec.zigzag(v)
    assert 0 <= z < 2**64 and codec.unzigzag(z) == v
    arr = np.array([v], dtype=np.int64)
    assert int(codec.zigzag_array(arr)[0]) == z
    assert int(codec.unzigzag_array(codec.zigzag_array(arr))[0]) == v
    assert [codec.zigzag(x) for x in (0, -1, 1, -2, 2)] == [0, 1, 2, 3, 4]


@settings(max_examples=100, deadline=None)
@given(k=hnp.arrays(np.int64, hnp.array_shapes(min_dims=2, max_dims=2, max_side=10),
                    elements=INT64))
def test_deltas_invert_with_wraparound(k: np.ndarray) -> None:
    assert np.array_equal(codec.undelta(codec.deltas(k, axis=0, first=True), axis=0), k)
    if k.shape[0] > 1:
        assert np.array_equal(codec.undelta(codec.deltas(k), start=k[0]), k[1:])
    assert np.array_equal(codec.undelta(codec.deltas(k, axis=1, first=True), axis=1), k)


@settings(max_examples=100, deadline=None)
@given(k=_steps(2**40), data=st.data())
def test_carry_through_gaps_keeps_present_samples_and_repeats_the_previous(
        k: np.ndarray, data: st.DataObject) -> None:
    missing = data.draw(hnp.arrays(np.bool_, k.shape))
    out = codec.carry_through_gaps(k, missing)
    assert np.array_equal(out[~missing], k[~missing])
    for j in range(k.shape[1]):
        present = np.flatnonzero(~missing[:, j])
        if present.size == 0:
            continue
        for i in np.flatnonzero(missing[:, j]):
            before = present[present < i]
            src = before[-1] if before.size else present[0]
            assert out[i, j] == k[src, j]


@settings(max_examples=150, deadline=None)
@given(widths=st.lists(st.integers(1, 64), min_size=1, max_size=6),
       n1=st.integers(1, 40), seed=st.integers(0, 2**32 - 1))
def test_bit_rows_unpack_to_what_was_packed(widths: list[int], n1: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    full = rng.integers(0, 2**64, (len(widths), n1), dtype=np.uint64, endpoint=False)
    rows = full >> np.array([64 - w for w in widths], dtype=np.uint64)[:, None]
    top = np.array([(2**w - 1) for w in widths], dtype=np.uint64)  # extremes of every width
    rows[:, 0] = top
    buf = codec.pack_rows(rows, tuple(widths))
    assert len(buf) == (n1 * sum(widths) + 7) // 8
    assert np.array_equal(codec.unpack_rows(buf, n1, tuple(widths)), rows)
    assert codec.row_widths(top) == widths


@settings(max_examples=100, deadline=None)
@given(z=hnp.arrays(np.uint64, hnp.array_shapes(min_dims=2, max_dims=2, max_side=12),
                    elements=st.integers(0, 2**64 - 1)))
def test_byte_planes_invert_at_the_smallest_width(z: np.ndarray) -> None:
    width = codec.byte_width(int(z.max()))
    assert width in (1, 2, 4, 8) and int(z.max()) < 2 ** (8 * width)
    planes = codec.byte_planes(z, width)
    assert planes.shape == (z.shape[0], width * z.shape[1])
    for r in range(z.shape[0]):
        assert np.array_equal(codec.from_byte_planes(planes[r].tobytes(), width, z.shape[1]),
                              z[r])


def test_codec_imports_numpy_only() -> None:
    code = ("import sys, cranetwin.codec; bad = {'socket', 'asyncio', 'sqlalchemy', 'fastapi', "
            "'scipy', 'numba', 'cranetwin.protocol', 'cranetwin.storage'} & set(sys.modules); "
            "print(sorted(bad))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
