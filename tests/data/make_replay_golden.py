"""Write ``replay_golden.npz``: crane recordings and what the twin, the physics functions and
the simulator made of them, kept so that a change of structure can prove it changed no output.

It was run once (commit c4b71cb), on the code before the physics/twin core was reorganised
into one module per concept; ``tests/test_replay_golden.py`` compares today's code with it.
The model-based cylinder forces (``twin.force_model``, the default since) came later: the first
five cases pin ``model_forces="off"`` and keep that code's arrays; the case
``loading_model_1k`` was added with ``--add`` (its arrays are the code's at its addition).
Run it again only when an output is meant to change, and say why in the commit.

    python tests/data/make_replay_golden.py          # every array anew
    python tests/data/make_replay_golden.py --add    # only the arrays of new cases
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from cranetwin import physics
from cranetwin.model import load_machine
from cranetwin.samples import SampleArrays
from cranetwin.signal import inject_uniform_noise
from cranetwin.sim import load_scenario, simulate
from cranetwin.twin import ReplayOptions, replay

OUT = Path(__file__).with_name("replay_golden.npz")
RESULT_FIELDS = ("t_s", "q", "qd", "qdd", "rod_s", "rod_v", "p_a", "p_b", "cyl_force",
                 "actuator_torque", "id_torque", "residual", "joint_wrench", "payload_kg",
                 "payload_std_kg", "gap")
TRUTH_FIELDS = ("t_s", "q", "qd", "qdd", "rod_s", "rod_v", "p_a", "p_b", "cyl_force",
                "slew_torque", "joint_torque", "joint_wrench", "payload_kg", "u")

# (name, scenario, seconds, noise fraction, drop slew angle, replay keyword arguments)
# The first five are the pre-redesign code's, with the cylinder forces from the pressures only
# (model_forces="off": that code had no model-based forces, the default since); the last one
# was added with the model-based forces (commit message of its addition) and holds today's
# values from then on. All but ``loading_fixed_200`` pin the LPA-ICI pressures
# (``adaptive_pressures=True``), the default until the per-cylinder split choice
# (``"choose"``) became it.
CASES: list[tuple[str, str, float, float, bool, dict[str, Any]]] = [
    ("fig3_1k", "fig3", 6.0, 0.0, False, {"grid_hz": 1000.0, "model_forces": "off",
                                         "adaptive_pressures": True}),
    ("fig3_noisy_100", "fig3", 12.0, 0.02, False, {"grid_hz": 100.0, "model_forces": "off",
                                                   "adaptive_pressures": True}),
    ("loading_torque_1k", "log-loading", 6.0, 0.01, True,
     {"grid_hz": 1000.0, "model_forces": "off", "adaptive_pressures": True}),
    ("loading_fixed_200", "log-loading", 12.0, 0.02, False,
     {"grid_hz": 200.0, "adaptive_pressures": False, "model_forces": "off"}),
    ("loading_payload_kin_100", "log-loading", 12.0, 0.0, False,
     {"grid_hz": 100.0, "payload": 300.0, "wrench_acceleration": "kinematic",
      "model_forces": "off", "adaptive_pressures": True}),
    ("loading_model_1k", "log-loading", 12.0, 0.05, False,
     {"grid_hz": 1000.0, "model_forces": "on", "adaptive_pressures": True}),
]

EVERY = {name: 5 if kw["grid_hz"] >= 1000 else 1 for name, *_, kw in CASES}


def compute() -> dict[str, np.ndarray]:
    """Every array the golden file holds, computed by today's code."""
    machine = load_machine("patu655")
    out: dict[str, np.ndarray] = {}
    recordings = {}
    for scenario in ("fig3", "log-loading"):
        rec = simulate(machine, load_scenario(scenario), duration_s=12.0, seed=7)
        recordings[scenario] = rec
        out[f"sim_{scenario}_channels"] = np.array(rec.samples.channels)
        out[f"sim_{scenario}_t_s"] = rec.samples.t_s
        out[f"sim_{scenario}_values"] = rec.samples.values
        for f in TRUTH_FIELDS:  # every 10th instant of the truth's grid
            out[f"sim_{scenario}_truth_{f}"] = np.asarray(getattr(rec.truth, f))[::10]
    for name, scenario, seconds, noise, drop_angle, kwargs in CASES:
        s = recordings[scenario].samples
        keep = s.t_s <= s.t_s[0] + seconds
        samples = SampleArrays(s.machine_id, s.t_s[keep], s.channels, s.values[keep])
        if noise > 0:
            samples = inject_uniform_noise(samples, machine, noise, seed=11)
        if drop_angle:
            cols = [i for i, c in enumerate(samples.channels) if c != "slew_angle"]
            samples = SampleArrays(samples.machine_id, samples.t_s,
                                   tuple(samples.channels[i] for i in cols),
                                   samples.values[:, cols])
        kw = dict(kwargs)
        grid_hz = kw.pop("grid_hz")
        payload = kw.pop("payload", None)
        options = ReplayOptions(grid_hz=grid_hz, **kw)
        res = replay(samples, machine, grid_hz=grid_hz, payload=payload, options=options)
        out[f"{name}_in_channels"] = np.array(samples.channels)
        out[f"{name}_in_t_s"] = samples.t_s
        out[f"{name}_in_values"] = samples.values
        every = EVERY[name]  # every instant, or every 5th on a 1 kHz grid (file size)
        for f in RESULT_FIELDS:
            out[f"{name}_out_{f}"] = np.asarray(getattr(res, f))[::every]
        if every > 1:
            continue
        # the physics functions on the replayed motion, called directly
        payload_kg = np.maximum(res.payload_kg, 0.0)
        tau, wrench = physics.inverse_dynamics(machine, res.q, res.qd, res.qdd,
                                               payload_kg=payload_kg)
        out[f"{name}_phys_tau"] = tau
        out[f"{name}_phys_wrench"] = wrench
        out[f"{name}_phys_rod_s"] = physics.cylinder_lengths(machine, res.q)
        out[f"{name}_phys_arms"] = physics.moment_arms(machine, res.q)
        out[f"{name}_phys_force"] = physics.cylinder_forces(machine, res.p_a, res.p_b, res.rod_v)
        out[f"{name}_phys_mass"] = physics.mass_matrix(machine, res.q[::50],
                                                       payload_kg[::50])
    return out


def main(add: bool = False) -> None:
    """Write the file; ``add`` (``--add``): keep the arrays it holds, add only new ones (a new
    case keeps the older cases' arrays as first written)."""
    out = compute()
    if add and OUT.exists():
        with np.load(OUT) as f:
            out.update({k: f[k] for k in f.files})
    np.savez_compressed(OUT, **out)
    print(f"{OUT}: {OUT.stat().st_size / 1e6:.1f} MB, {len(out)} arrays")


if __name__ == "__main__":
    import sys

    main(add="--add" in sys.argv[1:])
