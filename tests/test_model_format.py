"""Machine-format additions: point masses folded into their body, the inertia frame stated,
per-cylinder dead volume, a sensor's stated accuracy."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from cranetwin.errors import MachineFileError
from cranetwin.model import Machine, load_machine, machine_from_dict

POINTS = [{"name": "bracket", "mass_kg": 35.0, "position_m": (0.4, 0.05, -0.1)},
          {"name": "valve block", "mass_kg": 12.0, "position_m": (1.2, -0.08, 0.12),
           "inertia_kgm2": ((0.05, 0.0, 0.0), (0.0, 0.04, 0.0), (0.0, 0.0, 0.03))}]


def _data() -> dict[str, Any]:
    return load_machine("patu655").model_dump(mode="python")


def _by_hand(body: dict[str, Any]) -> dict[str, Any]:
    """The body with POINTS folded in, written out term by term (Steiner for each part)."""
    parts = [(body["mass_kg"], np.array(body["com_m"]), np.array(body["inertia_kgm2"]))]
    parts += [(p["mass_kg"], np.array(p["position_m"]),
               np.array(p.get("inertia_kgm2", np.zeros((3, 3))))) for p in POINTS]
    m = sum(p[0] for p in parts)
    c = sum(p[0] * p[1] for p in parts) / m
    inertia = np.zeros((3, 3))
    for mi, xi, ii in parts:
        dx, dy, dz = xi - c
        steiner = mi * np.array([[dy**2 + dz**2, -dx * dy, -dx * dz],
                                 [-dx * dy, dx**2 + dz**2, -dy * dz],
                                 [-dx * dz, -dy * dz, dx**2 + dy**2]])
        inertia += ii + steiner
    return {**body, "mass_kg": m, "com_m": tuple(c), "inertia_kgm2": tuple(map(tuple, inertia))}


def _torques(machine: Machine, seed: int = 3) -> np.ndarray:
    from cranetwin import physics

    rng = np.random.default_rng(seed)
    n = 20
    lo = np.array([j.lower for j in machine.joints])
    hi = np.array([j.upper for j in machine.joints])
    q = lo + (hi - lo) * rng.uniform(0.2, 0.8, (n, machine.n_joints))
    qd = rng.normal(0.0, 0.3, q.shape)
    qdd = rng.normal(0.0, 1.0, q.shape)
    return np.asarray(physics.joint_torques(machine, q, qd, qdd, 150.0))


def test_point_masses_equal_the_body_folded_by_hand() -> None:
    """A boom with a bracket and a valve block attached gives the same body, and the same
    inverse dynamics, as the boom whose mass, centre and inertia were folded by hand; the
    loaded machine lists the masses it folded and dumps/reloads without folding twice."""
    data = _data()
    k = [b["name"] for b in data["bodies"]].index(data["joints"][2]["child"])
    hand = _data()
    hand["bodies"][k] = _by_hand(data["bodies"][k])
    data["bodies"][k] = {**data["bodies"][k], "point_masses": POINTS}
    with_points = machine_from_dict(data)
    folded = machine_from_dict(hand)
    a, b = with_points.bodies[k], folded.bodies[k]
    assert a.mass_kg == pytest.approx(b.mass_kg, rel=1e-14)
    np.testing.assert_allclose(a.com_m, b.com_m, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(a.inertia_kgm2, b.inertia_kgm2, rtol=1e-12, atol=1e-12)
    assert [p.name for p in a.folded_point_masses] == ["bracket", "valve block"]
    assert a.point_masses == [] and a.inertia_frame == "com"
    np.testing.assert_allclose(_torques(with_points), _torques(folded), rtol=1e-12, atol=1e-9)
    assert not np.allclose(_torques(with_points), _torques(load_machine("patu655")))
    again = Machine.model_validate(with_points.model_dump(mode="python"))
    assert again.bodies[k] == a


def test_inertia_about_the_body_origin_is_converted_to_the_centre_of_mass() -> None:
    """``inertia_frame = "origin"``: the inertia given about the body frame's origin equals,
    after loading, the file's inertia about the centre of mass (I_o = I_c + m·(|c|²E − ccᵀ))."""
    data = _data()
    body = data["bodies"][1]
    m, c = body["mass_kg"], np.array(body["com_m"])
    i_origin = np.array(body["inertia_kgm2"]) + m * (c @ c * np.eye(3) - np.outer(c, c))
    data["bodies"][1] = {**body, "inertia_kgm2": tuple(map(tuple, i_origin)),
                         "inertia_frame": "origin"}
    got = machine_from_dict(data).bodies[1]
    np.testing.assert_allclose(got.inertia_kgm2, body["inertia_kgm2"], atol=1e-9)
    assert got.inertia_frame == "com"


def test_bad_inertia_frame_and_point_mass_are_reported_with_their_field_path() -> None:
    data = _data()
    data["bodies"][1] = {**data["bodies"][1], "inertia_frame": "joint"}
    data["bodies"][2] = {**data["bodies"][2],
                         "point_masses": [{"mass_kg": -3.0, "position_m": (0, 0, 0)}]}
    with pytest.raises(MachineFileError) as err:
        machine_from_dict(data)
    text = str(err.value)
    assert "bodies.1.inertia_frame" in text
    assert "bodies.2" in text and "mass_kg" in text


def test_dead_volume_per_cylinder_reaches_the_simulator() -> None:
    """A cylinder's own dead volume replaces the circuit's in the simulator's parameters;
    the others keep the circuit's."""
    from cranetwin.sim.hydraulics import C_V0, pack

    data = _data()
    data["cylinders"][2] = {**data["cylinders"][2], "dead_volume_m3": 2.5e-4}
    m = machine_from_dict(data)
    cyl = pack(m).cyl
    assert cyl[2, C_V0] == 2.5e-4
    assert m.hydraulics is not None
    assert cyl[0, C_V0] == cyl[1, C_V0] == m.hydraulics.dead_volume_m3


def test_stated_accuracy_must_be_positive() -> None:
    data = _data()
    data["channels"][0] = {**data["channels"][0], "accuracy": -1.0}
    with pytest.raises(MachineFileError, match="channels.0.accuracy"):
        machine_from_dict(data)
