"""Laws of the twin replay on synthetic recordings with exactly known truth."""

from __future__ import annotations

from typing import Literal

import numpy as np
import numpy.typing as npt
import pytest

from conftest import stream_in_random_chunks
from cranetwin.errors import TwinError
from cranetwin.model import Machine, load_machine
from cranetwin.samples import SampleArrays
from cranetwin.signal import inject_uniform_noise, nrmse
from cranetwin.testing.recordings import Synthetic, make
from cranetwin.twin import ReplayOptions, TwinResult, TwinStream, replay

F64 = npt.NDArray[np.float64]

INNER = slice(1000, -1000)  # away from the natural-spline ends (first and last second)


@pytest.fixture(scope="module")
def machine() -> Machine:
    return load_machine("patu655")


@pytest.fixture(scope="module")
def syn(machine: Machine) -> Synthetic:
    return make(machine, duration_s=12.0, payload=150.0, with_angle=True)


def test_replay_reconstructs_motion_and_forces_of_clean_data(machine: Machine,
                                                             syn: Synthetic) -> None:
    res = replay(syn.samples, machine, grid_hz=1000, payload=150.0)
    np.testing.assert_allclose(res.t_s, syn.t, atol=1e-9)
    np.testing.assert_allclose(res.q, syn.q, atol=1e-4)
    np.testing.assert_allclose(res.qd[INNER], syn.qd[INNER], atol=1e-3)
    # derivative windows are chosen for the 0.1 mm position resolution: about 1 % bias
    qdd_scale = np.abs(syn.qdd).max(axis=0)
    assert np.all(np.abs(res.qdd - syn.qdd)[INNER].max(axis=0) < 0.02 * qdd_scale)
    np.testing.assert_allclose(res.rod_s, syn.s, atol=3e-5)  # < the 0.1 mm resolution
    assert np.all(nrmse(res.cyl_force, syn.force) < 1e-3)
    # inverse dynamics of the reconstructed motion explains the actuator loads
    scale = np.abs(syn.tau[INNER]).max(axis=0)
    assert np.all(np.abs(res.residual[INNER]).max(axis=0) < 0.02 * scale)  # from the qdd bias
    assert res.joint_wrench.shape == (res.n, 4, 6)
    assert np.all(res.payload_std_kg == 0.0)
    tip = res.tip_path(machine)
    assert tip.shape == (res.n, 3) and np.all(np.isfinite(tip))


def test_payload_estimated_from_pressures_with_honest_uncertainty(machine: Machine,
                                                                  syn: Synthetic) -> None:
    res = replay(syn.samples, machine, grid_hz=1000)
    est = res.payload_kg[INNER]
    assert np.abs(est - 150.0).max() < 3.0
    # at half the synthetic's (3x crane-like) speed; at full speed noise in the accelerations
    # biases the estimate upwards (errors in variables), a known limit
    slow = make(machine, duration_s=12.0, payload=150.0, with_angle=True, scale=0.5)
    noisy = inject_uniform_noise(slow.samples, machine, 0.02, seed=3)
    r2 = replay(noisy, machine, grid_hz=1000)
    err = r2.payload_kg[INNER] - 150.0
    std = r2.payload_std_kg[INNER]
    assert np.sqrt(np.mean(err**2)) < 10.0
    # the stated one-sigma uncertainty is the right size: z-scores neither tiny nor huge
    z = np.sqrt(np.mean((err / std) ** 2))
    assert 0.3 < z < 3.0


def test_payload_step_is_followed(machine: Machine) -> None:
    step = make(machine, duration_s=16.0, payload=lambda t: np.where(t < 8.0, 0.0, 300.0),
                with_angle=True)
    res = replay(step.samples, machine, grid_hz=1000)
    before = (res.t_s > 2.0) & (res.t_s < 6.5)
    after = (res.t_s > 9.5) & (res.t_s < 14.0)
    assert np.abs(res.payload_kg[before]).max() < 5.0
    assert np.abs(res.payload_kg[after] - 300.0).max() < 5.0


