"""An independent forward simulation of a PATU 655-class knuckle-boom crane (numpy + scipy only).

Written to check the twin on data the project did not make: nothing here imports
``cranetwin.physics``, ``cranetwin.model``, ``cranetwin.sim`` or ``cranetwin.twin`` (a test
proves it), and the formulation differs from the project's recursive Newton–Euler:

* **Geometry** from ``reference/patu655.md`` (own parameter record :data:`PATU655`): the boom is
  planar in the pillar's vertical plane (x forward, y up), turned by the slew angle theta0 about
  the vertical. Generalised coordinates q = [theta0, theta1, theta2, L] [rad, rad, rad, m]:
  theta1 the lift boom's angle (counter-clockwise), theta2 the jib's angle relative to the lift
  boom, L the telescope's extension (a prismatic joint along the jib).
* **Mechanics** from the Lagrangian L = T − V with
  T = ½·q̇ᵀM(q)q̇, M = Σ_b (m_b·J_bᵀJ_b + J_ω,bᵀ·I_b·J_ω,b), where J_b = ∂p_b/∂q are the
  3-D centre-of-mass Jacobians by central finite differences of :func:`points` (bodies and the
  tool + payload as a point mass at the tip), J_ω,b the bodies' angular-velocity Jacobians in
  their own axes. Coriolis/centrifugal terms from the Christoffel symbols,
  c_i = Σ_jk (∂M_ij/∂q_k − ½·∂M_jk/∂q_i)·q̇_j·q̇_k, with ∂M/∂q again by central differences;
  gravity Q_g = Σ m_b·J_bᵀ·g. So  M·q̈ + c = Q_g + Q_act.
* **Cylinders** as pin-to-pin lengths ℓ_k(q) = |p_base − p_rod| from triangle / four-bar
  geometry (the jib's rod end E by circle intersection); force → generalised force by
  Q_act = (∂ℓ/∂q)ᵀ·F (finite differences), rod velocity v = (∂ℓ/∂q)·q̇. Rod position
  s = ℓ − closed length.
* **Hydraulics** per cylinder: a 4/3 critically lapped valve, Q = K·U·sign(Δp)·sqrt(|Δp|)
  (regularised below ``dp_laminar_pa``), spool U with a first-order lag, chamber pressures
  ṗ = β/V·(Q ∓ A·v) with V = V_dead + A·(travel), β the oil and hose in series, a relief and an
  anti-cavitation valve on each chamber. Friction Fc·tanh(v/vc) + b·v. End stops as stiff
  spring-dampers (scenarios stay off them). The slewing drive is a torque with a first-order
  lag, its own Coulomb + viscous friction.

Cylinder force, the truth the twin is compared with: F = pA·A1 − pB·A2 − F_fr(v) [N], the net
rod force on the structure (docs/PHYSICS.md), > 0 pushing. The slew torque channel is the
drive's torque before its friction (the twin subtracts the drive friction itself).

Integrated with ``scipy.integrate.solve_ivp`` (LSODA, ``max_step``) in segments between payload
steps (the mass jumps at the tip), sampled at 100 Hz (:func:`simulate`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt
from scipy.integrate import solve_ivp
from scipy.optimize import brentq

F64 = npt.NDArray[np.float64]

CYLINDERS = ("lift", "jib", "extension")
NQ = 4
NC = 3


@dataclass(frozen=True)
class Body:
    """A rigid body of the boom plane.

    Attributes:
        mass_kg: Mass [kg].
        com_m: Centre of mass (x, y) in the body's planar frame [m].
        inertia_kgm2: Principal inertia about the centre of mass [kg·m²]: (along the boom,
            about the plane normal, about the in-plane transverse axis).
    """

    mass_kg: float
    com_m: tuple[float, float]
    inertia_kgm2: tuple[float, float, float]


@dataclass(frozen=True)
class Cyl:
    """A double-acting cylinder with its valve and friction.

    Attributes:
        bore_m, rod_m: Piston and rod diameter [m].
        closed_m: Pin-to-pin length at zero stroke [m]; stroke_m: stroke [m].
        flow_gain: Valve Qn [m³/(s·V·√Pa)]; fc_n, vc_mps, b_nspm: friction Fc [N], vc [m/s],
            b [N·s/m].
    """

    bore_m: float
    rod_m: float
    closed_m: float
    stroke_m: float
    flow_gain: float
    fc_n: float
    vc_mps: float
    b_nspm: float

    @property
    def a1(self) -> float:
        """Piston area [m²]."""
        return float(np.pi / 4 * self.bore_m ** 2)

    @property
    def a2(self) -> float:
        """Annulus (rod-side) area [m²]."""
        return float(np.pi / 4 * (self.bore_m ** 2 - self.rod_m ** 2))


@dataclass(frozen=True)
class CraneParams:
    """Everything the independent simulation knows about the crane (SI units).

    Points are planar (x, y): ``o1`` in the pillar frame; ``lift_*`` in the lift boom frame
    (origin O1, turned by theta1); ``jib_*`` in the jib frame (origin O2, turned by theta1 +
    theta2); ``ext_*`` in the extension frame (origin = jib's ``ext_attach`` + (L, 0), axes of
    the jib).
    """

    g: float = 9.81
    o1: tuple[float, float] = (-0.09, 1.4261)
    lift_cyl_base: tuple[float, float] = (0.17, 0.386113)        # A, pillar
    lift_cyl_rod: tuple[float, float] = (0.3025, -0.105)         # B, lift boom
    lift_o2: tuple[float, float] = (2.881, 0.0216)               # O2, lift boom
    jib_cyl_base: tuple[float, float] = (1.263, 0.2067)          # C, lift boom
    bracket_pivot: tuple[float, float] = (2.69, -0.0066)         # D, lift boom
    bracket1_m: float = 0.4578                                   # D→E
    bracket2_m: float = 0.48                                     # E→F
    jib_bracket_pin: tuple[float, float] = (-0.095, 0.2404)      # F, jib
    jib_branch: float = 1.0                                      # E left of D→F
    jib_ext_attach: tuple[float, float] = (-0.415, 0.295)        # jib
    ext_cyl_base: tuple[float, float] = (-0.3, 0.295)            # jib (assumed)
    ext_cyl_rod: tuple[float, float] = (1.615, 0.0)              # extension (assumed)
    ext_tip: tuple[float, float] = (2.49, 0.0)                   # extension: load point
    pillar_mass_kg: float = 93.26
    pillar_izz_kgm2: float = 0.79                                # assumed: tube r 0.13 m
    lift: Body = Body(143.66, (1.229, 0.056), (1.5, 67.05, 67.05))
    jib: Body = Body(76.7, (0.6, 0.25), (1.0, 51.0, 51.0))        # COM assumed mid-tube
    ext: Body = Body(58.63, (1.245, 0.0), (0.3, 30.3, 30.3))      # uniform 2.49 m beam
    tool_kg: float = 90.0                                        # grapple + rotator (assumed)
    cyl: tuple[Cyl, Cyl, Cyl] = (
        Cyl(0.100, 0.056, 0.82, 0.535, 2.16e-8, 210.0, 0.005, 330.0),
        Cyl(0.100, 0.056, 1.05, 0.78, 4.05e-8, 210.0, 0.005, 330.0),
        Cyl(0.050, 0.032, 1.5, 1.2, 1.5e-8, 150.0, 0.005, 250.0),   # assumed
    )
    supply_pa: float = 16.0e6
    tank_pa: float = 1.0e5
    relief_pa: float = 18.0e6
    relief_gain: float = 2.0e-10         # relief flow per Pa above relief [m³/(s·Pa)]
    anticav_gain: float = 2.0e-9         # anti-cavitation flow per Pa below tank [m³/(s·Pa)]
    beta_oil_pa: float = 1.65e9
    beta_hose_pa: float = 7.0e8
    dead_volume_m3: float = 1.9e-4
    spool_tau_s: float = 0.02
    dp_laminar_pa: float = 2.0e5         # valve law linear below this pressure drop
    slew_tau_s: float = 0.05             # slewing torque lag (assumed)
    slew_max_nm: float = 12000.0
    slew_fc_nm: float = 300.0
    slew_vc_rps: float = 0.01
    slew_b_nmsprad: float = 200.0
    stop_k_npm: float = 2.0e7            # end-stop stiffness [N/m] and damping [N·s/m]
    stop_c_nspm: float = 2.0e5
    fd_h: float = 1e-6                   # finite-difference steps: Jacobians, ∂M/∂q
    fd_h2: float = 1e-4

    @property
    def beta_pa(self) -> float:
        """Effective bulk modulus, oil and hose in series [Pa]."""
        return 1.0 / (1.0 / self.beta_oil_pa + 1.0 / self.beta_hose_pa)

    def frictionless(self) -> CraneParams:
        """The same crane without any friction (cylinders and slewing drive)."""
        cyl = tuple(replace(c, fc_n=0.0, b_nspm=0.0) for c in self.cyl)
        return replace(self, cyl=cyl, slew_fc_nm=0.0, slew_b_nmsprad=0.0)  # type: ignore[arg-type]


PATU655 = CraneParams()
"""The PATU 655 as published (reference/patu655.md); values the reference leaves open
("assumed") set as in the project's machine file, so the comparison tests physics, not guesses."""


