"""Deployment files: docker-compose.yml and Dockerfile are consistent with the code.

No Docker engine runs on the development machines: `docker compose config` (which only parses and
resolves the file) runs when a Docker client with the compose plugin is installed, else skips.
The structural checks below run everywhere.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest
import typer
import yaml

ROOT = Path(__file__).resolve().parents[1]
COMPOSE = ROOT / "docker-compose.yml"
DOCKERFILE = ROOT / "Dockerfile"


def _compose() -> dict:  # type: ignore[type-arg]
    data = yaml.safe_load(COMPOSE.read_text())
    assert isinstance(data, dict)
    return data


def _cli_commands() -> set[str]:
    from cranetwin.cli import app

    names = set()
    for cmd in app.registered_commands:
        names.add(cmd.name or (cmd.callback.__name__.replace("_", "-") if cmd.callback else ""))
    for group in app.registered_groups:
        names.add(group.name or "")
    return names


def _compose_command() -> list[str] | None:
    """`docker compose` (v2 plugin) or Debian's `docker-compose` (v1.29), whichever is present."""
    docker = shutil.which("docker")
    if docker is not None:
        probe = subprocess.run([docker, "compose", "version"], capture_output=True, text=True)
        if probe.returncode == 0:
            return [docker, "compose"]
    legacy = shutil.which("docker-compose")
    return [legacy] if legacy is not None else None


