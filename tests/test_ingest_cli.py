"""``cranetwin machines add|list`` and ``cranetwin ingest`` argument handling."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from cranetwin.cli import app
from cranetwin.errors import CraneTwinError
from cranetwin.storage import Store


def test_machines_add_and_list_never_show_the_secret(sqlite_url: str,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    r = CliRunner()
    out = r.invoke(app, ["machines", "add", "crane-9", "--wire-id", "9", "--db", sqlite_url,
                         "--metadata", '{"site": "Mikkeli"}'])
    assert out.exit_code == 0, out.output
    secret = out.output.split("shown once): ")[1].strip()
    assert len(bytes.fromhex(secret)) == 32
    given = "00112233445566778899aabbccddeeff"
    monkeypatch.setenv("CRANETWIN_MACHINE_SECRET", given)  # never on the command line
    out = r.invoke(app, ["machines", "add", "crane-10", "--wire-id", "10", "--db", sqlite_url])
    monkeypatch.delenv("CRANETWIN_MACHINE_SECRET")
    assert out.exit_code == 0 and given not in out.output
    listing = r.invoke(app, ["machines", "list", "--db", sqlite_url, "--json"])
    assert listing.exit_code == 0
    assert secret not in listing.output and given not in listing.output
    rows = json.loads(listing.output)
    assert [m["machine_id"] for m in rows] == ["crane-10", "crane-9"]
    assert rows[1]["metadata"] == {"site": "Mikkeli"}
    keys = Store.open(sqlite_url).machine_keys()
    assert keys[9][1].hex() == secret and keys[10][1].hex() == given


def test_machines_add_rejects_bad_input(sqlite_url: str,
                                        monkeypatch: pytest.MonkeyPatch) -> None:
    r = CliRunner()
    monkeypatch.setenv("CRANETWIN_MACHINE_SECRET", "zz")
    bad = r.invoke(app, ["machines", "add", "x", "--wire-id", "1", "--db", sqlite_url])
    assert bad.exit_code != 0
    monkeypatch.delenv("CRANETWIN_MACHINE_SECRET")
    assert r.invoke(app, ["machines", "add", "x", "--wire-id", "1", "--db", sqlite_url]
                    ).exit_code == 0
    dup = r.invoke(app, ["machines", "add", "y", "--wire-id", "1", "--db", sqlite_url])
    assert dup.exit_code != 0


def test_send_reports_the_given_position_in_its_status(sqlite_url: str, tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """`cranetwin send --position LAT,LON` puts that GPS position in its status datagrams (the
    demo passes each crane's registered location, so status reports keep it)."""
    from conftest import running_daemon

    secret = "00112233445566778899aabbccddeeff"
    store = Store.open(sqlite_url)
    store.add_machine("crane-5", 5, bytes.fromhex(secret))
    monkeypatch.setenv("CRANETWIN_MACHINE_KEY", secret)
    with running_daemon(store) as d:
        host = f"{d.address[0]}:{d.address[1]}"
        out = CliRunner().invoke(app, [
            "send", "--machine", "crane-5", "--wire-id", "5", "--journal", str(tmp_path / "j"),
            "--scenario", "synthetic", "--duration", "0.3", "--batch", "10", "--host", host,
            "--speed", "4", "--position", "62.61,29.78", "--json"])
        assert out.exit_code == 0, out.output
    m = store.get_machine("crane-5")
    assert m.latitude_deg == pytest.approx(62.61, abs=1e-6)
    assert m.longitude_deg == pytest.approx(29.78, abs=1e-6)


@pytest.mark.parametrize("bad", ["62.6", "62.6,29.7,1", "north,east", "95,20", "60,nan"])
def test_send_rejects_a_bad_position(bad: str) -> None:
    from cranetwin.cli.send import parse_position

    with pytest.raises(CraneTwinError, match="--position"):
        parse_position(bad)
    assert parse_position("-33.9,151.2") == (-33.9, 151.2)
