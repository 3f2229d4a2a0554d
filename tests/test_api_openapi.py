"""The OpenAPI document says what the server does, and docs/API.md lists every route.

Walks the generated document: every operation's real answers without a key, with a key of too
low a role, for an unknown machine and for a good request are statuses it documents, with a
documented content type (text/html for export.html, text/csv for a CSV export, …); a method a
path does not serve is 405 with ``Allow`` naming exactly the methods it does; bounds that are
settings are the running server's. Then the route table of docs/API.md against the app's routes.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from fastapi import FastAPI
from fastapi.routing import APIRoute, APIWebSocketRoute, iter_route_contexts
from fastapi.testclient import TestClient

from cranetwin.api import create_app
from cranetwin.model import load_machine
from cranetwin.settings import Settings
from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

T0 = 1795420800.0
MID = "crane-1"
API_MD = Path(__file__).resolve().parents[1] / "docs" / "API.md"
METHODS = ("get", "post", "put", "patch", "delete")


@dataclass
class Ctx:
    app: FastAPI
    client: TestClient
    keys: dict[str, str]
    schema: dict[str, Any]


@pytest.fixture(scope="module")
def ctx(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Ctx]:
    db = tmp_path_factory.mktemp("openapi") / "o.db"
    app = create_app(Settings(database_url=f"sqlite:///{db}", worker_in_process=False,
                              warm_up=False, max_samples_limit=5000, rate_limit=False))
    with TestClient(app, raise_server_exceptions=False) as client:
        services = app.state.services
        keys = {r: services.backend.create_key(r, r)[1] for r in ("viewer", "fleet", "admin")}
        machine = load_machine("patu655")
        services.backend.store.add_machine(MID, wire_id=1, secret=b"s" * 32)
        services.backend.store.write_blocks(list(tiled_blocks(
            MID, machine, T0, 30.0, 1.0, base=kinematic_samples(machine, 30.0))))
        yield Ctx(app, client, keys, client.get("/openapi.json").json())


def _operations(schema: dict[str, Any]) -> Iterator[tuple[str, str, dict[str, Any]]]:
    for path, item in schema["paths"].items():
        for method in METHODS:
            if method in item:
                yield path, method, item[method]


PATH_VALUES = {"page": "1", "element": "CumulativeOperatingHours",
               "start": "2026-11-23T08:00:00Z", "end": "2026-11-23T08:01:00Z", "event_id": "1"}
QUERY_VALUES = {"from": str(T0), "to": str(T0 + 10), "channels": "lift_pA",
                "channel": "lift_pA", "op": "gt", "value": "1e5"}
EXTRA_QUERY = {("/export", "format"): "csv", ("/report", "format"): "html"}


def _request(path: str, op: dict[str, Any], machine_id: str) -> tuple[str, dict[str, str]]:
    url = path.replace("{machine_id}", machine_id)
    for name, value in PATH_VALUES.items():
        url = url.replace("{" + name + "}", value)
    params = {p["name"]: QUERY_VALUES[p["name"]] for p in op.get("parameters", [])
              if p["in"] == "query" and p.get("required") and p["name"] in QUERY_VALUES}
    for (suffix, name), value in EXTRA_QUERY.items():
        if path.endswith(suffix):
            params[name] = value
    return url, params


def _documented(op: dict[str, Any], status: int) -> bool:
    return str(status) in op["responses"]


def _media(content_type: str) -> str:
    return content_type.split(";")[0].strip()


@pytest.mark.timeout(300)
def test_every_operation_answers_only_what_it_documents(ctx: Ctx) -> None:
    problems = []
    for path, method, op in _operations(ctx.schema):
        keyed = bool(op.get("security"))
        for who, machine_id in ((None, MID), ("viewer", MID), ("admin", "no-such-machine"),
                                ("admin", MID)):
            if who is not None and not keyed:
                continue
            if method != "get" and who == "admin":
                continue  # writes: the key checks only (their bodies are tested elsewhere)
            url, params = _request(path, op, machine_id)
            headers = {"X-API-Key": ctx.keys[who]} if who else {}
            r = ctx.client.request(method.upper(), url, params=params, headers=headers)
            label = f"{method.upper()} {path} ({who}, {machine_id})"
            if not _documented(op, r.status_code):
                problems.append(f"{label}: {r.status_code} not documented ({r.text[:120]})")
                continue
            if r.status_code == 204:
                continue
            content = op["responses"][str(r.status_code)].get("content", {})
            if _media(r.headers["content-type"]) not in content:
                problems.append(f"{label}: {r.status_code} as {r.headers['content-type']}, "
                                f"documented {sorted(content)}")
            if who is None and keyed:
                assert r.status_code == 401, label
            if machine_id != MID and "{machine_id}" in path:
                assert r.status_code == 404, (label, r.text[:200])
    assert not problems, "\n".join(problems)


@pytest.mark.timeout(60)
def test_every_keyed_operation_documents_401_429_and_503(ctx: Ctx) -> None:
    for path, method, op in _operations(ctx.schema):
        if op.get("security"):
            assert {"401", "429", "503"} <= set(op["responses"]), (method, path)
            assert "Retry-After" in op["responses"]["429"]["headers"], (method, path)


@pytest.mark.timeout(60)
def test_content_types_of_files_are_documented(ctx: Ctx) -> None:
    paths = ctx.schema["paths"]
    base = "/api/v1/machines/{machine_id}"
    assert set(paths[f"{base}/export.html"]["get"]["responses"]["200"]["content"]) == \
        {"text/html"}
    assert {"text/csv", "application/vnd.apache.parquet"} <= \
        set(paths[f"{base}/export"]["get"]["responses"]["200"]["content"])
    assert "text/plain" in paths["/metrics"]["get"]["responses"]["200"]["content"]
    assert "404" in paths[f"{base}/scene"]["get"]["responses"]


@pytest.mark.timeout(60)
def test_bounds_that_are_settings_are_the_servers(ctx: Ctx) -> None:
    op = ctx.schema["paths"]["/api/v1/machines/{machine_id}/samples"]["get"]
    limit = next(p for p in op["parameters"] if p["name"] == "limit")
    assert limit["schema"]["maximum"] == 5000  # the app's max_samples_limit
    r = ctx.client.get(f"/api/v1/machines/{MID}/samples", headers={
        "X-API-Key": ctx.keys["viewer"]}, params={"from": T0, "to": T0 + 1, "limit": 5000})
    assert r.status_code == 200, r.text  # the largest documented value is accepted


RANGE_PAIRS = (("from", "to"), ("start", "end"))
"""Parameter pairs that make a range: the second must be after the first."""


@pytest.mark.timeout(120)
def test_every_range_says_an_inverted_one_is_422_and_is_refused_so(ctx: Ctx) -> None:
    checked = []
    for path, method, op in _operations(ctx.schema):
        params = {p["name"]: p for p in op.get("parameters", [])}
        for lo, hi in RANGE_PAIRS:
            if lo not in params or hi not in params:
                continue
            label = f"{method.upper()} {path}"
            assert "422" in op["responses"], label
            text = params[hi].get("description", "")
            assert f"after `{lo}`" in text and "422" in text, (label, text)
            late, early = "2026-11-23T08:01:00Z", "2026-11-23T08:00:00Z"
            for t_lo, t_hi in ((late, early), (late, late)):  # inverted, then empty
                inverted = path.replace("{" + lo + "}", t_lo).replace("{" + hi + "}", t_hi)
                url, query = _request(inverted, op, MID)
                if params[lo]["in"] == "query":
                    query.update({lo: t_lo, hi: t_hi})
                r = ctx.client.get(url, params=query, headers={"X-API-Key": ctx.keys["admin"]})
                assert r.status_code == 422, (label, t_lo, t_hi, r.status_code, r.text[:200])
                assert _media(r.headers["content-type"]) in op["responses"]["422"]["content"]
            checked.append(label)
    assert len(checked) >= 9, checked  # the data routes, export.html, alarms, the AEMP series


@pytest.mark.timeout(120)
def test_a_method_a_path_does_not_serve_is_405_with_allow(ctx: Ctx) -> None:
    for path, item in ctx.schema["paths"].items():
        declared = {m.upper() for m in METHODS if m in item}
        other = next(m for m in ("PUT", "DELETE", "PATCH", "POST") if m not in declared)
        url, _ = _request(path, item[next(iter(m for m in METHODS if m in item))], MID)
        r = ctx.client.request(other, url, headers={"X-API-Key": ctx.keys["admin"]})
        assert r.status_code == 405, (other, path, r.status_code)
        allow = {m.strip() for m in r.headers["allow"].split(",")}
        assert declared <= allow <= declared | {"HEAD"}, (path, allow, declared)
        assert r.headers["content-type"].startswith("application/problem+json")


# --- docs/API.md --------------------------------------------------------------------------------
ROW = re.compile(r"^\| (GET|POST|PUT|PATCH|DELETE|WS) \| `([^`]+)` \|", re.M)


def _norm(path: str) -> str:
    return re.sub(r"\{[^}]*\}", "{}", path.split("?")[0])


def _app_routes(app: FastAPI) -> set[tuple[str, str]]:
    out = set()
    for ctx in iter_route_contexts(app.routes):
        route, path = ctx.original_route, str(ctx.path)
        if isinstance(route, APIWebSocketRoute):
            out.add(("WS", _norm(path)))
        elif isinstance(route, APIRoute) or path == "/openapi.json":
            out |= {(m, _norm(path)) for m in (ctx.methods or ()) if m != "HEAD"}
    return out


@pytest.mark.timeout(60)
def test_api_md_lists_every_route_of_the_app(ctx: Ctx) -> None:
    listed = {(m, _norm(p)) for m, p in ROW.findall(API_MD.read_text())}
    routes = _app_routes(ctx.app)
    assert routes - listed == set(), "routes missing from docs/API.md"
    assert listed - routes == set(), "docs/API.md lists routes the app does not have"
