"""Run a scenario on a machine: set up the state, drive the compiled loop, build a Recording."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt

from cranetwin.errors import ScenarioError, SimulationError
from cranetwin.model import Machine
from cranetwin.physics import inverse_dynamics
from cranetwin.physics.chain import ChainParams, compile_chain
from cranetwin.physics.kernels import bias, cylinder_joint, cylinder_kinematics
from cranetwin.samples import SampleArrays
from cranetwin.sim import engine as E
from cranetwin.sim.hydraulics import HydraulicParams, HydraulicSettings, pack
from cranetwin.sim.layout import Layout, layout_of
from cranetwin.sim.recording import Recording, Topology, Truth
from cranetwin.sim.scenario import Scenario, actuator_names
from cranetwin.sim.sensors import SampleClock, SensorModel, SensorReader

log = logging.getLogger(__name__)
F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class SimOptions:
    """Integration and model switches.

    Attributes:
        step_s: Integration step [s] (1e-4 as in the paper).
        truth_rate_hz: Rate at which the ground truth is stored [Hz]; must divide 1/step_s.
        scheme: ``semi-implicit`` (fast, default) or ``rk4`` (energy-accurate).
        friction: Cylinder and slewing friction (Eq. 2) on.
        valves: Valve flows on (off = all valves closed, slewing motor locked hydraulically).
        hydraulic_losses: Relief valves (cylinders and the slewing torque cap) and slewing-motor
            leakage on.
        holding_pressure_pa: Low-side chamber pressure of the initial static equilibrium [Pa].
        initial_pressures_pa: Override of the initial (pA, pB) per cylinder, shape (2, nc) [Pa].
        hydraulics: Simulator-side hydraulic constants.
    """

    step_s: float = 1.0e-4
    truth_rate_hz: float = 1000.0
    scheme: Literal["semi-implicit", "rk4"] = "semi-implicit"
    friction: bool = True
    valves: bool = True
    hydraulic_losses: bool = True
    holding_pressure_pa: float = 2.0e6
    initial_pressures_pa: tuple[tuple[float, ...], tuple[float, ...]] | None = None
    hydraulics: HydraulicSettings = field(default_factory=HydraulicSettings)


@dataclass(frozen=True)
class Prepared:
    """A machine compiled for the loop (reusable for several runs).

    Attributes:
        machine: The description.
        chain: Its chain and cylinder arrays (``physics.chain``).
        hyd: Cylinder, circuit, drive and free-joint tables.
        layout: Array layout (:mod:`cranetwin.sim.layout`).
        actuators: Actuator names in the loop's order (drives, then cylinders).
    """

    machine: Machine
    chain: ChainParams
    hyd: HydraulicParams
    layout: Layout
    actuators: tuple[str, ...]

    @property
    def model(self) -> E.SimModel:
        """The loop's ``model`` record (:class:`cranetwin.sim.engine.SimModel`)."""
        h = self.hyd
        return E.SimModel(self.chain.chain, self.chain.cyl, h.cyl, h.glob, h.drives, h.free,
                          h.drive_joint, h.free_joint, self.layout.array(),
                          passive_joints(self.machine))


def prepare(machine: Machine, options: SimOptions | None = None) -> Prepared:
    """Compile ``machine`` for the loop: any serial chain, each joint driven by one cylinder
    (with a valve), by one torque drive, or by nothing (a free joint).

    Raises:
        SimulationError: a cylinder has no valve, or cylinders but no hydraulics section.
    """
    opts = options or SimOptions()
    try:
        hyd = pack(machine, opts.hydraulics)
    except ValueError as exc:
        raise SimulationError(f"machine {machine.name!r}: {exc}") from exc
    chain = compile_chain(machine)
    return Prepared(machine, chain, hyd, layout_of(machine), actuator_names(machine))


