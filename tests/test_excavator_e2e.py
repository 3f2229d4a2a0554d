"""The Bobcat 435-class excavator end to end, with no excavator-specific code on the way: a
machine registered with model ``bobcat435`` streams the ``dig-cycle`` scenario over UDP from a
real ``cranetwin send`` process to a real ``cranetwin ingest`` daemon (SQLite); the twin worker
replays the stored samples; the API serves positions, forces, the bucket load and the estimated
tool force; its 3D scene has meshes for every body; ``cranetwin report`` writes a report.

Every figure is checked against the simulator's ground truth of the same run (the sender
simulates ``dig-cycle`` with seed 0 and repeats it cyclically; the test simulates it again and
finds which recording row each stored sample is by matching the values), never against numbers
written down from an earlier run.
"""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from typer.testing import CliRunner

from cranetwin.api import create_app
from cranetwin.bench.ingest import free_udp_port, start_daemon
from cranetwin.cli import app as cli_app
from cranetwin.model import Machine, load_machine
from cranetwin.samples import SampleArrays
from cranetwin.service.backend import Backend
from cranetwin.service.worker import TwinWorker
from cranetwin.settings import Settings
from cranetwin.sim import Recording, load_scenario, simulate
from cranetwin.viz.scene import build_scene

MID = "exc-7"
WIRE_ID = 4350
SECRET = "00112233445566778899aabbccddeeff"
STREAM_S = 30.0    # data seconds streamed: any 30 s of the 18 s cycle hold one whole dig + carry
SPEED = 10.0       # × real time
RATE_HZ = 25.0     # twin output rate asked of the API
# phases of dig-cycle (machines/scenarios/bobcat435/dig-cycle.toml), scenario seconds
FULL_CONTACT = (4.6, 6.7)   # contact force held at (4000, 0, 2000) N (ramps 3.5–4.5, 6.8–7.5)
CARRY = (8.5, 12.5)         # 180 kg in the bucket (7.5–13.5 s; the payload window is 2 s)
FREE = (0.5, 3.0)           # no contact, empty bucket


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-c", "from cranetwin.cli import main; main()", *args]


def _truth() -> Recording:
    """What the sender streams: ``simulator_source`` simulates the scenario once (seed 0, at
    most ``--sim-seconds``) without wrenches; the same call here gives the same samples."""
    m = load_machine("bobcat435")
    sc = load_scenario("dig-cycle", machine="bobcat435")
    return simulate(m, sc, duration_s=sc.duration_s, seed=0, wrenches=False)


def _recording_rows(stored: SampleArrays, rec: Recording, machine: Machine) -> np.ndarray:
    """The recording row of every stored sample (the sender repeats the recording cyclically,
    from a row that depends on the clock): the offset at which the stored values equal the
    recording's, to half a resolution step, NaN (dropout) where the recording has NaN."""
    src = rec.samples
    cols = [src.channels.index(c) for c in stored.channels]
    ref = src.values[:, cols]
    res = np.array([machine.channel(c).resolution for c in stored.channels])
    n, k = ref.shape[0], min(200, stored.values.shape[0])
    head = stored.values[:k]
    step = np.rint((stored.t_s - stored.t_s[0]) * 100.0).astype(np.int64)
    hits = []
    for off in range(n):
        cand = ref[(off + step[:k]) % n]
        same = (np.abs(cand - head) <= 0.51 * res) | (np.isnan(cand) & np.isnan(head))
        if same.all():
            hits.append(off)
    assert len(hits) == 1, f"stored samples match the recording at offsets {hits}"
    return np.asarray((hits[0] + step) % n)


def _in(t: np.ndarray, span: tuple[float, float]) -> np.ndarray:
    return (t >= span[0]) & (t <= span[1])