# --- kinematics ------------------------------------------------------------------------------

def _rot(a: F64, p: tuple[float, float] | tuple[F64, F64]) -> tuple[F64, F64]:
    c, s = np.cos(a), np.sin(a)
    return c * p[0] - s * p[1], s * p[0] + c * p[1]


def _four_bar_e(p: CraneParams, th2: F64) -> tuple[F64, F64]:
    """Rod end E of the jib cylinder in the lift-boom frame, shape (...,) each [m]: the
    intersection of |E − D| = bracket 1 and |E − F| = bracket 2 on the side ``jib_branch`` of
    the line D→F (+1: left). The reference's rule "E on C's side of D→F" gives +1 from the
    straight jib down to theta2 ≈ −131°; below that C crosses the line and the rule would jump
    to the other branch (a length discontinuity of up to 0.28 m at −170°), so the side is
    held fixed: the assembly cannot change branch while it moves."""
    fx, fy = _rot(th2, p.jib_bracket_pin)
    fx, fy = fx + p.lift_o2[0], fy + p.lift_o2[1]
    dx, dy = fx - p.bracket_pivot[0], fy - p.bracket_pivot[1]
    d = np.hypot(dx, dy)
    a = (p.bracket1_m ** 2 - p.bracket2_m ** 2 + d ** 2) / (2 * d)
    h = np.sqrt(np.maximum(p.bracket1_m ** 2 - a ** 2, 0.0))
    ux, uy = dx / d, dy / d
    mx, my = p.bracket_pivot[0] + a * ux, p.bracket_pivot[1] + a * uy
    side = p.jib_branch
    return mx - side * h * uy, my + side * h * ux