def check_scenario(machine: Machine, scenario: Scenario) -> None:
    """Check a scenario against a machine: actuators it names exist, targets lie inside the
    strokes and joint limits, the initial pose has one value per joint.

    Raises:
        ScenarioFileError: one ``field.path: message`` line per problem.
    """
    from cranetwin.sim.scenario import ScenarioFileError

    problems: list[str] = []
    ranges: dict[str, tuple[float, float, str, str]] = {}
    for d in machine.torque_drives:
        j = machine.joints[machine.joint_index(d.joint)]
        ranges[d.name] = (j.lower, j.upper, j.unit or "rad", "joint limits")
    for c in machine.cylinders:
        ranges[c.name] = (0.0, c.stroke_m, "m", "stroke")
    for name, prog in scenario.actuators.items():
        if name not in ranges:
            problems.append(f"actuators.{name}: {machine.name} has no actuator {name!r} "
                            f"(expected one of {', '.join(ranges) or 'none'})")
            continue
        lo, hi, unit, what = ranges[name]
        for i, (_, r) in enumerate(prog.target):
            if not lo <= r <= hi:
                problems.append(f"actuators.{name}.target.{i}: {r:g} {unit} is outside the "
                                f"{what} [{lo:g}, {hi:g}] {unit} of {machine.name}")
    for what in ("q", "qd"):
        value = getattr(scenario.initial, what)
        if value is not None and len(value) != machine.n_joints:
            problems.append(f"initial.{what}: {len(value)} values, expected one per joint "
                            f"({machine.n_joints}: {', '.join(j.name for j in machine.joints)})")
    if problems:
        raise ScenarioFileError(scenario.name, problems)


def passive_joints(machine: Machine) -> npt.NDArray[np.int64]:
    """Indices of the passive joints (no actuator, held at ``fixed_value``)."""
    return np.array([i for i, j in enumerate(machine.joints) if j.fixed_value is not None],
                    dtype=np.int64)


def default_pose(machine: Machine) -> F64:
    """Every cylinder's rod at mid-stroke, a passive joint at its fixed value, every other
    joint at 0 clipped into its limits."""
    q = np.array([j.fixed_value if j.fixed_value is not None else min(max(0.0, j.lower), j.upper)
                  for j in machine.joints])
    chain = compile_chain(machine)
    for k, c in enumerate(machine.cylinders):
        ji = int(chain.cylinder_joint[k])
        q[ji] = float(cylinder_joint(chain.cyl, k, 0.5 * c.stroke_m))
    return q


def initial_state(prep: Prepared, scenario: Scenario, options: SimOptions) -> F64:
    """State in the scenario's initial pose and velocities, with the chamber pressures (and
    drive torques) that balance the bias forces h(q, qd), so the machine starts unaccelerated
    (free joints are not held: they start as the dynamics take them; passive joints are at
    their fixed value, at rest).

    Raises:
        ScenarioError: a rod of the initial pose is outside its stroke.
    """
    lay = prep.layout
    nj, nc = lay.nj, lay.nc
    q0 = (np.asarray(scenario.initial.q, dtype=np.float64) if scenario.initial.q is not None
          else default_pose(prep.machine))
    s = np.empty(nc)
    dsdq = np.empty(nc)
    cylinder_kinematics(prep.chain.cyl, q0, s, dsdq)
    for k, c in enumerate(prep.machine.cylinders):
        if not (np.isfinite(s[k]) and -1e-9 <= s[k] <= c.stroke_m + 1e-9):
            raise ScenarioError(f"initial.q: the {c.name} rod position would be {s[k]:.4f} m, "
                                f"outside its stroke [0, {c.stroke_m}] m")
    qd0 = (np.asarray(scenario.initial.qd, dtype=np.float64) if scenario.initial.qd is not None
           else np.zeros(nj))
    q0 = np.array(q0, dtype=np.float64)
    qd0 = np.array(qd0, dtype=np.float64)
    for j in passive_joints(prep.machine):  # held at its fixed value, whatever the scenario
        q0[j] = prep.machine.joints[j].fixed_value
        qd0[j] = 0.0
    h = np.empty(nj)
    bias(prep.chain.chain, q0, qd0, scenario.initial.payload_kg, h)
    x = np.zeros(lay.n_x)
    x[lay.x_q:lay.x_q + nj] = q0
    x[lay.x_qd:lay.x_qd + nj] = qd0
    p_low = options.holding_pressure_pa
    cj = prep.chain.cylinder_joint
    for k, c in enumerate(prep.machine.cylinders):
        f = h[cj[k]] / dsdq[k]            # static rod force that holds gravity
        a1, a2 = c.area_a_m2, c.area_b_m2
        if f >= 0:
            x[lay.x_pa + k], x[lay.x_pb + k] = (f + p_low * a2) / a1, p_low
        else:
            x[lay.x_pa + k], x[lay.x_pb + k] = p_low, (p_low * a1 - f) / a2
    if options.initial_pressures_pa is not None:
        p = np.asarray(options.initial_pressures_pa, dtype=np.float64)
        x[lay.x_pa:lay.x_pa + nc] = p[0]
        x[lay.x_pb:lay.x_pb + nc] = p[1]
    for d, jd in enumerate(prep.hyd.drive_joint):
        x[lay.x_ts + d] = h[jd]
    return x


