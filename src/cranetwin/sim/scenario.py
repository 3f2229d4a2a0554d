"""Valve-voltage scenarios: what the operator does with the levers, when loads are taken, and
what the tool touches.

A :class:`Scenario` gives each actuator of the machine, by name (its torque drives and
cylinders, e.g. ``slew, lift, jib, extension`` on the PATU 655 or ``swing, boom, arm, bucket``
on the excavator), a feed-forward voltage U(t) (piecewise linear through ``voltage`` knots; two
knots at the same time make a step) and, optionally, a ``target`` path that a simple operator
tracks: ``U = clip(U_ff + gain·(r − y), ±max_voltage_v)``, where y is the rod position s [m]
of a cylinder or the position of a drive's joint [rad]. Actuators not named keep their lever in
neutral. ``payload`` events set the payload mass [kg] at the load point from their time on
(grab / release / bucket filled). ``contact`` knots give an external force [N] on the tool at
the load point, in the world frame (piecewise linear, 0 before the first knot, held after the
last): the soil's reaction while digging.

Built-ins (:func:`builtin_scenario`, PATU 655): ``fig3`` (steps and ramps of U lift, U jib
and U slewing over 20 s, like Figure 3 of the paper), ``log-loading`` (the timber-loading work
cycle, repeated), ``random`` (a seeded random operator). A machine's own scenarios are files in
``cranetwin/machines/scenarios/<machine>/<name>.toml`` (:func:`machine_scenarios`). User files
are TOML or JSON with the same fields as :class:`Scenario` (:func:`load_scenario`); every
problem is reported with its field path::

    name = "my-run"
    duration_s = 12.0
    [initial]
    q = [0.0, 0.6, -1.6, 0.3]        # one per joint [rad or m]; default: every rod mid-stroke
    payload_kg = 0.0
    [actuators.lift]
    voltage = [[0, 0], [1, 0], [1.5, 6], [4, 6], [4.5, 0]]    # [t_s, U_V] knots
    [[payload]]
    t_s = 6.0
    mass_kg = 250.0
    [[contact]]
    t_s = 7.0
    force_n = [0.0, 0.0, 0.0]        # world frame, at the load point
"""

from __future__ import annotations

import json
import math
import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import numpy.typing as npt
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from cranetwin.errors import ScenarioError
from cranetwin.model import Machine

F64 = npt.NDArray[np.float64]

ACTUATORS = ("slew", "lift", "jib", "extension")   # the PATU 655's, for its built-ins
MACHINE_SCENARIOS = "scenarios"     # folder under cranetwin/machines
Knot = Annotated[tuple[float, float], Field(description="(t_s, value)")]


class ScenarioFileError(ScenarioError):
    """A scenario file failed validation.

    Attributes:
        source: File path or scenario name.
        problems: One ``"field.path: message"`` string per problem.
    """

    def __init__(self, source: str, problems: list[str]) -> None:
        self.source = source
        self.problems = list(problems)
        lines = "\n".join(f"  - {p}" for p in self.problems)
        super().__init__(f"{source}: {len(self.problems)} problem(s)\n{lines}")


class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


def _check_knots(knots: list[tuple[float, float]], what: str) -> None:
    for i in range(1, len(knots)):
        if knots[i][0] < knots[i - 1][0]:
            raise ValueError(f"{what} knot {i}: time {knots[i][0]} s is before the previous "
                             f"knot's {knots[i - 1][0]} s (times must not decrease)")
    for i, (t, v) in enumerate(knots):
        if not (math.isfinite(t) and math.isfinite(v)):
            raise ValueError(f"{what} knot {i}: values must be finite")
        if t < 0:
            raise ValueError(f"{what} knot {i}: time {t} s must be >= 0")


