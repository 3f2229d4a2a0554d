"""Pydantic schema of a machine description (TOML file).

All quantities are SI. Frames: every body has a frame; a joint's frame sits at ``origin_m`` in the
parent body's frame (rotated by ``origin_rpy_rad``, roll-pitch-yaw, XYZ fixed axes), and the child
body's frame equals the joint frame moved by the joint coordinate q (rotation by q [rad] about
``axis`` for revolute, translation by q [m] along ``axis`` for prismatic). Joints form a serial
chain from the world (``parent = "world"``) to the tip body. Inertia tensors are about the body's
centre of mass, in the body frame's axes [kg·m²] (``Body.inertia_frame`` = "com", the default;
"origin" states them about the body frame's origin); point masses on a body are folded into it
at load (parallel-axis theorem).
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from cranetwin.model.references import WORLD as WORLD  # re-exported
from cranetwin.model.references import reference_problems as reference_problems

Vec3 = Annotated[tuple[float, float, float], Field(description="3-vector [m] or unit-free")]
Mat3 = tuple[Vec3, Vec3, Vec3]


class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class Visual(_Frozen):
    """A primitive for the 3D view, in the body frame.

    ``segment``: a cylinder of ``radius_m`` from ``from_m`` to ``to_m``; ``box``: a box of
    ``size_m`` centred at ``from_m``; ``mesh``: an STL/GLB file (path relative to the machine file).
    """

    kind: Literal["segment", "box", "mesh"] = "segment"
    from_m: Vec3 = (0.0, 0.0, 0.0)
    to_m: Vec3 = (0.0, 0.0, 0.0)
    radius_m: float = Field(0.05, gt=0)
    size_m: Vec3 = (0.1, 0.1, 0.1)
    mesh_file: str | None = None
    color: str = "#f2b01e"


class PointMass(_Frozen):
    """A mass attached to a body (bracket, valve block, rotator): ``mass_kg`` [kg] at
    ``position_m`` [m] in the body frame, with its own ``inertia_kgm2`` about its centre in
    the body's axes [kg·m²] (zero: a point)."""

    name: str = ""
    mass_kg: float = Field(gt=0)
    position_m: Vec3
    inertia_kgm2: Mat3 = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))


InertiaFrame = Literal["com", "origin"]


def fold_point_masses(mass: float, com: np.ndarray, inertia: np.ndarray,
                      points: list[PointMass]) -> tuple[float, np.ndarray, np.ndarray]:
    """A body with point masses as one body: total mass [kg], centre of mass (3,) [m] and
    inertia about that centre (3, 3) [kg·m²] (parallel-axis theorem, body axes).

    Args:
        mass, com, inertia: The bare body: mass, centre of mass, inertia about its centre.
        points: The masses attached to it.
    """
    items = [(mass, com, inertia)] + [(p.mass_kg, np.asarray(p.position_m, dtype=float),
                                       np.asarray(p.inertia_kgm2, dtype=float)) for p in points]
    total = sum(m for m, _, _ in items)
    if total <= 0:
        return 0.0, com, inertia
    c: np.ndarray = np.sum([m * x for m, x, _ in items], axis=0) / total
    out = np.zeros((3, 3))
    for m, x, i in items:
        d = x - c
        out += i + m * (float(d @ d) * np.eye(3) - np.outer(d, d))
    return float(total), c, out


