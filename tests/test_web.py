"""Web front end without a browser: scene geometry laws, routes, exports (preview app)."""

from __future__ import annotations

import base64
import gzip
import json
import re

import httpx
import numpy as np
import pytest
import trimesh

from cranetwin.api.preview import PREVIEW_KEY, create_preview_app
from cranetwin.api.routes_web import vendor_file, web_dir
from cranetwin.model import load_machine
from cranetwin.physics.kinematics import body_poses, load_point_position
from cranetwin.viz.export import (
    EXPORT_MAX_FRAMES,
    bundle_modules,
    export_rate_hz,
    join_twin,
)
from cranetwin.viz.poses import column_major, frame_arrays
from cranetwin.viz.scene import (
    LOG_DENSITY_KGM3,
    LOG_LENGTH_M,
    build_scene,
    log_radius_m,
    payload_matrix,
    segment_matrix,
    set_transform,
)

KEY = {"X-API-Key": PREVIEW_KEY}


@pytest.fixture(scope="module")
def machine():  # type: ignore[no-untyped-def]
    return load_machine("patu655")


def test_segment_matrix_maps_unit_axis_onto_segment() -> None:
    rng = np.random.default_rng(1)
    p0 = rng.normal(size=(50, 3))
    p1 = rng.normal(size=(50, 3))
    p1[0] = p0[0] + [0, 0.5, 0]  # parallel to the helper axis
    m = segment_matrix(p0, p1)
    assert np.allclose(m[:, :3, 3], p0)
    end = np.einsum("nij,j->ni", m, [0, 0, 1, 1])[:, :3]
    assert np.allclose(end, p1)
    u, w = m[:, :3, 0], m[:, :3, 1]
    d = p1 - p0
    assert np.allclose(np.linalg.norm(u, axis=1), 1) and np.allclose(np.linalg.norm(w, axis=1), 1)
    assert np.allclose(np.einsum("ni,ni->n", u, d), 0, atol=1e-12)
    assert np.allclose(np.einsum("ni,ni->n", w, d), 0, atol=1e-12)
    assert np.allclose(np.einsum("ni,ni->n", u, w), 0, atol=1e-12)


def test_column_major_matches_three_js_order() -> None:
    rng = np.random.default_rng(2)
    t = rng.normal(size=(3, 4, 4))
    flat = column_major(t)
    assert flat.shape == (3, 16)
    for k in range(3):
        # three.js Matrix4.fromArray: element (r, c) at index 4 c + r
        for r in range(4):
            for c in range(4):
                assert flat[k, 4 * c + r] == t[k, r, c]
    assert set_transform("/x", t[0])["matrix"] == flat[0].tolist()


def test_log_radius_gives_the_payload_mass() -> None:
    for kg in (10.0, 300.0, 1000.0):
        r = float(log_radius_m(kg))
        assert LOG_DENSITY_KGM3 * np.pi * r**2 * LOG_LENGTH_M == pytest.approx(kg)
    m = payload_matrix(500.0, slew_rad=0.3)
    assert np.linalg.norm(m[:3, 1]) == pytest.approx(LOG_LENGTH_M)
    assert np.linalg.norm(m[:3, 0]) == pytest.approx(float(log_radius_m(500.0)))
    assert np.allclose(payload_matrix(0.0)[:3, :3], 0)


def _mesh(cmd: dict) -> trimesh.Trimesh:  # type: ignore[type-arg]
    geo = cmd["object"]["geometries"][0]["data"]
    v = np.asarray(geo["attributes"]["position"]["array"]).reshape(-1, 3)
    f = np.asarray(geo["index"]["array"]).reshape(-1, 3)
    return trimesh.Trimesh(v, f, process=False)


def test_scene_meshes_cover_every_visual(machine) -> None:  # type: ignore[no-untyped-def]
    cmds, spec = build_scene(machine)
    json.dumps(cmds)  # plain JSON, no msgpack extension types
    paths = {c["path"]: c for c in cmds}
    assert spec.bodies == [j.child for j in machine.joints]
    for body in machine.bodies:
        for i, v in enumerate(body.visuals):
            mesh = _mesh(paths[f"{spec.body_paths[body.name]}/v{i}"])
            assert int(mesh.faces.max()) < len(mesh.vertices)
            n = np.asarray(paths[f"{spec.body_paths[body.name]}/v{i}"]["object"]["geometries"][0]
                           ["data"]["attributes"]["normal"]["array"]).reshape(-1, 3)
            assert np.allclose(np.linalg.norm(n, axis=1), 1, atol=2e-3)
            # the segment's end points lie on the axis of the drawn tube, within its bounds
            lo, hi = mesh.bounds
            for p in (v.from_m, v.to_m):
                assert np.all(np.asarray(p) >= lo - 1e-3) and np.all(np.asarray(p) <= hi + 1e-3)
            # the tube's volume is that of a cylinder of the visual's radius (within faceting)
            length = float(np.linalg.norm(np.subtract(v.to_m, v.from_m)))
            assert abs(mesh.volume) == pytest.approx(np.pi * v.radius_m**2 * length, rel=0.05)
    for c in machine.cylinders:
        assert f"/cranetwin/cylinders/{c.name}/barrel" in paths
    assert spec.payload_path in paths and f"{spec.trail_path}" in paths