@pytest.mark.timeout(40)
def test_excavator_scene_has_meshes_for_every_body() -> None:
    m = load_machine("bobcat435")
    cmds, spec = build_scene(m)
    paths = [c["path"] for c in cmds if c["type"] == "set_object"]
    assert spec.bodies == ["upper", "boom", "arm", "bucket"]
    for body in spec.bodies:
        meshes = [p for p in paths if p.startswith(spec.body_paths[body] + "/")]
        assert meshes, f"no mesh for body {body}"
        for p in meshes:
            geo = next(c for c in cmds if c["path"] == p)["object"]["geometries"][0]["data"]
            assert len(geo["index"]["array"]) >= 3 * 8   # real triangles, not a placeholder
    for c in m.cylinders:
        assert f"/cranetwin/cylinders/{c.name}/barrel" in paths
    # the bucket is the tool: no grapple hangs at the tip, the payload is drawn as soil
    assert not any(p.endswith(("/grapple", "/rotator")) for p in paths)
    assert spec.payload_path in paths and spec.extras["payload_kind"] == "soil"
    assert spec.extras["linkages"]["bucket"]["child_body"] == "bucket"


@pytest.mark.timeout(60)
@pytest.mark.parametrize("name", ["patu655", "bobcat435"])
def test_served_tool_force_is_zero_without_an_external_force(name: str) -> None:
    """Exact samples of a motion with a known payload (cranetwin.testing.blocks): the twin's
    residual holds no external force, so neither does the served tool force."""
    from cranetwin.service.views import twin_json
    from cranetwin.testing.blocks import kinematic_samples
    from cranetwin.twin import replay

    m = load_machine(name)
    res = replay(kinematic_samples(m, 30.0), m, grid_hz=100.0)
    tw = twin_json(m, res, 5.0, 25.0, 25.0)
    force = np.asarray(tw["tool_force"]["n"], dtype=float)
    assert force.shape == (500, 3)
    weight = 9.81 * float(max(m.rated_load.payload_kg))
    assert np.nanmax(np.abs(force)) < 0.02 * weight


@pytest.mark.timeout(60)
def test_simulated_blocks_use_the_machines_own_scenario() -> None:
    from cranetwin.testing.blocks import default_scenario, simulated_samples, tiled_blocks

    m = load_machine("bobcat435")
    assert default_scenario("bobcat435") == "dig-cycle"
    assert default_scenario("patu655") == "log-loading"
    s = simulated_samples("bobcat435", 120.0)
    assert s.channels == tuple(c.name for c in m.channels)
    assert s.t_s[-1] == pytest.approx(18.0)    # one dig cycle, repeated by tiled_blocks
    blocks = list(tiled_blocks("exc", m, 1795420800.0, 40.0, 1.0, base=s))
    assert len(blocks) == 40 and blocks[0].channels == s.channels