def test_theta0_integrated_from_slewing_torque(machine: Machine) -> None:
    s = make(machine, duration_s=12.0, payload=150.0, with_angle=False)
    res = replay(s.samples, machine, grid_hz=1000, payload=150.0,
                 options=ReplayOptions(theta0_initial=float(s.q[0, 0])))
    assert np.abs(res.q[:, 0] - s.q[:, 0]).max() < 3e-3
    assert np.abs(res.qd[INNER, 0] - s.qd[INNER, 0]).max() < 5e-3




@pytest.mark.parametrize("pressures", ["choose", True])
@pytest.mark.parametrize("with_angle", [True, False])
def test_streaming_equals_batch_across_seams(machine: Machine, with_angle: bool,
                                             pressures: bool | Literal["choose"]) -> None:
    """With the default choice of the pressure smoothing (here fixed windows on every
    cylinder: these smooth synthetic pressures) and with LPA-ICI on every cylinder."""
    s = make(machine, duration_s=12.0, payload=150.0, with_angle=with_angle, fine_hz=None)
    noisy = inject_uniform_noise(s.samples, machine, 0.03, seed=1)
    first = replay(noisy, machine, options=ReplayOptions(adaptive_pressures=pressures))
    assert all(c.adaptive is (pressures is True)
               for k, c in first.smoothing.items() if k.endswith("_pA"))
    opt = ReplayOptions(smoothing=tuple(first.smoothing.values()), sample_period_s=0.01,
                        chunk_samples=700)
    batch = replay(noisy, machine, options=opt)
    streamed = stream_in_random_chunks(noisy, machine, opt, seed=2)
    assert streamed.n == batch.n
    np.testing.assert_array_equal(streamed.t_s, batch.t_s)
    for name in ("q", "qd", "qdd", "rod_s", "p_a", "cyl_force", "actuator_torque",
                 "id_torque", "joint_wrench", "payload_kg", "payload_std_kg"):
        a = getattr(streamed, name)
        b = getattr(batch, name)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-8 * np.abs(b).max(), err_msg=name)


def test_dropouts_and_irregular_timestamps(machine: Machine, syn: Synthetic) -> None:
    rng = np.random.default_rng(4)
    t = syn.samples.t_s + rng.uniform(-1e-3, 1e-3, syn.samples.t_s.shape[0])
    t[0] = syn.samples.t_s[0]
    vals = syn.samples.values.copy()
    vals[300:320, 0] = np.nan  # 0.2 s dropout of lift_pA
    vals[500, :] = np.nan
    vals[700:703, 2] = np.nan
    # the values stay those of the nominal times: the jitter acts as a timing error
    jit = SampleArrays("j", t, syn.samples.channels, vals)
    res = replay(jit, machine, grid_hz=1000, payload=150.0,
                 options=ReplayOptions(sample_period_s=0.01))
    assert res.n == syn.t.shape[0]
    gap_t = res.t_s[res.gap]
    assert gap_t.size > 0 and gap_t.min() > 2.9 and gap_t.max() < 3.2
    # values were sampled at the nominal times, so jitter is an error of up to 1 ms
    assert np.all(nrmse(res.rod_s[INNER], syn.s[INNER]) < 0.01)


def test_newton_velocity_option_agrees_with_spline(machine: Machine, syn: Synthetic) -> None:
    a = replay(syn.samples, machine, payload=150.0)
    b = replay(syn.samples, machine, payload=150.0, options=ReplayOptions(velocity="newton"))
    np.testing.assert_allclose(b.rod_v[INNER], a.rod_v[INNER], atol=2e-4)
    np.testing.assert_allclose(b.rod_v[INNER], syn.v[INNER], atol=2e-4)


def test_missing_channel_and_bad_grid_raise(machine: Machine, syn: Synthetic) -> None:
    cols = tuple(c for c in syn.samples.channels if c != "jib_pB")
    idx = [syn.samples.channels.index(c) for c in cols]
    bad = SampleArrays("x", syn.samples.t_s, cols, syn.samples.values[:, idx])
    with pytest.raises(TwinError, match="jib"):
        replay(bad, machine)
    with pytest.raises(TwinError, match="multiple"):
        replay(syn.samples, machine, grid_hz=1234.5)


