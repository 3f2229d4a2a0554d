"""Build the 3D scene of a machine as meshcat commands (three.js Object JSON).

Every body of the machine description becomes a node ``/cranetwin/bodies/<body>`` whose children
are triangle meshes made with trimesh from the body's ``visuals`` (segments, boxes, mesh files),
expressed in the body frame; the browser (or an exported replay) moves the node with the body pose
(``set_transform``, 16 floats, column-major). Hydraulic cylinders are not rigid bodies: each is a
barrel and a rod mesh of unit length along +z (``/cranetwin/cylinders/<name>/barrel|rod``) that the
browser stretches between the cylinder's two pins every frame (:func:`segment_matrix`). The tool
and the payload sit at the load point under ``/cranetwin/tool``: a machine whose load point carries
a tool of its own (``load_point.tool_mass_kg`` > 0, the crane's rotator and grapple) gets that tool
drawn and the payload as a log hanging under it; a machine whose load body is the tool
(``tool_mass_kg`` = 0, the excavator's bucket, drawn by the body's visuals) gets no extra tool and
the payload as a lump of soil at the load point. Either payload's size follows the payload mass
(the spec's ``log_length_m``/``log_density_kgm3``/``tool_drop_m`` tell the browser how).

The command dicts are plain JSON (lists, no msgpack extension types), so they go over HTTP or are
embedded in an HTML file unchanged and are passed to ``viewer.handle_command(cmd)``.
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np
import numpy.typing as npt
import trimesh

from cranetwin.errors import CraneTwinError
from cranetwin.model import FourBar, Machine, Visual

log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]

ROOT = "/cranetwin"
LOG_DENSITY_KGM3 = 900.0
"""Density of green softwood [kg/m³], used to size the payload log from its mass."""
LOG_LENGTH_M = 3.0
"""Length of the drawn log [m]."""
TOOL_DROP_M = 0.55
"""Distance from the load point down to the grapple jaws [m] (drawing only)."""
SOIL_DENSITY_KGM3 = 1600.0
"""Density of loose soil [kg/m³], used to size the payload lump of a bucket (drawing only)."""
SOIL_WIDTH_M = 0.5
"""Width of the drawn soil lump across the arm's plane [m] (drawing only)."""


def tool_is_load_body(machine: Machine) -> bool:
    """Whether the machine's tool is its load body (no separate tool mass at the load point, e.g.
    an excavator's bucket), so that no grapple is drawn and the payload is drawn as soil."""
    return machine.load_point.tool_mass_kg == 0.0


class SceneError(CraneTwinError):
    """A scene could not be built (e.g. an unreadable mesh file in the machine description)."""


@dataclass(frozen=True)
class SceneSpec:
    """What the browser needs besides the meshes to animate the scene.

    Attributes:
        bodies: Body names in chain order; pose arrays use this order.
        body_paths: meshcat path of each body node.
        cylinders: Cylinder names (order of ``machine.cylinders``).
        barrel_lengths_m: Drawn barrel length per cylinder [m] (≈ closed length).
        tool_path: meshcat path of the tool node (placed at the load point, world-aligned).
        payload_path: meshcat path of the payload log (unit mesh, scaled by :func:`payload_matrix`).
        trail_path: meshcat path of the tip-path line.
        rated_payload_kg: Largest rated payload [kg], for the payload bar; None: no rated-load
            chart (unknown).
    """

    bodies: list[str]
    body_paths: dict[str, str]
    cylinders: list[str]
    barrel_lengths_m: dict[str, float]
    tool_path: str
    payload_path: str
    trail_path: str
    rated_payload_kg: float | None
    extras: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """JSON-ready dict."""
        return {
            "bodies": self.bodies,
            "body_paths": self.body_paths,
            "cylinders": self.cylinders,
            "barrel_lengths_m": self.barrel_lengths_m,
            "tool_path": self.tool_path,
            "payload_path": self.payload_path,
            "trail_path": self.trail_path,
            "rated_payload_kg": self.rated_payload_kg,
            **self.extras,
        }


# --- geometry ------------------------------------------------------------------------------------