@pytest.mark.timeout(120)   # ≈ 25–35 s on a shared 2-core machine, numba caches warm
def test_excavator_streamed_replayed_served_and_reported(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'exc.db'}"
    machine = load_machine("bobcat435")
    env = {**os.environ, "CRANETWIN_MACHINE_KEY": SECRET}
    env.pop("CRANETWIN_DATABASE_URL", None)
    out = CliRunner().invoke(cli_app, ["machines", "add", MID, "--wire-id", str(WIRE_ID),
                                       "--model", "bobcat435", "--db", url],
                             env={"CRANETWIN_MACHINE_SECRET": SECRET})
    assert out.exit_code == 0, out.output

    # --- streamed over UDP: real daemon, real sender process ------------------------------
    port = free_udp_port()
    daemon = start_daemon(url, port, tmp_path)
    try:
        sent = subprocess.run(
            _cli("send", "--machine", MID, "--wire-id", str(WIRE_ID), "--model", "bobcat435",
                 "--scenario", "dig-cycle", "--loop", "--sim-seconds", "18",
                 "--host", f"127.0.0.1:{port}",
                 "--speed", str(SPEED), "--duration", str(STREAM_S), "--batch", "50",
                 "--journal", str(tmp_path / "journal"), "--json", "--log-level", "WARNING"),
            env=env, capture_output=True, text=True, timeout=90)
    finally:
        counters = daemon.stop()
    assert sent.returncode == 0, sent.stderr[-2000:]
    n_sent = int(round(STREAM_S * 100))
    assert f'"acked_samples": {n_sent}' in sent.stdout, sent.stdout
    assert counters.get("stored_samples") == n_sent, counters

    # --- replayed by the twin worker --------------------------------------------------------
    settings = Settings(database_url=url, worker_in_process=False, worker_window_s=5.0)
    backend = Backend.open(url)
    rec = backend.machine(MID)
    t_start, t_end = backend.data_range(MID)  # type: ignore[misc]
    done = TwinWorker(backend, settings).catch_up(rec)
    prog = backend.progress(MID)
    assert prog is not None and done >= 4 and prog.watermark_s >= t_end - 5.0 - 5.0

    # ground truth of every stored sample
    truth = _truth()
    stored = backend.read_samples(MID, t_start, t_end + 1.0)
    assert stored.values.shape[0] == n_sent
    rows = _recording_rows(stored, truth, machine)
    t_rec = truth.samples.t_s                                 # scenario time of each row
    ti_rec = np.searchsorted(truth.truth.t_s, t_rec - 1e-9)   # its truth instant

    def scenario_time(t_epoch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(scenario time, truth index) of epoch times on the sample grid."""
        i = np.clip(np.rint((t_epoch - stored.t_s[0]) * 100.0).astype(np.int64), 0,
                    rows.shape[0] - 1)
        return t_rec[rows[i]], ti_rec[rows[i]]

    # the worker's stored payload (1-s buckets) while carrying 180 kg
    app = create_app(Settings(database_url=url, worker_in_process=False))
    with TestClient(app) as client:
        _, key = app.state.services.backend.create_key("admin")
        h = {"Authorization": f"Bearer {key}"}
        hist = client.get(f"/api/v1/machines/{MID}/history", headers=h, params={
            "from": t_start, "to": prog.watermark_s, "channels": "payload,force:boom",
            "max_points": 1000}).json()["channels"]
        assert set(hist) == {"payload", "force:boom"}
        ht = np.asarray(hist["payload"]["t"], dtype=float)
        hmean = np.asarray(hist["payload"]["mean"], dtype=float)
        tau_h, _ = scenario_time(ht + 0.5)       # bucket centres
        carry_h = _in(tau_h, CARRY) & _in(tau_h - 0.5, CARRY) & _in(tau_h + 0.5, CARRY)
        assert carry_h.sum() >= 2
        worker_carry_kg = float(np.median(hmean[carry_h]))
        assert worker_carry_kg == pytest.approx(180.0, abs=12.0)

        # --- served: positions, forces, bucket load, tool force ------------------------------
        t0 = float(np.ceil(t_start + 1.0))
        twin = client.get(f"/api/v1/machines/{MID}/twin", headers=h, params={
            "from": t0, "to": t0 + STREAM_S - 2.0, "rate_hz": RATE_HZ})
        assert twin.status_code == 200, twin.text
        tw = twin.json()
        scene = client.get(f"/api/v1/machines/{MID}/scene", headers=h)
        assert scene.status_code == 200, scene.text
        spec = scene.json()["spec"]
        assert spec["bodies"] == ["upper", "boom", "arm", "bucket"]
        assert spec["payload_kind"] == "soil"
    backend.close()

    t = np.asarray(tw["t"], dtype=float)
    assert t.shape[0] == pytest.approx((STREAM_S - 2.0) * RATE_HZ, abs=2)
    tau, ti = scenario_time(t)
    inner = np.ones_like(t, dtype=bool)
    # the replay sees a seam where the recording wraps (18 s → 0 s): leave 1 s either side out
    wrap = np.abs(((tau + 9.0) % 18.0) - 9.0) < 1.0
    inner &= ~wrap
    tr = truth.truth
    q = np.asarray(tw["q"], dtype=float)
    q_err = np.abs(q - tr.q[ti])[inner]
    # swing from the streamed swing_angle channel, boom/arm/bucket from the rod positions
    assert np.all(q_err.max(axis=0) < [2e-2, 5e-3, 5e-3, 1e-2]), q_err.max(axis=0)
    # the tip follows the arm: the load point is 3–7 m from the swing axis when digging
    tip = np.asarray(tw["tip"], dtype=float)
    reach = np.hypot(tip[:, 0], tip[:, 1])
    assert np.all((reach[inner] > 1.0) & (reach[inner] < 7.0))
    # cylinder forces (Eq. 1–2 on the streamed pressures) against the simulator's
    for k, c in enumerate(machine.cylinders):
        f = np.asarray(tw["cylinder_forces"][c.name], dtype=float)
        true_f = tr.cyl_force[ti, k]
        scale = float(np.ptp(true_f[inner]))
        rms = float(np.sqrt(np.mean((f - true_f)[inner] ** 2)))
        assert rms < 0.10 * scale, (c.name, rms, scale)

    # the bucket load: the twin's payload estimate while carrying 180 kg of soil
    kg = np.asarray(tw["payload"]["kg"], dtype=float)
    carry = _in(tau, CARRY) & inner
    assert carry.sum() >= 50
    assert float(np.nanmedian(kg[carry])) == pytest.approx(180.0, abs=10.0)
    free = _in(tau, FREE) & inner
    assert float(np.nanmedian(kg[free])) == pytest.approx(0.0, abs=15.0)

    # the tool force while the contact force is held: horizontal component directly; the
    # vertical one together with the payload estimate (a vertical force at the tip and a
    # payload are the same load up to the payload's inertia: the estimate takes part of it;
    # the twin's dynamics use the estimate where it is positive, max(m, 0))
    tf = tw["tool_force"]
    assert tf is not None
    force = np.asarray([[np.nan if v is None else v for v in row] for row in tf["n"]])
    dig = _in(tau, FULL_CONTACT) & inner
    assert dig.sum() >= 30
    fc = tr.contact_force[ti]
    assert np.allclose(fc[dig], [4000.0, 0.0, 2000.0])
    fx = float(np.nanmean(force[dig, 0]))
    assert fx == pytest.approx(4000.0, rel=0.05)
    net_z = force[:, 2] - np.clip(np.nan_to_num(kg), 0.0, None) * 9.81   # beyond the bucket
    true_net_z = fc[:, 2] - tr.payload_kg[ti] * 9.81
    assert float(np.nanmean(net_z[dig])) == pytest.approx(float(true_net_z[dig].mean()),
                                                          abs=400.0)
    assert np.nanmax(np.abs(force[free][:, [0, 2]])) < 1500.0
    assert np.all(np.asarray(tf["sigma_min_m"], dtype=float)[inner] > 0.5)

    # --- reported -----------------------------------------------------------------------------
    rep = tmp_path / "report"
    out = CliRunner().invoke(cli_app, ["report", "--machine", MID, "--db", url, "--from",
                                       str(t_start), "--to", str(t_end + 1.0), "--format",
                                       "csv", "--out", str(rep), "-q"], env=env)
    assert out.exit_code == 0, out.output
    with open(rep / "damage.csv", newline="") as fh:
        damage = list(csv.DictReader(fh))
    assert [d["detail"] for d in damage] == [f.name for f in machine.fatigue]
    assert all(float(d["damage D"]) > 0 for d in damage)
    with open(rep / "spectra.csv", newline="") as fh:
        spectra = {r["channel"] for r in csv.DictReader(fh)}
    assert {f.load for f in machine.fatigue} <= spectra
    with open(rep / "summary.csv", newline="") as fh:
        summary = {r["item"]: r["value"] for r in csv.DictReader(fh)}
    assert summary["Machine"] == "bobcat435"
    assert int(summary["Samples analysed"].replace(",", "")) == pytest.approx(n_sent, abs=2)
    assert (rep / "events.csv").exists() and (rep / "duty.csv").exists()
