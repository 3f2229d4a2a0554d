"""Energy bookkeeping of a simulated run (for checking the integrator, not for the hot path).

With friction, valves and hydraulic losses off, the simulated system is conservative and

    E = ½·qdᵀ·M(q)·qd − Σ m·g·r_com  + Σ_chambers −(p + B_oil)·Ve  + T²/(2·K_s)

is constant, where Ve = B_oil·C(s) is the chamber's effective volume (oil in the cylinder plus
the hose volume scaled by B_oil/B_hose, see :mod:`cranetwin.sim.hydraulics`): the chamber law
dp = −B_oil·dVe/Ve makes d[−(p + B_oil)·Ve] = −p·dVe, the work the oil does on the piston.
T²/(2·K_s), summed over the torque drives, is the energy of their hydraulic torsional springs.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from cranetwin.errors import SimulationError
from cranetwin.model import Machine
from cranetwin.physics import body_poses, load_point_position, mass_matrix
from cranetwin.sim.hydraulics import HydraulicSettings
from cranetwin.sim.recording import Truth

F64 = npt.NDArray[np.float64]


def energy_terms(machine: Machine, truth: Truth,
                 settings: HydraulicSettings | None = None) -> dict[str, F64]:
    """Kinetic, gravitational, hydraulic and slewing-spring energy along a run.

    Args:
        machine: The simulated machine.
        truth: Ground truth of the run (payload may vary; energy jumps where it does).
        settings: Hydraulic settings used in the run (slewing stiffness).

    Raises:
        SimulationError: the machine has no hydraulics.

    Returns:
        ``kinetic``, ``gravity``, ``hydraulic``, ``slew_spring`` and ``total``, each shape (n,)
        [J]; ``hydraulic`` carries a large constant offset, only its changes mean something.
    """
    st = settings or HydraulicSettings()
    q, qd = truth.q, truth.qd
    m = mass_matrix(machine, q, truth.payload_kg)
    kinetic = 0.5 * np.einsum("ni,nij,nj->n", qd, m, qd)
    g = np.asarray(machine.machine.gravity_mps2, dtype=np.float64)
    poses = body_poses(machine, q)
    gravity = np.zeros(truth.n)
    for i, body in enumerate(machine.chain_bodies()):
        com = poses[:, i, :3, :3] @ np.asarray(body.com_m) + poses[:, i, :3, 3]
        gravity -= body.mass_kg * (com @ g)
    tip = load_point_position(machine, q)
    gravity -= (machine.load_point.tool_mass_kg + truth.payload_kg) * (tip @ g)
    h = machine.hydraulics
    if h is None:
        raise SimulationError(f"machine {machine.name!r} has no hydraulics section")
    b_oil = h.oil_bulk_modulus_pa
    hydraulic = np.zeros(truth.n)
    for k, c in enumerate(machine.cylinders):
        v0 = h.dead_volume_m3 if c.dead_volume_m3 is None else c.dead_volume_m3
        v0e = v0 * b_oil / h.hose_bulk_modulus_pa
        s = np.clip(truth.rod_s[:, k], 0.0, c.stroke_m)
        va = c.area_a_m2 * s + v0e
        vb = c.area_b_m2 * (c.stroke_m - s) + v0e
        hydraulic -= (truth.p_a[:, k] + b_oil) * va + (truth.p_b[:, k] + b_oil) * vb
    slew = np.sum(truth.drive_torque**2, axis=1) / (2.0 * st.slew_stiffness_nm_rad)
    return {"kinetic": kinetic, "gravity": gravity, "hydraulic": hydraulic, "slew_spring": slew,
            "total": kinetic + gravity + hydraulic + slew}