def cylinder_lengths(p: CraneParams, q: F64) -> F64:
    """Pin-to-pin lengths of lift, jib and extension cylinder, shape (..., 3) [m], q (..., 4)."""
    th1, th2, ext = q[..., 1], q[..., 2], q[..., 3]
    bx, by = _rot(th1, p.lift_cyl_rod)
    l1 = np.hypot(p.o1[0] + bx - p.lift_cyl_base[0], p.o1[1] + by - p.lift_cyl_base[1])
    ex, ey = _four_bar_e(p, th2)
    l2 = np.hypot(ex - p.jib_cyl_base[0], ey - p.jib_cyl_base[1])
    rx = p.jib_ext_attach[0] + ext + p.ext_cyl_rod[0]
    ry = p.jib_ext_attach[1] + p.ext_cyl_rod[1]
    l3 = np.hypot(rx - p.ext_cyl_base[0], ry - p.ext_cyl_base[1])
    return np.stack([l1, l2, l3], axis=-1)


def points(p: CraneParams, q: F64) -> F64:
    """World positions of the point masses, shape (..., 5, 3) [m]: pillar, lift, jib and
    extension centres of mass, and the tip (tool + payload)."""
    th0, th1, ext = q[..., 0], q[..., 1], q[..., 3]
    a2 = th1 + q[..., 2]
    lx, ly = _rot(th1, p.lift.com_m)
    o2x, o2y = _rot(th1, p.lift_o2)
    o2x, o2y = o2x + p.o1[0], o2y + p.o1[1]
    jx, jy = _rot(a2, p.jib.com_m)
    ox, oy = _rot(a2, (p.jib_ext_attach[0] + ext, np.full_like(ext, p.jib_ext_attach[1])))
    ox, oy = ox + o2x, oy + o2y
    xx, xy = _rot(a2, p.ext.com_m)
    tx, ty = _rot(a2, p.ext_tip)
    zero = np.zeros_like(th0)
    px = np.stack([zero, p.o1[0] + lx, o2x + jx, ox + xx, ox + tx], axis=-1)
    py = np.stack([zero + 0.7, p.o1[1] + ly, o2y + jy, oy + xy, oy + ty], axis=-1)
    c0, s0 = np.cos(th0)[..., None], np.sin(th0)[..., None]
    return np.stack([px * c0, px * s0, py], axis=-1)