class Body(_Frozen):
    """A rigid body: mass [kg], centre of mass [m] in its frame, inertia [kg·m²].

    Inertia convention (``inertia_frame``): ``"com"`` (the default): about the centre of mass,
    along the body frame's axes; ``"origin"``: about the body frame's origin, along its axes
    (converted at load, I_com = I_origin − m·(|c|²·E − c·cᵀ)). Point masses (``point_masses``)
    are folded into the body at load by the parallel-axis theorem: after loading, ``mass_kg``,
    ``com_m`` and ``inertia_kgm2`` (about the centre of mass) are the whole body's, the
    masses are listed in ``folded_point_masses`` and ``inertia_frame`` is ``"com"``.
    """

    name: str
    mass_kg: float = Field(ge=0)
    com_m: Vec3 = (0.0, 0.0, 0.0)
    inertia_kgm2: Mat3 = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    inertia_frame: InertiaFrame = Field(
        "com", description="inertia_kgm2 about the centre of mass ('com') or about the body "
        "frame's origin ('origin'), body axes either way")
    point_masses: list[PointMass] = Field(
        default_factory=list, description="masses attached to the body (folded in at load)")
    folded_point_masses: list[PointMass] = Field(
        default_factory=list, description="the point masses already folded into mass_kg, "
        "com_m and inertia_kgm2 (set at load)")
    assumed: list[str] = Field(default_factory=list, description="fields whose values are assumed")
    visuals: list[Visual] = Field(default_factory=list)

    @model_validator(mode="before")
    @classmethod
    def _fold(cls, data: object) -> object:
        if not isinstance(data, dict):
            return data
        frame = data.get("inertia_frame", "com")
        points = data.get("point_masses") or []
        if frame == "com" and not points:
            return data
        out = dict(data)
        try:
            m = float(out.get("mass_kg", 0.0))
            c = np.asarray(out.get("com_m", (0.0, 0.0, 0.0)), dtype=float).reshape(3)
            i = np.asarray(out.get("inertia_kgm2", np.zeros((3, 3))), dtype=float).reshape(3, 3)
            pts = [p if isinstance(p, PointMass) else PointMass.model_validate(p)
                   for p in points]
        except (TypeError, ValueError):
            return data  # the field validators report it
        if frame == "origin":
            i = i - m * (float(c @ c) * np.eye(3) - np.outer(c, c))
        elif frame != "com":
            return data
        m, c, i = fold_point_masses(m, c, i, pts)
        out.update(mass_kg=m, com_m=tuple(float(x) for x in c),
                   inertia_kgm2=tuple(tuple(float(x) for x in row) for row in i),
                   inertia_frame="com", point_masses=[],
                   folded_point_masses=list(out.get("folded_point_masses") or []) + pts)
        return out

    @field_validator("inertia_kgm2")
    @classmethod
    def _inertia_physical(cls, value: Mat3) -> Mat3:
        m = np.asarray(value, dtype=float)
        if not np.allclose(m, m.T, atol=1e-9 * max(1.0, float(np.abs(m).max()))):
            raise ValueError("inertia tensor must be symmetric")
        eig = np.linalg.eigvalsh(m)
        if np.any(eig < -1e-12):
            raise ValueError(f"inertia tensor must be positive semi-definite (eigenvalues {eig})")
        a, b, c = sorted(eig)
        tol = 1e-9 * max(1.0, c)
        if a + b < c - tol:
            raise ValueError(f"inertia eigenvalues {eig} violate the triangle inequality")
        return value


class Joint(_Frozen):
    """A one-degree-of-freedom joint joining ``parent`` body (or the world) to ``child`` body."""

    name: str
    kind: Literal["revolute", "prismatic"]
    parent: str
    child: str
    axis: Vec3
    origin_m: Vec3 = (0.0, 0.0, 0.0)
    origin_rpy_rad: Vec3 = (0.0, 0.0, 0.0)
    lower: float = Field(description="lower limit [rad or m]")
    upper: float = Field(description="upper limit [rad or m]")
    velocity_limit: float | None = Field(
        None, gt=0, description="[rad/s or m/s]; None: unknown (no overspeed check, and the "
        "simulator cannot drive a torque drive on the joint)")
    unit: str = ""
    fixed_value: float | None = Field(
        None, description="passive joint (no actuator): held at this value [rad or m], within "
        "[lower, upper]; required on a joint without an actuator, not allowed with one")

    @field_validator("axis")
    @classmethod
    def _unit_axis(cls, value: Vec3) -> Vec3:
        n = float(np.linalg.norm(value))
        if n < 1e-9:
            raise ValueError("axis must be non-zero")
        if abs(n - 1.0) > 1e-6:
            raise ValueError(f"axis must be a unit vector (norm {n:.6g})")
        return value

    @model_validator(mode="after")
    def _limits(self) -> Joint:
        if not self.lower < self.upper:
            raise ValueError(f"lower limit {self.lower} must be below upper limit {self.upper}")
        if self.fixed_value is not None and not self.lower <= self.fixed_value <= self.upper:
            raise ValueError(f"fixed_value {self.fixed_value} must lie within the limits "
                             f"[{self.lower}, {self.upper}]")
        return self


