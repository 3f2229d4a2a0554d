"""Kinematics: closed forms, finite differences, round trips, pins, reach validation."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from cranetwin.errors import PhysicsError
from cranetwin.model import Machine, load_machine, machine_from_dict
from cranetwin.physics import (
    body_poses,
    cylinder_lengths,
    cylinder_pins,
    horizontal_reach,
    joints_from_cylinders,
    load_point_position,
    moment_arms,
    reach_problems,
)


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load_machine("patu655")


def working_grid(machine: Machine, n: int = 400, seed: int = 0) -> np.ndarray:
    """Joint positions inside the joint limits and with every rod inside its stroke."""
    rng = np.random.default_rng(seed)
    lo = np.array([j.lower for j in machine.joints])
    hi = np.array([j.upper for j in machine.joints])
    q = rng.uniform(lo, hi, size=(4 * n, machine.n_joints))
    s = cylinder_lengths(machine, q)
    stroke = np.array([c.stroke_m for c in machine.cylinders])
    keep = np.all((s >= 0) & (s <= stroke), axis=1)
    assert keep.sum() >= n
    return q[keep][:n]


def test_lift_cylinder_matches_published_triangle(machine: Machine) -> None:
    """s1 = sqrt(a² + b² − 2ab·cos(theta1 + gamma)) with the constants of the reference."""
    a, b, gamma = 1.07199, 0.32021, np.radians(56.821)
    th = np.linspace(machine.joints[1].lower, machine.joints[1].upper, 50)
    q = np.zeros((50, 4))
    q[:, 1] = th
    length = np.sqrt(a * a + b * b - 2 * a * b * np.cos(th + gamma))
    s = cylinder_lengths(machine, q)[:, 0]
    np.testing.assert_allclose(s + 0.82, length, atol=2e-5)   # published constants: 5 digits
    arm = a * b * np.sin(th + gamma) / length
    np.testing.assert_allclose(moment_arms(machine, q)[:, 0], arm, atol=2e-5)
    # the limits are the lift cylinder's end stops
    assert abs(s[0]) < 1e-3 and abs(s[-1] - 0.535) < 1e-3


def test_four_bar_satisfies_its_link_constraints(machine: Machine) -> None:
    q = working_grid(machine, 50)
    pins = cylinder_pins(machine, q)
    lk = machine.cylinders[1].linkage
    assert lk is not None
    e, d, f = pins.rod[:, 1], pins.pivot[:, 1], pins.coupler[:, 1]
    np.testing.assert_allclose(np.linalg.norm(e - d, axis=1), lk.pivot_link_m, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(e - f, axis=1), lk.coupler_link_m, atol=1e-12)
    # branch +1: (F − D) × (E − D) along the joint axis (−y of the boom plane, in the world)
    axis_world = body_poses(machine, q)[:, 1, :3, :3] @ np.array(machine.joints[2].axis)
    side = np.einsum("ni,ni->n", np.cross(f - d, e - d), axis_world)
    assert np.all(side > 0)
    # the reference: ds/dtheta2 < 0 and |ds/dtheta2| between about 0.11 and 0.33 m
    arm = moment_arms(machine, q)[:, 1]
    assert np.all(arm < 0) and np.all((-arm > 0.10) & (-arm < 0.34))


def test_pin_distance_equals_rod_position_plus_closed_length(machine: Machine) -> None:
    q = working_grid(machine, 100)
    pins = cylinder_pins(machine, q)
    closed = np.array([c.closed_length_m for c in machine.cylinders])
    np.testing.assert_allclose(np.linalg.norm(pins.rod - pins.base, axis=2) - closed,
                               cylinder_lengths(machine, q), atol=1e-12)


def test_moment_arms_match_finite_differences(machine: Machine) -> None:
    q = working_grid(machine, 100)
    h = 1e-6
    arms = moment_arms(machine, q)
    for k, cyl in enumerate(machine.cylinders):
        j = machine.joint_index(cyl.joint)
        qp, qm = q.copy(), q.copy()
        qp[:, j] += h
        qm[:, j] -= h
        fd = (cylinder_lengths(machine, qp)[:, k] - cylinder_lengths(machine, qm)[:, k]) / (2 * h)
        np.testing.assert_allclose(arms[:, k], fd, rtol=0, atol=1e-8)


def test_q_to_s_to_q_round_trip(machine: Machine) -> None:
    q = working_grid(machine, 400)
    s = cylinder_lengths(machine, q)
    back = joints_from_cylinders(machine, s, q[:, 0])
    np.testing.assert_allclose(back, q, rtol=0, atol=1e-12)
    # and across each cylinder's whole stroke inside the joint limits
    for cyl in machine.cylinders:
        j = machine.joint_index(cyl.joint)
        grid = np.zeros((2001, 4))
        grid[:, j] = np.linspace(machine.joints[j].lower, machine.joints[j].upper, 2001)
        sk = cylinder_lengths(machine, grid)
        inside = np.all((sk >= 0) & (sk <= [c.stroke_m for c in machine.cylinders]), axis=1)
        back = joints_from_cylinders(machine, sk[inside], grid[inside, 0])
        np.testing.assert_allclose(back[:, j], grid[inside, j], rtol=0, atol=1e-12)


def test_unreachable_rod_position_raises(machine: Machine) -> None:
    with pytest.raises(PhysicsError, match="lift"):
        joints_from_cylinders(machine, [[5.0, 0.3, 0.3]], [0.0])
    with pytest.raises(PhysicsError, match="expected shape"):
        joints_from_cylinders(machine, [[0.1, 0.3]])


def test_body_poses_are_rigid_and_reach_matches_reference(machine: Machine) -> None:
    q = working_grid(machine, 50)
    poses = body_poses(machine, q)
    rot = poses[..., :3, :3]
    eye = np.broadcast_to(np.eye(3), rot.shape)
    np.testing.assert_allclose(rot @ np.swapaxes(rot, -1, -2), eye, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-12)
    # slewing turns the tip about z without changing height or reach
    q2 = q.copy()
    q2[:, 0] += 0.7
    t1, t2 = load_point_position(machine, q), load_point_position(machine, q2)
    np.testing.assert_allclose(t1[:, 2], t2[:, 2], atol=1e-12)
    np.testing.assert_allclose(horizontal_reach(machine, q), horizontal_reach(machine, q2),
                               atol=1e-12)
    # booms straight and level, telescope retracted: reach ≈ 4.87 m (reference)
    assert abs(horizontal_reach(machine, np.zeros(4))[0] - 4.87) < 0.01


def _patu_dict() -> dict[str, object]:
    import tomllib
    from importlib import resources

    text = (resources.files("cranetwin") / "machines" / "patu655.toml").read_text("utf-8")
    return tomllib.loads(text)


def test_reach_problems_passes_builtin(machine: Machine) -> None:
    assert reach_problems(machine) == []


def test_reach_problems_flags_bad_pins() -> None:
    data = _patu_dict()
    cyls = data["cylinders"]
    assert isinstance(cyls, list)
    cyls[0]["base_pin_m"] = [0.17, 0.0, -1.5]          # lift base pin far below: too long
    cyls[1]["linkage"]["pivot_link_m"] = 0.05          # four-bar swings the rod end too little
    problems = reach_problems(machine_from_dict(data))
    assert len(problems) == 2
    assert problems[0].startswith("cylinders.0.base_pin_m: pin-to-pin length spans only")
    assert "needs 0.82 … 1.355 m" in problems[0]
    assert problems[1].startswith("cylinders.1.linkage: pin-to-pin length spans only")
    cyls[1]["linkage"]["pivot_link_m"] = 0.4578
    cyls[1]["linkage"]["coupler_link_m"] = 2.0         # longer than D and F can ever be apart
    problems = reach_problems(machine_from_dict(data))
    assert problems[-1].startswith("cylinders.1.linkage: the linkage cannot assemble at any")


def test_reach_problems_flags_joint_limits_beyond_stroke() -> None:
    data = _patu_dict()
    joints = data["joints"]
    assert isinstance(joints, list)
    joints[1]["lower"] = -0.8                          # lift boom below the closed cylinder
    problems = reach_problems(machine_from_dict(data))
    assert len(problems) == 1 and problems[0].startswith("cylinders.0: rod position runs")


def test_model_validate_cli_reports_bad_pins(tmp_path: Path) -> None:
    import tomli_w
    from typer.testing import CliRunner

    from cranetwin.cli import app

    data = _patu_dict()
    cyls = data["cylinders"]
    assert isinstance(cyls, list)
    cyls[0]["base_pin_m"] = [0.17, 0.0, -1.5]
    path = tmp_path / "bad.toml"
    path.write_bytes(tomli_w.dumps(data).encode())
    res = CliRunner().invoke(app, ["model", "validate", str(path)])
    assert res.exit_code == 1
    assert "cylinders.0.base_pin_m: pin-to-pin length spans only" in res.output


def test_physics_import_does_not_pull_web_or_database() -> None:
    code = textwrap.dedent("""
        import sys
        import cranetwin.physics
        import cranetwin.physics.kernels
        bad = [m for m in ("fastapi", "sqlalchemy", "starlette") if m in sys.modules]
        assert not bad, bad
        print("ok")
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=False)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


