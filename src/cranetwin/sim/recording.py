"""The output of a simulation run: sampled sensor channels plus fine-step ground truth.

A :class:`Recording` is what the simulator hands to everyone else: the twin replays
``recording.samples`` and checks itself against ``recording.truth``; the ingest sender streams
``recording.samples`` as datagrams. Both live in one timebase: seconds since the Unix epoch,
``start_epoch_s`` + simulation time (``start_epoch_s`` defaults to 0, so times are simulation
seconds).

Files:
    ``.npz``: lossless, every array plus the metadata as JSON (:meth:`Recording.save`).
    ``.csv``: the sampled channels, one row per sample (``t_s`` then the channel columns, NaN =
    dropout, ``# key: value`` metadata lines on top); the truth goes to ``<stem>.truth.csv``
    next to it with the columns listed by :func:`truth_columns` (named after the machine's
    joints, cylinders and drives, kept in the header's ``topology``). Floats are written with 17
    significant digits, so a CSV round trip is lossless too.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from cranetwin.errors import SimulationError
from cranetwin.model import Machine
from cranetwin.samples import SampleArrays, SampleBlock
from cranetwin.sim.layout import Layout

F64 = npt.NDArray[np.float64]

WRENCH = ("fx", "fy", "fz", "mx", "my", "mz")
FORCE = ("fx", "fy", "fz")


@dataclass(frozen=True)
class Topology:
    """Names of a machine's joints, cylinders and torque drives (the truth's column names).

    The default is the PATU 655's (recordings written before the topology was stored).
    """

    joints: tuple[str, ...] = ("theta0", "theta1", "theta2", "L")
    cylinders: tuple[str, ...] = ("lift", "jib", "extension")
    drives: tuple[str, ...] = ("slew",)

    @classmethod
    def of(cls, machine: Machine) -> Topology:
        return cls(joints=tuple(j.name for j in machine.joints),
                   cylinders=tuple(c.name for c in machine.cylinders),
                   drives=tuple(d.name for d in machine.torque_drives))

    @classmethod
    def from_json(cls, data: dict[str, Any] | None) -> Topology:
        if not data:
            return cls()
        return cls(joints=tuple(data["joints"]), cylinders=tuple(data["cylinders"]),
                   drives=tuple(data["drives"]))

    def to_json(self) -> dict[str, list[str]]:
        return {"joints": list(self.joints), "cylinders": list(self.cylinders),
                "drives": list(self.drives)}

    @property
    def layout(self) -> Layout:
        return Layout(nj=len(self.joints), nc=len(self.cylinders), nd=len(self.drives))


@dataclass(frozen=True)
class Truth:
    """Ground truth on the fine (decimated) grid, exactly as the integrator computed it.

    Shapes for a machine of nj joints, nc cylinders and nd torque drives (machine order;
    actuators = drives then cylinders):

    Attributes:
        t_s: Times, shape (n,) [s, same timebase as the samples].
        q: Joint positions, shape (n, nj) [rad or m].
        qd: Joint velocities, shape (n, nj) [rad/s or m/s].
        qdd: Joint accelerations the integrator used at that instant, shape (n, nj)
            [rad/s² or m/s²]: M(q)·qdd + h(q, qd) = joint_torque + J_p(q)ᵀ·contact_force holds
            to round-off.
        rod_s: Cylinder rod positions, shape (n, nc) [m].
        rod_v: Cylinder rod velocities, shape (n, nc) [m/s].
        p_a: Piston-side chamber pressures, shape (n, nc) [Pa].
        p_b: Rod-side chamber pressures, shape (n, nc) [Pa].
        cyl_force: Cylinder forces on the mechanism, Eq. 1–2 incl. friction (and end-stop
            force if the rod is in its end stop), shape (n, nc) [N], > 0 pushes.
        drive_torque: Torque-drive torques before friction (what a ``torque`` channel
            measures), shape (n, nd) [N·m].
        joint_torque: Actuator joint loads driving the dynamics (cylinder force · ds/dq,
            drive torque − drive friction, end stops of free joints), shape (n, nj) [N·m or N];
            the contact force is not included.
        joint_wrench: Joint reaction wrenches from ``physics.inverse_dynamics`` of (q, qd, qdd),
            shape (n, nj, 6) [N, N·m], in that function's convention; all-NaN if it was not
            computed.
        payload_kg: Payload mass at the load point (excluding the tool), shape (n,) [kg].
        u: Valve commands (actuator order), shape (n, na) [V].
        contact_force: External force on the tool at the load point, world frame, shape
            (n, 3) [N] (zero without contact).
    """

    t_s: F64
    q: F64
    qd: F64
    qdd: F64
    rod_s: F64
    rod_v: F64
    p_a: F64
    p_b: F64
    cyl_force: F64
    drive_torque: F64
    joint_torque: F64
    joint_wrench: F64
    payload_kg: F64
    u: F64
    contact_force: F64

    @property
    def n(self) -> int:
        """Number of truth instants."""
        return int(self.t_s.shape[0])

    @property
    def slew_torque(self) -> F64:
        """The first torque drive's torque, shape (n,) [N·m] (NaN if the machine has none)."""
        if self.drive_torque.shape[1] == 0:
            return np.full(self.n, np.nan)
        return np.ascontiguousarray(self.drive_torque[:, 0])

    def validate(self) -> None:
        """Check the array shapes.

        Raises:
            SimulationError: an array has a shape inconsistent with ``t_s`` and the others.
        """
        n = self.n
        nj = self.q.shape[1] if self.q.ndim == 2 else -1
        nc = self.rod_s.shape[1] if self.rod_s.ndim == 2 else -1
        nd = self.drive_torque.shape[1] if self.drive_torque.ndim == 2 else -1
        expected: dict[str, tuple[int, ...]] = {
            "t_s": (n,), "q": (n, nj), "qd": (n, nj), "qdd": (n, nj), "rod_s": (n, nc),
            "rod_v": (n, nc), "p_a": (n, nc), "p_b": (n, nc), "cyl_force": (n, nc),
            "drive_torque": (n, nd), "joint_torque": (n, nj), "joint_wrench": (n, nj, 6),
            "payload_kg": (n,), "u": (n, nc + nd), "contact_force": (n, 3),
        }
        for name, shape in expected.items():
            got = getattr(self, name).shape
            if got != shape:
                raise SimulationError(f"truth.{name}: shape {got}, expected {shape}")


