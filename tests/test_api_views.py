"""Live frames take the rod velocity from the sample times the data carry, at any rate."""

from __future__ import annotations

import numpy as np
import pytest

from cranetwin.model import load_machine
from cranetwin.physics import cylinder_force
from cranetwin.service.views import LiveKinematics
from cranetwin.testing.blocks import kinematic_samples


@pytest.mark.parametrize("rate_hz", [20.0, 50.0, 100.0])
def test_live_force_uses_the_backward_difference_over_the_sample_times(rate_hz: float) -> None:
    machine = load_machine("patu655")
    s = kinematic_samples(machine, 2.0, rate_hz=rate_hz, t0_s=1_800_000_000.0)
    kin = LiveKinematics(machine, s.channels)
    (frame,) = kin.frames(s.t_s[-1:], s.values[-1:], s.values[-2], float(s.t_s[-2]))
    dt = float(s.t_s[-1] - s.t_s[-2])
    for c in machine.cylinders:
        col = {ch.quantity: s.channels.index(ch.name) for ch in machine.channels
               if ch.source == c.name and ch.name in s.channels}
        v = (s.values[-1, col["position"]] - s.values[-2, col["position"]]) / dt
        want = cylinder_force(np.array([s.values[-1, col["pressure_a"]]]),
                              np.array([s.values[-1, col["pressure_b"]]]), np.array([v]), c)
        assert frame["cylinder_forces"][c.name] == pytest.approx(float(want[0]), abs=0.1)


def test_a_previous_row_needs_its_time() -> None:
    machine = load_machine("patu655")
    s = kinematic_samples(machine, 1.0)
    with pytest.raises(ValueError, match="prev_t_s"):
        LiveKinematics(machine, s.channels).frames(s.t_s[-1:], s.values[-1:], s.values[-2])