def test_docker_compose_config_resolves() -> None:
    cmd = _compose_command()
    if cmd is None:
        pytest.skip("neither `docker compose` nor `docker-compose` installed: config not checked")
    res = subprocess.run([*cmd, "-f", str(COMPOSE), "config", "--quiet"],
                         capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 0, res.stderr


def test_compose_has_every_service_with_a_health_check() -> None:
    services = _compose()["services"]
    assert {"db", "ingest", "api", "fleet"} <= set(services)
    for name, svc in services.items():
        assert "healthcheck" in svc, f"{name} has no health check"
        assert svc["healthcheck"]["test"], name
    # start order follows health, not just container start
    assert services["api"]["depends_on"]["db"]["condition"] == "service_healthy"
    assert services["ingest"]["depends_on"]["db"]["condition"] == "service_healthy"
    assert services["fleet"]["depends_on"]["api"]["condition"] == "service_healthy"
    assert services["fleet"]["depends_on"]["ingest"]["condition"] == "service_healthy"


def test_compose_services_use_postgres_and_existing_commands() -> None:
    services = _compose()["services"]
    assert services["db"]["image"].startswith("postgres:")
    known = _cli_commands()
    for name in ("ingest", "api", "fleet"):
        svc = services[name]
        url = svc["environment"]["CRANETWIN_DATABASE_URL"]
        assert url.startswith("postgresql+psycopg://") and "@db:5432/" in url
        assert svc["command"][0] == "cranetwin"
        sub = svc["command"][1]
        if sub == "ingest" and "ingest" not in known:
            pytest.skip("`cranetwin ingest` is not available in this installation")
        assert sub in known, f"service {name} runs unknown command `cranetwin {sub}`"
    ports = [str(p) for p in services["ingest"]["ports"]]
    assert any(p.endswith("/udp") for p in ports)


def test_fleetdemo_accepts_the_compose_options() -> None:
    from typer.testing import CliRunner

    from cranetwin.cli import app

    fleet = _compose()["services"]["fleet"]["command"]
    res = CliRunner().invoke(app, [*fleet[1:2], "--help"])
    assert res.exit_code == 0, res.output
    for opt in [a for a in fleet[2:] if a.startswith("--")]:
        assert opt in res.output, f"fleetdemo has no option {opt}"
    assert isinstance(app, typer.Typer)


def test_dockerfile_copies_what_the_app_needs() -> None:
    text = DOCKERFILE.read_text()
    assert re.search(r"^FROM python:3\.11", text, re.MULTILINE)
    for path in ("pyproject.toml", "src", "web"):
        assert re.search(rf"^COPY .*\b{re.escape(path)}\b", text, re.MULTILINE), path
        assert (ROOT / path).exists()
    assert "CRANETWIN_WEB_DIR=/app/web" in text  # a non-editable install finds web/ through it
    assert "HEALTHCHECK" in text and "/healthz" in text
    assert re.search(r'^CMD \["cranetwin", "serve"\]', text, re.MULTILINE)
    assert "serve" in _cli_commands()


# --- the distributed topology (docs/SCALING.md) --------------------------------------------------
FLEET = ROOT / "docker-compose.fleet.yml"


def _fleet() -> dict:  # type: ignore[type-arg]
    data = yaml.safe_load(FLEET.read_text())
    assert isinstance(data, dict)
    return data


def test_fleet_compose_config_resolves() -> None:
    cmd = _compose_command()
    if cmd is None:
        pytest.skip("neither `docker compose` nor `docker-compose` installed: config not checked")
    res = subprocess.run([*cmd, "-f", str(FLEET), "config", "--quiet"],
                         capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 0, res.stderr


def test_fleet_compose_has_each_role_twice_behind_one_proxy() -> None:
    services = _fleet()["services"]
    for role in ("ingest", "worker", "api"):
        assert {f"{role}-1", f"{role}-2"} <= set(services), role
    assert {"db", "nats", "proxy", "store-writer-a", "store-writer-b"} <= set(services)
    for name, svc in services.items():
        assert svc.get("healthcheck", {}).get("test"), f"{name} has no health check"
    # only the proxy is published: UDP for machines, HTTP for people and fleet tools
    published = {n for n, s in services.items() if s.get("ports")}
    assert published == {"proxy"}
    assert {"8000:8000", "5005:5005/udp"} == {str(p) for p in services["proxy"]["ports"]}
    conf = (ROOT / "deploy" / "nginx-fleet.conf").read_text()
    for target in ("api-1:8000", "api-2:8000", "ingest-1:5005", "ingest-2:5005"):
        assert target in conf, target
    assert "listen 5005 udp" in conf and "hash $remote_addr consistent" in conf


def test_fleet_compose_commands_and_options_exist() -> None:
    """Every cranetwin command and option the topology uses exists, and the bus and worker
    partition counts agree (the same machine → partition function lines them up)."""
    from typer.testing import CliRunner

    from cranetwin.cli import app

    services = _fleet()["services"]
    known = _cli_commands()
    writer_parts: list[str] = []
    for name, svc in services.items():
        cmd = svc.get("command")
        if not cmd or cmd[0] != "cranetwin":
            continue
        assert cmd[1] in known, f"{name} runs unknown command `cranetwin {cmd[1]}`"
        res = CliRunner().invoke(app, [cmd[1], "--help"], terminal_width=200)
        assert res.exit_code == 0, res.output
        for opt in [a for a in cmd[2:] if a.startswith("--")]:
            assert opt in res.output, f"`cranetwin {cmd[1]}` has no option {opt}"
        env = svc["environment"]
        assert env["CRANETWIN_BUS_URL"] == "nats://nats:4222"
        assert env["CRANETWIN_DATABASE_URL"].startswith("postgresql+psycopg://")
        if cmd[1] == "store-writer":
            writer_parts.append(cmd[cmd.index("--partitions") + 1])
        if cmd[1] == "worker":
            assert cmd[cmd.index("--of") + 1] == env["CRANETWIN_BUS_PARTITIONS"]
    # the two store-writers cover every bus partition exactly once
    covered: list[int] = []
    for spec in writer_parts:
        lo, hi = (int(x) for x in spec.split("-"))
        covered += range(lo, hi + 1)
    n = int(services["store-writer-a"]["environment"]["CRANETWIN_BUS_PARTITIONS"])
    assert sorted(covered) == list(range(n))
