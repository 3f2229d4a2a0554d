"""One settings object for every command: read from ``CRANETWIN_…`` when a command starts, with
command-line options over the environment; ``cranetwin serve`` runs no twin worker unless asked."""

from __future__ import annotations

from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from cranetwin.api import create_app
from cranetwin.settings import Settings, SettingsError, load_settings


def test_settings_are_read_when_built_and_options_override_the_environment(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("CRANETWIN_DATABASE_URL", "sqlite:///from-env.db")
    monkeypatch.setenv("CRANETWIN_WEB_DIR", str(tmp_path / "web"))
    monkeypatch.setenv("CRANETWIN_DEMO_LOGS", str(tmp_path / "logs"))
    monkeypatch.setenv("CRANETWIN_STATE_DIR", str(tmp_path / "state"))
    monkeypatch.setenv("CRANETWIN_WORKER_IN_PROCESS", "1")
    s = load_settings(Settings)
    assert s.database_url == "sqlite:///from-env.db"
    assert s.web_dir == tmp_path / "web" and s.demo_logs == tmp_path / "logs"
    assert s.worker_in_process is True
    assert load_settings(Settings, database_url="sqlite:///opt.db",
                         worker_in_process=None).database_url == "sqlite:///opt.db"
    monkeypatch.setenv("CRANETWIN_WORKER_WINDOW_S", "-5")
    with pytest.raises(SettingsError, match="CRANETWIN_WORKER_WINDOW_S"):
        load_settings(Settings)


def test_commands_take_their_folders_from_the_settings(monkeypatch: pytest.MonkeyPatch,
                                                       tmp_path: Path) -> None:
    from cranetwin.api.routes_web import web_dir
    from cranetwin.cli.send import default_journal_root
    from cranetwin.demo import DemoConfig, FleetDemo

    monkeypatch.setenv("CRANETWIN_WEB_DIR", str(tmp_path / "web"))
    monkeypatch.setenv("CRANETWIN_DEMO_LOGS", str(tmp_path / "logs"))
    monkeypatch.setenv("CRANETWIN_STATE_DIR", str(tmp_path / "state"))
    assert web_dir() == tmp_path / "web"
    assert web_dir(Settings(web_dir=tmp_path / "other")) == tmp_path / "other"
    assert FleetDemo(DemoConfig()).logdir == tmp_path / "logs"
    assert default_journal_root() == tmp_path / "state" / "send"


@pytest.mark.parametrize("in_process", [False, True])
def test_serve_runs_the_twin_worker_only_when_asked(sqlite_url: str, in_process: bool) -> None:
    app = create_app(Settings(database_url=sqlite_url, warm_up=False,
                              worker_in_process=in_process))
    with TestClient(app):
        fleet = app.state.services.fleet
        assert (fleet.worker is not None) is in_process
