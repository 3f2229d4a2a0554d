"""``cranetwin machines add|list`` and ``cranetwin ingest`` argument handling."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from cranetwin.cli import app
from cranetwin.storage import Store


def test_machines_add_and_list_never_show_the_secret(sqlite_url: str) -> None:
    r = CliRunner()
    out = r.invoke(app, ["machines", "add", "crane-9", "--wire-id", "9", "--db", sqlite_url,
                         "--metadata", '{"site": "Mikkeli"}'])
    assert out.exit_code == 0, out.output
    secret = out.output.split("shown once): ")[1].strip()
    assert len(bytes.fromhex(secret)) == 32
    given = "00112233445566778899aabbccddeeff"
    out = r.invoke(app, ["machines", "add", "crane-10", "--wire-id", "10", "--secret", given,
                         "--db", sqlite_url])
    assert out.exit_code == 0 and given not in out.output
    listing = r.invoke(app, ["machines", "list", "--db", sqlite_url, "--json"])
    assert listing.exit_code == 0
    assert secret not in listing.output and given not in listing.output
    rows = json.loads(listing.output)
    assert [m["machine_id"] for m in rows] == ["crane-10", "crane-9"]
    assert rows[1]["metadata"] == {"site": "Mikkeli"}
    keys = Store.open(sqlite_url).machine_keys()
    assert keys[9][1].hex() == secret and keys[10][1].hex() == given


def test_machines_add_rejects_bad_input(sqlite_url: str) -> None:
    r = CliRunner()
    bad = r.invoke(app, ["machines", "add", "x", "--wire-id", "1", "--secret", "zz",
                         "--db", sqlite_url])
    assert bad.exit_code != 0
    assert r.invoke(app, ["machines", "add", "x", "--wire-id", "1", "--db", sqlite_url]
                    ).exit_code == 0
    dup = r.invoke(app, ["machines", "add", "y", "--wire-id", "1", "--db", sqlite_url])
    assert dup.exit_code != 0
