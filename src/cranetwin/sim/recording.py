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
    next to it with the columns listed by :func:`truth_columns`. Floats are written with 17
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
from cranetwin.samples import SampleArrays, SampleBlock

F64 = npt.NDArray[np.float64]

JOINTS = ("theta0", "theta1", "theta2", "L")
CYLINDERS = ("lift", "jib", "extension")
WRENCH = ("fx", "fy", "fz", "mx", "my", "mz")


@dataclass(frozen=True)
class Truth:
    """Ground truth on the fine (decimated) grid, exactly as the integrator computed it.

    Attributes:
        t_s: Times, shape (n,) [s, same timebase as the samples].
        q: Joint positions [theta0, theta1, theta2, L], shape (n, 4) [rad or m].
        qd: Joint velocities, shape (n, 4) [rad/s or m/s].
        qdd: Joint accelerations the integrator used at that instant, shape (n, 4)
            [rad/s² or m/s²]: M(q)·qdd + h(q, qd) = joint_torque holds to round-off.
        rod_s: Cylinder rod positions (lift, jib, extension), shape (n, 3) [m].
        rod_v: Cylinder rod velocities, shape (n, 3) [m/s].
        p_a: Piston-side chamber pressures, shape (n, 3) [Pa].
        p_b: Rod-side chamber pressures, shape (n, 3) [Pa].
        cyl_force: Cylinder forces on the mechanism, Eq. 1–2 incl. friction (and end-stop
            force if the rod is in its end stop), shape (n, 3) [N], > 0 pushes.
        slew_torque: Slewing drive torque before friction (what the ``slew_torque`` channel
            measures), shape (n,) [N·m].
        joint_torque: Actuator joint loads driving the dynamics (cylinder force · ds/dq,
            slewing torque − slewing friction), shape (n, 4) [N·m or N].
        joint_wrench: Joint reaction wrenches from ``physics.inverse_dynamics`` of (q, qd, qdd),
            shape (n, 4, 6) [N, N·m], in that function's convention; all-NaN if it was not
            computed.
        payload_kg: Payload mass at the tip (excluding the tool), shape (n,) [kg].
        u: Valve commands [slew, lift, jib, extension], shape (n, 4) [V].
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
    slew_torque: F64
    joint_torque: F64
    joint_wrench: F64
    payload_kg: F64
    u: F64

    @property
    def n(self) -> int:
        """Number of truth instants."""
        return int(self.t_s.shape[0])

    def validate(self) -> None:
        """Check the array shapes.

        Raises:
            SimulationError: an array has a shape inconsistent with ``t_s``.
        """
        n = self.n
        expected: dict[str, tuple[int, ...]] = {
            "t_s": (n,), "q": (n, 4), "qd": (n, 4), "qdd": (n, 4), "rod_s": (n, 3),
            "rod_v": (n, 3), "p_a": (n, 3), "p_b": (n, 3), "cyl_force": (n, 3),
            "slew_torque": (n,), "joint_torque": (n, 4), "joint_wrench": (n, 4, 6),
            "payload_kg": (n,), "u": (n, 4),
        }
        for name, shape in expected.items():
            got = getattr(self, name).shape
            if got != shape:
                raise SimulationError(f"truth.{name}: shape {got}, expected {shape}")


def truth_columns() -> list[str]:
    """Column names of the truth CSV, in order (flattening of :class:`Truth`)."""
    cols = ["t_s"]
    for prefix in ("q", "qd", "qdd"):
        cols += [f"{prefix}_{j}" for j in JOINTS]
    for prefix in ("rod_s", "rod_v", "p_a", "p_b", "cyl_force"):
        cols += [f"{prefix}_{c}" for c in CYLINDERS]
    cols.append("slew_torque")
    cols += [f"joint_torque_{j}" for j in JOINTS]
    cols += [f"joint_wrench_{j}_{w}" for j in JOINTS for w in WRENCH]
    cols.append("payload_kg")
    cols += [f"u_{a}" for a in ("slew", *CYLINDERS)]
    return cols


def _truth_matrix(tr: Truth) -> F64:
    n = tr.n
    parts = [tr.t_s[:, None], tr.q, tr.qd, tr.qdd, tr.rod_s, tr.rod_v, tr.p_a, tr.p_b,
             tr.cyl_force, tr.slew_torque[:, None], tr.joint_torque,
             tr.joint_wrench.reshape(n, 24), tr.payload_kg[:, None], tr.u]
    return np.hstack(parts).astype(np.float64)


def _truth_from_matrix(m: F64) -> Truth:
    n = m.shape[0]
    widths = [("t_s", 1), ("q", 4), ("qd", 4), ("qdd", 4), ("rod_s", 3), ("rod_v", 3),
              ("p_a", 3), ("p_b", 3), ("cyl_force", 3), ("slew_torque", 1),
              ("joint_torque", 4), ("joint_wrench", 24), ("payload_kg", 1), ("u", 4)]
    out: dict[str, F64] = {}
    col = 0
    for name, w in widths:
        block = np.ascontiguousarray(m[:, col:col + w])
        col += w
        if w == 1:
            out[name] = block[:, 0].copy()
        elif name == "joint_wrench":
            out[name] = block.reshape(n, 4, 6)
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
            w.writerow(truth_columns())
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
                    truth = Truth(**{f.name: np.asarray(z[f"truth_{f.name}"], dtype=np.float64)
                                     for f in fields(Truth)})
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
    if trows[0] != truth_columns():
        raise ValueError("truth CSV columns differ from truth_columns()")
    tm = np.array([[float(x) for x in r] for r in trows[1:]], dtype=np.float64)
    tm = tm.reshape(-1, len(trows[0]))
    return header, data[:, 0].copy(), np.ascontiguousarray(data[:, 1:]), _truth_from_matrix(tm)
