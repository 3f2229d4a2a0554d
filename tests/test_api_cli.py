"""``cranetwin keys create|list|revoke`` against a real database, checked through the API."""

from __future__ import annotations

from fastapi.testclient import TestClient
from typer.testing import CliRunner

from cranetwin.api import create_app
from cranetwin.cli import app as cli
from cranetwin.settings import Settings


def test_keys_create_list_revoke(sqlite_url: str) -> None:
    runner = CliRunner()
    r = runner.invoke(cli, ["keys", "create", "--role", "fleet", "--name", "ops", "--db",
                            sqlite_url])
    assert r.exit_code == 0, r.output
    token = r.output.strip()
    assert token.startswith("ctk_")
    key_id = token.split("_")[1]
    listing = runner.invoke(cli, ["keys", "list", "--db", sqlite_url]).output
    assert key_id in listing and "fleet" in listing and token not in listing
    app = create_app(Settings(database_url=sqlite_url, worker_in_process=False))
    with TestClient(app) as client:
        assert client.get("/api/v1/aemp/Fleet/1", headers={"X-API-Key": token}).status_code == 200
        r = runner.invoke(cli, ["keys", "revoke", key_id, "--db", sqlite_url])
        assert r.exit_code == 0
        app.state.services.keys.forget()  # servers forget verified keys within 10 s
        assert client.get("/api/v1/aemp/Fleet/1", headers={"X-API-Key": token}).status_code == 401
    bad = runner.invoke(cli, ["keys", "create", "--role", "root", "--db", sqlite_url])
    assert bad.exit_code != 0