def test_frame_arrays_follow_physics_poses(machine) -> None:  # type: ignore[no-untyped-def]
    q = np.array([[0.3, 0.5, -1.4, 0.4], [-1.0, 0.1, -2.0, 0.0]])
    f = frame_arrays(machine, q)
    poses = body_poses(machine, q)
    for i, j in enumerate(machine.joints):
        m = np.asarray(f["poses"][j.child]).reshape(2, 4, 4).transpose(0, 2, 1)
        assert np.allclose(m, poses[:, i])
    assert np.allclose(f["tip"], load_point_position(machine, q))
    # the load point computed in the browser from the pose (column-major product) is the tip
    ext = np.asarray(f["poses"]["extension_boom"][0])
    p = machine.load_point.point_m
    tip = [ext[i] * p[0] + ext[4 + i] * p[1] + ext[8 + i] * p[2] + ext[12 + i] for i in range(3)]
    assert np.allclose(tip, f["tip"][0])
    for name, pins in f["cylinder_pins"].items():
        k = [c.name for c in machine.cylinders].index(name)
        s = np.linalg.norm(np.asarray(pins)[:, 3:] - np.asarray(pins)[:, :3], axis=1)
        s -= machine.cylinders[k].closed_length_m
        assert np.all(s > -1e-6) and np.all(s < machine.cylinders[k].stroke_m + 1e-6)


def test_join_twin_drops_seam_duplicates() -> None:
    a = {"t": [0.0, 1.0, 2.0], "q": [[0], [1], [2]], "poses": {"b": [[0], [1], [2]]},
         "payload": {"t": [0.0, 2.0], "kg": [1.0, 2.0]}}
    b = {"t": [2.0, 3.0], "q": [[2], [3]], "poses": {"b": [[2], [3]]},
         "payload": {"t": [2.0, 3.0], "kg": [2.0, 3.0]}}
    j = join_twin([a, b])
    assert j["t"] == [0.0, 1.0, 2.0, 3.0]
    assert j["q"] == [[0], [1], [2], [3]] and j["poses"]["b"] == [[0], [1], [2], [3]]
    assert j["payload"]["t"] == [0.0, 2.0, 3.0]
    assert join_twin([])["t"] == []


def test_join_twin_keeps_each_windows_verdicts() -> None:
    """The verdicts are per replayed window: a joined export keeps each part's, not the first's
    for all (the exported page picks the part its chunk overlaps)."""
    def verdict(ok: bool) -> dict[str, object]:
        return {"cylinder": "lift", "observable": ok, "causes": [] if ok else ["noise share"]}

    a = {"t": [0.0, 1.0, 2.0], "force_observability": [verdict(True)],
         "model_consistency": [{"cylinder": "lift", "consistent": True}]}
    b = {"t": [2.0, 3.0], "force_observability": [verdict(False)], "model_consistency": []}
    j = join_twin([a, b])
    assert "force_observability" not in j and "model_consistency" not in j
    assert [(n["from"], n["to"]) for n in j["notes"]] == [(0.0, 2.0), (2.0, 3.0)]
    assert [n["force_observability"][0]["observable"] for n in j["notes"]] == [True, False]
    assert j["notes"][0]["model_consistency"] == a["model_consistency"]
    assert j["notes"][1]["model_consistency"] == []


def test_the_pages_limits_are_the_services() -> None:
    """The Now card states the limits the service judges by: the same numbers."""
    from cranetwin.twin import consistency, observability

    js = (web_dir() / "js" / "nowcard.js").read_text()

    def const(name: str) -> float:
        m = re.search(rf"export const {name} = ([0-9.]+);", js)
        assert m, name
        return float(m.group(1))

    assert const("RESOLVABLE_SHARE") == observability.RESOLVABLE_SHARE
    assert const("FORCE_ACCURACY_TARGET") == observability.FORCE_ACCURACY_TARGET
    assert const("CONSISTENCY_SHARE") == consistency.SHARE_LIMIT
    assert const("CONSISTENCY_NOISE") == consistency.NOISE_FACTOR


