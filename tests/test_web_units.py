"""Numbers for people: event texts in kN·m, bar, %, never "2.84e+04 N*m"; the API rewrites stored
events' messages from their evidence."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from cranetwin.service.events import (
    event_message,
    format_duration,
    format_quantity,
    format_time,
    readable_message,
)


@pytest.mark.parametrize(("value", "unit", "text"), [
    (2.84e4, "N*m", "28.4 kN·m"), (3.2e6, "N*m", "3.2 MN·m"), (950.0, "N*m", "950 N·m"),
    (999.6, "N", "1000 N"), (2.12e7, "Pa", "212 bar"), (1234.0, "kg", "1.23 t"),
    (450.4, "kg", "450 kg"), (0.52, "rad/s", "0.52 rad/s"), (0.004, "", "0.4 %"),
    (1.5e-6, "m", "0 m"), (float("nan"), "N", "–"), (-4.5e4, "N", "-45 kN"),
])
def test_quantities_read_like_a_person_writes_them(value: float, unit: str, text: str) -> None:
    assert format_quantity(value, unit) == text


@pytest.mark.parametrize(("seconds", "text"), [
    (0.4, "0 s"), (59.6, "60 s"), (119.0, "119 s"), (120.0, "2 min"), (200.0, "3 min 20 s"),
    (7199.0, "119 min 59 s"), (7200.0, "2 h"), (7530.0, "2 h 5 min"), (172_799.0, "47 h 59 min"),
    (3 * 86400 + 4 * 3600 + 59.0, "3 d 4 h"), (-1.0, "–"), (float("inf"), "–"),
])
def test_durations_read_like_a_person_says_them(seconds: float, text: str) -> None:
    assert format_duration(seconds) == text


def test_times_are_utc_to_the_second() -> None:
    assert format_time(1_796_208_899.99) == "2026-12-02 10:54:59 UTC"


def test_event_messages_have_no_exponents_or_asterisks() -> None:
    msg = event_message("overload", "load", 2.84e4, 2.0e4, "N*m")
    assert msg == "overload on load: 28.4 kN·m (limit 20 kN·m, 142 % of it)"
    for v, lim, u in ((4.5, 0.52, "rad/s"), (2.1e7, 2e7, "Pa"), (3.3e6, 1e6, "N/s"),
                      (1e-9, 1.0, "m/s"), (5e9, 1e9, "N")):
        m = event_message("k", "c", v, lim, u)
        assert not re.search(r"\de[+-]?\d", m) and "*" not in m, m
    assert readable_message("overload", {"value": "x"}, "stored") == "stored"


@pytest.mark.timeout(30)
def test_the_events_api_returns_readable_messages(tmp_path: Path) -> None:
    from cranetwin.analytics import Event
    from cranetwin.api import create_app
    from cranetwin.service.analytics import stored_events
    from cranetwin.settings import Settings

    app = create_app(Settings(database_url=f"sqlite:///{tmp_path}/u.db",
                              worker_in_process=False))
    with TestClient(app) as client:
        services = app.state.services
        admin = services.backend.create_key("admin", "t")[1]
        h = {"X-API-Key": admin}
        assert client.post("/api/v1/machines", headers=h,
                           json={"machine_id": "c1", "model": "patu655"}).status_code == 201
        ev = Event("overload", 1000.0, 1001.0, "warning", "load", 2.84e4, 2.0e4, "N*m")
        services.backend.store.add_events(stored_events("c1", [ev]))
        r = client.get("/api/v1/machines/c1/events?from=900&to=1100", headers=h)
        assert r.status_code == 200, r.text
        (got,) = r.json()
        assert got["message"] == "overload on load: 28.4 kN·m (limit 20 kN·m, 142 % of it)"
        assert got["evidence"]["value"] == pytest.approx(2.84e4)  # evidence stays SI