class ActuatorProgram(_Frozen):
    """What the operator does with one lever.

    Attributes:
        voltage: Feed-forward valve voltage knots (t [s], U [V]); linear in between, held after
            the last knot, 0 V before the first knot.
        target: Optional tracked path knots (t [s], rod position [m] or slewing angle [rad]).
        gain: Tracking gain [V per m of rod position, or V per rad of slewing angle].
        max_voltage_v: Clip of the total command [V].
    """

    voltage: list[Knot] = Field(default_factory=list)
    target: list[Knot] = Field(default_factory=list)
    gain: float = Field(60.0, ge=0)
    max_voltage_v: float = Field(10.0, gt=0, le=10.0)

    @model_validator(mode="after")
    def _knots(self) -> ActuatorProgram:
        _check_knots(self.voltage, "voltage")
        _check_knots(self.target, "target")
        for i, (_, u) in enumerate(self.voltage):
            if abs(u) > 10.0:
                raise ValueError(f"voltage knot {i}: |U| = {abs(u)} V exceeds the 10 V valve range")
        return self


class PayloadEvent(_Frozen):
    """From ``t_s`` on, the payload at the tip weighs ``mass_kg`` (0 = released)."""

    t_s: float = Field(ge=0)
    mass_kg: float = Field(ge=0, le=5000.0)


class InitialState(_Frozen):
    """Initial pose, velocities and payload.

    Attributes:
        q: Joint positions, one per joint in chain order [rad or m]; None = every cylinder's rod
            at mid-stroke and the other joints at 0 (clipped into their limits).
        qd: Joint velocities [rad/s or m/s]; None = at rest.
        payload_kg: Payload at the load point at t = 0 [kg].
    """

    q: tuple[float, ...] | None = None
    qd: tuple[float, ...] | None = None
    payload_kg: float = Field(0.0, ge=0, le=5000.0)


class ContactKnot(_Frozen):
    """From ``t_s`` on (linearly towards the next knot), the tool feels ``force_n`` [N], world
    frame, at the load point."""

    t_s: float = Field(ge=0)
    force_n: tuple[float, float, float]


class Scenario(_Frozen):
    """A complete scenario (see the module docstring for the file format)."""

    name: str = Field(min_length=1)
    description: str = ""
    duration_s: float = Field(20.0, gt=0, le=86400.0)
    initial: InitialState = Field(default_factory=InitialState)
    actuators: dict[str, ActuatorProgram] = Field(default_factory=dict)
    payload: list[PayloadEvent] = Field(default_factory=list)
    contact: list[ContactKnot] = Field(default_factory=list)

    @model_validator(mode="after")
    def _events(self) -> Scenario:
        for i in range(1, len(self.payload)):
            if self.payload[i].t_s < self.payload[i - 1].t_s:
                raise ValueError(f"payload.{i}.t_s: events must be in time order")
        for i in range(1, len(self.contact)):
            if self.contact[i].t_s < self.contact[i - 1].t_s:
                raise ValueError(f"contact.{i}.t_s: knots must be in time order")
        return self

    def program(self, actuator: str) -> ActuatorProgram:
        """The program of ``actuator`` (lever in neutral if the scenario does not name it)."""
        return self.actuators.get(actuator, _NEUTRAL)

    def tables(self, actuators: tuple[str, ...] = ACTUATORS) -> ScenarioTables:
        """Pack the scenario into fixed arrays for the compiled integration loop.

        Args:
            actuators: Actuator names in the loop's order (the machine's torque drives, then
                its cylinders; :func:`actuator_names`).
        """
        progs = [self.program(a) for a in actuators]
        na = len(progs)
        kv = max(1, max((len(p.voltage) for p in progs), default=0))
        kt = max(1, max((len(p.target) for p in progs), default=0))
        u_t = np.zeros((na, kv))
        u_v = np.zeros((na, kv))
        u_n = np.zeros(na, dtype=np.int64)
        r_t = np.zeros((na, kt))
        r_v = np.zeros((na, kt))
        r_n = np.zeros(na, dtype=np.int64)
        gain = np.zeros(na)
        umax = np.zeros(na)
        for a, p in enumerate(progs):
            u_n[a] = len(p.voltage)
            for k, (t, v) in enumerate(p.voltage):
                u_t[a, k], u_v[a, k] = t, v
            r_n[a] = len(p.target)
            for k, (t, v) in enumerate(p.target):
                r_t[a, k], r_v[a, k] = t, v
            gain[a] = p.gain if p.target else 0.0
            umax[a] = p.max_voltage_v
        pay_t = np.array([0.0] + [e.t_s for e in self.payload])
        pay_m = np.array([self.initial.payload_kg] + [e.mass_kg for e in self.payload])
        f_t = np.array([c.t_s for c in self.contact] or [0.0])
        f_v = np.ascontiguousarray(np.array([c.force_n for c in self.contact] or [(0.0,) * 3]).T)
        return ScenarioTables(u_t, u_v, u_n, r_t, r_v, r_n, gain, umax, pay_t, pay_m, f_t, f_v,
                              len(self.contact))