def test_export_rate_keeps_frames_bounded() -> None:
    for seconds in (5.0, 60.0, 600.0):
        assert seconds * export_rate_hz(seconds) <= EXPORT_MAX_FRAMES + 1e-9
    assert export_rate_hz(10.0) == 25.0


def test_bundle_has_no_imports_and_every_module() -> None:
    src = bundle_modules(web_dir())
    assert not re.search(r"^import\s", src, re.MULTILINE)
    assert not re.search(r"^export\s", src, re.MULTILINE)
    for name in ("class Crane3D", "class ReplayStore", "class Charts", "function start"):
        assert name in src


def test_bundle_order_follows_the_imports_and_names_are_unique() -> None:
    """Every module the machine page imports (transitively) is in the export bundle after the
    modules it imports, and no two modules declare the same top-level name (the bundle joins
    them into one scope)."""
    from cranetwin.viz.export import MODULE_ORDER

    js = web_dir() / "js"
    imports = {name: re.findall(r'^import\s.*?from\s+"\./([\w.]+)";', (js / name).read_text(),
                                re.MULTILINE) for name in MODULE_ORDER}
    seen: list[str] = []
    todo = ["machine.js"]
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.append(name)
        todo += re.findall(r'^import\s.*?from\s+"\./([\w.]+)";', (js / name).read_text(),
                           re.MULTILINE)
    assert set(seen) <= set(MODULE_ORDER)
    for name, deps in imports.items():
        assert all(MODULE_ORDER.index(d) < MODULE_ORDER.index(name) for d in deps), name
    declared: dict[str, str] = {}
    decl = re.compile(r"^(?:export\s+)?(?:async\s+)?(?:function|class|const|let)\s+([\w$]+)",
                      re.MULTILINE)
    for name in MODULE_ORDER:
        for n in decl.findall((js / name).read_text()):
            assert n not in declared, f"{n} declared in {declared.get(n)} and {name}"
            declared[n] = name


def test_vendor_files_are_the_packaged_bundles() -> None:
    meshcat = vendor_file("meshcat.min.js")
    plotly = vendor_file("plotly.min.js")
    assert meshcat.stat().st_size > 500_000 and plotly.stat().st_size > 1_000_000


# --- routes, through the preview app ------------------------------------------------------------


@pytest.fixture(scope="module")
def client():  # type: ignore[no-untyped-def]
    app = create_preview_app(history_s=900.0, end=1_795_000_000.0)
    transport = httpx.ASGITransport(app=app)
    return httpx.AsyncClient(transport=transport, base_url="http://test")


@pytest.mark.asyncio
async def test_pages_and_static_files_are_served(client) -> None:  # type: ignore[no-untyped-def]
    r = await client.get("/")
    assert r.status_code == 200 and "fleet" in r.text and "/static/js/fleet.js" in r.text
    r = await client.get("/machines/crane-1")
    assert r.status_code == 200 and "/static/js/machine.js" in r.text
    r = await client.get("/static/js/crane3d.js")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/javascript")
    r = await client.get("/static/vendor/meshcat.min.js")
    assert r.status_code == 200 and "MeshCat" in r.text[:2000] + r.text[-2000:]
    r = await client.get("/static/vendor/plotly.min.js")
    assert r.status_code == 200
    for bad in ("/static/../pyproject.toml", "/static/%2e%2e/pyproject.toml", "/static/nope.js",
                "/static/vendor/evil.js"):
        r = await client.get(bad)
        assert r.status_code == 404, bad


@pytest.mark.asyncio
async def test_scene_needs_a_key_and_lists_bodies(client) -> None:  # type: ignore[no-untyped-def]
    assert (await client.get("/api/v1/machines/crane-1/scene")).status_code == 401
    r = await client.get("/api/v1/machines/crane-1/scene", headers={"X-API-Key": "nope"})
    assert r.status_code == 403 and r.headers["content-type"] == "application/problem+json"
    r = await client.get("/api/v1/machines/crane-1/scene", params={"key": PREVIEW_KEY})
    assert r.status_code == 200
    body = r.json()
    assert body["spec"]["bodies"] == ["pillar", "lift_boom", "jib_boom", "extension_boom"]
    assert body["spec"]["load_point"]["body"] == "extension_boom"
    assert all(c["type"] == "set_object" for c in body["commands"])
    r = await client.get("/api/v1/machines/nope/scene", headers=KEY)
    assert r.status_code == 404


