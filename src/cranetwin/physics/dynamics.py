"""Inverse dynamics by the recursive Newton–Euler formulation, vectorised over time; mass
matrix and bias forces for forward dynamics.

Equation of motion (paper Eq. 3, in joint coordinates X = [theta0, theta1, theta2, L], Eq. 4)::

    M(q)·qdd + C(q, qd)·qd + g(q) = tau

``inverse_dynamics`` evaluates the right-hand side for given motion; ``mass_matrix`` and
``bias_forces`` (= C·qd + g) give the pieces the simulator needs to solve for qdd. The tool
mass is always included; the payload [kg] is a point mass at ``machine.load_point`` and may vary
with time. The loops over samples run in numba kernels (:mod:`cranetwin.physics.kernels`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from cranetwin.errors import PhysicsError
from cranetwin.model import Machine
from cranetwin.physics import kernels as K
from cranetwin.physics.chain import ChainParams, compile_chain
from cranetwin.physics.kinematics import as_columns, as_joint_array

F64 = npt.NDArray[np.float64]
RneaKernels = tuple[Callable[..., None], Callable[..., None]]

_log = logging.getLogger(__name__)


def rnea_kernels(params: ChainParams, specialised: bool = True) -> RneaKernels:
    """``(rnea_batch, rnea_tau_batch)`` of :func:`batch_kernels` (their ``rnea`` and
    ``rnea_tau``): ``rnea_batch(q, qd, qdd, payload, tau, wrench)``, ``rnea_tau_batch(q, qd,
    qdd, payload, tau)`` on contiguous float64 arrays."""
    k = batch_kernels(params, specialised)
    return k.rnea, k.rnea_tau


class BatchKernels(NamedTuple):
    """A machine's batch kernels (loops over the rows of contiguous float64 arrays; q, qd,
    qdd, acc (n, nj); payload (n,) [kg]; tau (n, nj); wrench (n, nj, 6); mm (n, nj, nj)):

    * ``rnea(q, qd, qdd, payload, tau, wrench)``: inverse dynamics with reaction wrenches;
    * ``rnea_tau(q, qd, qdd, payload, tau)``: joint loads only;
    * ``rnea_payload(q, qd, qdd, tau0, tau1)``: loads without payload and with 1 kg;
    * ``rnea_lin(q, acc, payload, rows, wrench)``: adds the wrenches' part linear in the
      accelerations (qd = 0, no gravity) at ``acc`` on the rows where ``rows`` (n,) is true;
    * ``mass_matrix(q, payload, mm)``: M(q).
    """

    rnea: Callable[..., None]
    rnea_tau: Callable[..., None]
    rnea_payload: Callable[..., None]
    rnea_lin: Callable[..., None]
    mass_matrix: Callable[..., None]


def generic_batch_kernels(params: ChainParams) -> BatchKernels:
    """:class:`BatchKernels` of the generic kernels (:mod:`kernels`) bound to ``params``."""
    chain = params.chain
    return BatchKernels(
        rnea=lambda q, qd, qdd, pl, tau, wrench: K.rnea_batch(chain, q, qd, qdd, pl, tau, wrench),
        rnea_tau=lambda q, qd, qdd, pl, tau: K.rnea_tau_batch(chain, q, qd, qdd, pl, tau),
        rnea_payload=lambda q, qd, qdd, t0, t1: K.rnea_payload_batch(chain, q, qd, qdd, t0, t1),
        rnea_lin=lambda q, acc, pl, rows, wrench: K.rnea_lin_batch(chain, q, acc, pl, rows,
                                                                   wrench),
        mass_matrix=lambda q, pl, mm: K.mass_matrix_batch(chain, q, pl, mm),
    )


_BATCH: dict[int, tuple[ChainParams, BatchKernels]] = {}


def batch_kernels(params: ChainParams, specialised: bool = True) -> BatchKernels:
    """The machine's :class:`BatchKernels`: generated for it (straight-line code from its data,
    :mod:`cranetwin.physics.codegen`) with ``specialised``, else, or if generation fails
    (logged; it is an optimisation and never fails the physics), the generic ones."""
    if not specialised:
        return generic_batch_kernels(params)
    hit = _BATCH.get(id(params))
    if hit is not None and hit[0] is params:
        return hit[1]
    try:
        from cranetwin.physics.codegen import specialised_module

        mod = specialised_module(params)
        kernels = BatchKernels(mod.rnea_batch, mod.rnea_tau_batch, mod.rnea_payload_batch,
                               mod.rnea_lin_batch, mod.mass_matrix_batch)
    except Exception as exc:
        _log.warning("specialised kernels unavailable (%s); using the generic ones", exc)
        kernels = generic_batch_kernels(params)
    _BATCH[id(params)] = (params, kernels)
    return kernels


def as_payload(payload_kg: npt.ArrayLike, n: int) -> F64:
    """Payload as a contiguous (n,) float64 array [kg] (a scalar is broadcast).

    Raises:
        PhysicsError: wrong length, negative or non-finite values.
    """
    p = np.asarray(payload_kg, dtype=np.float64)
    if p.ndim == 0:
        p = np.full(n, float(p))
    if p.shape != (n,):
        raise PhysicsError(f"payload_kg: expected a scalar or shape ({n},), got {p.shape}")
    if not np.all(np.isfinite(p)) or np.any(p < 0):
        raise PhysicsError("payload_kg: must be finite and non-negative [kg]")
    return np.ascontiguousarray(p)


def _states(machine: Machine, *arrays: npt.ArrayLike) -> list[F64]:
    names = ("q", "qd", "qdd")
    out = [as_joint_array(machine, a, names[i]) for i, a in enumerate(arrays)]
    if len({a.shape for a in out}) != 1:
        raise PhysicsError(f"{', '.join(names[:len(out)])}: shapes differ "
                           f"({', '.join(str(a.shape) for a in out)})")
    return out


def inverse_dynamics(
    machine: Machine,
    q: npt.ArrayLike,
    qd: npt.ArrayLike,
    qdd: npt.ArrayLike,
    payload_kg: npt.ArrayLike = 0.0,
    out: tuple[F64, F64] | None = None,
) -> tuple[F64, F64]:
    """Joint torques/forces and joint reaction wrenches for a motion (RNEA).

    Args:
        machine: Machine description (gravity from ``machine.machine.gravity_mps2``).
        q: Joint positions, shape (n, n_joints) [rad or m].
        qd: Joint velocities, shape (n, n_joints) [rad/s or m/s].
        qdd: Joint accelerations, shape (n, n_joints) [rad/s² or m/s²].
        payload_kg: Payload at the load point, scalar or shape (n,) [kg] (tool mass added).
        out: Optional preallocated ``(tau, wrench)`` (C-contiguous float64, shapes as returned)
            to write into, e.g. when processing a long history chunk by chunk.

    Returns:
        ``(tau, wrench)``: tau, shape (n, n_joints) [N·m for revolute, N for prismatic joints],
        the generalised force the actuators must supply; wrench, shape (n, n_joints, 6),
        rows [fx, fy, fz, mx, my, mz] [N, N·m]: the force and moment the parent body transmits
        to body i (and everything beyond it) across joint i, expressed in body i's frame at the
        joint origin (Pinocchio's ``data.f[i]``). For n = 3.6 M samples the wrenches take
        690 MB: process long histories in chunks.
    """
    qa, qda, qdda = _states(machine, q, qd, qdd)
    p = compile_chain(machine)
    n = qa.shape[0]
    if out is None:
        tau = np.empty((n, p.n_joints))
        wrench = np.empty((n, p.n_joints, 6))
    else:
        tau, wrench = out
        ok = (tau.shape == (n, p.n_joints) and wrench.shape == (n, p.n_joints, 6)
              and tau.dtype == wrench.dtype == np.float64
              and tau.flags.c_contiguous and wrench.flags.c_contiguous)
        if not ok:
            raise PhysicsError(f"out: expected C-contiguous float64 arrays of shapes "
                               f"({n}, {p.n_joints}) and ({n}, {p.n_joints}, 6)")
    rnea_kernels(p)[0](qa, qda, qdda, as_payload(payload_kg, n), tau, wrench)
    return tau, wrench


def joint_torques(
    machine: Machine,
    q: npt.ArrayLike,
    qd: npt.ArrayLike,
    qdd: npt.ArrayLike,
    payload_kg: npt.ArrayLike = 0.0,
) -> F64:
    """Only the joint torques/forces of :func:`inverse_dynamics`, shape (n, n_joints)."""
    qa, qda, qdda = _states(machine, q, qd, qdd)
    p = compile_chain(machine)
    tau = np.empty((qa.shape[0], p.n_joints))
    rnea_kernels(p)[1](qa, qda, qdda, as_payload(payload_kg, qa.shape[0]), tau)
    return tau


def mass_matrix(machine: Machine, q: npt.ArrayLike, payload_kg: npt.ArrayLike = 0.0) -> F64:
    """Joint-space mass matrix M(q), shape (n, n_joints, n_joints) [kg, kg·m, kg·m²].

    Symmetric positive definite; by the composite-rigid-body algorithm (column j equals the
    RNEA torque for qdd = e_j without gravity and velocity, which the tests check).
    """
    (qa,) = _states(machine, q)
    p = compile_chain(machine)
    out = np.empty((qa.shape[0], p.n_joints, p.n_joints))
    K.mass_matrix_batch(p.chain, qa, as_payload(payload_kg, qa.shape[0]), out)
    return out


def bias_forces(
    machine: Machine, q: npt.ArrayLike, qd: npt.ArrayLike, payload_kg: npt.ArrayLike = 0.0
) -> F64:
    """Bias forces C(q, qd)·qd + g(q), shape (n, n_joints) [N·m or N]: RNEA with qdd = 0."""
    qa, qda = _states(machine, q, qd)
    p = compile_chain(machine)
    out = np.empty((qa.shape[0], p.n_joints))
    K.bias_batch(p.chain, qa, qda, as_payload(payload_kg, qa.shape[0]), out)
    return out


def gravity_torques(machine: Machine, q: npt.ArrayLike, payload_kg: npt.ArrayLike = 0.0) -> F64:
    """Static joint torques/forces g(q) holding the machine still, shape (n, n_joints)."""
    qa = as_joint_array(machine, q)
    return bias_forces(machine, qa, np.zeros_like(qa), payload_kg)


def forward_dynamics(
    machine: Machine,
    q: npt.ArrayLike,
    qd: npt.ArrayLike,
    tau: npt.ArrayLike,
    payload_kg: npt.ArrayLike = 0.0,
) -> F64:
    """Joint accelerations qdd = M⁻¹(tau − C·qd − g), shape (n, n_joints)."""
    qa, qda, ta = _states(machine, q, qd, tau)
    m = mass_matrix(machine, qa, payload_kg)
    b = bias_forces(machine, qa, qda, payload_kg)
    return np.asarray(np.linalg.solve(m, (ta - b)[..., None])[..., 0], dtype=np.float64)


def acceleration_correction(
    machine: Machine,
    q: npt.ArrayLike,
    residual: npt.ArrayLike,
    payload_kg: npt.ArrayLike = 0.0,
    joints: npt.ArrayLike | None = None,
) -> F64:
    """Δqdd that makes a motion agree with the actuator loads (forward dynamics, Eq. 3/4).

    For a motion (q, qd, qdd) and actuator loads tau with residual r = tau − ID(q, qd, qdd),
    qdd + Δqdd with M_DD(q)·Δqdd_D = r_D is the forward-dynamics acceleration
    M⁻¹(tau − C·qd − g) on the joints D whose loads are known (the others keep their qdd:
    Δ = 0 there). Samples with a non-finite residual on a D joint get Δ = 0.

    Args:
        machine: Machine description.
        q: Joint positions, shape (n, n_joints) [rad or m].
        residual: tau − ID torques, shape (n, n_joints) [N·m or N].
        payload_kg: Payload at the load point, scalar or (n,) [kg] (tool mass added).
        joints: Booleans (n_joints,): the joints D; all when None.

    Returns:
        Δqdd, shape (n, n_joints) [rad/s² or m/s²].
    """
    (qa,) = _states(machine, q)
    p = compile_chain(machine)
    ra = np.ascontiguousarray(as_columns("residual", residual, qa.shape[0], p.n_joints))
    use = (np.ones(p.n_joints, dtype=np.bool_) if joints is None
           else np.asarray(joints, dtype=np.bool_).reshape(p.n_joints))
    out = np.empty_like(qa)
    K.accel_correction_batch(p.chain, qa, as_payload(payload_kg, qa.shape[0]), ra, use, out)
    return out