def _flags(o: SimOptions) -> F64:
    f = np.zeros(4)
    f[E.F_FRICTION] = float(o.friction)
    f[E.F_VALVES] = float(o.valves)
    f[E.F_LOSSES] = float(o.hydraulic_losses)
    f[E.F_SCHEME] = E.SCHEME_RK4 if o.scheme == "rk4" else E.SCHEME_SEMI_IMPLICIT
    return f


class Session:
    """A simulation that advances chunk by chunk: the core of :func:`simulate`, and a live
    source of samples (e.g. a simulated fleet streaming to the ingest daemon).

    Example::

        live = Session(prepare(machine), load_scenario("log-loading", duration_s=86400.0),
                       keep_truth=False, start_epoch_s=time.time())
        while True:
            block = live.advance(0.1)     # SampleArrays of the samples taken in the last 0.1 s
            ...

    Args:
        prep: Compiled machine (:func:`prepare`).
        scenario: Operator program (commands hold their last value after its knots end).
        options: Integration settings.
        sensors: Sensor model.
        seed: Seed of the sensor model's randomness.
        start_epoch_s: Epoch time of t = 0 [s].
        keep_truth: Accumulate the ground truth (≈ 0.3 MB per simulated second at 1 kHz).
        machine_id: Identifier stamped on the samples (default: the machine's name); give each
            crane of a simulated fleet its own.

    Raises:
        ScenarioError: initial pose outside the machine's range.
        SimulationError: bad options.
    """

    def __init__(self, prep: Prepared, scenario: Scenario, *, options: SimOptions | None = None,
                 sensors: SensorModel | None = None, seed: int = 0, start_epoch_s: float = 0.0,
                 keep_truth: bool = True, machine_id: str | None = None) -> None:
        self.prep = prep
        self.machine_id = machine_id or prep.machine.name
        self.scenario = scenario
        self.options = opts = options or SimOptions()
        self.sensors = sensors or SensorModel()
        self.seed = seed
        self.start_epoch_s = start_epoch_s
        self.keep_truth = keep_truth
        dt = opts.step_s
        if not 0 < dt <= 1e-2:
            raise SimulationError(f"step {dt} s must be in (0, 0.01]")
        every = int(round(1.0 / (opts.truth_rate_hz * dt)))
        if every < 1 or abs(every * opts.truth_rate_hz * dt - 1.0) > 1e-6:
            raise SimulationError(f"truth rate {opts.truth_rate_hz} Hz must divide the step rate "
                                  f"{1 / dt:g} Hz")
        self.every = every
        check_scenario(prep.machine, scenario)
        # separate streams: the sampling schedule does not depend on how the run is chunked
        self._clock = SampleClock(self.sensors, dt, np.random.default_rng([seed, 1]))
        self._reader = SensorReader(prep.machine, self.sensors, np.random.default_rng([seed, 2]))
        self.x = initial_state(prep, scenario, opts)
        self._sched = scenario.tables(prep.actuators).as_tuple()
        self._cur = np.zeros(2 * prep.layout.na + 2, dtype=np.int64)
        self._flags = _flags(opts)
        self._model = prep.model
        self.step_index = 0
        self._truth_chunks: list[F64] = []
        self._finished = False

    @property
    def channels(self) -> tuple[str, ...]:
        """Channel names of the samples, in column order."""
        return self._reader.names

    @property
    def t_s(self) -> float:
        """Current simulation time [s]."""
        return self.step_index * self.options.step_s

    def _run(self, i1: int, final: bool) -> tuple[F64, F64]:
        """Integrate to step i1 (and record step i1 itself when ``final``)."""
        i0 = self.step_index
        t_nom, steps = self._clock.take(i1, inclusive=final)
        hi = i1 if final else i1 - 1
        n_truth = 0
        if self.keep_truth and hi >= i0:
            n_truth = hi // self.every - (i0 - 1) // self.every if i0 > 0 else hi // self.every + 1
        lay = self.prep.layout
        truth = np.full((n_truth, lay.n_t), np.nan)
        snaps = np.full((steps.shape[0], lay.n_snap), np.nan)
        idx = np.zeros(3, dtype=np.int64)
        E.run_steps(self._model, self._sched, self._flags, self.options.step_s, self.x,
                    (i0, i1, i1 if final else -1),
                    E.Records(self.every, truth, steps, snaps, idx), self._cur)
        if idx[2]:
            raise SimulationError(
                f"integration unstable before t = {i1 * self.options.step_s:.4f} s (non-finite "
                f"accelerations); try a smaller step than {self.options.step_s} s")
        self.step_index = i1
        if self.keep_truth:
            self._truth_chunks.append(truth[:idx[0]])
        return t_nom[:idx[1]], snaps[:idx[1]]

    def advance(self, seconds: float, *, final: bool = False) -> SampleArrays:
        """Simulate ``seconds`` more and return the samples taken meanwhile.

        Args:
            seconds: Simulated time to add [s] (rounded to whole steps).
            final: Also record the state at the new end time (truth row and a sample due
                then); the session cannot advance afterwards.

        Raises:
            SimulationError: the session is finished, or the integration went unstable.
        """
        if self._finished:
            raise SimulationError("session already finished")
        i1 = self.step_index + int(round(seconds / self.options.step_s))
        t_nom, snaps = self._run(i1, final)
        self._finished = final
        return SampleArrays(machine_id=self.machine_id, t_s=self.start_epoch_s + t_nom,
                            channels=self.channels, values=self._reader.read(snaps))

    def truth(self, wrenches: bool = True) -> Truth:
        """Ground truth accumulated so far (empty when ``keep_truth`` is off)."""
        rows = (np.concatenate(self._truth_chunks) if self._truth_chunks
                else np.zeros((0, self.prep.layout.n_t)))
        return _truth(self.prep, rows, self.start_epoch_s, wrenches)