def masses(p: CraneParams, payload_kg: float) -> F64:
    """Masses of :func:`points`, shape (5,) [kg]."""
    return np.array([p.pillar_mass_kg, p.lift.mass_kg, p.jib.mass_kg, p.ext.mass_kg,
                     p.tool_kg + payload_kg])


def _fd_jacobian(f: Callable[[F64], F64], q: F64, h: float) -> F64:
    """Central-difference Jacobian of f at configurations q (..., 4): shape f(q).shape + (4,)."""
    e = np.eye(NQ) * h
    qp = q[..., None, :] + e               # (..., 4, 4): perturbation k in row k
    qm = q[..., None, :] - e
    fp, fm = f(qp), f(qm)                  # (..., 4, *out)
    d = (fp - fm) / (2 * h)
    return np.moveaxis(d, q.ndim - 1, -1)


def _rot_mass(p: CraneParams, q: F64) -> F64:
    """Rotational part Σ J_ωᵀ·I·J_ω of the mass matrix, shape (..., 4, 4) [kg·m², kg·m]."""
    m = np.zeros(q.shape[:-1] + (NQ, NQ))
    m[..., 0, 0] = p.pillar_izz_kgm2
    for body, a, cols in ((p.lift, q[..., 1], (1,)),
                          (p.jib, q[..., 1] + q[..., 2], (1, 2)),
                          (p.ext, q[..., 1] + q[..., 2], (1, 2))):
        ixx, iyy, izz = body.inertia_kgm2
        # slew rate in body axes: (sin a, 0, cos a); planar rates: (0, −1, 0)
        m[..., 0, 0] += ixx * np.sin(a) ** 2 + izz * np.cos(a) ** 2
        for i in cols:
            for j in cols:
                m[..., i, j] += iyy
    return m


def mass_matrix(p: CraneParams, q: F64, payload_kg: float) -> F64:
    """M(q), shape (..., 4, 4), q (..., 4)."""
    jac = _fd_jacobian(lambda x: points(p, x), q, p.fd_h)          # (..., 5, 3, 4)
    mk = masses(p, payload_kg)
    mt: F64 = np.einsum("b,...bxi,...bxj->...ij", mk, jac, jac)
    return mt + _rot_mass(p, q)


@dataclass(frozen=True)
class Dynamics:
    """M, Coriolis/centrifugal c, gravity Q_g and the cylinders' geometry at one state."""

    m: F64          # (4, 4)
    c: F64          # (4,)
    qg: F64         # (4,)
    length: F64     # (3,) pin-to-pin [m]
    dldq: F64       # (3, 4)


def dynamics(p: CraneParams, q: F64, qd: F64, payload_kg: float) -> Dynamics:
    """The Lagrangian terms at one state q, qd (4,) with the payload at the tip [kg]."""
    h2 = p.fd_h2
    qs = np.concatenate([q[None], q + np.eye(NQ) * h2, q - np.eye(NQ) * h2])   # (9, 4)
    ms = mass_matrix(p, qs, payload_kg)
    m = ms[0]
    dm = (ms[1:1 + NQ] - ms[1 + NQ:]) / (2 * h2)       # dm[k] = ∂M/∂q_k
    # c_i = Σ_jk (∂M_ij/∂q_k − ½ ∂M_jk/∂q_i) qd_j qd_k
    c = np.einsum("kij,j,k->i", dm, qd, qd) - 0.5 * np.einsum("ijk,j,k->i", dm, qd, qd)
    jac = _fd_jacobian(lambda x: points(p, x), q, p.fd_h)      # (5, 3, 4)
    grav = np.array([0.0, 0.0, -p.g])
    qg = np.einsum("b,bxi,x->i", masses(p, payload_kg), jac, grav)
    length = cylinder_lengths(p, q)
    dldq = _fd_jacobian(lambda x: cylinder_lengths(p, x), q, p.fd_h)
    return Dynamics(m, c, qg, length, dldq)


def potential_energy(p: CraneParams, q: F64, payload_kg: float) -> F64:
    """Gravity potential Σ m·g·z, shape (...,) [J]."""
    z = points(p, q)[..., 2]
    return np.asarray(p.g * (z @ masses(p, payload_kg)), dtype=np.float64)