def test_moment_arm_rates_match_finite_differences(machine: Machine) -> None:
    from cranetwin.physics import moment_arm_rates

    q = working_grid(machine, 100, seed=4)
    h = 1e-6
    rates = moment_arm_rates(machine, q)
    for k, cyl in enumerate(machine.cylinders):
        j = machine.joint_index(cyl.joint)
        qp, qm = q.copy(), q.copy()
        qp[:, j] += h
        qm[:, j] -= h
        fd = (moment_arms(machine, qp)[:, k] - moment_arms(machine, qm)[:, k]) / (2 * h)
        np.testing.assert_allclose(rates[:, k], fd, rtol=0, atol=1e-8)


def test_joint_motion_from_cylinders_inverts_the_chain_rule(machine: Machine) -> None:
    from cranetwin.physics import joint_motion_from_cylinders

    t = np.linspace(0.0, 3.0, 301)
    mid = np.array([0.2, 0.5, -1.3, 0.5])
    amp = np.array([0.5, 0.3, 0.5, 0.3])
    w = np.array([1.1, 1.7, 1.3, 2.0])
    q = mid + amp * np.sin(np.outer(t, w))
    qd = amp * w * np.cos(np.outer(t, w))
    qdd = -amp * w**2 * np.sin(np.outer(t, w))
    # rod motion by finite differences in time of s(q(t)) (independent of the chain rule)
    h = 1e-4
    s = cylinder_lengths(machine, q)
    sp = cylinder_lengths(machine, mid + amp * np.sin(np.outer(t + h, w)))
    sm = cylinder_lengths(machine, mid + amp * np.sin(np.outer(t - h, w)))
    v = (sp - sm) / (2 * h)
    a = (sp - 2 * s + sm) / h**2
    q2, qd2, qdd2 = joint_motion_from_cylinders(machine, s, v, a, q[:, 0], qd[:, 0], qdd[:, 0])
    np.testing.assert_allclose(q2, q, atol=1e-12)
    np.testing.assert_allclose(qd2, qd, atol=1e-7)
    np.testing.assert_allclose(qdd2, qdd, atol=1e-4)


