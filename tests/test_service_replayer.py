"""The service's replayer keeps a machine's smoothing choice between replays; a later replay with
fewer samples than a kept window chooses on its own samples instead of failing."""

from __future__ import annotations

import importlib

import numpy as np
import pytest

from cranetwin.model import load_machine
from cranetwin.service.replayer import Replayer
from cranetwin.testing.blocks import kinematic_samples

pytestmark = pytest.mark.timeout(180)


def test_a_short_span_after_a_long_smooth_one_is_replayed() -> None:
    machine = load_machine("patu655")
    rate = 10.0
    long = kinematic_samples(machine, 40.0, rate_hz=rate)
    rp = Replayer()
    first = rp.replay("m", machine, long, rate)
    kept = [c.window for c in first.smoothing.values() if not c.adaptive]
    short_n = 60  # 6 s at 10 Hz, as a worker's span with its margins
    assert max(kept) > short_n, "the case needs a kept window longer than the short span"
    later = kinematic_samples(machine, 46.0, rate_hz=rate)
    keep = later.t_s >= later.t_s[-1] - (short_n - 0.5) / rate
    short = later.take(keep)
    assert short.t_s.shape[0] == short_n
    res = rp.replay("m", machine, short, rate)
    assert res.n > 0 and np.all(np.isfinite(res.cyl_force))


def test_a_span_a_little_longer_than_a_kept_window_is_replayed() -> None:
    """More samples than the kept window, but fewer than it plus the stream's look-ahead (50
    samples): the replay smoothed the first part of the span before the rest was in, on fewer
    rows than the window, and failed (seen on the fleet senders' data at 10 Hz: 18-s spans,
    window 131)."""
    machine = load_machine("patu655")
    rate = 10.0
    rp = Replayer()
    first = rp.replay("m", machine, kinematic_samples(machine, 40.0, rate_hz=rate), rate)
    kept = max(c.window for c in first.smoothing.values() if not c.adaptive)
    n = kept + 20
    later = kinematic_samples(machine, 80.0, rate_hz=rate)
    span = later.take(later.t_s >= later.t_s[-1] - (n - 0.5) / rate)
    assert span.t_s.shape[0] == n
    res = rp.replay("m", machine, span, rate)
    assert res.n == n and np.all(np.isfinite(res.cyl_force))


def test_the_choice_of_a_short_span_is_kept_for_spans_as_long(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Spans shorter than the machine's windows choose on their own samples once per length,
    not at every span (the worker's 10-Hz spans: choosing cost more than the rest)."""
    twin_replay = importlib.import_module("cranetwin.twin.replay")  # (the package exports
    # a function of that name)
    machine = load_machine("patu655")
    rate = 10.0
    rp = Replayer()
    rp.replay("m", machine, kinematic_samples(machine, 40.0, rate_hz=rate), rate)
    calls: list[int] = []
    choose = twin_replay.choose_smoothing

    def counted(*args: object, **kw: object) -> object:
        calls.append(1)
        return choose(*args, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(twin_replay, "choose_smoothing", counted)
    later = kinematic_samples(machine, 70.0, rate_hz=rate)
    spans = [later.take((later.t_s >= a) & (later.t_s < a + 6.0)) for a in (40.0, 46.0, 52.0)]
    results = [rp.replay("m", machine, s, rate) for s in spans]
    assert len(calls) == 1
    assert all(r.smoothing == results[0].smoothing for r in results)
    other = later.take((later.t_s >= 58.0) & (later.t_s < 62.0))  # another length: its own
    rp.replay("m", machine, other, rate)
    assert len(calls) == 2