def joints_from_rods(p: CraneParams, s: F64, slew: float = 0.0) -> F64:
    """q (4,) that puts the rods at strokes s (3,) [m] (each cylinder drives one joint)."""
    q = np.array([slew, 0.5, -1.5, 0.3])
    brackets = ((1, -0.7, 1.9), (2, -3.0, -0.01), (3, -0.5, 1.7))
    for k, (j, lo, hi) in enumerate(brackets):
        def f(x: float, k: int = k, j: int = j) -> float:
            qq = q.copy()
            qq[j] = x
            return float(cylinder_lengths(p, qq)[k] - p.cyl[k].closed_m - s[k])
        q[j] = brentq(f, lo, hi, xtol=1e-13)
    return q


# --- hydraulics ------------------------------------------------------------------------------

def _orifice(p: CraneParams, dp: F64 | float) -> F64:
    """sign(Δp)·sqrt(|Δp|), linear below ``dp_laminar_pa`` (smooth) [√Pa]."""
    d = np.asarray(dp, dtype=np.float64)
    return np.asarray(d / np.sqrt(np.sqrt(d * d + p.dp_laminar_pa ** 2)), dtype=np.float64)


def valve_flows(p: CraneParams, u: F64, pa: F64, pb: F64, cyl: tuple[Cyl, ...]) -> tuple[F64, F64]:
    """Flows into chamber A and B [m³/s], spool voltages u (3,) [V]: a critically lapped 4/3
    valve, P→A and B→T for u > 0, P→B and A→T for u < 0, plus relief and anti-cavitation."""
    k = np.array([c.flow_gain for c in cyl])
    up, un = np.maximum(u, 0.0), np.minimum(u, 0.0)
    qa = k * (up * _orifice(p, p.supply_pa - pa) + un * _orifice(p, pa - p.tank_pa))
    qb = k * (-up * _orifice(p, pb - p.tank_pa) - un * _orifice(p, p.supply_pa - pb))
    for pc, qc in ((pa, qa), (pb, qb)):
        qc -= p.relief_gain * np.maximum(pc - p.relief_pa, 0.0)
        qc += p.anticav_gain * np.maximum(p.tank_pa - pc, 0.0)
    return qa, qb


def friction(v: F64 | float, fc: F64 | float, vc: F64 | float, b: F64 | float) -> F64:
    """Coulomb (smooth) + viscous friction opposing v [N or N·m]."""
    return np.asarray(fc * np.tanh(np.asarray(v) / vc) + b * np.asarray(v), dtype=np.float64)


# --- state and right-hand side ---------------------------------------------------------------

# state x: q (4), qd (4), pA (3), pB (3), spool u (3) [V], slew torque T [N·m]
SQ, SQD, SPA, SPB, SU, ST = slice(0, 4), slice(4, 8), slice(8, 11), slice(11, 14), slice(14, 17), 17
NX = 18

Commands = Callable[[float, F64], tuple[F64, float]]
"""(t, x) → (valve voltages (3,) [V], slew torque command [N·m])."""


@dataclass(frozen=True)
class Forces:
    """Forces at one state: cylinder force F = pA·A1 − pB·A2 − F_fr (3,) [N], end-stop force
    (3,) [N], rod positions s (3,) [m] and velocities v (3,) [m/s]."""

    cylinder: F64
    stop: F64
    s: F64
    v: F64


def cylinder_forces(p: CraneParams, x: F64, dyn: Dynamics) -> Forces:
    """Eq.-1-like cylinder forces and end stops from state x and the geometry in ``dyn``."""
    a1 = np.array([c.a1 for c in p.cyl])
    a2 = np.array([c.a2 for c in p.cyl])
    closed = np.array([c.closed_m for c in p.cyl])
    stroke = np.array([c.stroke_m for c in p.cyl])
    s = dyn.length - closed
    v = dyn.dldq @ x[SQD]
    fr = friction(v, np.array([c.fc_n for c in p.cyl]), np.array([c.vc_mps for c in p.cyl]),
                  np.array([c.b_nspm for c in p.cyl]))
    f = x[SPA] * a1 - x[SPB] * a2 - fr
    pen_lo, pen_hi = np.minimum(s, 0.0), np.maximum(s - stroke, 0.0)
    stop = -p.stop_k_npm * (pen_lo + pen_hi) - p.stop_c_nspm * v * ((pen_lo < 0) | (pen_hi > 0))
    return Forces(f, stop, s, v)


