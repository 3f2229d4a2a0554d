"""The simulator runs machines of other topologies: no slewing drive (a free slewing joint, or
no slewing joint at all)."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest

from cranetwin.model import Machine, load_machine, machine_from_dict
from cranetwin.physics import mass_matrix
from cranetwin.sim import Scenario, SensorModel, simulate
from cranetwin.sim.scenario import ActuatorProgram, InitialState

PATU = Path(__file__).parents[1] / "src/cranetwin/machines/patu655.toml"


@pytest.fixture(scope="module")
def free_slew() -> Machine:
    """The PATU 655 with its slewing drive removed: theta0 turns freely (no actuator; the
    schema requires one, so this is built past validation)."""
    m = load_machine("patu655")
    channels = [c for c in m.channels if c.quantity != "torque"]
    return m.model_copy(update={"torque_drives": [], "channels": channels})


def test_free_slewing_joint_keeps_its_angular_momentum(free_slew: Machine) -> None:
    # nothing acts about the vertical axis: p0 = (M(q)·qd)_0 is conserved while the lift moves
    sc = Scenario(name="spin", duration_s=4.0,
                  initial=InitialState(q=(0.0, 0.6, -1.6, 0.3), qd=(0.3, 0.0, 0.0, 0.0)),
                  actuators={"lift": ActuatorProgram(voltage=[(0.0, 0.0), (0.5, 8.0)]),
                             "extension": ActuatorProgram(voltage=[(0.0, 0.0), (1.0, 8.0)])})
    rec = simulate(free_slew, sc, sensors=SensorModel.ideal(), wrenches=False)
    tr = rec.truth
    assert tr.drive_torque.shape == (tr.n, 0) and np.isnan(tr.slew_torque).all()
    assert "slew_torque" not in rec.samples.channels
    p0 = np.einsum("nj,nj->n", mass_matrix(free_slew, tr.q, tr.payload_kg)[:, 0], tr.qd)
    assert np.ptp(tr.rod_s[:, 2]) > 0.3                 # the telescope really moved out
    assert np.ptp(tr.qd[:, 0]) > 0.02                   # ... and the slewing rate changed
    assert np.ptp(p0) < 1e-3 * abs(p0[0])


def test_crane_without_a_slewing_joint_runs() -> None:
    data = tomllib.loads(PATU.read_text())
    data["joints"] = data["joints"][1:]
    data["joints"][0]["parent"] = "world"
    data["bodies"] = data["bodies"][1:]
    data["torque_drives"] = []
    data["channels"] = [c for c in data["channels"] if c["source"] not in ("slew", "theta0")]
    data["fatigue"] = [f for f in data["fatigue"] if "theta0" not in f["load"]]
    m = machine_from_dict(data, "fixed-pillar")
    sc = Scenario(name="lift", duration_s=2.0, initial=InitialState(q=(0.6, -1.6, 0.3)),
                  actuators={"lift": ActuatorProgram(voltage=[(0.0, 0.0), (0.5, 6.0)])})
    rec = simulate(m, sc, seed=2)
    assert rec.truth.q.shape == (2001, 3) and rec.samples.values.shape == (201, 9)
    assert rec.truth.q[-1, 0] > rec.truth.q[0, 0] + 0.05


def _passive_slew(value: float) -> dict[str, object]:
    data = tomllib.loads(PATU.read_text())
    data["torque_drives"] = []
    data["channels"] = [c for c in data["channels"] if c["source"] not in ("slew", "theta0")]
    data["joints"][0]["fixed_value"] = value
    return data


def test_a_passive_joint_is_held_at_its_fixed_value_by_simulator_and_twin() -> None:
    from cranetwin.twin import replay

    m = machine_from_dict(_passive_slew(0.4), "passive-slew")
    sc = Scenario(name="lift", duration_s=3.0, initial=InitialState(q=(0.0, 0.6, -1.6, 0.3)),
                  actuators={"lift": ActuatorProgram(voltage=[(0.0, 0.0), (0.5, 6.0)]),
                             "extension": ActuatorProgram(voltage=[(0.0, 0.0), (1.0, 8.0)])})
    rec = simulate(m, sc, seed=3, wrenches=False)
    tr = rec.truth
    assert np.all(tr.q[:, 0] == 0.4) and np.all(tr.qd[:, 0] == 0.0)
    assert tr.q[-1, 1] > tr.q[0, 1] + 0.05  # the lift moved
    res = replay(rec, m, grid_hz=100, payload=float(tr.payload_kg[0]))
    assert np.all(res.q[:, 0] == 0.4)
    assert np.all(np.isnan(res.actuator_torque[:, 0]))  # its load is a reaction, not measured
    t = np.interp(res.t_s, tr.t_s, tr.q[:, 1])
    assert np.abs(res.q[20:-20, 1] - t[20:-20]).max() < 5e-3
    assert np.all(np.isfinite(res.joint_wrench))
