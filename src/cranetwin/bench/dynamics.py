"""``cranetwin bench dynamics``: one hour of 1 kHz data through inverse dynamics.

Measures :func:`cranetwin.physics.inverse_dynamics` (joint torques AND the joint reaction
wrenches) over 3.6 M samples of a smooth motion of the built-in crane with a time-varying
payload, on one thread, in chunks (the wrenches of a whole hour alone would take 690 MB; each
chunk's outputs are reused). Input generation is not timed; JIT compile time (or numba's
cache load) is reported apart as ``compile_seconds``.

Baselines in the same run, each as a ratio (> 1: ours is faster):

* ``generic_ratio``: the generic kernel (array-driven, no code generated for the machine) on
  one chunk, against the generated one the physics API uses (``tau_wrench_ns_per_sample`` of
  the bare kernel, without the API's input checks);
* ``pinocchio_batch_ratio``: Pinocchio's C++ RNEA called once for a batch of samples
  (``pinocchio.rneaInParallel`` on a ``ModelPool`` with one thread: no Python per sample), on
  ``pinocchio_batch_samples`` samples. It returns joint torques only, so it is compared with our
  torques-only kernel (``tau_ns_per_sample``); ``pinocchio_batch`` says why when it is not
  callable;
* ``speedup`` (and ``baseline_ns_per_call``): a Python loop of ``pinocchio.rnea``, one call per
  sample, timed on a subset spread over the hour and scaled to all samples; the same subset
  gives ``max_rel_error``. This one includes Python's call overhead per sample.
"""

from __future__ import annotations

import resource
import time
from typing import Any

import numpy as np
import numpy.typing as npt
import typer

from cranetwin.bench import emit
from cranetwin.errors import MissingExtraError
from cranetwin.model import Machine, load_machine
from cranetwin.physics import compile_chain, inverse_dynamics
from cranetwin.physics.dynamics import rnea_kernels

F64 = npt.NDArray[np.float64]


def motion(machine: Machine, t: F64) -> tuple[F64, F64, F64, F64]:
    """A smooth working motion (sum of sines inside the joint limits) and a payload [kg].

    Returns q, qd, qdd of shape (len(t), n_joints) and payload of shape (len(t),).
    """
    lo = np.array([j.lower for j in machine.joints])
    hi = np.array([j.upper for j in machine.joints])
    mid, half = 0.5 * (lo + hi), 0.4 * (hi - lo)
    half[0] = min(half[0], 1.5)
    w = np.array([0.21, 0.37, 0.29, 0.43])[: machine.n_joints] * 2 * np.pi / 10
    ph = np.outer(t, w)
    q = mid + half * np.sin(ph)
    qd = half * w * np.cos(ph)
    qdd = -half * w**2 * np.sin(ph)
    payload = 250.0 + 200.0 * np.sin(2 * np.pi * t / 37.0)
    return q, qd, qdd, payload


def _pin() -> Any:
    """The ``pinocchio`` module (the baseline's library, installed by the ``dev`` extra)."""
    try:
        import pinocchio
    except ImportError as exc:
        raise MissingExtraError("dev", "the Pinocchio baseline of bench dynamics") from exc
    return pinocchio


def pinocchio_model(machine: Machine, payload_kg: float) -> Any:
    """The same chain in Pinocchio (tool + payload as a point inertia on the load body)."""
    pin = _pin()

    model = pin.Model()
    model.gravity.linear = np.asarray(machine.machine.gravity_mps2)
    parent = 0
    for joint, body in zip(machine.joints, machine.chain_bodies(), strict=True):
        axis = np.asarray(joint.axis, dtype=float)
        jm = (pin.JointModelRevoluteUnaligned(axis) if joint.kind == "revolute"
              else pin.JointModelPrismaticUnaligned(axis))
        placement = pin.SE3(pin.rpy.rpyToMatrix(*joint.origin_rpy_rad),
                            np.asarray(joint.origin_m))
        jid = model.addJoint(parent, jm, placement, joint.name)
        model.appendBodyToJoint(jid, pin.Inertia(body.mass_kg, np.asarray(body.com_m),
                                                 np.asarray(body.inertia_kgm2)),
                                pin.SE3.Identity())
        if body.name == machine.load_point.body:
            model.appendBodyToJoint(
                jid, pin.Inertia(machine.load_point.tool_mass_kg + payload_kg,
                                 np.asarray(machine.load_point.point_m), np.zeros((3, 3))),
                pin.SE3.Identity())
        parent = jid
    return model


