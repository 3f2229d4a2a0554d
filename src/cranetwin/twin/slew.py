"""Slew angle from the measured slewing torque, when the machine sends no angle (paper's case).

The slew axis is vertical, so gravity does no work on theta0 and the kinetic energy does not
depend on theta0: its generalised momentum ``p0 = Σ_j M_0j(q)·qd_j`` obeys::

    dp0/dt = tau_drive − F_fr(qd0)      (friction per Eq. 2 with the drive's Fc, vc, b)

so theta0 is integrated from the torque without the boom accelerations: qd0 =
(p0 − Σ_{j≠0} M_0j·qd_j) / M_00, trapezoidal in the torque and theta0, friction explicit. The
machine is assumed at rest at the start of the recording (p0 = 0) with theta0 = ``theta0_initial``;
an angle integrated from a torque drifts (a random walk driven by torque noise), which is why a
slew-angle channel is used whenever the machine sends one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt
from numba import njit

from cranetwin.physics.actuator import eq2_friction

if TYPE_CHECKING:
    from cranetwin.twin.plan import ReplayPlan

F64 = npt.NDArray[np.float64]


@dataclass
class SlewState:
    """Integrator state after the last integrated sample.

    Attributes:
        momentum: p0 [kg·m²/s].
        theta0: Slew angle [rad].
        velocity: qd0 [rad/s].
        torque: Drive torque at that sample [N·m].
        started: False until the first sample has been integrated.
    """

    momentum: float = 0.0
    theta0: float = 0.0
    velocity: float = 0.0
    torque: float = 0.0
    started: bool = False


@njit(cache=True)
def _integrate(dt, tau, m00, coupling, fc, vc, b, state, theta, thd):  # type: ignore[no-untyped-def]
    p, th, vprev, tprev, started = state[0], state[1], state[2], state[3], state[4]
    for k in range(tau.shape[0]):
        if started > 0.5:
            fr = eq2_friction(vprev, fc, vc, b)
            p = p + dt * (0.5 * (tprev + tau[k]) - fr)
            v = (p - coupling[k]) / m00[k]
            th = th + 0.5 * dt * (vprev + v)
        else:
            v = (p - coupling[k]) / m00[k]
            started = 1.0
        theta[k] = th
        thd[k] = v
        vprev = v
        tprev = tau[k]
    state[0], state[1], state[2], state[3], state[4] = p, th, vprev, tprev, started


def integrate_slew(
    dt: float,
    torque: F64,
    m00: F64,
    coupling: F64,
    coulomb: float,
    coulomb_velocity: float,
    viscous: float,
    state: SlewState,
) -> tuple[F64, F64]:
    """Integrate theta0 over consecutive samples, continuing from ``state`` (updated in place).

    Args:
        dt: Sample period [s].
        torque: Measured drive torque, shape (n,) [N·m].
        m00: Mass-matrix entry M_00 at each sample, shape (n,) [kg·m²].
        coupling: Σ_{j≠0} M_0j·qd_j at each sample, shape (n,) [kg·m²/s].
        coulomb, coulomb_velocity, viscous: Drive friction Fc [N·m], vc [rad/s], b [N·m·s/rad].
        state: Integrator state; on the first call p0 = ``state.momentum`` at the first sample.

    Returns:
        (theta0, qd0), each shape (n,) [rad, rad/s].
    """
    n = torque.shape[0]
    theta = np.empty(n)
    thd = np.empty(n)
    if n == 0:
        return theta, thd
    st = np.array([state.momentum, state.theta0, state.velocity, state.torque,
                   1.0 if state.started else 0.0])
    _integrate(float(dt), np.ascontiguousarray(torque, dtype=np.float64),
               np.ascontiguousarray(m00, dtype=np.float64),
               np.ascontiguousarray(coupling, dtype=np.float64),
               float(coulomb), float(coulomb_velocity), float(viscous), st, theta, thd)
    state.momentum, state.theta0, state.velocity, state.torque = (float(x) for x in st[:4])
    state.started = True
    return theta, thd


def integrate_free_joints(plan: ReplayPlan, dt: float, motion: tuple[F64, F64], mm: F64,
                          torques: F64, states: list[SlewState]) -> F64:
    """Angles of the integrated free joints (``plan.integrated``) over consecutive samples.

    Each joint j is integrated as the slew above (:func:`integrate_slew`): its momentum
    p_j = Σ_k M_jk·qd_k obeys dp_j/dt = tau_j − F_fr,j, and qd_j = (p_j − Σ_{k≠j} M_jk·qd_k) /
    M_jj with its own diagonal inertia M_jj and coupling. The joints are integrated one after
    the other in drive order, and each one's velocities enter the couplings of the joints
    after it. Neglected: the coupling M_jk·qd_k of a joint j to the integrated joints k after
    it, and to free joints whose angle is sent (their rates are 0 in ``motion``); M is taken
    with every free joint at 0. Exact for a vertical slew axis alone (gravity does no work on
    it and M does not depend on its angle); for another joint, exact only if its axis is
    vertical or its bodies' centre of mass lies on it, and if M does not depend on its angle.
    Put the heavy joint first: its M_jj dwarfs the couplings to light joints after it
    (a tip rotator), while theirs to it is kept.

    Args:
        plan: The replay plan.
        dt: Sample period [s].
        motion: (q, qd) at the samples, (n, n_j), the integrated joints' entries 0.
        mm: Mass matrices at the samples, (n, n_j, n_j) [kg·m², kg·m, kg].
        torques: Drive torque of each integrated joint (n, n_int) [N·m] (0 where not sent).
        states: One integrator state per integrated joint, updated in place.

    Returns:
        Angles, shape (n, n_int) [rad].
    """
    qd = motion[1].copy() if plan.n_int > 1 else motion[1]
    nj = plan.machine.n_joints
    theta = np.empty((qd.shape[0], plan.n_int))
    for i, d in enumerate(plan.integrated):
        j0 = plan.drive_joints[d]
        # column j0 of M (= row j0, M symmetric)
        row = mm[:, :, j0]
        others = [j for j in range(nj) if j != j0]
        coupling = np.einsum("nj,nj->n", row[:, others], qd[:, others])
        fr = plan.machine.torque_drives[d].friction
        theta[:, i], rate = integrate_slew(dt, torques[:, i], row[:, j0], coupling, fr.coulomb,
                                           fr.coulomb_velocity, fr.viscous, states[i])
        if i + 1 < plan.n_int:
            qd[:, j0] = rate
    return theta
