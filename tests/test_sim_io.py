"""Scenario files, the sensor model and Recording files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cranetwin.errors import ScenarioError, SimulationError
from cranetwin.model import Machine, load_machine
from cranetwin.sim import (
    Prepared,
    Recording,
    ScenarioFileError,
    SensorModel,
    load_scenario,
    prepare,
    scenario_from_dict,
    simulate,
)
from cranetwin.sim.scenario import InitialState
from cranetwin.sim.sensors import sample_steps

VALID_TOML = """
name = "nudge"
duration_s = 1.5
[initial]
q = [0.0, 0.6, -1.6, 0.3]
payload_kg = 100.0
[actuators.lift]
voltage = [[0, 0], [0.2, 0], [0.2, 6], [1.0, 6], [1.2, 0]]
[actuators.slew]
target = [[0, 0], [1.5, 0.2]]
gain = 30.0
[[payload]]
t_s = 1.0
mass_kg = 0.0
"""


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load_machine("patu655")


@pytest.fixture(scope="module")
def prep(machine: Machine) -> Prepared:
    return prepare(machine)


@pytest.fixture(scope="module")
def recording(prep: Prepared) -> Recording:
    return simulate(prep, load_scenario("fig3"), duration_s=2.0, seed=7)


def test_valid_toml_and_json_scenarios_run(tmp_path: Path, prep: Prepared) -> None:
    toml_file = tmp_path / "nudge.toml"
    toml_file.write_text(VALID_TOML)
    sc = load_scenario(toml_file)
    assert sc.name == "nudge" and sc.payload[0].mass_kg == 0.0
    json_file = tmp_path / "nudge.json"
    json_file.write_text(json.dumps(sc.model_dump()))
    assert load_scenario(json_file) == sc
    rec = simulate(prep, sc, sensors=SensorModel.ideal())
    tr = rec.truth
    assert tr.rod_s[-1, 0] > tr.rod_s[0, 0] + 0.01       # the lift valve opened
    assert tr.q[-1, 0] > 0.02                             # the operator slewed toward 0.2 rad
    assert tr.payload_kg[0] == 100.0 and tr.payload_kg[-1] == 0.0


@pytest.mark.parametrize(("text", "path"), [
    ('name = "x"\n[actuators.lift]\nvoltage = [[0, 0], [1, 12]]\n', "actuators.lift"),
    ('name = "x"\n[actuators.jib]\nvoltage = [[1, 0], [0.5, 2]]\n', "actuators.jib"),
    ('name = "x"\n[initial]\npayload_kg = -5\n', "initial.payload_kg"),
    ('name = "x"\n[[payload]]\nt_s = "soon"\nmass_kg = 1\n', "payload.0.t_s"),
    ('name = "x"\nduration_s = 0\n', "duration_s"),
])
def test_malformed_scenario_names_the_field(tmp_path: Path, text: str, path: str) -> None:
    f = tmp_path / "bad.toml"
    f.write_text(text)
    with pytest.raises(ScenarioFileError) as exc:
        load_scenario(f)
    assert any(p.startswith(path) for p in exc.value.problems), exc.value.problems
    assert str(f) in str(exc.value)


def test_unreadable_scenarios_raise_scenario_error(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("name = [unclosed")
    with pytest.raises(ScenarioError, match="syntax"):
        load_scenario(bad)
    with pytest.raises(ScenarioError, match="built-in"):
        load_scenario("no-such-scenario")
    with pytest.raises(ScenarioError, match="cannot read"):
        load_scenario(tmp_path / "missing.json")


def test_initial_pose_outside_the_stroke_is_a_scenario_error(prep: Prepared) -> None:
    sc = load_scenario("fig3").model_copy(
        update={"initial": InitialState(q=(0.0, 1.9, -1.0, 0.3))})
    with pytest.raises(ScenarioError, match="lift rod"):
        simulate(prep, sc, duration_s=0.1)


def test_builtin_scenarios_are_seeded() -> None:
    a = load_scenario("random", seed=1)
    assert a == load_scenario("random", seed=1)
    assert a != load_scenario("random", seed=2)
    ll = load_scenario("log-loading", seed=1, duration_s=60.0, payload_kg=400.0)
    grabs = [e.mass_kg for e in ll.payload if e.mass_kg > 0]
    assert len(grabs) >= 2 and all(340 <= m <= 460 for m in grabs)


def test_sensor_readings_are_quantised_and_in_range(machine: Machine,
                                                    recording: Recording) -> None:
    smp = recording.samples
    assert smp.channels == tuple(c.name for c in machine.channels)
    assert np.allclose(np.diff(smp.t_s), 0.01)
    for j, name in enumerate(smp.channels):
        ch = machine.channel(name)
        col = smp.values[:, j]
        ok = col[np.isfinite(col)]
        steps = ok / ch.resolution
        assert np.allclose(steps, np.round(steps), atol=1e-6)
        assert ok.min() >= ch.min and ok.max() <= ch.max


def test_ideal_sensors_read_the_truth(prep: Prepared, machine: Machine) -> None:
    rec = simulate(prep, load_scenario("fig3"), duration_s=1.0, sensors=SensorModel.ideal())
    smp, tr = rec.samples, rec.truth
    # 100 Hz samples without jitter land on every 10th 1-kHz truth row
    idx = np.searchsorted(tr.t_s, smp.t_s)
    assert np.allclose(tr.t_s[idx], smp.t_s)
    half = {c.name: c.resolution / 2 + 1e-9 for c in machine.channels}
    assert np.all(np.abs(smp.column("lift_pA") - tr.p_a[idx, 0]) <= half["lift_pA"])
    assert np.all(np.abs(smp.column("jib_s") - tr.rod_s[idx, 1]) <= half["jib_s"])
    assert np.all(np.abs(smp.column("slew_torque") - tr.slew_torque[idx]) <= half["slew_torque"])
    assert not np.isnan(smp.values).any()


def test_noise_bias_dropouts_and_seed(prep: Prepared) -> None:
    noisy = SensorModel(noise_fraction=2e-3, bias_fraction=1e-3, dropout_probability=0.05,
                        jitter_s=1e-3)
    sc = load_scenario("fig3")
    a = simulate(prep, sc, duration_s=3.0, sensors=noisy, seed=5)
    b = simulate(prep, sc, duration_s=3.0, sensors=noisy, seed=5)
    c = simulate(prep, sc, duration_s=3.0, sensors=noisy, seed=6)
    assert np.array_equal(a.samples.values, b.samples.values, equal_nan=True)
    assert not np.array_equal(a.samples.values, c.samples.values, equal_nan=True)
    lost = np.isnan(a.samples.values).mean()
    assert 0.01 < lost < 0.12
    ideal = simulate(prep, sc, duration_s=3.0, sensors=SensorModel.ideal())
    err = a.samples.column("lift_pA") - ideal.samples.column("lift_pA")
    err = err[np.isfinite(err)]
    assert 0.2 * 2e-3 * 25e6 < err.std() < 5 * 2e-3 * 25e6


def test_jittered_sampling_steps_stay_ordered() -> None:
    rng = np.random.default_rng(0)
    t, steps = sample_steps(2.0, 1e-4, SensorModel(jitter_s=3e-3), rng)
    assert len(t) == 201 and np.all(np.diff(steps) >= 0)
    assert steps.min() >= 0 and steps.max() <= 20000
    assert np.abs(steps * 1e-4 - t).max() <= 0.4 * 0.01 + 1e-4


@pytest.mark.parametrize("suffix", [".npz", ".csv"])
def test_recording_round_trips(tmp_path: Path, recording: Recording, suffix: str) -> None:
    path = recording.save(tmp_path / f"rec{suffix}")
    back = Recording.load(path)
    assert back.machine == recording.machine and back.seed == 7
    assert back.samples.channels == recording.samples.channels
    assert np.array_equal(back.samples.values, recording.samples.values, equal_nan=True)
    assert np.array_equal(back.samples.t_s, recording.samples.t_s)
    for name in ("q", "qdd", "p_a", "cyl_force", "joint_wrench", "payload_kg", "u"):
        assert np.array_equal(getattr(back.truth, name), getattr(recording.truth, name))
    assert back.meta == recording.meta
    if suffix == ".csv":
        assert (tmp_path / "rec.truth.csv").exists()


def test_loading_a_foreign_file_is_a_clear_error(tmp_path: Path) -> None:
    f = tmp_path / "x.csv"
    f.write_text("a,b\n1,2\n")
    with pytest.raises(SimulationError, match="not a readable cranetwin recording"):
        Recording.load(f)


def test_live_session_in_chunks_matches_the_batch_run(prep: Prepared) -> None:
    from cranetwin.sim import Session

    sensors = SensorModel.ideal().model_copy(update={"jitter_s": 1e-3})
    sc = load_scenario("log-loading", duration_s=30.0)
    batch = simulate(prep, sc, duration_s=1.5, sensors=sensors, seed=3)
    live = Session(prep, sc, sensors=sensors, seed=3, start_epoch_s=0.0)
    blocks = [live.advance(dt) for dt in (0.13, 0.5, 0.37)]
    blocks.append(live.advance(0.5, final=True))
    t = np.concatenate([b.t_s for b in blocks])
    v = np.concatenate([b.values for b in blocks])
    assert np.array_equal(t, batch.samples.t_s)
    assert np.array_equal(v, batch.samples.values)
    assert np.array_equal(live.truth(wrenches=False).q, batch.truth.q)
    assert live.t_s == pytest.approx(1.5)
    with pytest.raises(SimulationError, match="finished"):
        live.advance(0.1)


def test_actuators_the_machine_lacks_are_named(prep: Prepared) -> None:
    sc = scenario_from_dict({"name": "x", "actuators": {"boom": {"voltage": []}},
                             "initial": {"q": [0.0, 0.6, -1.6]}})
    with pytest.raises(ScenarioFileError) as exc:
        simulate(prep, sc, duration_s=0.1)
    assert any(p.startswith("actuators.boom:") for p in exc.value.problems)
    assert any(p.startswith("initial.q:") and "one per joint" in p for p in exc.value.problems)


def test_targets_outside_the_machine_are_named(prep: Prepared, tmp_path: Path) -> None:
    f = tmp_path / "far.toml"
    f.write_text('name = "far"\n[actuators.lift]\ntarget = [[0, 0.3], [2, 0.9]]\n'
                 '[actuators.slew]\ntarget = [[0, 0.0], [1, 4.0]]\n')
    with pytest.raises(ScenarioFileError) as exc:
        simulate(prep, load_scenario(f), duration_s=0.1)
    assert any(p.startswith("actuators.lift.target.1:") for p in exc.value.problems)
    assert any(p.startswith("actuators.slew.target.1:") for p in exc.value.problems)


def test_recording_cuts_into_sample_blocks(recording: Recording, machine: Machine) -> None:
    blocks = recording.blocks(samples_per_block=25, first_seq=100)
    assert [b.seq for b in blocks] == list(range(100, 100 + len(blocks)))
    assert sum(b.n for b in blocks) == recording.samples.values.shape[0]
    assert blocks[0].period_ns == 10_000_000
    assert blocks[0].resolution == tuple(machine.channel(c).resolution
                                         for c in recording.samples.channels)
    times = np.concatenate([b.times_ns() for b in blocks]) / 1e9
    assert np.allclose(times, recording.samples.t_s, atol=1e-9)
    assert np.array_equal(np.concatenate([b.values for b in blocks]), recording.samples.values,
                          equal_nan=True)
