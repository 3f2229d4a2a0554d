"""Inverse dynamics specialised to one machine: straight-line numba code generated from its data.

The generic kernel (:func:`cranetwin.physics.kernels.rnea_into`) reads every parameter from an
array and multiplies through all nine entries of every rotation and inertia, although a real
machine's axes, joint origins and principal inertias are mostly zeros and ones. Here the same
recursive Newton–Euler algorithm is run once on symbols ("traced"): arithmetic on two
numbers is folded, multiplications by 0 and ±1 and additions of 0 vanish, and what is left is
written out as the body of a loop over samples. For the PATU 655 this removes about two thirds of
the floating-point work (``cranetwin bench dynamics`` reports the effect).

The source is written to a per-user cache directory named by a hash of the generated text
(``CRANETWIN_CACHE_DIR``, default ``~/.cache/cranetwin``), so numba's ``cache=True`` keeps the
compiled machine code between runs. Tests compare it with the generic kernel and Pinocchio.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from cranetwin.physics.chain import ChainParams
from cranetwin.physics.layout import HEADER, JOINT_BLOCK, PRISMATIC

Ex = float | str
Vec = list[Ex]


class _Tracer:
    """Records straight-line code for arithmetic on numbers (folded) and variable names.

    Expressions are hash-consed: the same operation on the same operands (commutative ones in
    either order) is computed once and its name reused, so passes traced into one tracer share
    what they have in common (rotations, velocity terms). A few exact rewrites keep the code
    short: −(−x) = x, a + (−b) = a − b, a − (−b) = a + b, c·(−x) = (−c)·x, and a product of
    constants with a product of a constant, c1·(c2·x) = (c1·c2)·x (this one rounds the constant
    once instead of twice: results move by an ulp or so).
    """

    def __init__(self) -> None:
        self.lines: list[str] = []
        self._n = 0
        self._memo: dict[str, str] = {}
        self._defs: dict[str, tuple[str, Ex, Ex]] = {}

    def _new(self, op: str, a: Ex, b: Ex = 0.0) -> str:
        if op == "neg":
            expr = f"-{a}"
        else:
            fa, fb = self._fmt(a), self._fmt(b)
            if op in ("+", "*") and fb < fa:
                fa, fb = fb, fa
            expr = f"{fa} {op} {fb}"
        hit = self._memo.get(expr)
        if hit is not None:
            return hit
        name = f"t{self._n}"
        self._n += 1
        self.lines.append(f"{name} = {expr}")
        self._memo[expr] = name
        self._defs[name] = (op, a, b)
        return name

    @staticmethod
    def _fmt(a: Ex) -> str:
        return a if isinstance(a, str) else f"({a!r})"

    def _negated(self, a: Ex) -> Ex | None:
        """x if ``a`` is the name of −x, else None."""
        d = self._defs.get(a) if isinstance(a, str) else None
        return d[1] if d is not None and d[0] == "neg" else None

    def add(self, a: Ex, b: Ex) -> Ex:
        if isinstance(a, float) and isinstance(b, float):
            return a + b
        if a == 0.0:
            return b
        if b == 0.0:
            return a
        nb = self._negated(b)
        if nb is not None:
            return self.sub(a, nb)
        na = self._negated(a)
        if na is not None:
            return self.sub(b, na)
        return self._new("+", a, b)

    def sub(self, a: Ex, b: Ex) -> Ex:
        if isinstance(a, float) and isinstance(b, float):
            return a - b
        if b == 0.0:
            return a
        if a == 0.0:
            return self.neg(b)
        nb = self._negated(b)
        if nb is not None:
            return self.add(a, nb)
        return self._new("-", a, b)

    def neg(self, a: Ex) -> Ex:
        if isinstance(a, float):
            return -a
        na = self._negated(a)
        if na is not None:
            return na
        d = self._defs.get(a)
        if d is not None and d[0] == "*" and isinstance(d[1], float):
            return self.mul(-d[1], d[2])
        return self._new("neg", a)

    def mul(self, a: Ex, b: Ex) -> Ex:
        if isinstance(a, float) and isinstance(b, float):
            return a * b
        if isinstance(b, float):
            a, b = b, a
        if a == 0.0 or b == 0.0:
            return 0.0
        if a == 1.0:
            return b
        if b == 1.0:
            return a
        if a == -1.0:
            return self.neg(b)
        if isinstance(a, float):
            nb = self._negated(b)
            if nb is not None:
                return self.mul(-a, nb)
            d = self._defs.get(b) if isinstance(b, str) else None
            if d is not None and d[0] == "*" and isinstance(d[1], float):
                return self.mul(a * d[1], d[2])
        return self._new("*", a, b)

    def sum(self, terms: list[Ex]) -> Ex:
        acc: Ex = 0.0
        for t in terms:
            acc = self.add(acc, t)
        return acc

    # --- 3-vectors and 3x3 matrices (row-major lists) ---------------------------------------
    def vadd(self, a: Vec, b: Vec) -> Vec:
        return [self.add(x, y) for x, y in zip(a, b, strict=True)]

    def vscale(self, a: Vec, s: Ex) -> Vec:
        return [self.mul(x, s) for x in a]

    def cross(self, a: Vec, b: Vec) -> Vec:
        return [self.sub(self.mul(a[1], b[2]), self.mul(a[2], b[1])),
                self.sub(self.mul(a[2], b[0]), self.mul(a[0], b[2])),
                self.sub(self.mul(a[0], b[1]), self.mul(a[1], b[0]))]

    def dot(self, a: Vec, b: Vec) -> Ex:
        return self.sum([self.mul(x, y) for x, y in zip(a, b, strict=True)])

    def matvec(self, m: list[Ex], v: Vec) -> Vec:
        return [self.dot(m[3 * r:3 * r + 3], v) for r in range(3)]

    def matTvec(self, m: list[Ex], v: Vec) -> Vec:
        return [self.dot([m[c], m[3 + c], m[6 + c]], v) for c in range(3)]

    def matmul(self, a: list[Ex], b: list[Ex]) -> list[Ex]:
        return [self.dot(a[3 * r:3 * r + 3], [b[c], b[3 + c], b[6 + c]])
                for r in range(3) for c in range(3)]


def _consts(values: np.ndarray) -> list[Ex]:
    return [float(v) for v in values]


def _axis_rotation(tr: _Tracer, k: list[float], c: str, s: str) -> list[Ex]:
    """Rodrigues' rotation about unit axis k by the angle whose cos/sin are named c, s:
    Rq = c·I + s·[k]x + (1 − c)·k·kᵀ, row-major, with the diagonal written as k² + (1 − k²)·c
    so that an axis along x, y or z gives exact zeros and ones."""
    kx, ky, kz = k
    v: Ex = "" if kx * ky == 0.0 and kx * kz == 0.0 and ky * kz == 0.0 else tr.sub(1.0, c)

    def off(kk: float, kl: float, ks: float, sign: float) -> Ex:
        lin = 0.0 if kk * kl == 0.0 else tr.mul(kk * kl, v)
        return tr.add(lin, tr.mul(sign * ks, s))

    def diag(kk: float) -> Ex:
        return tr.add(kk * kk, tr.mul(1.0 - kk * kk, c))

    return [diag(kx), off(kx, ky, kz, -1.0), off(kx, kz, ky, 1.0),
            off(ky, kx, kz, 1.0), diag(ky), off(ky, kz, kx, -1.0),
            off(kz, kx, ky, -1.0), off(kz, ky, kx, 1.0), diag(kz)]


def trace_rnea(chain: np.ndarray, qd: list[Ex] | None = None, qdd: list[Ex] | None = None,
               gravity: bool = True, tracer: _Tracer | None = None,
               payload: Ex = "pl") -> tuple[list[str], list[Ex], list[list[Ex]]]:
    """Trace the RNEA of :func:`kernels.rnea_into` for one sample on symbols.

    Inputs are the names ``q{i}``, ``qd{i}``, ``qdd{i}``, ``c{i}``/``s{i}`` (cos/sin of q{i})
    and ``pl`` (payload [kg]); ``qd``/``qdd`` replace the velocity/acceleration names by
    values (numbers fold away) and ``gravity=False`` leaves gravity out, e.g. a column of the
    mass matrix is the trace with qd = 0, qdd = e_j and no gravity. ``payload`` names the
    payload variable or gives its value [kg]. Passes traced into one ``tracer`` share their
    common subexpressions (a later pass's lines may use an earlier one's names). Returns
    (the code lines this pass added, tau expressions, wrench expressions).
    """
    tr = _Tracer() if tracer is None else tracer
    first_line = len(tr.lines)
    nj = int(chain[0])
    lb = int(chain[4])
    lp = _consts(chain[5:8])
    w: Vec = [0.0, 0.0, 0.0]
    dw: Vec = [0.0, 0.0, 0.0]
    acc: Vec = [-float(g) if gravity else 0.0 for g in chain[1:4]]
    rots: list[list[Ex]] = []
    origins: list[Vec] = []
    wrenches: list[list[Ex]] = []
    kinds: list[bool] = []
    axes: list[Vec] = []
    for i in range(nj):
        o = HEADER + i * JOINT_BLOCK
        prismatic = chain[o] == PRISMATIC
        k = _consts(chain[o + 1:o + 4])
        r0 = _consts(chain[o + 4:o + 13])
        p: Vec = _consts(chain[o + 13:o + 16])
        qi = f"q{i}"
        vd: Ex = f"qd{i}" if qd is None else qd[i]
        ad: Ex = f"qdd{i}" if qdd is None else qdd[i]
        if prismatic:
            rot = r0
            p = tr.vadd(p, tr.vscale(tr.matvec(r0, k), qi))
        else:
            rq = _axis_rotation(tr, [float(x) for x in chain[o + 1:o + 4]], f"c{i}", f"s{i}")
            rot = tr.matmul(r0, rq)
        rots.append(rot)
        origins.append(p)
        kinds.append(bool(prismatic))
        axes.append(k)
        b = tr.vadd(tr.vadd(acc, tr.cross(dw, p)), tr.cross(w, tr.cross(w, p)))
        nw = tr.matTvec(rot, w)
        nd = tr.matTvec(rot, dw)
        na = tr.matTvec(rot, b)
        if prismatic:
            na = tr.vadd(na, tr.vadd(tr.vscale(k, ad), tr.vscale(tr.cross(nw, k), tr.mul(2.0, vd))))
        else:
            nd = tr.vadd(nd, tr.vadd(tr.vscale(k, ad), tr.vscale(tr.cross(nw, k), vd)))
            nw = tr.vadd(nw, tr.vscale(k, vd))
        w, dw, acc = nw, nd, na
        m = float(chain[o + 16])
        h = _consts(chain[o + 17:o + 20])
        io = _consts(chain[o + 20:o + 29])
        f = tr.vadd(tr.vadd(tr.vscale(acc, m), tr.cross(dw, h)), tr.cross(w, tr.cross(w, h)))
        n = tr.vadd(tr.vadd(tr.matvec(io, dw), tr.cross(w, tr.matvec(io, w))), tr.cross(h, acc))
        if i == lb:
            fp = tr.vscale(tr.vadd(tr.vadd(acc, tr.cross(dw, lp)), tr.cross(w, tr.cross(w, lp))),
                           payload)
            f = tr.vadd(f, fp)
            n = tr.vadd(n, tr.cross(lp, fp))
        wrenches.append(f + n)
    taus: list[Ex] = [0.0] * nj
    for i in range(nj - 1, -1, -1):
        f, n = wrenches[i][:3], wrenches[i][3:]
        taus[i] = tr.dot(axes[i], f if kinds[i] else n)
        if i > 0:
            rf = tr.matvec(rots[i], f)
            rn = tr.vadd(tr.matvec(rots[i], n), tr.cross(origins[i], rf))
            pf, pn = wrenches[i - 1][:3], wrenches[i - 1][3:]
            wrenches[i - 1] = tr.vadd(pf, rf) + tr.vadd(pn, rn)
    return tr.lines[first_line:], taus, wrenches


def _ex(a: Ex) -> str:
    return a if isinstance(a, str) else repr(a)


def _head(nj: int, revolute: list[int], velocities: bool, accelerations: str | None) -> list[str]:
    """Loads of row ``g``: q{i} (and qd{i}; qdd{i} from the array named ``accelerations``)
    and cos/sin of the revolute angles, under the names :func:`trace_rnea` reads."""
    out = [f"q{i} = q[g, {i}]" for i in range(nj)]
    if velocities:
        out += [f"qd{i} = qd[g, {i}]" for i in range(nj)]
    if accelerations is not None:
        out += [f"qdd{i} = {accelerations}[g, {i}]" for i in range(nj)]
    for i in revolute:
        out += [f"c{i} = math.cos(q{i})", f"s{i} = math.sin(q{i})"]
    return out


def _function(signature: str, body: list[str], skip: str | None = None) -> list[str]:
    """A compiled loop over the rows g of ``q`` around ``body`` (``skip``: a condition under
    which a row is left alone)."""
    lines = ["@njit(cache=True, nogil=True)", f"def {signature}:",
             "    for g in range(q.shape[0]):"]
    if skip is not None:
        lines += [f"        if {skip}:", "            continue"]
    return lines + ["        " + x for x in body] + ["", ""]


def _revolute(chain: np.ndarray) -> list[int]:
    nj = int(chain[0])
    return [i for i in range(nj) if chain[HEADER + i * JOINT_BLOCK] != PRISMATIC]


def generate_source(chain: np.ndarray) -> str:
    """Python source of the batch kernels specialised to ``chain``, each a loop over rows g:

    * ``rnea_batch(q, qd, qdd, payload, tau, wrench)`` and ``rnea_tau_batch(q, qd, qdd,
      payload, tau)``: inverse dynamics (meaning of :func:`kernels.rnea_batch`);
    * ``rnea_payload_batch(q, qd, qdd, tau0, tau1)``: joint loads without payload and with
      1 kg at the load point, traced together (they share all but the payload's terms);
    * ``rnea_lin_batch(q, acc, payload, rows, wrench)``: adds to ``wrench`` the part of the
      wrenches linear in the accelerations (qd = 0, no gravity) at ``acc``, on the rows where
      ``rows`` is true;
    * ``mass_matrix_batch(q, payload, mm)``: M(q) from unit-acceleration traces.
    """
    nj = int(chain[0])
    rev = _revolute(chain)
    lines, taus, wrenches = trace_rnea(chain)
    body = _head(nj, rev, True, "qdd") + ["pl = payload[g]"] + lines
    out_tau = [f"tau[g, {i}] = {_ex(t)}" for i, t in enumerate(taus)]
    out_w = [f"wrench[g, {i}, {j}] = {_ex(x)}" for i, wr in enumerate(wrenches)
             for j, x in enumerate(wr)]
    tr = _Tracer()  # the payload regression's two passes, sharing a tracer
    l0, t0, _ = trace_rnea(chain, tracer=tr, payload=0.0)
    l1, t1, _ = trace_rnea(chain, tracer=tr, payload=1.0)
    payload = (_head(nj, rev, True, "qdd") + l0 + l1
               + [f"tau0[g, {i}] = {_ex(t)}" for i, t in enumerate(t0)]
               + [f"tau1[g, {i}] = {_ex(t)}" for i, t in enumerate(t1)])
    ll, _, lin = trace_rnea(chain, qd=[0.0] * nj, gravity=False)
    linear = (_head(nj, rev, False, "acc") + ["pl = payload[g]"] + ll
              + [f"wrench[g, {i}, {j}] += {_ex(x)}" for i, wr in enumerate(lin)
                 for j, x in enumerate(wr)])
    src = [
        '"""Generated by cranetwin.physics.codegen: batch kernels specialised to one machine."""',
        "import math",
        "from numba import njit",
        "",
        "",
        *_function("rnea_batch(q, qd, qdd, payload, tau, wrench)", body + out_tau + out_w),
        *_function("rnea_tau_batch(q, qd, qdd, payload, tau)", body + out_tau),
        *_function("rnea_payload_batch(q, qd, qdd, tau0, tau1)", payload),
        *_function("rnea_lin_batch(q, acc, payload, rows, wrench)", linear, "not rows[g]"),
        *_function("mass_matrix_batch(q, payload, mm)", mass_matrix_body(chain, rev)),
    ]
    return "\n".join(src)


def mass_matrix_body(chain: np.ndarray, revolute: list[int]) -> list[str]:
    """Loop body of ``mass_matrix_batch(q, payload, mm)``: M(q) with the payload, column j as
    the RNEA traced with qd = 0, qdd = e_j and no gravity (numbers folded, so each column keeps
    only what its unit acceleration reaches), all columns traced into one tracer so that they
    share cos/sin, the rotations and whatever else they have in common."""
    nj = int(chain[0])
    body = _head(nj, revolute, False, None) + ["pl = payload[g]"]
    tr = _Tracer()
    for j in range(nj):
        unit: list[Ex] = [1.0 if i == j else 0.0 for i in range(nj)]
        lines, taus, _ = trace_rnea(chain, qd=[0.0] * nj, qdd=unit, gravity=False, tracer=tr)
        body += lines
        body += [f"mm[g, {i}, {j}] = {_ex(t)}" for i, t in enumerate(taus)]
    return body


def _cache_dir() -> Path:
    env = os.environ.get("CRANETWIN_CACHE_DIR")
    base = Path(env) if env else Path.home() / ".cache" / "cranetwin"
    path = base / "physics"
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = path / ".probe"
        probe.write_text("")
        probe.unlink()
    except OSError:
        path = Path(tempfile.gettempdir()) / f"cranetwin-physics-{os.getuid()}"
        path.mkdir(parents=True, exist_ok=True)
    return path


_MODULES: dict[str, Any] = {}


def _load(path: Path, name: str) -> Any:
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot load generated kernels from {path}")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod  # numba's cache resolves the module by name when loading
    spec.loader.exec_module(mod)
    return mod


def _warm_up(mod: Any, nj: int) -> None:
    z = np.zeros((1, nj))
    mod.rnea_batch(z, z, z, np.zeros(1), np.empty((1, nj)), np.empty((1, nj, 6)))
    mod.rnea_tau_batch(z, z, z, np.zeros(1), np.empty((1, nj)))


def specialised_module(params: ChainParams) -> Any:
    """The generated module of ``params.chain`` (every kernel of :func:`generate_source`),
    loaded once per process. Its kernels are compiled (or loaded from numba's on-disk cache)
    on first call; a cache that cannot be loaded is deleted and the kernels compiled afresh.
    """
    src, digest = _source(params.chain)
    mod = _MODULES.get(digest)
    if mod is None:
        folder = _cache_dir()
        path = folder / f"rnea_{digest}.py"
        if not path.exists() or path.read_text("utf-8") != src:
            tmp = path.with_suffix(f".{os.getpid()}.tmp")
            tmp.write_text(src, "utf-8")
            os.replace(tmp, path)
        name = f"cranetwin_rnea_{digest}"
        mod = _load(path, name)
        try:
            _warm_up(mod, params.n_joints)
        except Exception:  # a stale or foreign numba cache: drop it and compile again
            for stale in (folder / "__pycache__").glob(f"rnea_{digest}*"):
                stale.unlink(missing_ok=True)
            mod = _load(path, name)
            _warm_up(mod, params.n_joints)
        _MODULES[digest] = mod
    return mod


_SOURCES: dict[bytes, tuple[str, str]] = {}


def _source(chain: np.ndarray) -> tuple[str, str]:
    """(generated source, its digest) for a chain, generated once per process (the tracing
    takes ≈ 0.1 s: a replay of a few seconds must not pay it)."""
    key = np.ascontiguousarray(chain, dtype=np.float64).tobytes()
    hit = _SOURCES.get(key)
    if hit is None:
        src = generate_source(chain)
        hit = (src, hashlib.sha256(src.encode()).hexdigest()[:16])
        _SOURCES[key] = hit
    return hit