def _baseline(machine: Machine, t: F64, reps: int) -> tuple[float, float, float]:
    """(seconds per call of a Python loop of pin.rnea, max rel. error of tau, of wrenches)."""
    pin = _pin()

    q, qd, qdd, payload = motion(machine, t)
    # the payload changes the model: Pinocchio needs one model per payload value, so the
    # subset uses the mean payload for the timed loop and per-sample models for the errors
    model = pinocchio_model(machine, float(payload.mean()))
    data = model.createData()
    best = np.inf
    for _ in range(reps):
        t0 = time.perf_counter()
        for k in range(len(t)):
            pin.rnea(model, data, q[k], qd[k], qdd[k])
        best = min(best, (time.perf_counter() - t0) / len(t))
    tau, wrench = inverse_dynamics(machine, q, qd, qdd, payload)
    err_t = err_w = 0.0
    for k in range(0, len(t), max(1, len(t) // 500)):
        m = pinocchio_model(machine, float(payload[k]))
        d = m.createData()
        ref = pin.rnea(m, d, q[k], qd[k], qdd[k])
        ref_w = np.array([d.f[i + 1].vector for i in range(machine.n_joints)])
        err_t = max(err_t, float(np.max(np.abs(tau[k] - ref)) / max(1.0, np.max(np.abs(ref)))))
        err_w = max(err_w, float(np.max(np.abs(wrench[k] - ref_w))
                                 / max(1.0, np.max(np.abs(ref_w)))))
    return best, err_t, err_w


def _pinocchio_batch(machine: Machine, q: F64, qd: F64, qdd: F64, payload: float,
                     reps: int) -> float:
    """Seconds per sample of ``pinocchio.rneaInParallel`` (one thread) over the batch."""
    pin = _pin()

    model = pinocchio_model(machine, payload)
    pool = pin.ModelPool(model, 1)
    qf, qdf, qddf = (np.asfortranarray(x.T) for x in (q, qd, qdd))
    tau = np.asfortranarray(np.empty_like(qf))
    pin.rneaInParallel(1, pool, qf[:, :10], qdf[:, :10], qddf[:, :10],
                       np.asfortranarray(tau[:, :10]))
    best = np.inf
    for _ in range(reps):
        t0 = time.perf_counter()
        pin.rneaInParallel(1, pool, qf, qdf, qddf, tau)
        best = min(best, time.perf_counter() - t0)
    return float(best / q.shape[0])


def run(samples: int = 3_600_000, rate_hz: float = 1000.0, chunk: int = 65_536,
        baseline_samples: int = 20_000, reps: int = 3) -> dict[str, Any]:
    """Run the benchmark and return its figures (see the module docstring)."""
    machine = load_machine("patu655")
    t0 = time.perf_counter()
    params = compile_chain(machine)
    rnea_kernels(params)  # code generation + JIT compile or numba cache load
    probe = np.zeros((1, machine.n_joints))
    inverse_dynamics(machine, probe, probe, probe, 0.0)
    compile_seconds = time.perf_counter() - t0

    tau = np.empty((chunk, machine.n_joints))
    wrench = np.empty((chunk, machine.n_joints, 6))
    best = np.inf
    checksum = 0.0
    for _ in range(reps):
        total = 0.0
        checksum = 0.0
        for start in range(0, samples, chunk):
            n = min(chunk, samples - start)
            t = (start + np.arange(n)) / rate_hz
            q, qd, qdd, payload = motion(machine, t)
            out = (tau[:n], wrench[:n])
            t1 = time.perf_counter()
            inverse_dynamics(machine, q, qd, qdd, payload, out=out)
            total += time.perf_counter() - t1
            checksum = max(checksum, float(np.abs(wrench[:n, :, 3:]).max()))
        best = min(best, total)

    # the bare kernels on one chunk: generated and generic, with wrenches and torques only
    n = min(chunk, samples)
    q, qd, qdd, payload = motion(machine, np.arange(n) / rate_hz)

    def per_sample(fn: Any, *args: Any) -> float:
        fn(*(a[:10] for a in args))
        t = np.inf
        for _ in range(reps):
            t1 = time.perf_counter()
            fn(*args)
            t = min(t, time.perf_counter() - t1)
        return float(t / n * 1e9)

    gen_w, gen_t = rnea_kernels(params)
    generic_w, generic_t = rnea_kernels(params, specialised=False)
    tau_wrench_ns = per_sample(gen_w, q, qd, qdd, payload, tau[:n], wrench[:n])
    tau_ns = per_sample(gen_t, q, qd, qdd, payload, tau[:n])
    generic_ns = per_sample(generic_w, q, qd, qdd, payload, tau[:n], wrench[:n])
    generic_tau_ns = per_sample(generic_t, q, qd, qdd, payload, tau[:n])

    result: dict[str, Any] = {
        "benchmark": "dynamics",
        "machine": machine.name,
        "samples": samples,
        "rate_hz": rate_hz,
        "seconds": best,
        "ns_per_sample": best / samples * 1e9,
        "includes": "joint torques + joint reaction wrenches (n, 4, 6), input checks",
        "chunk_samples": chunk,
        "threads": 1,
        "compile_seconds": compile_seconds,
        "tau_wrench_ns_per_sample": tau_wrench_ns,
        "tau_ns_per_sample": tau_ns,
        "generic_kernel_ns_per_sample": generic_ns,
        "generic_tau_ns_per_sample": generic_tau_ns,
        "generic_ratio": generic_ns / tau_wrench_ns,
        "generic_tau_ratio": generic_tau_ns / tau_ns,
        "pinocchio_batch": None,
        "pinocchio_batch_samples": n,
        "pinocchio_batch_ns_per_sample": None,
        "pinocchio_batch_ratio": None,
        "baseline": "Python loop of pinocchio.rnea, timed on a subset and scaled",
        "baseline_subset_samples": baseline_samples,
        "baseline_seconds": None,
        "speedup": None,
        "max_rel_error": None,
        "max_rel_error_definition": "max over checked samples of max|ours - pinocchio| / "
                                    "max(1, max|pinocchio|), torques and wrenches (data.f)",
    }
    try:
        import pinocchio  # noqa: F401
    except ImportError:
        result["baseline"] = "pinocchio not installed (pip install pin): no baseline"
    else:
        t_sub = np.linspace(0.0, (samples - 1) / rate_hz, baseline_samples)
        per_call, err_t, err_w = _baseline(machine, t_sub, reps)
        result["baseline_seconds"] = per_call * samples
        result["baseline_ns_per_call"] = per_call * 1e9
        result["speedup"] = per_call * samples / best
        result["max_rel_error"] = max(err_t, err_w)
        result["max_rel_error_tau"] = err_t
        result["max_rel_error_wrench"] = err_w
        try:
            batch = _pinocchio_batch(machine, q, qd, qdd, float(payload.mean()), reps)
        except (AttributeError, RuntimeError, TypeError, ValueError) as exc:
            result["pinocchio_batch"] = f"not callable: {exc}"
        else:
            result["pinocchio_batch"] = ("pinocchio.rneaInParallel, 1 thread, ModelPool; "
                                         "torques only, against tau_ns_per_sample")
            result["pinocchio_batch_ns_per_sample"] = batch * 1e9
            result["pinocchio_batch_ratio"] = batch * 1e9 / tau_ns
    result["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    result["max_joint_moment_nm"] = checksum  # keeps the outputs observable
    return result


def register(bench_app: typer.Typer) -> None:
    @bench_app.command("dynamics")
    def dynamics(
        as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
        samples: int = typer.Option(3_600_000, help="Samples (3.6 M = one hour at 1 kHz)."),
        chunk: int = typer.Option(65_536, help="Samples per chunk (outputs reused)."),
        reps: int = typer.Option(3, help="Repetitions; the best time is reported."),
    ) -> None:
        """Inverse dynamics with joint reaction wrenches over one hour of 1 kHz data."""
        r = run(samples=samples, chunk=chunk, reps=reps)
        emit(r, as_json)