def rhs(p: CraneParams, t: float, x: F64, payload_kg: float, commands: Commands) -> F64:
    """dx/dt of the state x (18,)."""
    q, qd = x[SQ], x[SQD]
    dyn = dynamics(p, q, qd, payload_kg)
    fo = cylinder_forces(p, x, dyn)
    tau = dyn.qg + dyn.dldq.T @ (fo.cylinder + fo.stop)
    tau[0] += x[ST] - float(friction(qd[0], p.slew_fc_nm, p.slew_vc_rps, p.slew_b_nmsprad))
    qdd = np.linalg.solve(dyn.m, tau - dyn.c)
    u_cmd, t_cmd = commands(t, x)
    qa, qb = valve_flows(p, x[SU], x[SPA], x[SPB], p.cyl)
    a1 = np.array([c.a1 for c in p.cyl])
    a2 = np.array([c.a2 for c in p.cyl])
    stroke = np.array([c.stroke_m for c in p.cyl])
    s = np.clip(fo.s, 0.0, stroke)
    va = p.dead_volume_m3 + a1 * s
    vb = p.dead_volume_m3 + a2 * (stroke - s)
    dx = np.empty(NX)
    dx[SQ] = qd
    dx[SQD] = qdd
    dx[SPA] = p.beta_pa / va * (qa - a1 * fo.v)
    dx[SPB] = p.beta_pa / vb * (qb + a2 * fo.v)
    dx[SU] = (np.clip(u_cmd, -10.0, 10.0) - x[SU]) / p.spool_tau_s
    dx[ST] = (float(np.clip(t_cmd, -p.slew_max_nm, p.slew_max_nm)) - x[ST]) / p.slew_tau_s
    return dx


def holding_state(p: CraneParams, q: F64, payload_kg: float, p_low_pa: float = 2.0e6) -> F64:
    """A state at rest at q: chamber pressures that hold the boom against gravity (the lower
    chamber at ``p_low_pa``), spools closed, no slew torque. Shape (18,)."""
    dyn = dynamics(p, q, np.zeros(NQ), payload_kg)
    # each cylinder drives one joint: F_k·∂ℓ_k/∂q_j(k) = −Q_g,j(k)
    need = np.array([-dyn.qg[1] / dyn.dldq[0, 1], -dyn.qg[2] / dyn.dldq[1, 2],
                     -dyn.qg[3] / dyn.dldq[2, 3]])
    x = np.zeros(NX)
    x[SQ] = q
    for k, c in enumerate(p.cyl):
        if need[k] >= 0:
            x[SPB.start + k] = p_low_pa
            x[SPA.start + k] = (need[k] + p_low_pa * c.a2) / c.a1
        else:
            x[SPA.start + k] = p_low_pa
            x[SPB.start + k] = (p_low_pa * c.a1 - need[k]) / c.a2
    return x


# --- simulation ------------------------------------------------------------------------------

@dataclass(frozen=True)
class Scenario:
    """A run: duration [s], initial state (18,), commands, payload steps [(t_s, kg), …] (the
    payload before the first step is ``payload0_kg``)."""

    name: str
    duration_s: float
    x0: F64
    commands: Commands
    payload0_kg: float = 0.0
    payload_steps: tuple[tuple[float, float], ...] = ()


@dataclass(frozen=True)
class Run:
    """Sampled output of :func:`simulate` (n samples at ``rate_hz``).

    Attributes:
        t_s: (n,) [s from start]. q, qd: (n, 4). qdd: (n, 4) (from the equations of motion).
        pa_pa, pb_pa: chamber pressures (n, 3) [Pa]. length_m: pin-to-pin lengths (n, 3) [m].
        s_m, v_mps: rod position (stroke) and velocity (n, 3). force_n: cylinder force
        pA·A1 − pB·A2 − F_fr (n, 3) [N]. stop_n: end-stop force (n, 3) [N] (0 off the stops).
        slew_torque_nm: drive torque (n,). payload_kg: (n,). energy_j: kinetic + gravity (n,).
        nfev: right-hand-side evaluations.
    """

    name: str
    t_s: F64
    q: F64
    qd: F64
    qdd: F64
    pa_pa: F64
    pb_pa: F64
    length_m: F64
    s_m: F64
    v_mps: F64
    force_n: F64
    stop_n: F64
    slew_torque_nm: F64
    payload_kg: F64
    energy_j: F64
    nfev: int = 0

    def save(self, path: str) -> None:
        """Write to an ``.npz`` file."""
        arrays = {k: getattr(self, k) for k in self.__dataclass_fields__
                  if k not in ("name", "nfev")}
        np.savez(path, name=np.array(self.name), nfev=np.array(self.nfev), **arrays)

    @staticmethod
    def load(path: str) -> Run:
        """Read a file of :meth:`save`."""
        with np.load(path) as z:
            kw = {k: z[k] for k in z.files if k not in ("name", "nfev")}
            return Run(name=str(z["name"]), nfev=int(z["nfev"]), **kw)