def segment_matrix(p0: F64, p1: F64) -> F64:
    """Homogeneous matrix taking a unit mesh along +z (z ∈ [0, 1]) onto the segment p0→p1.

    Args:
        p0: Segment start, shape (..., 3) [m].
        p1: Segment end, shape (..., 3) [m].

    Returns:
        Matrices, shape (..., 4, 4): columns are u, w (unit, orthogonal to the segment), the
        segment vector d = p1 − p0 (so the z scale is the segment length) and p0. A zero-length
        segment gives a zero z column (the mesh collapses to a disc).
    """
    p0 = np.asarray(p0, dtype=float)
    p1 = np.asarray(p1, dtype=float)
    d = p1 - p0
    length = np.linalg.norm(d, axis=-1, keepdims=True)
    n = np.where(length > 1e-12, d / np.maximum(length, 1e-12), np.array([0.0, 0.0, 1.0]))
    # helper axis: world y unless nearly parallel to n, then world x
    helper = np.where(np.abs(n[..., 1:2]) < 0.9, np.array([0.0, 1.0, 0.0]), np.array([1.0, 0, 0]))
    u = np.cross(helper, n)
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    w = np.cross(n, u)
    out = np.zeros(p0.shape[:-1] + (4, 4))
    out[..., :3, 0] = u
    out[..., :3, 1] = w
    out[..., :3, 2] = d
    out[..., :3, 3] = p0
    out[..., 3, 3] = 1.0
    return out


def log_radius_m(payload_kg: F64 | float) -> F64:
    """Radius [m] of a log of length :data:`LOG_LENGTH_M` weighing ``payload_kg`` [kg]."""
    m = np.maximum(np.asarray(payload_kg, dtype=float), 0.0)
    return np.asarray(np.sqrt(m / (LOG_DENSITY_KGM3 * np.pi * LOG_LENGTH_M)), dtype=float)


def _segment_mesh(v: Visual) -> trimesh.Trimesh:
    p0 = np.asarray(v.from_m, dtype=float)
    p1 = np.asarray(v.to_m, dtype=float)
    if np.linalg.norm(p1 - p0) < 1e-9:
        sphere = trimesh.creation.icosphere(subdivisions=1, radius=v.radius_m)
        return cast(trimesh.Trimesh, sphere.apply_translation(p0))
    seg = np.stack([p0, p1])
    return cast(trimesh.Trimesh, trimesh.creation.cylinder(radius=v.radius_m, segment=seg,
                                                           sections=20))


def visual_mesh(v: Visual, base_dir: Path | None = None) -> trimesh.Trimesh:
    """Triangle mesh of one visual primitive, in its body's frame [m].

    Raises:
        SceneError: a ``mesh`` visual whose file is missing or unreadable.
    """
    if v.kind == "segment":
        return _segment_mesh(v)
    if v.kind == "box":
        box = trimesh.creation.box(extents=v.size_m)
        return cast(trimesh.Trimesh, box.apply_translation(v.from_m))
    if not v.mesh_file:
        raise SceneError("mesh visual without mesh_file: expected a path to an STL/GLB/OBJ file")
    path = Path(v.mesh_file)
    if not path.is_absolute() and base_dir is not None:
        path = base_dir / path
    try:
        loaded = trimesh.load(str(path), force="mesh")
    except (OSError, ValueError) as exc:
        raise SceneError(f"mesh file {path}: cannot load ({exc}); expected STL, GLB or OBJ"
                         ) from exc
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise SceneError(f"mesh file {path}: no triangles found")
    return cast(trimesh.Trimesh, loaded.apply_translation(v.from_m))


# --- three.js JSON -------------------------------------------------------------------------------


def _uuid() -> str:
    return str(uuid.uuid4())


def _hex_color(color: str) -> int:
    c = color.lstrip("#")
    if len(c) == 3:
        c = "".join(ch * 2 for ch in c)
    try:
        return int(c, 16)
    except ValueError as exc:
        raise SceneError(f"colour {color!r}: expected #rrggbb") from exc


def mesh_object(mesh: trimesh.Trimesh, color: str, *, name: str = "",
                opacity: float = 1.0, decimals: int = 4) -> dict[str, Any]:
    """three.js Object JSON (format 4.5) of one triangle mesh with a Lambert material.

    Vertices are split at sharp edges (trimesh ``smooth_shaded``) so that caps and box faces
    shade flat while round surfaces shade smooth.
    """
    shaded = mesh.smooth_shaded
    verts = np.round(np.asarray(shaded.vertices, dtype=float), decimals)
    normals = np.round(np.asarray(shaded.vertex_normals, dtype=float), 3)
    faces = np.asarray(shaded.faces, dtype=np.int64)
    geom_id, mat_id = _uuid(), _uuid()
    material: dict[str, Any] = {
        "uuid": mat_id,
        "type": "MeshLambertMaterial",
        "color": _hex_color(color),
        "side": 2,
    }
    if opacity < 1.0:
        material.update(transparent=True, opacity=opacity)
    return {
        "metadata": {"version": 4.5, "type": "Object"},
        "geometries": [{
            "uuid": geom_id,
            "type": "BufferGeometry",
            "data": {
                "attributes": {
                    "position": {"itemSize": 3, "type": "Float32Array",
                                 "array": verts.ravel().tolist(), "normalized": False},
                    "normal": {"itemSize": 3, "type": "Float32Array",
                               "array": normals.ravel().tolist(), "normalized": False},
                },
                "index": {"type": "Uint32Array", "array": faces.ravel().tolist()},
            },
        }],
        "materials": [material],
        "object": {
            "uuid": _uuid(),
            "type": "Mesh",
            "name": name,
            "geometry": geom_id,
            "material": mat_id,
            "matrix": np.eye(4).ravel().tolist(),
        },
    }