def test_regression_payload_equals_windowed_payload_of_its_inputs() -> None:
    """The fused pass (g, r at the cylinder joints, then the window, two passes over the
    data) equals windowed_payload of g = (tau1 − tau0)/arm and r = (F·arm − tau0)/arm formed
    with numpy, bit for bit, with and without the prefilter."""
    from cranetwin.twin.payload import regression_payload, windowed_payload

    rng = np.random.default_rng(6)
    n, nj = 200, 4
    joints = np.array([1, 2, 3])
    tau0 = rng.normal(0.0, 1e4, (n, nj))
    tau1 = tau0 + rng.normal(50.0, 5.0, (n, nj))
    arm = rng.uniform(0.05, 0.3, (n, 3))
    force = rng.normal(1e5, 1e4, (n, 3))
    w = np.array([1.0, 0.5, 2.0])
    frac = np.array([0.5, 0.25, 1.0])
    g = (tau1 - tau0)[:, joints] / arm
    r = (force * arm - tau0[:, joints]) / arm
    noise = np.array([300.0, 100.0, 50.0])
    for pf in (0, 4):
        m, std = regression_payload(tau0, tau1, force, arm, joints, w, pf, 9, frac, noise)
        m_ref, std_ref = windowed_payload(g, r, w, pf, 9, frac, noise)
        np.testing.assert_array_equal(m, m_ref)
        np.testing.assert_array_equal(std, std_ref)


def test_windowed_payload_equals_direct_window_sums() -> None:
    """The compiled payload window against the definition (twin.payload's docstring): moving
    averages, then weighted least squares over each centred window, summed directly; σ² the
    raw noise propagated through both moving averages (the weight of each raw sample, summed)
    plus the residual scatter beyond that noise over 1 + n_c·N/P independent errors."""

    rng = np.random.default_rng(5)
    n, nc, pf, half = 120, 3, 4, 9
    g = rng.normal(1.0, 0.3, (n, nc))
    r = 150.0 * g + rng.normal(0.0, 5.0, (n, nc))
    w = np.array([1.0, 0.5, 2.0])
    frac = np.array([0.5, 0.25, 1.0])
    for noise in (np.zeros(3), np.array([30.0, 10.0, 50.0])):
        _check_window_sums(g, r, w, frac, noise, pf, half)


def _check_window_sums(g: np.ndarray, r: np.ndarray, w: np.ndarray, frac: np.ndarray,
                       noise: np.ndarray, pf: int, half: int) -> None:
    from cranetwin.twin.payload import windowed_payload

    n = g.shape[0]
    m, std = windowed_payload(g, r, w, pf, half, frac, noise)

    def avg(x: np.ndarray) -> np.ndarray:
        return np.array([x[max(0, i - pf) : i + pf + 1].mean(axis=0) for i in range(n)])

    ga, ra = avg(g), avg(r)
    p = 2 * pf + 1
    for i in (0, 5, 60, n - 1):
        sl = slice(max(0, i - half), i + half + 1)
        sgg = float(np.sum(w * ga[sl] ** 2))
        sgr = float(np.sum(w * ga[sl] * ra[sl]))
        srr = float(np.sum(w * ra[sl] ** 2))
        m_ref = sgr / sgg
        cnt = ga[sl].shape[0]
        n_eff = 1.0 + g.shape[1] * cnt / p
        excess = max(srr - m_ref * sgr - cnt * float(np.sum(w * noise**2)) / p, 0.0)
        var_e = excess / max(n_eff - 1.0, 1.0) / sgg
        # the raw noise: weight of each raw sample k on the estimate, u_k = Σ_window box_p/p
        u = np.convolve(np.ones(cnt), np.ones(p) / p)
        var_p = (u @ u) / cnt * float(np.sum(w**2 * ga[sl] ** 2 * noise**2)) / sgg**2
        std_ref = np.sqrt(var_e + var_p)
        assert m[i] == pytest.approx(m_ref, rel=1e-12)
        assert std[i] == pytest.approx(std_ref, rel=1e-9)
    assert abs(np.median(m) - 150.0) < 2.0