@pytest.mark.asyncio
async def test_export_is_self_contained(client) -> None:  # type: ignore[no-untyped-def]
    t1 = 1_795_000_000.0
    r = await client.get("/api/v1/machines/crane-2/export.html",
                         params={"from": t1 - 120, "to": t1}, headers=KEY)
    assert r.status_code == 200, r.text[:300]
    html = r.text
    assert "attachment" in r.headers["content-disposition"]
    assert 'src="/' not in html and 'href="/static' not in html  # nothing fetched from a server
    pattern = r'<script type="text/plain" id="(ct-[a-z]+)">([A-Za-z0-9+/=]*)</script>'
    blobs = dict(re.findall(pattern, html))
    assert set(blobs) == {"ct-meshcat", "ct-plotly", "ct-data", "ct-app"}
    text = {k: gzip.decompress(base64.b64decode(v)).decode() for k, v in blobs.items()}
    assert text["ct-meshcat"] == vendor_file("meshcat.min.js").read_text()
    assert text["ct-plotly"] == vendor_file("plotly.min.js").read_text()
    assert text["ct-app"] == bundle_modules(web_dir())
    embed = json.loads(text["ct-data"])
    assert embed["from"] == t1 - 120 and embed["to"] == t1
    assert embed["machine"]["machine_id"] == "crane-2"
    assert len(embed["twin"]["t"]) == pytest.approx(120 * export_rate_hz(120), abs=2)
    assert set(embed["twin"]["poses"]) == {"pillar", "lift_boom", "jib_boom", "extension_boom"}
    # each minute's verdicts on the forces (none from the preview's synthetic twin), for the
    # page to show the ones of the cursor's minute
    notes = embed["twin"]["notes"]
    assert [n["from"] for n in notes] == pytest.approx([t1 - 120, t1 - 60], abs=0.1)
    assert notes[0]["to"] <= notes[1]["from"] and notes[1]["to"] <= t1
    assert all(isinstance(n["force_observability"], list) for n in notes)
    assert len(html) < 5_000_000  # e-mailable


@pytest.mark.asyncio
async def test_export_rejects_bad_ranges(client) -> None:  # type: ignore[no-untyped-def]
    url = "/api/v1/machines/crane-2/export.html"
    for params in ({"from": 10, "to": 5}, {"from": 0, "to": 4000}, {"from": "yesterday", "to": 5}):
        r = await client.get(url, params=params, headers=KEY)
        assert r.status_code == 422, params
        assert r.json()["detail"]
    assert (await client.get(url, params={"from": 0, "to": 5})).status_code == 401


def test_rest_frame_is_inside_the_joint_limits(machine) -> None:  # type: ignore[no-untyped-def]
    from cranetwin.viz.poses import rest_frame, rest_q

    q = rest_q(machine)
    for qi, j in zip(q, machine.joints, strict=True):
        assert j.lower <= qi <= j.upper, j.name
    f = rest_frame(machine)
    assert f["payload_kg"] == 0.0
    assert np.allclose(f["tip"], load_point_position(machine, q[None, :])[0])


def test_linkage_drawing_closes_the_four_bar(machine) -> None:  # type: ignore[no-untyped-def]
    """The browser draws D→E and E→F from the body poses and the rod pin E: their lengths must
    be the linkage's link lengths at every pose (as the page computes them, column-major)."""
    _, spec = build_scene(machine)
    links = spec.extras["linkages"]
    assert set(links) == {c.name for c in machine.cylinders if c.linkage is not None}
    rng = np.random.default_rng(3)
    lo = np.array([j.lower for j in machine.joints])
    hi = np.array([j.upper for j in machine.joints])
    q = lo + (hi - lo) * rng.uniform(0.1, 0.9, size=(20, 4))
    f = frame_arrays(machine, q)

    def world(body: str, p: list[float], k: int) -> np.ndarray:
        m = np.asarray(f["poses"][body][k])
        return np.array([m[i] * p[0] + m[4 + i] * p[1] + m[8 + i] * p[2] + m[12 + i]
                         for i in range(3)])

    for name, lk in links.items():
        cyl = machine.cylinder(name)
        assert cyl.linkage is not None
        for k in range(len(q)):
            e = np.asarray(f["cylinder_pins"][name][k][3:])
            d = world(lk["parent_body"], lk["pivot_m"], k)
            fc = world(lk["child_body"], lk["coupler_m"], k)
            assert np.linalg.norm(e - d) == pytest.approx(cyl.linkage.pivot_link_m, abs=1e-9)
            assert np.linalg.norm(e - fc) == pytest.approx(cyl.linkage.coupler_link_m, abs=1e-9)
