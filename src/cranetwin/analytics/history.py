"""The input of every analytics function: a load history as plain arrays.

:class:`LoadHistory` is deliberately small and made of numpy arrays only, so analytics never
depends on how the history was produced (twin replay, simulator ground truth, synthetic demo).
Adapters from :class:`cranetwin.twin.TwinResult` and :class:`cranetwin.sim.Recording` live in
:mod:`cranetwin.reports.sources` (they need the kinematics to compute the reach).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from cranetwin.errors import AnalyticsError
from cranetwin.model import Machine

F64 = npt.NDArray[np.float64]


def median_step(t: F64) -> float:
    """Median of the steps of the times ``t`` [s], shape (n,), n ≥ 2: the same value as
    ``float(np.median(np.diff(t)))`` (the middle step, or the mean of the two middle ones), for
    short series without its fixed cost (the steps are sorted as Python floats; long series go
    to ``np.median``). The look-back sizes of the event detector read it per chunk."""
    d = np.diff(t)
    if d.shape[0] > 256 or not np.all(np.isfinite(d)):
        return float(np.median(d))
    s: list[float] = sorted(d.tolist())
    k = len(s) // 2
    return s[k] if len(s) % 2 else (s[k - 1] + s[k]) / 2


def _arr(name: str, value: npt.ArrayLike | None, shape: tuple[int, ...]) -> F64 | None:
    if value is None:
        return None
    a = np.ascontiguousarray(value, dtype=np.float64)
    if a.shape != shape:
        raise AnalyticsError(f"{name}: shape {a.shape}, expected {shape}")
    return a


@dataclass(frozen=True)
class LoadHistory:
    """One contiguous stretch of machine history on a common time grid of n instants.

    Joints in ``machine.joints`` order, cylinders in ``machine.cylinders`` order. Build it with
    :meth:`from_arrays` (which checks the shapes); optional channels may be ``None`` and the
    analyses that need them are skipped.

    Attributes:
        t_s: Times, strictly increasing, shape (n,) [s since the Unix epoch, or simulation s].
        cyl_force: Cylinder forces, > 0 pushes, shape (n, n_cyl) [N].
        joint_moment: Magnitude of the joint reaction moment |(mx, my, mz)|, shape (n, n_joints)
            [N·m] (what ``FatigueDetail.load = "joint:<name>:moment"`` refers to).
        q: Joint positions, shape (n, n_joints) [rad or m].
        qd: Joint velocities, shape (n, n_joints) [rad/s or m/s].
        payload_kg: Payload at the tip, excluding the tool, shape (n,) [kg].
        reach_m: Horizontal distance of the load point from the slewing axis, shape (n,) [m].
        height_m: Height of the load point above the slewing base, shape (n,) [m] or None.
        rod_s: Cylinder rod positions in [0, stroke], shape (n, n_cyl) [m] or None.
        rod_v: Cylinder rod velocities, shape (n, n_cyl) [m/s] or None.
        p_a: Piston-side pressures, shape (n, n_cyl) [Pa] or None.
        p_b: Rod-side pressures, shape (n, n_cyl) [Pa] or None.
        payload_steady: Where ``payload_kg`` is a steady estimate of the load carried,
            shape (n,) bool, or None (everywhere). An estimate from a sliding window smears
            grab and release into ramps; a work cycle's payload is the mean over its steady
            instants only (see :mod:`cranetwin.analytics.productivity`).
        cyl_load: Axial load each cylinder carries by inverse dynamics, τ_ID / (ds/dq),
            shape (n, n_cyl) [N], or None. The chamber pressures' force (``cyl_force`` of a
            replay) misses what the pressures cannot see: a rod driven into its end stop is
            stopped by the stop, not the oil. The shock detector takes it where a rod is at a
            stroke end (:func:`cranetwin.analytics.events.load_force`); a simulator's true
            cylinder force already includes the stop (give None).
    """

    t_s: F64
    cyl_force: F64
    joint_moment: F64
    q: F64
    qd: F64
    payload_kg: F64
    reach_m: F64
    height_m: F64 | None = None
    rod_s: F64 | None = None
    rod_v: F64 | None = None
    p_a: F64 | None = None
    p_b: F64 | None = None
    payload_steady: npt.NDArray[np.bool_] | None = None
    cyl_load: F64 | None = None

    @property
    def n(self) -> int:
        """Number of instants."""
        return int(self.t_s.shape[0])

    @classmethod
    def from_arrays(
        cls,
        machine: Machine,
        *,
        t_s: npt.ArrayLike,
        cyl_force: npt.ArrayLike,
        q: npt.ArrayLike,
        payload_kg: npt.ArrayLike,
        reach_m: npt.ArrayLike,
        joint_wrench: npt.ArrayLike | None = None,
        joint_moment: npt.ArrayLike | None = None,
        qd: npt.ArrayLike | None = None,
        height_m: npt.ArrayLike | None = None,
        rod_s: npt.ArrayLike | None = None,
        rod_v: npt.ArrayLike | None = None,
        p_a: npt.ArrayLike | None = None,
        p_b: npt.ArrayLike | None = None,
        payload_steady: npt.ArrayLike | None = None,
        cyl_load: npt.ArrayLike | None = None,
    ) -> LoadHistory:
        """Check and assemble a history from plain arrays.

        Args:
            machine: The machine the history belongs to (sets n_joints, n_cyl).
            t_s: Times, strictly increasing, shape (n,) [s].
            cyl_force: Cylinder forces, shape (n, n_cyl) [N].
            q: Joint positions, shape (n, n_joints) [rad or m].
            payload_kg: Payload, shape (n,) [kg].
            reach_m: Horizontal reach of the load point, shape (n,) [m].
            joint_wrench: Joint reaction wrenches [fx, fy, fz, mx, my, mz], shape
                (n, n_joints, 6) [N, N·m]; the moment magnitude is taken from it.
            joint_moment: Alternatively the moment magnitudes, shape (n, n_joints) [N·m].
            qd: Joint velocities, shape (n, n_joints); central differences of q if None.
            height_m, rod_s, rod_v, p_a, p_b: Optional channels, see the class docstring.
                rod_v is differentiated from rod_s if only rod_s is given.
            payload_steady: Where the payload estimate is steady, shape (n,) bool (None:
                everywhere).
            cyl_load: Cylinder load forces by inverse dynamics, shape (n, n_cyl) [N] (None:
                ``cyl_force`` is the shock detector's force).

        Raises:
            AnalyticsError: A shape is wrong, times are not strictly increasing, a value is
                not finite, or neither joint_wrench nor joint_moment is given.
        """
        t = np.ascontiguousarray(t_s, dtype=np.float64)
        if t.ndim != 1 or t.shape[0] < 1:
            raise AnalyticsError(f"t_s: shape {t.shape}, expected (n,) with n >= 1")
        n, nj, nc = t.shape[0], machine.n_joints, len(machine.cylinders)
        if n > 1 and not np.all(np.diff(t) > 0):
            raise AnalyticsError("t_s must be strictly increasing")
        if joint_moment is None:
            if joint_wrench is None:
                raise AnalyticsError(
                    "give joint_wrench (n, n_joints, 6) or joint_moment (n, n_joints)")
            w = _arr("joint_wrench", joint_wrench, (n, nj, 6))
            assert w is not None
            jm = np.sqrt(np.einsum("njk,njk->nj", w[:, :, 3:], w[:, :, 3:]))
        else:
            jm_ = _arr("joint_moment", joint_moment, (n, nj))
            assert jm_ is not None
            jm = jm_
        qa = _arr("q", q, (n, nj))
        assert qa is not None
        qda = _arr("qd", qd, (n, nj))
        if qda is None:
            qda = np.gradient(qa, t, axis=0) if n > 1 else np.zeros_like(qa)
        rs = _arr("rod_s", rod_s, (n, nc))
        rv = _arr("rod_v", rod_v, (n, nc))
        if rv is None and rs is not None:
            rv = np.gradient(rs, t, axis=0) if n > 1 else np.zeros_like(rs)
        f = _arr("cyl_force", cyl_force, (n, nc))
        pl = _arr("payload_kg", payload_kg, (n,))
        re = _arr("reach_m", reach_m, (n,))
        assert f is not None and pl is not None and re is not None
        steady = None
        if payload_steady is not None:
            steady = np.ascontiguousarray(payload_steady, dtype=bool)
            if steady.shape != (n,):
                raise AnalyticsError(f"payload_steady: shape {steady.shape}, expected {(n,)}")
        h = cls(t_s=t, cyl_force=f, joint_moment=jm, q=qa, qd=qda, payload_kg=pl, reach_m=re,
                height_m=_arr("height_m", height_m, (n,)), rod_s=rs, rod_v=rv,
                p_a=_arr("p_a", p_a, (n, nc)), p_b=_arr("p_b", p_b, (n, nc)),
                payload_steady=steady, cyl_load=_arr("cyl_load", cyl_load, (n, nc)))
        if h.cyl_load is not None and not np.all(np.isfinite(h.cyl_load)):
            raise AnalyticsError("cyl_load: contains NaN or inf; bridge gaps before analytics")
        for name in ("t_s", "cyl_force", "joint_moment", "q", "qd", "payload_kg", "reach_m"):
            if not np.all(np.isfinite(getattr(h, name))):
                raise AnalyticsError(f"{name}: contains NaN or inf; bridge gaps before analytics")
        return h

    def slice(self, start: int, stop: int) -> LoadHistory:
        """Instants ``start:stop`` as a new history (views, no copy)."""
        def cut(a: F64 | None) -> F64 | None:
            return None if a is None else a[start:stop]
        return replace(
            self, t_s=self.t_s[start:stop], cyl_force=self.cyl_force[start:stop],
            joint_moment=self.joint_moment[start:stop], q=self.q[start:stop],
            qd=self.qd[start:stop], payload_kg=self.payload_kg[start:stop],
            reach_m=self.reach_m[start:stop], height_m=cut(self.height_m),
            rod_s=cut(self.rod_s), rod_v=cut(self.rod_v), p_a=cut(self.p_a), p_b=cut(self.p_b),
            payload_steady=None if self.payload_steady is None
            else self.payload_steady[start:stop], cyl_load=cut(self.cyl_load))

    def load_channel(self, machine: Machine, spec: str) -> F64:
        """The load history a ``FatigueDetail.load`` string names.

        Args:
            machine: The machine (to resolve names to columns).
            spec: ``"cylinder:<name>:force"`` [N] or ``"joint:<name>:moment"`` [N·m].

        Returns:
            The load, shape (n,).

        Raises:
            AnalyticsError: Unknown kind or name.
        """
        parts = spec.split(":")
        if len(parts) != 3:
            raise AnalyticsError(f"load {spec!r}: expected 'cylinder:<name>:force' or "
                                 "'joint:<name>:moment'")
        kind, name, what = parts
        if kind == "cylinder" and what == "force":
            names = [c.name for c in machine.cylinders]
            if name in names:
                return self.cyl_force[:, names.index(name)]
        elif kind == "joint" and what == "moment":
            names = [j.name for j in machine.joints]
            if name in names:
                return self.joint_moment[:, names.index(name)]
        raise AnalyticsError(f"load {spec!r}: unknown component (cylinders "
                             f"{[c.name for c in machine.cylinders]}, joints "
                             f"{[j.name for j in machine.joints]})")