def _without_slew_drive(machine: Machine) -> Machine:
    """The crane without its slewing drive: the slew joint, its torque drive and channels and
    the pillar removed, the lift boom's joint on the world frame (the pillar's frame at
    theta0 = 0, so every pin keeps its coordinates)."""
    from cranetwin.model.loader import machine_from_dict

    data = machine.model_dump(mode="python")
    drive = data["torque_drives"][0]
    slew = next(j for j in data["joints"] if j["name"] == drive["joint"])
    data["torque_drives"] = []
    data["joints"] = [j for j in data["joints"] if j is not slew]
    for j in data["joints"]:
        if j["parent"] == slew["child"]:
            j["parent"] = slew["parent"]
    data["bodies"] = [b for b in data["bodies"] if b["name"] != slew["child"]]
    data["channels"] = [c for c in data["channels"]
                        if c["source"] not in (drive["name"], slew["name"])]
    return machine_from_dict(data, "patu655 without slew drive")


def _boom_samples(machine: Machine, payload: float, duration_s: float = 12.0,
                  rate_hz: float = 100.0) -> tuple[SampleArrays, F64, F64]:
    """Samples of the synthetic boom motion (:func:`cranetwin.testing.recordings.motion` without
    theta0) on a machine whose joints are all cylinder-driven, pA from inverse dynamics and
    Eq. 1–2 at pB = 2 MPa: (samples, true q, true cylinder forces)."""
    from cranetwin import physics
    from cranetwin.testing.recordings import motion

    t = np.arange(int(round(duration_s * rate_hz)) + 1) / rate_hz
    q, qd, qdd = (x[:, 1:] for x in motion(t, 0.5))
    tau = physics.joint_torques(machine, q, qd, qdd, np.full(t.shape, payload))
    s, arm = physics.cylinder_kinematics(machine, q)
    v = arm * qd
    force = tau / arm
    cols: dict[str, F64] = {}
    for c, cyl in enumerate(machine.cylinders):
        pb = 2.0e6
        pa = (force[:, c] + physics.friction_force(v[:, c], cyl.friction)
              + pb * cyl.area_b_m2) / cyl.area_a_m2
        by_q = {ch.quantity: ch.name for ch in machine.channels if ch.source == cyl.name}
        cols[by_q["pressure_a"]] = pa
        cols[by_q["pressure_b"]] = np.full(t.shape, pb)
        cols[by_q["position"]] = s[:, c]
    return (SampleArrays("bare", t, tuple(cols), np.column_stack(list(cols.values()))), q,
            force)


def test_replay_of_a_machine_without_torque_drive(machine: Machine) -> None:
    bare = _without_slew_drive(machine)
    assert not bare.torque_drives and bare.n_joints == 3
    samples, q_true, f_true = _boom_samples(bare, 150.0)
    res = replay(samples, bare, grid_hz=100)
    np.testing.assert_allclose(res.q, q_true, atol=1e-4)
    assert np.all(nrmse(res.cyl_force, f_true) < 1e-3)
    for name in ("q", "qd", "qdd", "cyl_force", "actuator_torque", "id_torque",
                 "joint_wrench"):
        assert np.all(np.isfinite(getattr(res, name))), name
    assert np.abs(res.payload_kg[100:-100] - 150.0).max() < 5.0
    # streaming equals batch for it too
    stream = TwinStream(bare, samples.channels,
                        ReplayOptions(grid_hz=100, smoothing=tuple(res.smoothing.values())))
    parts = [stream.push(SampleArrays(samples.machine_id, samples.t_s[i:i + 317],
                                      samples.channels, samples.values[i:i + 317]))
             for i in range(0, samples.t_s.shape[0], 317)]
    parts.append(stream.flush())
    got = TwinResult.concat([p for p in parts if p is not None])
    np.testing.assert_allclose(got.cyl_force, res.cyl_force, rtol=1e-9, atol=1e-6)


