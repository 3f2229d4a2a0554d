"""An independent model of a PATU 655-class knuckle-boom crane (numpy + scipy only): parameters,
kinematics and the Lagrangian equations of motion. :mod:`cranetwin.testing.indep_sim` adds the
hydraulics and integrates it.

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
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt
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
