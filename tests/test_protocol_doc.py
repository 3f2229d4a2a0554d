"""The worked examples of docs/PROTOCOL.md decode; re-encoding their values gives the same bytes."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

from cranetwin.model import load_machine
from cranetwin.protocol import (
    REFUSAL_CODES,
    BadHmacError,
    Layout,
    MachineKey,
    Refusal,
    StatusReport,
    decode_ack,
    decode_data,
    decode_refusal,
    decode_status,
    encode_ack,
    encode_data,
    encode_refusal,
    encode_status,
)

DOC = Path(__file__).resolve().parents[1] / "docs" / "PROTOCOL.md"
KEY = MachineKey(42, "crane-042", b"cranetwin-example-key-32-bytes!!",
                 Layout.from_channels(load_machine("patu655").channels))
T0 = 1795428000000000000  # 2026-11-23T10:00:00Z
EPOCH = 0x1F2E3D4C5B6A7988


def _hex_blocks() -> list[bytes]:
    blocks = re.findall(r"```hex\n(.*?)```", DOC.read_text(), flags=re.S)
    out = []
    for b in blocks:
        rows = [line.split()[1:] for line in b.strip().splitlines()]  # drop the offset column
        out.append(bytes.fromhex("".join("".join(r) for r in rows)))
    return out


def test_doc_has_data_status_ack_and_refusal_examples() -> None:
    assert [b[3] for b in _hex_blocks()] == [1, 2, 3, 4]
    assert {b[2] for b in _hex_blocks()} == {2}


def test_layout_id_in_doc_matches() -> None:
    assert f"{KEY.layout.layout_id:#010x}" == "0x4054a329"
    assert "0x4054a329" in DOC.read_text()


def test_data_example_decodes_to_the_documented_values() -> None:
    dg = _hex_blocks()[0]
    assert len(dg) == 119
    block = decode_data(dg, KEY)
    assert (block.seq, block.t0_ns, block.period_ns, block.n) == (1000, T0, 10_000_000, 4)
    assert block.epoch == EPOCH
    mpa, m, nm = 1e6, 1.0, 1.0
    expect = np.array([
        # lift_pA, lift_pB, lift_s, jib_pA, jib_pB, jib_s, ext_pA, ext_pB, ext_s, slew_torque
        [12.000 * mpa, 3.500 * mpa, 0.2500 * m, 9.00 * mpa, 4.000 * mpa, 0.4000 * m],
        [12.005 * mpa, 3.500 * mpa, 0.2503 * m, 9.01 * mpa, 4.000 * mpa, 0.4001 * m],
        [12.015 * mpa, 3.495 * mpa, 0.2506 * m, 9.02 * mpa, 4.005 * mpa, np.nan],
        [12.010 * mpa, 3.505 * mpa, 0.2509 * m, 9.03 * mpa, 3.995 * mpa, 0.4003 * m],
    ])
    expect = np.hstack([expect, np.tile([2e6, 2e6, 0.1], (4, 1)),
                        np.array([[1200.0], [1205.0], [1190.0], [1200.0]]) * nm,
                        np.full((4, 1), np.nan)])
    res = np.asarray(KEY.layout.resolutions)
    assert np.allclose(block.values, expect, rtol=0, atol=1e-9, equal_nan=True)
    # and re-encoding the documented values reproduces the documented bytes
    assert encode_data(KEY, 1000, T0, 10_000_000, expect, oldest_unacked=998, epoch=EPOCH) == dg
    assert np.array_equal(np.isnan(block.values), np.isnan(expect))
    assert np.all(np.isnan(block.values) | (np.abs(block.values / res - np.round(
        block.values / res)) < 1e-6))


def test_status_example_decodes() -> None:
    dg = _hex_blocks()[1]
    rep = decode_status(dg, KEY)
    assert (rep.seq, rep.t_ns, rep.epoch) == (1001, T0 + 40_000_000, EPOCH)
    assert math.isclose(rep.latitude_deg, 62.2415) and math.isclose(rep.longitude_deg, 25.7209)
    assert math.isclose(rep.altitude_m, 84.25) and math.isclose(rep.operating_hours, 1234.5)
    assert rep.channels == {"slew_angle": pytest.approx(-0.7854)}
    again = StatusReport("crane-042", 1001, T0 + 40_000_000, 62.2415, 25.7209, 84.25, 1234.5,
                         {"slew_angle": -0.7854}, epoch=EPOCH)
    assert encode_status(KEY, again, oldest_unacked=998) == dg


def test_ack_example_decodes() -> None:
    dg = _hex_blocks()[2]
    ack = decode_ack(dg, KEY)
    assert (ack.cumulative, ack.selective, ack.server_time_ns, ack.epoch) == (
        999, (1001, 1003), T0 + 1_250_000_000, EPOCH)
    assert encode_ack(KEY, 999, [1001, 1003], server_time_ns=T0 + 1_250_000_000,
                      epoch=EPOCH) == dg


def test_refusal_example_decodes() -> None:
    dg = _hex_blocks()[3]
    ref = decode_refusal(dg, KEY)
    assert ref == Refusal(EPOCH, 1002, "out_of_range", T0 + 1_250_000_000)
    assert encode_refusal(KEY, EPOCH, 1002, "out_of_range",
                          server_time_ns=T0 + 1_250_000_000) == dg
    assert all(f"| {code} | `{name}` |" in DOC.read_text() for name, code in
               REFUSAL_CODES.items())


def test_doc_examples_do_not_verify_under_another_key() -> None:
    other = MachineKey(42, "x", b"another-key-of-at-least-16-bytes", KEY.layout)
    with pytest.raises(BadHmacError):
        decode_data(_hex_blocks()[0], other)
