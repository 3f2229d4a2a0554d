"""Hydraulic actuator models for the simulator, as compiled single-sample kernels.

Per cylinder (all pressures gauge [Pa], flows into a chamber positive [m³/s]):

* Proportional 4/3 valve, critically lapped, first-order spool lag τ:
  ``dU/dt = (U_cmd − U)/τ`` (solved exactly over a step).
* Orifice (paper/reference model) ``Q = Qn·U·sign(Δp)·sqrt(|Δp|)``, regularised near Δp = 0 as
  ``Q = Qn·U·Δp / sqrt(|Δp| + p_tr)`` (laminar below ``p_tr`` ≈ 1 bar; 1.4 % less flow at 35 bar).
  U > 0: supply → A, B → tank; U < 0: supply → B, A → tank.
* Chambers: ``dpA/dt = (QA − A1·v)/C_A``, ``dpB/dt = (QB + A2·v)/C_B`` with the capacitance of the
  oil in the cylinder plus the hose dead volume, ``C_A = A1·s/B_oil + V0/B_hose`` and
  ``C_B = A2·(stroke − s)/B_oil + V0/B_hose`` (steel cylinder walls taken rigid; the hose
  figure is an effective modulus of oil in hose). Pressures are clamped at ``p_min`` (cavitation).
* Relief valve per chamber to tank: ``Q = −K_r·max(0, p − p_relief)``.
* End stops (stiff, damped) at s = 0 and s = stroke: ``F = k·δ + c·δ̇`` pushing out of the stop,
  only while pushing.
* Friction and cylinder force, paper Eq. 1–2: :mod:`cranetwin.physics.actuator` (the loop
  calls ``eq1_cylinder_force`` and ``eq2_friction``; nothing here re-derives them).

Torque drives (a slewing/swing motor; zero or more, each on its own joint): a flow-controlled
hydraulic motor through its gear, modelled at the joint:
``dT/dt = K_s·(ω_cmd − ω) − T/τ_leak`` with ω_cmd = (U/U_max)·ω_max, the torque clipped at
±T_max (relief). K_s is the hydraulic torsional stiffness seen at the joint, τ_leak the motor
leakage time constant. The measured drive torque is T (before friction); the joint receives
``T − F_fr(ω)`` (Eq. 2 with the drive's friction).

Free joints (no actuator) get only end stops at their joint limits (rows of the same table as
the drives, of which only the limit columns are used).

The pressure update is linearly implicit in the valve and relief flows (robust at 1e-4 s near
Δp = 0), explicit in the piston motion (see :mod:`cranetwin.sim.engine`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from numba import njit

from cranetwin.errors import SimulationError
from cranetwin.model import Hydraulics, Machine

F64 = npt.NDArray[np.float64]

# columns of the per-cylinder parameter table
C_A1, C_A2, C_STROKE, C_QN, C_TAU, C_UMAX, C_FC, C_VC, C_B, C_V0, C_KEND, C_CEND = range(12)
N_CYL_PARAMS = 12
# global hydraulic parameters
G_PS, G_PT, G_PREL, G_BOIL, G_BHOSE, G_PTR, G_KREL, G_PMIN = range(8)
N_GLOBAL = 8
# torque-drive parameters (one row per drive; free joints use the S_LO … S_CLIM columns)
(S_TMAX, S_FC, S_VC, S_B, S_KS, S_TLEAK, S_WMAX, S_TAU, S_UMAX, S_LO, S_HI, S_KLIM,
 S_CLIM) = range(13)
N_SLEW = 13


@dataclass(frozen=True)
class HydraulicSettings:
    """Simulator-side constants that the machine file does not carry (documented defaults).

    Attributes:
        transition_pressure_pa: Laminar/turbulent transition of the orifice [Pa].
        relief_gain_m3_s_pa: Relief-valve flow per pressure above the setting [m³/(s·Pa)].
        min_pressure_pa: Cavitation floor [Pa].
        end_stop_stiffness_n_m: End-stop contact stiffness [N/m].
        end_stop_damping_n_s_m: End-stop contact damping [N·s/m].
        slew_stiffness_nm_rad: Hydraulic torsional stiffness of the slewing drive at the pillar
            [N·m/rad] (≈ 2 Hz with 3000 kg·m² of slewing inertia).
        slew_leak_time_s: Slewing-motor leakage time constant [s].
        slew_spool_time_s: Slewing valve spool lag [s].
        slew_limit_stiffness_nm_rad, slew_limit_damping_nms_rad: Slewing end stops at the joint
            limits.
    """

    transition_pressure_pa: float = 1.0e5
    relief_gain_m3_s_pa: float = 1.0e-8
    min_pressure_pa: float = 0.0
    end_stop_stiffness_n_m: float = 2.0e8
    end_stop_damping_n_s_m: float = 2.0e5
    slew_stiffness_nm_rad: float = 4.7e5
    slew_leak_time_s: float = 0.2
    slew_spool_time_s: float = 0.03
    slew_limit_stiffness_nm_rad: float = 1.0e7
    slew_limit_damping_nms_rad: float = 2.0e5


@dataclass(frozen=True)
class HydraulicParams:
    """Packed parameters for the compiled loop.

    Attributes:
        cyl: Per-cylinder table, shape (n_cylinders, N_CYL_PARAMS) (columns ``C_*``).
        glob: Circuit constants, shape (N_GLOBAL,) (``G_*``).
        drives: Torque drives, shape (n_drives, N_SLEW) (``S_*``), machine order.
        free: End stops of the free (unactuated) joints, shape (n_free, N_SLEW) (only
            ``S_LO``, ``S_HI``, ``S_KLIM``, ``S_CLIM`` used).
        drive_joint: Joint index of each drive, shape (n_drives,).
        free_joint: Joint index of each free joint, shape (n_free,).
    """

    cyl: F64
    glob: F64
    drives: F64
    free: F64
    drive_joint: npt.NDArray[np.int64]
    free_joint: npt.NDArray[np.int64]


# a machine without cylinders (torque drives and free joints only) needs no circuit
_NO_CIRCUIT = Hydraulics(supply_pressure_pa=1.0, tank_pressure_pa=0.0, relief_pressure_pa=1.0,
                         oil_bulk_modulus_pa=1.0, hose_bulk_modulus_pa=1.0, dead_volume_m3=1.0)


def pack(machine: Machine, settings: HydraulicSettings | None = None) -> HydraulicParams:
    """Collect the hydraulic parameters of ``machine`` (cylinders in machine order).

    Raises:
        ValueError: the machine has cylinders but no hydraulics, or a cylinder has no valve.
    """
    st = settings or HydraulicSettings()
    h = machine.hydraulics
    if h is None:
        if machine.cylinders:
            raise ValueError("machine has cylinders but no [hydraulics] section")
        h = _NO_CIRCUIT
    cyl = np.zeros((len(machine.cylinders), N_CYL_PARAMS))
    for i, c in enumerate(machine.cylinders):
        if c.valve is None:
            raise ValueError(f"cylinder {c.name!r} has no valve")
        cyl[i, C_A1] = c.area_a_m2
        cyl[i, C_A2] = c.area_b_m2
        cyl[i, C_STROKE] = c.stroke_m
        cyl[i, C_QN] = c.valve.flow_gain
        cyl[i, C_TAU] = c.valve.spool_time_constant_s
        cyl[i, C_UMAX] = c.valve.max_voltage_v
        cyl[i, C_FC] = c.friction.coulomb
        cyl[i, C_VC] = c.friction.coulomb_velocity
        cyl[i, C_B] = c.friction.viscous
        cyl[i, C_V0] = h.dead_volume_m3 if c.dead_volume_m3 is None else c.dead_volume_m3
        cyl[i, C_KEND] = st.end_stop_stiffness_n_m
        cyl[i, C_CEND] = st.end_stop_damping_n_s_m
    glob = np.zeros(N_GLOBAL)
    glob[G_PS] = h.supply_pressure_pa
    glob[G_PT] = h.tank_pressure_pa
    glob[G_PREL] = h.relief_pressure_pa
    glob[G_BOIL] = h.oil_bulk_modulus_pa
    glob[G_BHOSE] = h.hose_bulk_modulus_pa
    glob[G_PTR] = st.transition_pressure_pa
    glob[G_KREL] = st.relief_gain_m3_s_pa
    glob[G_PMIN] = st.min_pressure_pa
    drives = np.zeros((len(machine.torque_drives), N_SLEW))
    for i, d in enumerate(machine.torque_drives):
        j = machine.joints[machine.joint_index(d.joint)]
        row = drives[i]
        row[S_TMAX] = d.max_torque_nm
        row[S_FC] = d.friction.coulomb
        row[S_VC] = d.friction.coulomb_velocity
        row[S_B] = d.friction.viscous
        row[S_KS] = st.slew_stiffness_nm_rad
        row[S_TLEAK] = st.slew_leak_time_s
        if j.velocity_limit is None:
            raise SimulationError(
                f"joints.{machine.joint_index(d.joint)}.velocity_limit: unknown; the simulator "
                f"drives torque drive {d.name!r} at velocity_limit × valve command, so it needs "
                "the joint's speed at full command")
        row[S_WMAX] = j.velocity_limit
        row[S_TAU] = st.slew_spool_time_s
        row[S_UMAX] = 10.0
        _limits(row, j.lower, j.upper, st)
    actuated = {c.joint for c in machine.cylinders} | {d.joint for d in machine.torque_drives}
    free_joint = [i for i, j in enumerate(machine.joints) if j.name not in actuated]
    free = np.zeros((len(free_joint), N_SLEW))
    for r, i in enumerate(free_joint):
        _limits(free[r], machine.joints[i].lower, machine.joints[i].upper, st)
    return HydraulicParams(
        cyl=cyl, glob=glob, drives=drives, free=free,
        drive_joint=np.array([machine.joint_index(d.joint) for d in machine.torque_drives],
                             dtype=np.int64),
        free_joint=np.array(free_joint, dtype=np.int64))


def _limits(row: F64, lower: float, upper: float, st: HydraulicSettings) -> None:
    row[S_LO] = lower
    row[S_HI] = upper
    row[S_KLIM] = st.slew_limit_stiffness_nm_rad
    row[S_CLIM] = st.slew_limit_damping_nms_rad


@njit(cache=True)
def orifice(qn: float, u: float, dp: float, p_tr: float) -> tuple[float, float]:
    """Regularised orifice flow and its slope.

    Args:
        qn: Flow gain Qn [m³/(s·V·√Pa)].
        u: Spool voltage (≥ 0 here; the sign is handled by the caller) [V].
        dp: Pressure drop across the orifice [Pa].
        p_tr: Transition pressure [Pa].

    Returns:
        (Q [m³/s], dQ/d(dp) [m³/(s·Pa)] ≥ 0).
    """
    a = abs(dp) + p_tr
    r = math.sqrt(a)
    q = qn * u * dp / r
    dq = qn * u * (0.5 * abs(dp) + p_tr) / (a * r)
    return q, dq


@njit(cache=True)
def valve_flows(qn: float, u: float, pa: float, pb: float, ps: float, pt: float,
                p_tr: float) -> tuple[float, float, float, float]:
    """Flows into chambers A and B through a critically lapped 4/3 valve.

    Returns:
        (QA, QB, gA, gB): flows into A and B [m³/s] and their sensitivities to the chamber's
        own pressure, gX = −∂QX/∂pX ≥ 0 [m³/(s·Pa)].
    """
    if u >= 0.0:
        qa, ga = orifice(qn, u, ps - pa, p_tr)
        qb, gb = orifice(qn, u, pb - pt, p_tr)
        return qa, -qb, ga, gb
    qa, ga = orifice(qn, -u, pa - pt, p_tr)
    qb, gb = orifice(qn, -u, ps - pb, p_tr)
    return -qa, qb, ga, gb


@njit(cache=True)
def capacitances(s: float, a1: float, a2: float, stroke: float, v0: float, b_oil: float,
                 b_hose: float) -> tuple[float, float]:
    """Hydraulic capacitances of chambers A and B [m³/Pa] at rod position s [m].

    The rod position is clamped to the stroke (inside an end stop the chamber volume does not
    shrink further).
    """
    sc = min(max(s, 0.0), stroke)
    ca = a1 * sc / b_oil + v0 / b_hose
    cb = a2 * (stroke - sc) / b_oil + v0 / b_hose
    return ca, cb


@njit(cache=True)
def end_stop(s: float, v: float, stroke: float, k: float, c: float) -> float:
    """Contact force of the end stops on the rod [N] (> 0 pushes out), 0 inside the stroke."""
    if s < 0.0:
        return max(0.0, -k * s - c * v)
    if s > stroke:
        return min(0.0, -k * (s - stroke) - c * v)
    return 0.0


@njit(cache=True)
def relief(p: float, p_relief: float, k: float) -> tuple[float, float]:
    """Relief flow into the chamber [m³/s] (≤ 0) and its sensitivity −∂Q/∂p ≥ 0."""
    if p > p_relief:
        return -k * (p - p_relief), k
    return 0.0, 0.0


@njit(cache=True)
def pressure_step(p: float, rhs: float, g: float, c: float, dt: float, p_min: float) -> float:
    """Linearly implicit Euler step of dp/dt = rhs/c, with rhs decreasing in p at rate g.

    Args:
        p: Pressure [Pa]; rhs: net flow into the chamber [m³/s]; g: −∂rhs/∂p [m³/(s·Pa)];
        c: Capacitance [m³/Pa]; dt: Step [s]; p_min: Cavitation floor [Pa].
    """
    return max(p + dt * rhs / (c + dt * g), p_min)


@njit(cache=True)
def spool_step(u: float, u_cmd: float, tau: float, dt: float) -> float:
    """Exact step of the first-order spool lag dU/dt = (U_cmd − U)/τ."""
    return u_cmd + (u - u_cmd) * math.exp(-dt / tau)


@njit(cache=True)
def slew_torque_rate(torque: float, u: float, omega: float, sp: F64) -> float:
    """dT/dt of the slewing drive [N·m/s] (without the ±T_max clip)."""
    w_cmd = u / sp[S_UMAX] * sp[S_WMAX]
    return float(sp[S_KS] * (w_cmd - omega) - torque / sp[S_TLEAK])


@njit(cache=True)
def joint_limit(theta: float, omega: float, lo: float, hi: float, k: float, c: float) -> float:
    """End-stop torque (or force) at joint limits lo, hi [rad or m], stiffness k, damping c;
    pushes back into the range only."""
    if theta < lo:
        return max(0.0, -k * (theta - lo) - c * omega)
    if theta > hi:
        return min(0.0, -k * (theta - hi) - c * omega)
    return 0.0


@njit(cache=True)
def slew_limit(theta: float, omega: float, sp: F64) -> float:
    """End-stop torque at the joint limits of a drive's parameter row ``sp`` [N·m]."""
    return joint_limit(theta, omega, sp[S_LO], sp[S_HI], sp[S_KLIM], sp[S_CLIM])