class Friction(_Frozen):
    """Friction of Eq. 2 of the paper: F_fr = Fc·tanh(v/vc) + b·v."""

    coulomb: float = Field(ge=0, description="Fc [N] (cylinder) or [N·m] (rotary)")
    coulomb_velocity: float = Field(gt=0, description="vc [m/s] or [rad/s]")
    viscous: float = Field(ge=0, description="b [N·s/m] or [N·m·s/rad]")


class FourBar(_Frozen):
    """Jib-style linkage: the rod end E is joined to the parent body by a link D→E of length
    ``pivot_link_m`` (pivoting at ``pivot_m`` on the joint's parent body) and to the child body by a
    link E→F of length ``coupler_link_m`` (F = ``coupler_pin_m`` in the child frame).

    ``branch`` (+1 or −1) selects the circle intersection of E: +1 puts E on the side of the line
    D→F where ``(F−D) × (E−D)`` points along the joint axis.
    """

    kind: Literal["four_bar"] = "four_bar"
    pivot_m: Vec3
    pivot_link_m: float = Field(gt=0)
    coupler_pin_m: Vec3
    coupler_link_m: float = Field(gt=0)
    branch: Literal[-1, 1] = 1


class LinearActuator(_Frozen):
    """A cylinder acting directly along a prismatic joint (a telescope, a directly acting linear
    actuator): rod position s = ``s0_m`` + q [m], q the joint position. The cylinder's force is
    the joint's force (moment arm 1); its pins (``base_pin_m``, ``rod_pin_m``) only draw it.
    """

    kind: Literal["linear"] = "linear"
    s0_m: float = Field(0.0, description="rod position s at joint position q = 0 [m]")


Linkage = Annotated[FourBar | LinearActuator, Field(discriminator="kind")]
"""The linkage kinds a cylinder may declare (a cylinder without one is pinned directly to the
two bodies of its joint)."""


class Valve(_Frozen):
    """Proportional valve: Q = Qn·U·sign(Δp)·sqrt(|Δp|), first-order spool lag."""

    flow_gain: float = Field(gt=0, description="Qn [m³/(s·V·√Pa)]")
    spool_time_constant_s: float = Field(gt=0)
    max_voltage_v: float = Field(10.0, gt=0)


class Cylinder(_Frozen):
    """A double-acting hydraulic cylinder driving ``joint``.

    The base pin sits on the joint's parent body, the rod pin on the child body (``linkage`` absent)
    or on the four-bar rod end E (a ``four_bar`` linkage; ``rod_pin_m`` then unused).
    Rod position s = cylinder pin-to-pin length − ``closed_length_m``, in [0, ``stroke_m``];
    with a ``linear`` linkage s = s0 + q along a prismatic joint and the pins only draw it.
    """

    name: str
    kind: Literal["cylinder"] = "cylinder"
    joint: str
    base_pin_m: Vec3
    rod_pin_m: Vec3 = (0.0, 0.0, 0.0)
    bore_m: float = Field(gt=0)
    rod_m: float = Field(gt=0)
    closed_length_m: float = Field(gt=0)
    stroke_m: float = Field(gt=0)
    friction: Friction
    valve: Valve | None = None
    linkage: Linkage | None = None
    dead_volume_m3: float | None = Field(
        None, gt=0, description="hose + port volume per chamber of this cylinder [m³]; None: "
        "hydraulics.dead_volume_m3")
    shock_rate_n_per_s: float | None = Field(
        None, gt=0, description="rate of change of the cylinder's load force above which a "
        "load is a shock [N/s]; None: 15/s × the push force at relief pressure "
        "(docs/ANALYTICS.md, shock_load)")
    assumed: list[str] = Field(default_factory=list)

    @model_validator(mode="after")
    def _rod_in_bore(self) -> Cylinder:
        if self.rod_m >= self.bore_m:
            raise ValueError(f"rod diameter {self.rod_m} m must be below bore {self.bore_m} m")
        return self

    @property
    def area_a_m2(self) -> float:
        """Piston-side area A1 [m²]."""
        return float(np.pi / 4 * self.bore_m**2)

    @property
    def area_b_m2(self) -> float:
        """Rod-side (annulus) area A2 [m²]."""
        return float(np.pi / 4 * (self.bore_m**2 - self.rod_m**2))