def test_reach_problems_flags_dead_centre_inside_working_range() -> None:
    data = _patu_dict()
    cyls, joints = data["cylinders"], data["joints"]
    assert isinstance(cyls, list) and isinstance(joints, list)
    # shortest pin distance 0.7518 m (at theta1 = −56.8°) ≈ closed length, and the joint limits
    # reach both sides of it: the lever changes sign inside the working range
    cyls[0]["closed_length_m"] = 0.752
    joints[1]["lower"] = -1.6
    joints[1]["upper"] = 0.99
    problems = reach_problems(machine_from_dict(data))
    assert len(problems) == 1
    assert problems[0].startswith("cylinders.0.base_pin_m: the moment arm vanishes (dead centre)")
    angle = float(problems[0].split("= ")[1].split("°")[0])
    assert abs(angle - -56.8) < 3.0


def test_each_linkage_kind_gives_consistent_derivatives_and_inverse() -> None:
    """For every cylinder of the crane (a direct revolute, a four-bar, a direct prismatic):
    s′ and s″ of ``linkage.state`` match central differences of s, ``inverse`` undoes it and
    ``motion`` equals (inverse, state) at once."""
    from cranetwin.physics import compile_chain, linkage
    from cranetwin.physics.layout import C_JOINT, C_KIND, cyl_block

    machine = load_machine("patu655")
    p = compile_chain(machine)
    kinds = set()
    for k in range(p.n_cylinders):
        o = cyl_block(k)
        kinds.add(int(p.cyl[o + C_KIND]))
        joint = machine.joints[int(p.cyl[o + C_JOINT])]
        h = 1e-4
        for qv in np.linspace(joint.lower + 0.1 * (joint.upper - joint.lower),
                              joint.upper - 0.1 * (joint.upper - joint.lower), 9):
            s, d1, d2 = linkage.state(p.cyl, o, qv)
            sp = linkage.state(p.cyl, o, qv + h)[0]
            sm = linkage.state(p.cyl, o, qv - h)[0]
            assert d1 == pytest.approx((sp - sm) / (2 * h), rel=1e-6, abs=1e-9)
            assert d2 == pytest.approx((sp - 2 * s + sm) / h**2, rel=1e-4, abs=1e-5)
            assert linkage.inverse(p.cyl, o, s) == pytest.approx(qv, abs=1e-9)
            np.testing.assert_allclose(linkage.motion(p.cyl, o, s), (qv, d1, d2), rtol=1e-9,
                                       atol=1e-12)
    assert kinds == {linkage.revolute.KIND, linkage.four_bar.KIND, linkage.prismatic.KIND}


@pytest.mark.parametrize("module", ["cranetwin.physics.layout", "cranetwin.physics.linkage",
                                    "cranetwin.physics.rnea", "cranetwin.physics.chain",
                                    "cranetwin.physics.kernels", "cranetwin.physics.codegen",
                                    "cranetwin.physics.actuator", "cranetwin.twin.gridpass"])
def test_module_imports_first_on_its_own(module: str) -> None:
    """No import circle: each module of the core imports first in a fresh interpreter."""
    code = f"import {module}"
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=False)
    assert res.returncode == 0, res.stderr[-2000:]