_NEUTRAL = ActuatorProgram()


def actuator_names(machine: Machine) -> tuple[str, ...]:
    """The machine's actuators in the simulator's order: torque drives, then cylinders."""
    return (*(d.name for d in machine.torque_drives), *(c.name for c in machine.cylinders))


@dataclass(frozen=True)
class ScenarioTables:
    """A scenario as arrays (na actuators in the order given to :meth:`Scenario.tables`).

    Attributes:
        u_t, u_v: Voltage knots (times [s], values [V]), shape (na, K); ``u_n`` (na,) counts.
        r_t, r_v: Target knots (times [s], values [m or rad]), shape (na, K'); ``r_n`` counts.
        gain: Tracking gains, shape (na,) [V/m or V/rad]; 0 = no tracking.
        umax: Command clip, shape (na,) [V].
        pay_t, pay_m: Payload events (times [s] ascending, masses [kg]), shape (P,).
        f_t, f_v, f_n: Contact-force knots: times (F,) [s], forces (3, F) [N, world frame],
            count (0 = no contact).
    """

    u_t: F64
    u_v: F64
    u_n: npt.NDArray[np.int64]
    r_t: F64
    r_v: F64
    r_n: npt.NDArray[np.int64]
    gain: F64
    umax: F64
    pay_t: F64
    pay_m: F64
    f_t: F64
    f_v: F64
    f_n: int

    def as_tuple(self) -> tuple[object, ...]:
        """The fields in order, as the compiled loop takes them (``sched``)."""
        return (self.u_t, self.u_v, self.u_n, self.r_t, self.r_v, self.r_n, self.gain,
                self.umax, self.pay_t, self.pay_m, self.f_t, self.f_v, self.f_n)


# --- loading ---------------------------------------------------------------------------------

def _problems(exc: ValidationError) -> list[str]:
    out = []
    for err in exc.errors():
        loc = ".".join(str(x) for x in err["loc"]) or "(file)"
        out.append(f"{loc}: {str(err['msg']).removeprefix('Value error, ')}")
    return out


def scenario_from_dict(data: dict[str, Any], source: str = "<dict>") -> Scenario:
    """Validate a parsed scenario.

    Raises:
        ScenarioFileError: one ``field.path: message`` line per problem.
    """
    try:
        return Scenario.model_validate(data)
    except ValidationError as exc:
        raise ScenarioFileError(source, _problems(exc)) from exc