def simulate(machine: Machine | Prepared, scenario: Scenario, *, duration_s: float | None = None,
             options: SimOptions | None = None, sensors: SensorModel | None = None,
             seed: int = 0, start_epoch_s: float = 0.0, wrenches: bool = True,
             progress: Callable[[float, float], None] | None = None,
             machine_id: str | None = None) -> Recording:
    """Simulate ``scenario`` on ``machine`` and sample its sensors.

    Args:
        machine: Machine description (or a :func:`prepare` result to skip compiling).
        scenario: What the operator does.
        duration_s: Simulated time [s] (default: the scenario's).
        options: Integration settings.
        sensors: Sensor model (default :class:`SensorModel`, 100 Hz).
        seed: Seed of the sensor model's randomness.
        start_epoch_s: Epoch time of t = 0 [s].
        wrenches: Compute joint reaction wrenches for the truth (else NaN).
        progress: Called as ``progress(simulated_s, total_s)`` between chunks.
        machine_id: Identifier stamped on the samples (default: the machine's name).

    Returns:
        The :class:`~cranetwin.sim.recording.Recording`: samples from t = 0 to ``duration_s``
        inclusive, truth at ``truth_rate_hz`` over the same span.

    Raises:
        ScenarioError: initial pose outside the machine's range.
        SimulationError: bad options, or the integration went unstable (non-finite state).
    """
    opts = options or SimOptions()
    prep = machine if isinstance(machine, Prepared) else prepare(machine, opts)
    duration = float(duration_s if duration_s is not None else scenario.duration_s)
    if duration <= 0:
        raise SimulationError(f"duration {duration} s must be > 0")
    session = Session(prep, scenario, options=opts, sensors=sensors, seed=seed,
                      start_epoch_s=start_epoch_s, machine_id=machine_id)
    n_steps = int(round(duration / opts.step_s))
    chunk = max(1, int(round(0.5 / opts.step_s)))
    parts: list[SampleArrays] = []
    wall = time.perf_counter()
    while True:
        n = min(chunk, n_steps - session.step_index)
        final = session.step_index + n == n_steps
        parts.append(session.advance(n * opts.step_s, final=final))
        if progress is not None:
            progress(session.t_s, duration)
        if final:
            break
    log.debug("simulated %.3f s in %.3f s", duration, time.perf_counter() - wall)
    samples = SampleArrays(machine_id=session.machine_id,
                           t_s=np.concatenate([p.t_s for p in parts]),
                           channels=session.channels,
                           values=np.concatenate([p.values for p in parts]))
    sensor_model = session.sensors
    meta = {"duration_s": duration, "truth_rate_hz": opts.truth_rate_hz, "scheme": opts.scheme,
            "friction": opts.friction, "valves": opts.valves,
            "hydraulic_losses": opts.hydraulic_losses,
            "sensors": sensor_model.model_dump(), "scenario_description": scenario.description,
            "channel_resolution": [prep.machine.channel(c).resolution for c in session.channels],
            "topology": Topology.of(prep.machine).to_json()}
    return Recording(machine=prep.machine.name, scenario=scenario.name, seed=seed,
                     step_s=opts.step_s, start_epoch_s=start_epoch_s, samples=samples,
                     truth=session.truth(wrenches), meta=meta)


def _truth(prep: Prepared, m: F64, t0: float, wrenches: bool) -> Truth:
    lay = prep.layout
    n = m.shape[0]
    block = {name: (lay.truth_offset(name), w) for name, w in lay.truth_blocks()}

    def cols(name: str) -> F64:
        c, w = block[name]
        return np.ascontiguousarray(m[:, c:c + w])

    q, qd, qdd = cols("q"), cols("qd"), cols("qdd")
    pay = cols("payload_kg")[:, 0].copy()
    wrench = np.full((n, lay.nj, 6), np.nan)
    if wrenches and n:
        _, wrench = inverse_dynamics(prep.machine, q, qd, qdd, pay)
    return Truth(t_s=t0 + cols("t_s")[:, 0], q=q, qd=qd, qdd=qdd, rod_s=cols("rod_s"),
                 rod_v=cols("rod_v"), p_a=cols("p_a"), p_b=cols("p_b"),
                 cyl_force=cols("cyl_force"), drive_torque=cols("drive_torque"),
                 joint_torque=cols("joint_torque"), joint_wrench=wrench, payload_kg=pay,
                 u=cols("u"), contact_force=cols("contact_force"))