class TorqueDrive(_Frozen):
    """A drive whose torque [N·m] is measured directly (e.g. the slewing rack-and-pinion)."""

    name: str
    kind: Literal["torque"] = "torque"
    joint: str
    max_torque_nm: float = Field(gt=0)
    friction: Friction
    assumed: list[str] = Field(default_factory=list)


Quantity = Literal["pressure_a", "pressure_b", "position", "torque", "angle", "load"]


class Channel(_Frozen):
    """A sensor channel sent by the machine."""

    name: str
    quantity: Quantity
    source: str = Field(description="actuator name (pressure/position/torque) or joint (angle)")
    unit: str
    min: float | None = Field(None, description="lower end of the sensor's range, in ``unit``; "
                              "None (with max): the range is unknown")
    max: float | None = Field(None, description="upper end of the sensor's range, in ``unit``; "
                              "None (with min): the range is unknown")
    resolution: float = Field(gt=0, description="quantisation step, in ``unit``")
    accuracy: float | None = Field(
        None, gt=0, description="stated accuracy of the sensor, ± bound in ``unit`` (e.g. "
        "0.5 % of the full range); None: not stated (the twin then uses the noise it "
        "estimates from the data)")
    optional: bool = False

    @model_validator(mode="after")
    def _range(self) -> Channel:
        if (self.min is None) != (self.max is None):
            raise ValueError("give both min and max (the sensor's range), or neither (unknown)")
        if self.min is not None and self.max is not None and not self.min < self.max:
            raise ValueError(f"min {self.min} must be below max {self.max}")
        return self

    @property
    def full_range(self) -> float | None:
        """max − min, in ``unit``; None when the range is unknown."""
        if self.min is None or self.max is None:
            return None
        return self.max - self.min


class Hydraulics(_Frozen):
    """Hydraulic circuit parameters for the machine-side simulator."""

    supply_pressure_pa: float = Field(gt=0)
    tank_pressure_pa: float = Field(ge=0)
    relief_pressure_pa: float = Field(gt=0)
    oil_bulk_modulus_pa: float = Field(gt=0)
    hose_bulk_modulus_pa: float = Field(gt=0)
    dead_volume_m3: float = Field(gt=0, description="hose + port volume per chamber, for "
                                  "every cylinder without its own dead_volume_m3")

    @property
    def effective_bulk_modulus_pa(self) -> float:
        """Series combination of oil and hose compliance [Pa]."""
        return 1.0 / (1.0 / self.oil_bulk_modulus_pa + 1.0 / self.hose_bulk_modulus_pa)


class LoadPoint(_Frozen):
    """Where the tool and payload hang: a point on a body, and the tool mass [kg]."""

    body: str
    point_m: Vec3
    tool_mass_kg: float = Field(ge=0, description="grapple + rotator, always present")


class RatedLoad(_Frozen):
    """Rated load chart: payload [kg] allowed at horizontal reach [m] from the slew axis."""

    reach_m: list[float]
    payload_kg: list[float]

    @model_validator(mode="after")
    def _chart(self) -> RatedLoad:
        if len(self.reach_m) != len(self.payload_kg) or len(self.reach_m) < 1:
            raise ValueError("reach_m and payload_kg must be non-empty and of equal length")
        if any(b <= a for a, b in zip(self.reach_m, self.reach_m[1:], strict=False)):
            raise ValueError("reach_m must be strictly increasing")
        if any(p <= 0 for p in self.payload_kg):
            raise ValueError("payload_kg must be positive")
        return self

    def payload_at(self, reach_m: np.ndarray) -> np.ndarray:
        """Rated payload [kg] at reach [m], linear in between, held beyond the chart's ends."""
        return np.asarray(np.interp(reach_m, self.reach_m, self.payload_kg), dtype=float)


