"""Property test of the API against its own OpenAPI document (schemathesis).

Every documented operation (the web front end's scene and export.html too) is called with
generated parameters and bodies (admin key, so that
authorisation does not hide the handlers), and every response must be no 5xx, carry a documented
status code and content type, and match the documented schema. Bounded: a fixed number of
examples per operation, no deadline.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import schemathesis
from fastapi import FastAPI
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from schemathesis import checks

from cranetwin.api import create_app
from cranetwin.model import load_machine
from cranetwin.settings import Settings
from cranetwin.testing.blocks import kinematic_samples, tiled_blocks

T0 = 1795420800.0
# schema-level checks; positive_data_acceptance is left out on purpose: a schema-valid request
# may still be a bad one (an inverted time range, an unknown channel name) and get a 4xx
CHECKS = [checks.not_a_server_error, checks.status_code_conformance,
          checks.content_type_conformance, checks.response_schema_conformance,
          checks.response_headers_conformance]


def _app(tmp: str) -> tuple[FastAPI, TestClient, str]:
    # rate limit off: the handlers are what is under test (429 is documented and tested in
    # test_api_limits.py and test_api_openapi.py)
    app = create_app(Settings(database_url=f"sqlite:///{tmp}/schema.db", worker_in_process=False,
                              max_analytics_range_s=120.0, rate_limit=False))
    client = TestClient(app)
    client.__enter__()
    services = app.state.services
    _, admin = services.backend.create_key("admin", "schemathesis")
    machine = load_machine("patu655")
    services.backend.store.add_machine("crane-1", wire_id=1, secret=b"s" * 32)
    services.backend.store.write_blocks(list(tiled_blocks(
        "crane-1", machine, T0, 30.0, 1.0, base=kinematic_samples(machine, 30.0))))
    return app, client, admin


@pytest.mark.slow
def test_api_conforms_to_its_openapi(tmp_path: Path) -> None:
    app, client, admin = _app(str(tmp_path))
    try:
        schema = schemathesis.openapi.from_asgi("/openapi.json", app)
        operations = [r.ok() for r in schema.get_all_operations()]
        assert len(operations) >= 28  # the web front end's scene and export.html included
        headers = {"X-API-Key": admin}
        for op in operations:

            @given(case=op.as_strategy())
            @settings(max_examples=15, deadline=None, derandomize=True,
                      suppress_health_check=list(HealthCheck), database=None)
            def run(case: schemathesis.Case) -> None:
                case.call_and_validate(headers=headers, checks=CHECKS)

            run()
    finally:
        client.__exit__(None, None, None)