def line_object(n_points: int, color: str, *, name: str = "") -> dict[str, Any]:
    """three.js Object JSON of a polyline with room for ``n_points`` vertices (all at the origin).

    The browser rewrites the position attribute in place (the tip-path trail).
    """
    geom_id, mat_id = _uuid(), _uuid()
    return {
        "metadata": {"version": 4.5, "type": "Object"},
        "geometries": [{
            "uuid": geom_id,
            "type": "BufferGeometry",
            "data": {"attributes": {"position": {
                "itemSize": 3, "type": "Float32Array", "array": [0.0] * (3 * n_points),
                "normalized": False}}},
        }],
        "materials": [{"uuid": mat_id, "type": "LineBasicMaterial",
                       "color": _hex_color(color), "linewidth": 2}],
        "object": {"uuid": _uuid(), "type": "Line", "name": name, "geometry": geom_id,
                   "material": mat_id, "frustumCulled": False,
                   "matrix": np.eye(4).ravel().tolist()},
    }


def set_object(path: str, obj: dict[str, Any]) -> dict[str, Any]:
    """A meshcat ``set_object`` command."""
    return {"type": "set_object", "path": path, "object": obj}


def set_transform(path: str, matrix: F64 | Sequence[float]) -> dict[str, Any]:
    """A meshcat ``set_transform`` command; ``matrix`` is (4, 4) or 16 column-major floats."""
    m = np.asarray(matrix, dtype=float)
    flat = m.T.ravel() if m.shape == (4, 4) else m.ravel()
    if flat.shape != (16,):
        raise SceneError(f"transform matrix has shape {m.shape}: expected (4, 4) or (16,)")
    return {"type": "set_transform", "path": path, "matrix": flat.tolist()}


def set_property(path: str, prop: str, value: Any) -> dict[str, Any]:
    """A meshcat ``set_property`` command."""
    return {"type": "set_property", "path": path, "property": prop, "value": value}


# --- the whole scene -----------------------------------------------------------------------------


def _body_path(name: str) -> str:
    return f"{ROOT}/bodies/{name}"