def machine_scenarios(machine: str) -> list[str]:
    """Names of the scenario files shipped for built-in machine ``machine`` (may be empty)."""
    folder = resources.files("cranetwin") / "machines" / MACHINE_SCENARIOS / machine
    if not folder.is_dir():
        return []
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def load_scenario(source: str | Path, *, seed: int = 0, machine: str | None = None,
                  **params: float) -> Scenario:
    """A built-in scenario by name, a machine's shipped scenario, or a TOML/JSON file.

    Args:
        source: ``fig3``, ``log-loading``, ``random`` (PATU 655 built-ins), the name of a
            scenario of ``machine`` (:func:`machine_scenarios`), or a ``.toml``/``.json`` path.
        seed: Seed of the random parts of built-in scenarios.
        machine: Built-in machine name whose shipped scenarios ``source`` may name.
        **params: Built-in parameters (``duration_s``, ``payload_kg``); for a file,
            ``duration_s`` overrides the file's.

    Raises:
        ScenarioError: unknown name, unreadable file, syntax error or invalid fields.
    """
    name = str(source)
    if name in BUILTIN:
        return builtin_scenario(name, seed=seed, **params)
    if machine is not None and name in machine_scenarios(machine):
        ref = resources.files("cranetwin") / "machines" / MACHINE_SCENARIOS / machine
        with resources.as_file(ref / f"{name}.toml") as shipped:
            sc = load_scenario(shipped)
        if "duration_s" in params:
            sc = sc.model_copy(update={"duration_s": float(params["duration_s"])})
        return sc
    path = Path(source)
    if path.suffix not in (".toml", ".json"):
        known = [*BUILTIN, *(machine_scenarios(machine) if machine else [])]
        raise ScenarioError(f"{name}: not a built-in scenario ({', '.join(known)}) "
                            "and not a .toml/.json file")
    try:
        text = path.read_text("utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ScenarioFileError(name, [f"(file): cannot read: {exc}"]) from exc
    try:
        data = tomllib.loads(text) if path.suffix == ".toml" else json.loads(text)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as exc:
        raise ScenarioFileError(name, [f"(file): syntax error: {exc}"]) from exc
    if not isinstance(data, dict):
        raise ScenarioFileError(name, ["(file): top level must be a table/object"])
    data.setdefault("name", path.stem)
    return scenario_from_dict(data, name)


# --- built-ins -------------------------------------------------------------------------------

def _steps(*segments: tuple[float, float, float, float, float]) -> list[tuple[float, float]]:
    """Trapezoid pulses (t_start, t_ramp, t_hold, t_ramp_down, U) as voltage knots."""
    knots: list[tuple[float, float]] = [(0.0, 0.0)]
    for t0, up, hold, down, u in segments:
        knots += [(t0, 0.0), (t0 + up, u), (t0 + up + hold, u), (t0 + up + hold + down, 0.0)]
    return knots


def fig3(duration_s: float = 20.0, payload_kg: float = 0.0) -> Scenario:
    """Steps and ramps of U lift, U jib and U slewing over ~20 s (cf. Figure 3 of the paper)."""
    return Scenario(
        name="fig3",
        description="Valve-voltage steps and ramps of lift, jib and slewing (paper, Figure 3)",
        duration_s=duration_s,
        initial=InitialState(q=(0.0, 0.45, -1.5, 0.3), payload_kg=payload_kg),
        actuators={
            "lift": ActuatorProgram(voltage=_steps((1.0, 0.0, 3.0, 0.0, 6.0),
                                                (8.0, 1.0, 2.0, 1.0, -5.0),
                                                (15.0, 0.0, 2.0, 0.0, 4.0))),
            "jib": ActuatorProgram(voltage=_steps((3.0, 0.5, 2.5, 0.5, -5.0),
                                               (11.0, 0.0, 2.5, 0.0, 6.0),
                                               (16.5, 1.0, 1.0, 1.0, -4.0))),
            "slew": ActuatorProgram(voltage=_steps((5.0, 1.0, 2.0, 1.0, 7.0),
                                                (12.0, 1.0, 2.0, 1.0, -7.0))),
        },
    )


def log_loading(duration_s: float = 60.0, payload_kg: float = 300.0, seed: int = 0) -> Scenario:
    """Timber loading, repeated until ``duration_s``: swing to the pile, lower, grab a log of
    ``payload_kg`` (± 15 % per log, seeded), lift, swing to the load space, lower, release.

    The operator tracks rod-position and slewing-angle waypoints (``target`` knots).
    """
    from cranetwin.model import load_machine
    from cranetwin.physics import joints_from_cylinders

    rng = np.random.default_rng(seed)
    pile, bunk = -1.3, 1.1           # slewing angles of the pile and the load space [rad]
    up = (0.40, 0.30, 0.35)          # lift, jib, extension rod positions high [m]
    down = (0.22, 0.48, 0.75)        # ... and lowered to the pile / bunk [m]
    knots: dict[str, list[tuple[float, float]]] = {a: [] for a in ACTUATORS}
    events: list[PayloadEvent] = []

    def at(t: float, slew: float, rods: tuple[float, float, float]) -> None:
        knots["slew"].append((t, slew))
        for name, s in zip(ACTUATORS[1:], rods, strict=True):
            knots[name].append((t, s))

    t = 0.0
    at(t, 0.0, up)
    while t < duration_s:
        at(t + 5.0, pile, up)            # swing to the pile
        at(t + 8.0, pile, down)          # lower the grapple
        mass = float(payload_kg * rng.uniform(0.85, 1.15))
        events.append(PayloadEvent(t_s=t + 9.0, mass_kg=mass))          # grab
        at(t + 10.0, pile, down)
        at(t + 13.0, pile, up)           # lift
        at(t + 19.0, bunk, up)           # swing to the load space
        at(t + 22.0, bunk, down)         # lower
        events.append(PayloadEvent(t_s=t + 23.0, mass_kg=0.0))          # release
        at(t + 24.0, bunk, down)
        at(t + 27.0, bunk, up)
        t += 27.0
    # start at rest in the "up" pose the operator's first waypoint asks for
    q_up = joints_from_cylinders(load_machine("patu655"), np.array([up]))[0]
    q0 = (0.0, float(q_up[1]), float(q_up[2]), float(q_up[3]))
    progs = {a: ActuatorProgram(target=knots[a], gain=(40.0 if a == "slew" else 80.0))
             for a in ACTUATORS}
    return Scenario(name="log-loading", duration_s=duration_s,
                    description=f"timber loading cycle, logs of ~{payload_kg:g} kg",
                    initial=InitialState(q=q0, payload_kg=0.0),
                    actuators=progs, payload=events)


def random_operator(duration_s: float = 30.0, payload_kg: float = 0.0, seed: int = 0) -> Scenario:
    """A seeded random operator: random waypoints every 1.5–5 s (within 10–90 % of each stroke
    and ±1.5 rad of slewing), random feed-forward bursts, random grabs and releases up to
    ``payload_kg`` (no payload changes when 0). The first waypoint is the initial pose."""
    from cranetwin.model import load_machine
    from cranetwin.physics import cylinder_kinematics

    rng = np.random.default_rng(seed)
    machine = load_machine("patu655")
    strokes = tuple(c.stroke_m for c in machine.cylinders)
    q0 = (0.0, 0.5, -1.4, 0.6)
    s0 = [float(v) for v in cylinder_kinematics(machine, np.array([q0]))[0][0]]
    knots: dict[str, list[tuple[float, float]]] = {a: [] for a in ACTUATORS}
    ff: dict[str, list[tuple[float, float]]] = {a: [(0.0, 0.0)] for a in ACTUATORS}
    for a in ACTUATORS:
        t = 0.0
        knots[a].append((0.0, q0[0] if a == "slew" else s0[ACTUATORS.index(a) - 1]))
        while t < duration_s:
            t += float(rng.uniform(1.5, 5.0))
            lo, hi = ((-1.5, 1.5) if a == "slew"
                      else (0.1 * strokes[ACTUATORS.index(a) - 1],
                            0.9 * strokes[ACTUATORS.index(a) - 1]))
            knots[a].append((t, float(rng.uniform(lo, hi))))
            if rng.uniform() < 0.3:
                u = float(rng.uniform(-3.0, 3.0))
                ff[a] += [(t, 0.0), (t + 0.3, u), (t + 0.8, u), (t + 1.1, 0.0)]
    events: list[PayloadEvent] = []
    if payload_kg > 0:
        t = 0.0
        while t < duration_s:
            t += float(rng.uniform(3.0, 8.0))
            events.append(PayloadEvent(t_s=t, mass_kg=float(rng.uniform(0.0, payload_kg))))
    progs = {a: ActuatorProgram(target=knots[a], voltage=ff[a],
                                gain=(30.0 if a == "slew" else 60.0)) for a in ACTUATORS}
    return Scenario(name="random", duration_s=duration_s,
                    description=f"random operator, seed {seed}",
                    initial=InitialState(q=q0, payload_kg=0.0),
                    actuators=progs, payload=events)


BUILTIN = ("fig3", "log-loading", "random")


def builtin_scenario(name: str, *, seed: int = 0, duration_s: float | None = None,
                     payload_kg: float | None = None) -> Scenario:
    """A built-in scenario by name (``fig3``, ``log-loading``, ``random``).

    Raises:
        ScenarioError: unknown name.
    """
    kw: dict[str, float] = {}
    if duration_s is not None:
        kw["duration_s"] = duration_s
    if payload_kg is not None:
        kw["payload_kg"] = payload_kg
    if name == "fig3":
        return fig3(**kw)
    if name == "log-loading":
        return log_loading(seed=seed, **kw)
    if name == "random":
        return random_operator(seed=seed, **kw)
    raise ScenarioError(f"unknown built-in scenario {name!r} (expected one of {BUILTIN})")