def truth_columns(topology: Topology | None = None) -> list[str]:
    """Column names of the truth CSV, in order (flattening of :class:`Truth`); default the
    PATU 655's names."""
    tp = topology or Topology()
    cols = ["t_s"]
    for prefix in ("q", "qd", "qdd"):
        cols += [f"{prefix}_{j}" for j in tp.joints]
    for prefix in ("rod_s", "rod_v", "p_a", "p_b", "cyl_force"):
        cols += [f"{prefix}_{c}" for c in tp.cylinders]
    cols += [f"drive_torque_{d}" for d in tp.drives]
    cols += [f"joint_torque_{j}" for j in tp.joints]
    cols += [f"joint_wrench_{j}_{w}" for j in tp.joints for w in WRENCH]
    cols.append("payload_kg")
    cols += [f"u_{a}" for a in (*tp.drives, *tp.cylinders)]
    cols += [f"contact_force_{f}" for f in FORCE]
    return cols


def _widths(tp: Topology) -> list[tuple[str, int]]:
    nj, nc, nd = len(tp.joints), len(tp.cylinders), len(tp.drives)
    return [("t_s", 1), ("q", nj), ("qd", nj), ("qdd", nj), ("rod_s", nc), ("rod_v", nc),
            ("p_a", nc), ("p_b", nc), ("cyl_force", nc), ("drive_torque", nd),
            ("joint_torque", nj), ("joint_wrench", 6 * nj), ("payload_kg", 1), ("u", nc + nd),
            ("contact_force", 3)]


def _truth_matrix(tr: Truth) -> F64:
    n = tr.n
    parts = [tr.t_s[:, None], tr.q, tr.qd, tr.qdd, tr.rod_s, tr.rod_v, tr.p_a, tr.p_b,
             tr.cyl_force, tr.drive_torque, tr.joint_torque,
             tr.joint_wrench.reshape(n, -1), tr.payload_kg[:, None], tr.u, tr.contact_force]
    return np.hstack(parts).astype(np.float64)


