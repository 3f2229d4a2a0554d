"""Machine descriptions: the built-in crane loads; bad files report every problem by field path."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cranetwin.errors import MachineFileError
from cranetwin.model import builtin_machines, load_machine


def test_builtin_patu655_loads_with_paper_coordinates() -> None:
    m = load_machine("patu655")
    assert "patu655" in builtin_machines()
    assert [j.name for j in m.joints] == ["theta0", "theta1", "theta2", "L"]
    assert [j.kind for j in m.joints] == ["revolute", "revolute", "revolute", "prismatic"]
    lift = m.cylinder("lift")
    # published areas: A1 = 7.854e-3, A2 = 5.391e-3 m²
    assert lift.area_a_m2 == pytest.approx(7.854e-3, rel=1e-3)
    assert lift.area_b_m2 == pytest.approx(5.391e-3, rel=1e-3)
    assert m.body("lift_boom").mass_kg == pytest.approx(143.66)
    assert {c.name for c in m.channels} >= {"lift_pA", "lift_pB", "lift_s", "slew_torque"}


def test_rated_load_chart_interpolates_and_holds_ends() -> None:
    chart = load_machine("patu655").rated_load
    got = chart.payload_at(np.array([0.0, 2.5, 100.0]))
    assert got[0] == chart.payload_kg[0]
    assert got[2] == chart.payload_kg[-1]
    assert chart.payload_kg[1] < got[1] < chart.payload_kg[0]


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "m.toml"
    p.write_text(text)
    return p


def test_load_machine_lists_every_field_problem(tmp_path: Path) -> None:
    src = Path(__file__).parents[1] / "src/cranetwin/machines/patu655.toml"
    text = src.read_text()
    text = text.replace("mass_kg = 93.26", "mass_kg = -93.26")
    text = text.replace("axis = [1.0, 0.0, 0.0]", "axis = [2.0, 0.0, 0.0]")
    text = text.replace(
        "inertia_kgm2 = [[16.7, 0.0, 0.0], [0.0, 16.7, 0.0], [0.0, 0.0, 0.79]]",
        "inertia_kgm2 = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 5.0]]",
    )
    with pytest.raises(MachineFileError) as info:
        load_machine(_write(tmp_path, text))
    problems = info.value.problems
    assert any(p.startswith("bodies.0.mass_kg:") for p in problems)
    assert any(p.startswith("bodies.0.inertia_kgm2:") for p in problems)
    assert any(p.startswith("joints.3.axis:") and "unit vector" in p for p in problems)


def test_load_machine_reports_broken_references(tmp_path: Path) -> None:
    src = Path(__file__).parents[1] / "src/cranetwin/machines/patu655.toml"
    text = src.read_text().replace('joint = "theta2"', 'joint = "nope"')
    with pytest.raises(MachineFileError) as info:
        load_machine(_write(tmp_path, text))
    assert any("cylinders.1.joint" in p and "nope" in p for p in info.value.problems)


def test_load_machine_rejects_toml_syntax_and_missing_file(tmp_path: Path) -> None:
    with pytest.raises(MachineFileError, match="TOML syntax"):
        load_machine(_write(tmp_path, "[machine\nname="))
    with pytest.raises(MachineFileError, match="no such file"):
        load_machine(tmp_path / "missing.toml")


def test_field_errors_and_reference_errors_reported_together(tmp_path: Path) -> None:
    src = Path(__file__).parents[1] / "src/cranetwin/machines/patu655.toml"
    text = src.read_text().replace("mass_kg = 93.26", "mass_kg = -93.26")
    text = text.replace('body = "extension_boom"', 'body = "nowhere"')
    with pytest.raises(MachineFileError) as info:
        load_machine(_write(tmp_path, text))
    problems = info.value.problems
    assert any(p.startswith("bodies.0.mass_kg:") for p in problems)
    assert any(p.startswith("load_point.body:") and "nowhere" in p for p in problems)


def test_a_joint_without_an_actuator_needs_a_fixed_value() -> None:
    import tomllib
    from pathlib import Path

    from cranetwin.model import machine_from_dict

    path = Path(__file__).parents[1] / "src/cranetwin/machines/patu655.toml"
    data = tomllib.loads(path.read_text())
    data["torque_drives"] = []
    data["channels"] = [c for c in data["channels"] if c["source"] not in ("slew", "theta0")]
    with pytest.raises(Exception, match="fixed_value"):
        machine_from_dict(data, "no actuator")
    data["joints"][0]["fixed_value"] = 0.2
    m = machine_from_dict(data, "passive")
    assert m.joints[0].fixed_value == 0.2
    data["joints"][0]["fixed_value"] = 99.0
    with pytest.raises(Exception, match="within the limits"):
        machine_from_dict(data, "outside")
    data["joints"][0]["fixed_value"] = None
    data["joints"][1]["fixed_value"] = 0.5  # the lift has a cylinder
    with pytest.raises(Exception, match="only a passive joint"):
        machine_from_dict(data, "actuated and fixed")