def _with_rotator(machine: Machine) -> Machine:
    """The crane with a second free joint: a rotator at the boom tip (revolute about the
    tip's z axis) carrying a 40 kg body, with its own torque drive, torque and angle channels.
    The load point stays on the extension boom."""
    from cranetwin.model.loader import machine_from_dict

    data = machine.model_dump(mode="python")
    data["bodies"].append({"name": "rotator", "mass_kg": 40.0, "com_m": (0.0, 0.0, -0.2),
                           "inertia_kgm2": ((0.8, 0.0, 0.0), (0.0, 0.8, 0.0), (0.0, 0.0, 0.3))})
    data["joints"].append({"name": "theta4", "kind": "revolute", "parent": "extension_boom",
                           "child": "rotator", "axis": (0.0, 0.0, 1.0),
                           "origin_m": (2.49, 0.0, 0.0), "lower": -3.5, "upper": 3.5,
                           "unit": "rad"})
    data["torque_drives"].append({"name": "rotator", "joint": "theta4", "max_torque_nm": 500.0,
                                  "friction": {"coulomb": 20.0, "coulomb_velocity": 0.01,
                                               "viscous": 10.0}})
    data["channels"] += [
        {"name": "rotator_torque", "quantity": "torque", "source": "rotator", "unit": "N*m",
         "min": -1000.0, "max": 1000.0, "resolution": 0.01},
        {"name": "rotator_angle", "quantity": "angle", "source": "theta4", "unit": "rad",
         "min": -3.5, "max": 3.5, "resolution": 1.0e-5},
    ]
    return machine_from_dict(data, "patu655 with a rotator")


def _rotator_recording(rot: Machine, angles: bool) -> tuple[F64, F64, F64, F64, SampleArrays]:
    """Exact samples of the crane with a tip rotator: the synthetic boom motion plus a rotator
    swing from rest (the slew's integration assumes the machine at rest), payload 150 kg.

    Returns:
        (t (n,) [s], q (n, 5), joint torques tau (n, 5), cylinder forces (n, 3) [N], samples
        with both drives' torques and, if ``angles``, the slew and rotator angles).
    """
    from cranetwin import physics
    from cranetwin.testing.recordings import motion

    t = np.arange(1201) / 100.0
    q4, qd4, qdd4 = motion(t, 0.5)
    w = 2 * np.pi * 0.2
    q = np.column_stack([q4, 0.6 * (1.0 - np.cos(w * t))])
    qd = np.column_stack([qd4, 0.6 * w * np.sin(w * t)])
    qdd = np.column_stack([qdd4, 0.6 * w * w * np.cos(w * t)])
    tau = physics.joint_torques(rot, q, qd, qdd, np.full(t.shape, 150.0))
    s, arm = physics.cylinder_kinematics(rot, q)
    force = tau[:, 1:4] / arm
    cols: dict[str, F64] = {}
    for c, cyl in enumerate(rot.cylinders):
        v = arm[:, c] * qd[:, c + 1]
        by_q = {ch.quantity: ch.name for ch in rot.channels if ch.source == cyl.name}
        cols[by_q["pressure_a"]] = (force[:, c] + physics.friction_force(v, cyl.friction)
                                    + 2.0e6 * cyl.area_b_m2) / cyl.area_a_m2
        cols[by_q["pressure_b"]] = np.full(t.shape, 2.0e6)
        cols[by_q["position"]] = s[:, c]
    for d in rot.torque_drives:
        j = rot.joint_index(d.joint)
        cols[f"{d.name}_torque"] = tau[:, j] + physics.friction_force(qd[:, j], d.friction)
    if angles:
        cols["slew_angle"] = q[:, 0]
        cols["rotator_angle"] = q[:, 4]
    samples = SampleArrays("rot", t, tuple(cols), np.column_stack(list(cols.values())))
    return t, q, tau, force, samples