def _truth_from_matrix(m: F64, tp: Topology) -> Truth:
    n = m.shape[0]
    out: dict[str, F64] = {}
    col = 0
    for name, w in _widths(tp):
        block = np.ascontiguousarray(m[:, col:col + w])
        col += w
        if name in ("t_s", "payload_kg"):
            out[name] = block[:, 0].copy()
        elif name == "joint_wrench":
            out[name] = block.reshape(n, len(tp.joints), 6)
        else:
            out[name] = block
    return Truth(**out)


@dataclass(frozen=True)
class Recording:
    """A simulated run: what the machine sent, and what really happened.

    Attributes:
        machine: Machine name (``machine.name``).
        scenario: Scenario name.
        seed: Random seed of the run (scenario randomness and sensor model).
        step_s: Integration step [s].
        start_epoch_s: Epoch time of simulation time 0 [s].
        samples: The sampled sensor channels (columns = the machine's channel names).
        truth: Fine-step ground truth.
        meta: Further settings (sensor model, truth rate, durations), JSON-serialisable.
    """

    machine: str
    scenario: str
    seed: int
    step_s: float
    start_epoch_s: float
    samples: SampleArrays
    truth: Truth
    meta: dict[str, Any] = field(default_factory=dict)

    def blocks(self, samples_per_block: int = 10, first_seq: int = 0) -> list[SampleBlock]:
        """The samples cut into datagram-sized :class:`~cranetwin.samples.SampleBlock` s.

        Args:
            samples_per_block: Samples per block (the last block may be shorter).
            first_seq: Sequence number of the first block (then +1 per block).

        Raises:
            SimulationError: the recording has no sample rate or resolutions in ``meta``.
        """
        try:
            rate = float(self.meta["sensors"]["rate_hz"])
            resolution = tuple(float(r) for r in self.meta["channel_resolution"])
        except (KeyError, TypeError) as exc:
            raise SimulationError(f"recording meta lacks {exc} (not made by simulate?)") from exc
        period_ns = int(round(1e9 / rate))
        smp = self.samples
        out = []
        for b, i in enumerate(range(0, smp.values.shape[0], samples_per_block)):
            out.append(SampleBlock(machine_id=smp.machine_id, seq=first_seq + b,
                                   t0_ns=int(round(smp.t_s[i] * 1e9)), period_ns=period_ns,
                                   channels=smp.channels, resolution=resolution,
                                   values=smp.values[i:i + samples_per_block].copy()))
        return out

    @property
    def duration_s(self) -> float:
        """Simulated time span [s]."""
        return float(self.truth.t_s[-1] - self.truth.t_s[0]) if self.truth.n else 0.0

    @property
    def topology(self) -> Topology:
        """Names of the machine's joints, cylinders and drives (PATU 655 if not recorded)."""
        return Topology.from_json(self.meta.get("topology"))

    def _header(self) -> dict[str, Any]:
        return {"machine": self.machine, "scenario": self.scenario, "seed": self.seed,
                "step_s": self.step_s, "start_epoch_s": self.start_epoch_s,
                "machine_id": self.samples.machine_id, "channels": list(self.samples.channels),
                "meta": self.meta}

    # --- npz ----------------------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        """Write to ``.npz`` (lossless) or ``.csv`` (see module docstring), by suffix.

        Returns:
            The path written (for CSV, the samples file; the truth is ``<stem>.truth.csv``).

        Raises:
            SimulationError: unknown suffix or the file cannot be written.
        """
        p = Path(path)
        try:
            if p.suffix == ".npz":
                arrays = {f"truth_{f.name}": getattr(self.truth, f.name) for f in fields(Truth)}
                np.savez_compressed(p, header=np.array(json.dumps(self._header())),
                                    samples_t_s=self.samples.t_s,
                                    samples_values=self.samples.values, **arrays)
            elif p.suffix == ".csv":
                self._save_csv(p)
            else:
                raise SimulationError(f"{p}: unknown recording format {p.suffix!r} "
                                      "(expected .npz or .csv)")
        except OSError as exc:
            raise SimulationError(f"{p}: cannot write recording: {exc}") from exc
        return p

    def _save_csv(self, p: Path) -> None:
        header = self._header()
        with p.open("w", newline="", encoding="utf-8") as fh:
            fh.write(f"# cranetwin-recording: {json.dumps(header)}\n")
            w = csv.writer(fh)
            w.writerow(["t_s", *self.samples.channels])
            for t, row in zip(self.samples.t_s, self.samples.values, strict=True):
                w.writerow([repr(float(t)), *(repr(float(x)) for x in row)])
        with truth_path(p).open("w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(truth_columns(self.topology))
            for row in _truth_matrix(self.truth):
                w.writerow([repr(float(x)) for x in row])

    @classmethod
    def load(cls, path: str | Path) -> Recording:
        """Read a recording written by :meth:`save` (``.npz`` or ``.csv``).

        Raises:
            SimulationError: missing file, unknown suffix, or not a cranetwin recording.
        """
        p = Path(path)
        try:
            if p.suffix == ".npz":
                with np.load(p, allow_pickle=False) as z:
                    header = json.loads(str(z["header"]))
                    truth = _truth_from_npz(z)
                    t_s = np.asarray(z["samples_t_s"], dtype=np.float64)
                    values = np.asarray(z["samples_values"], dtype=np.float64)
            elif p.suffix == ".csv":
                header, t_s, values, truth = _load_csv(p)
            else:
                raise SimulationError(f"{p}: unknown recording format {p.suffix!r} "
                                      "(expected .npz or .csv)")
        except (OSError, KeyError, ValueError) as exc:
            raise SimulationError(f"{p}: not a readable cranetwin recording: {exc}") from exc
        truth.validate()
        samples = SampleArrays(machine_id=str(header["machine_id"]), t_s=t_s,
                               channels=tuple(header["channels"]), values=values)
        return cls(machine=str(header["machine"]), scenario=str(header["scenario"]),
                   seed=int(header["seed"]), step_s=float(header["step_s"]),
                   start_epoch_s=float(header["start_epoch_s"]), samples=samples, truth=truth,
                   meta=dict(header.get("meta", {})))


def _truth_from_npz(z: Any) -> Truth:
    """Truth arrays of an ``.npz``; files written before the generic topology carry
    ``slew_torque`` (n,) instead of ``drive_torque`` and no contact force."""
    keys = set(z.files)
    arrays: dict[str, F64] = {}
    for f in fields(Truth):
        key = f"truth_{f.name}"
        if key in keys:
            arrays[f.name] = np.asarray(z[key], dtype=np.float64)
        elif f.name == "drive_torque" and "truth_slew_torque" in keys:
            arrays[f.name] = np.asarray(z["truth_slew_torque"], dtype=np.float64)[:, None]
        elif f.name == "contact_force":
            arrays[f.name] = np.zeros((np.asarray(z["truth_t_s"]).shape[0], 3))
        else:
            raise KeyError(key)
    return Truth(**arrays)


def truth_path(samples_csv: str | Path) -> Path:
    """Where the truth CSV of a samples CSV lives: ``<stem>.truth.csv`` next to it."""
    p = Path(samples_csv)
    return p.with_name(p.stem + ".truth.csv")


def _load_csv(p: Path) -> tuple[dict[str, Any], F64, F64, Truth]:
    with p.open(encoding="utf-8") as fh:
        first = fh.readline()
        prefix = "# cranetwin-recording: "
        if not first.startswith(prefix):
            raise ValueError("first line is not a cranetwin-recording header")
        header = json.loads(first[len(prefix):])
        rows = list(csv.reader(fh))
    cols = rows[0]
    if cols != ["t_s", *header["channels"]]:
        raise ValueError(f"column header {cols} does not match the channels {header['channels']}")
    data = np.array([[float(x) for x in r] for r in rows[1:]], dtype=np.float64)
    data = data.reshape(-1, len(cols))
    with truth_path(p).open(encoding="utf-8") as fh:
        trows = list(csv.reader(fh))
    topology = Topology.from_json(header.get("meta", {}).get("topology"))
    if trows[0] != truth_columns(topology):
        raise ValueError("truth CSV columns differ from truth_columns() of the recorded topology")
    tm = np.array([[float(x) for x in r] for r in trows[1:]], dtype=np.float64)
    tm = tm.reshape(-1, len(trows[0]))
    return (header, data[:, 0].copy(), np.ascontiguousarray(data[:, 1:]),
            _truth_from_matrix(tm, topology))