class FatigueDetail(_Frozen):
    """A structural detail for Miner damage: nominal stress = ``stress_per_load`` × load.

    ``load`` names a load history: ``cylinder:<name>:force`` [N] or ``joint:<name>:moment`` [N·m]
    (magnitude of the reaction moment at the joint). S-N curve per EN 13001-3-1:
    N = 2e6·(Δσc/Δσ)^m.
    """

    name: str
    load: str
    stress_per_load: float = Field(gt=0, description="[Pa per N] or [Pa per N·m]")
    detail_category_mpa: float = Field(gt=0, description="Δσc at 2e6 cycles [MPa]")
    slope_m: float = Field(3.0, gt=0)
    assumed: bool = True


class Classification(_Frozen):
    """Design classification (ISO 4301-1 / FEM 1.001)."""

    design_group: str = "A4"
    design_total_cycles: float = Field(gt=0, description="C_t, working cycles over design life")
    design_spectrum_factor: float = Field(gt=0, le=1, description="kp of the design")
    design_life_years: float = Field(10.0, gt=0)


class MachineInfo(_Frozen):
    name: str
    description: str = ""
    gravity_mps2: Vec3 = (0.0, 0.0, -9.81)


class Machine(_Frozen):
    """A whole machine description. Joints are ordered from the world to the tip."""

    machine: MachineInfo
    bodies: list[Body]
    joints: list[Joint]
    cylinders: list[Cylinder] = Field(default_factory=list)
    torque_drives: list[TorqueDrive] = Field(default_factory=list)
    channels: list[Channel] = Field(default_factory=list)
    hydraulics: Hydraulics | None = None
    load_point: LoadPoint
    rated_load: RatedLoad | None = Field(
        None, description="rated-load chart; None: unknown (no overload or above-rating "
        "events, load ratios unknown)")
    fatigue: list[FatigueDetail] = Field(default_factory=list)
    classification: Classification | None = None

    @model_validator(mode="after")
    def _references(self) -> Machine:
        problems = reference_problems(self.model_dump())
        if problems:
            raise ValueError("; ".join(problems))
        return self

    # --- lookups -------------------------------------------------------------------------
    @property
    def name(self) -> str:
        return self.machine.name

    @property
    def n_joints(self) -> int:
        return len(self.joints)

    def joint_index(self, name: str) -> int:
        """Index of joint ``name`` in the chain (0 = nearest the world)."""
        for i, j in enumerate(self.joints):
            if j.name == name:
                return i
        raise KeyError(name)

    def body(self, name: str) -> Body:
        for b in self.bodies:
            if b.name == name:
                return b
        raise KeyError(name)

    def cylinder(self, name: str) -> Cylinder:
        for c in self.cylinders:
            if c.name == name:
                return c
        raise KeyError(name)

    def channel(self, name: str) -> Channel:
        for c in self.channels:
            if c.name == name:
                return c
        raise KeyError(name)

    def unknowns(self) -> list[str]:
        """The optional fields this description leaves out, each as ``"path: what is then
        unknown"`` (consumers say "unknown" there rather than invent a value)."""
        out: list[str] = []
        if self.rated_load is None:
            out.append("rated_load: no rated-load chart; load ratios, overload and "
                       "payload-above-rating events and the 3D envelope are unknown")
        for i, j in enumerate(self.joints):
            if j.velocity_limit is None:
                out.append(f"joints.{i}.velocity_limit: unknown for {j.name!r}; no overspeed "
                           "check (the simulator needs it on a joint with a torque drive)")
        for i, c in enumerate(self.channels):
            if c.min is None or c.max is None:
                out.append(f"channels.{i}.min/max: sensor range of {c.name!r} unknown; its "
                           "values are not range-checked (import, ingest)")
        return out

    def chain_bodies(self) -> list[Body]:
        """Bodies in chain order: body i is the child of joint i."""
        return [self.body(j.child) for j in self.joints]