def simulate(p: CraneParams, sc: Scenario, rate_hz: float = 100.0, max_step_s: float = 2e-3,
             method: str = "LSODA", rtol: float = 1e-7, atol: F64 | None = None) -> Run:
    """Integrate the scenario and sample it at ``rate_hz``.

    Args:
        p: Crane parameters.
        sc: Scenario.
        rate_hz: Output rate [Hz].
        max_step_s: Largest integrator step [s].
        method: ``solve_ivp`` method (stiff-aware: LSODA, Radau, BDF).
        rtol, atol: Tolerances (atol default: 1e-8 m or rad, 1e-7 per s, 1 Pa, 1e-6 V, 1e-3 N·m).
    """
    if atol is None:
        atol = np.concatenate([np.full(4, 1e-8), np.full(4, 1e-7), np.full(6, 1.0),
                               np.full(3, 1e-6), [1e-3]])
    n = int(round(sc.duration_s * rate_hz)) + 1
    t_out = np.arange(n) / rate_hz
    edges = [0.0] + [t for t, _ in sc.payload_steps if 0 < t < sc.duration_s] + [sc.duration_s]
    masses_kg = [sc.payload0_kg] + [m for t, m in sc.payload_steps if 0 < t < sc.duration_s]
    xs = np.empty((n, NX))
    pay = np.empty(n)
    x = sc.x0.astype(np.float64).copy()
    nfev = 0
    for seg, (t0, t1) in enumerate(zip(edges[:-1], edges[1:], strict=True)):
        m = masses_kg[seg]
        last = seg == len(edges) - 2
        sel = (t_out >= t0) & ((t_out < t1) | (last & (t_out <= t1)))
        sol = solve_ivp(lambda t, y, m=m: rhs(p, t, y, m, sc.commands), (t0, t1), x,
                        method=method, max_step=max_step_s, rtol=rtol, atol=atol,
                        dense_output=True)
        if not sol.success:
            raise RuntimeError(f"{sc.name}: integration failed at t={sol.t[-1]:.3f} s: "
                               f"{sol.message}")
        nfev += int(sol.nfev)
        if sel.any():
            xs[sel] = sol.sol(t_out[sel]).T
        pay[sel] = m
        x = np.asarray(sol.y[:, -1], dtype=np.float64)
    return _sampled(p, sc.name, t_out, xs, pay, nfev)


def _sampled(p: CraneParams, name: str, t: F64, xs: F64, pay: F64, nfev: int) -> Run:
    n = t.shape[0]
    qdd = np.empty((n, NQ))
    length = np.empty((n, NC))
    s = np.empty((n, NC))
    v = np.empty((n, NC))
    force = np.empty((n, NC))
    stop = np.empty((n, NC))
    kin = np.empty(n)
    zero = lambda t, x: (np.zeros(NC), 0.0)  # noqa: E731 — commands do not enter qdd
    for i in range(n):
        x = xs[i]
        dyn = dynamics(p, x[SQ], x[SQD], float(pay[i]))
        fo = cylinder_forces(p, x, dyn)
        qdd[i] = rhs(p, float(t[i]), x, float(pay[i]), zero)[SQD]
        length[i], s[i], v[i], force[i], stop[i] = dyn.length, fo.s, fo.v, fo.cylinder, fo.stop
        kin[i] = 0.5 * x[SQD] @ dyn.m @ x[SQD]
    energy = kin + np.array([potential_energy(p, xs[i, SQ], float(pay[i])) for i in range(n)])
    return Run(name, t, xs[:, SQ].copy(), xs[:, SQD].copy(), qdd, xs[:, SPA].copy(),
               xs[:, SPB].copy(), length, s, v, force, stop, xs[:, ST].copy(), pay, energy, nfev)