def test_replay_of_a_machine_with_two_free_joints(machine: Machine) -> None:
    rot = _with_rotator(machine)
    assert rot.n_joints == 5 and len(rot.torque_drives) == 2
    t, q, tau, force, samples = _rotator_recording(rot, angles=True)
    res = replay(samples, rot, grid_hz=100, payload=150.0)
    inner = slice(100, -100)
    np.testing.assert_allclose(res.q[inner], q[inner], atol=1e-3)
    assert np.all(nrmse(res.cyl_force, force) < 1e-3)
    # both drives' loads are measured: actuator loads match the truth, residuals are small
    for j in (0, 4):
        scale = float(np.abs(tau[:, j]).max())
        assert np.abs(res.actuator_torque[inner, j] - tau[inner, j]).max() < 0.05 * scale
        assert np.abs(res.residual[inner, j]).max() < 0.05 * scale
    assert np.all(np.isfinite(res.joint_wrench))
    # without the slew angle, the slew is integrated from its torque; the rotator keeps its
    # angle channel
    keep = [i for i, c in enumerate(samples.channels) if c != "slew_angle"]
    no_slew = SampleArrays("rot", t, tuple(samples.channels[i] for i in keep),
                           samples.values[:, keep])
    res2 = replay(no_slew, rot, grid_hz=100, payload=150.0,
                  options=ReplayOptions(grid_hz=100, theta0_initial=float(q[0, 0])))
    np.testing.assert_allclose(res2.q[inner, 4], q[inner, 4], atol=1e-3)
    assert np.abs(res2.q[inner, 0] - q[inner, 0]).max() < 0.05


def test_replay_integrates_every_free_joint_without_an_angle(machine: Machine) -> None:
    """Neither the slew's nor the rotator's angle sent: both are integrated from their
    torques (the rotator after the slew, with the slew's rate in its coupling)."""
    rot = _with_rotator(machine)
    t, q, tau, force, samples = _rotator_recording(rot, angles=False)
    res = replay(samples, rot, grid_hz=100, payload=150.0,
                 options=ReplayOptions(grid_hz=100, theta0_initial=float(q[0, 0])))
    inner = slice(100, -100)
    assert np.abs(res.q[inner, 0] - q[inner, 0]).max() < 0.05
    assert np.abs(res.q[inner, 4] - q[inner, 4]).max() < 0.05
    assert np.abs(res.q[inner, 4]).max() > 0.5  # it moved, and was not held at 0
    assert np.all(np.isfinite(res.joint_wrench))
    # streaming equals batch
    stream = TwinStream(rot, samples.channels,
                        ReplayOptions(grid_hz=100, theta0_initial=float(q[0, 0]),
                                      smoothing=tuple(res.smoothing.values()),
                                      sample_period_s=0.01),
                        150.0)
    parts = [stream.push(SampleArrays("rot", t[i:i + 291], samples.channels,
                                      samples.values[i:i + 291]))
             for i in range(0, t.shape[0], 291)]
    parts.append(stream.flush())
    got = TwinResult.concat([p for p in parts if p is not None])
    np.testing.assert_allclose(got.q, res.q, rtol=1e-9, atol=1e-9)


@pytest.mark.timeout(120)
def test_pin_to_pin_lengths_given_as_strokes_are_refused_not_clipped(machine: Machine,
                                                                     syn: Synthetic) -> None:
    s = syn.samples
    cyl = machine.cylinders[1]
    col = s.channels.index(next(c.name for c in machine.channels
                                if c.quantity == "position" and c.source == cyl.name))
    lengths = s.values.copy()
    lengths[:, col] += cyl.closed_length_m  # pin-to-pin length = stroke + closed length
    with pytest.raises(TwinError, match="pin-to-pin"):
        replay(SampleArrays(s.machine_id, s.t_s, s.channels, lengths), machine, grid_hz=100)
    # the same data as stroke positions, even with 10 % of full range uniform error on every
    # rod (rods resting at an end of the stroke then read outside it half of the time), replays
    noisy = inject_uniform_noise(s, machine, 0.10, seed=5)
    assert replay(noisy, machine, grid_hz=100).n > 0