def build_scene(machine: Machine, base_dir: Path | None = None,
                trail_points: int = 600) -> tuple[list[dict[str, Any]], SceneSpec]:
    """Meshcat commands that draw ``machine`` at rest, and the spec that animates them.

    Args:
        machine: The machine description (its bodies' ``visuals`` are drawn).
        base_dir: Folder that relative ``mesh_file`` paths are resolved against.
        trail_points: Capacity of the tip-path line [points].

    Returns:
        ``(commands, spec)``: ``set_object`` commands (one per visual, cylinder part, tool part,
        payload and trail), in drawing order, and the :class:`SceneSpec`.

    Raises:
        SceneError: a visual cannot be turned into a mesh.
    """
    cmds: list[dict[str, Any]] = []
    bodies = [j.child for j in machine.joints]
    for body in machine.bodies:
        for i, v in enumerate(body.visuals):
            mesh = visual_mesh(v, base_dir)
            cmds.append(set_object(f"{_body_path(body.name)}/v{i}",
                                   mesh_object(mesh, v.color, name=f"{body.name}.{i}")))
    barrels: dict[str, float] = {}
    linkages: dict[str, dict[str, Any]] = {}
    for cyl in machine.cylinders:
        barrel_r = 0.5 * cyl.bore_m + 0.012
        barrel = trimesh.creation.cylinder(radius=barrel_r, segment=[[0, 0, 0], [0, 0, 1]],
                                           sections=16)
        rod = trimesh.creation.cylinder(radius=0.5 * cyl.rod_m, segment=[[0, 0, 0], [0, 0, 1]],
                                        sections=12)
        cmds.append(set_object(f"{ROOT}/cylinders/{cyl.name}/barrel",
                               mesh_object(barrel, "#2f6db5", name=f"{cyl.name}.barrel")))
        cmds.append(set_object(f"{ROOT}/cylinders/{cyl.name}/rod",
                               mesh_object(rod, "#c9ced6", name=f"{cyl.name}.rod")))
        barrels[cyl.name] = 0.92 * cyl.closed_length_m
        if isinstance(cyl.linkage, FourBar):
            # four-bar: link D→E (pivot on the parent body to the rod end) and E→F (rod end to
            # the coupler pin on the child body), unit +z meshes stretched every frame
            joint = machine.joints[machine.joint_index(cyl.joint)]
            link = trimesh.creation.box(extents=(0.05, 0.03, 1.0))
            link.apply_translation((0.0, 0.0, 0.5))
            for part in ("pivot_link", "coupler_link"):
                cmds.append(set_object(f"{ROOT}/cylinders/{cyl.name}/{part}",
                                       mesh_object(link, "#c9901a", name=f"{cyl.name}.{part}")))
            linkages[cyl.name] = {"parent_body": joint.parent, "pivot_m": list(cyl.linkage.pivot_m),
                                  "child_body": joint.child,
                                  "coupler_m": list(cyl.linkage.coupler_pin_m)}
    tool = f"{ROOT}/tool"
    if tool_is_load_body(machine):
        # the payload lump: unit mesh of radius 1 in x and z and width 1 along y (the browser
        # scales it like the log: radius from the mass, width = log_length_m), centred just
        # under the load point
        lump = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
        lump.apply_scale((1.0, 0.5, 1.0))
        cmds.append(set_object(f"{tool}/payload", mesh_object(lump, "#6b4f2a", name="payload")))
        drawing = {"tool_drop_m": 0.0, "log_length_m": SOIL_WIDTH_M,
                   "log_density_kgm3": SOIL_DENSITY_KGM3, "payload_kind": "soil"}
    else:
        rotator = trimesh.creation.cylinder(radius=0.06,
                                            segment=np.array([[0, 0, 0], [0, 0, -0.3]]),
                                            sections=12)
        cmds.append(set_object(f"{tool}/rotator", mesh_object(rotator, "#3d4b5c",
                                                              name="rotator")))
        jaws = [trimesh.creation.box(extents=(0.08, 0.5, 0.45)).apply_translation((sx, 0, -0.45))
                for sx in (-0.22, 0.22)]
        head = trimesh.creation.box(extents=(0.5, 0.3, 0.14)).apply_translation((0, 0, -0.28))
        grapple = cast(trimesh.Trimesh, trimesh.util.concatenate([head, *jaws]))
        cmds.append(set_object(f"{tool}/grapple", mesh_object(grapple, "#3d4b5c",
                                                              name="grapple")))
        log_mesh = trimesh.creation.cylinder(radius=1.0,
                                             segment=np.array([[0, -0.5, 0], [0, 0.5, 0]]),
                                             sections=16)
        cmds.append(set_object(f"{tool}/payload", mesh_object(log_mesh, "#8b5a2b",
                                                              name="payload")))
        drawing = {"tool_drop_m": TOOL_DROP_M, "log_length_m": LOG_LENGTH_M,
                   "log_density_kgm3": LOG_DENSITY_KGM3, "payload_kind": "log"}
    cmds.append(set_object(f"{ROOT}/trail", line_object(trail_points, "#e0457b", name="trail")))
    spec = SceneSpec(
        bodies=bodies,
        body_paths={b: _body_path(b) for b in bodies},
        cylinders=[c.name for c in machine.cylinders],
        barrel_lengths_m=barrels,
        tool_path=tool,
        payload_path=f"{tool}/payload",
        trail_path=f"{ROOT}/trail",
        rated_payload_kg=(None if machine.rated_load is None  # no chart: unknown
                          else float(max(machine.rated_load.payload_kg))),
        extras={"trail_points": trail_points, "linkages": linkages, **drawing},
    )
    return cmds, spec


def payload_matrix(payload_kg: float, slew_rad: float = 0.0) -> F64:
    """Pose (4, 4) of the unit payload log in the tool frame for a payload [kg].

    The unit log (radius 1 m, length 1 m along y) is scaled to radius :func:`log_radius_m` and
    length :data:`LOG_LENGTH_M`, turned with the slew angle [rad] so it lies across the boom, and
    hung under the grapple. Zero payload gives a zero-size log.
    """
    r = float(log_radius_m(payload_kg))
    c, s = np.cos(slew_rad), np.sin(slew_rad)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    m = np.eye(4)
    m[:3, :3] = rot @ np.diag([r, LOG_LENGTH_M if r > 0 else 0.0, r])
    m[:3, 3] = (0.0, 0.0, -TOOL_DROP_M - r)
    return m
