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
import re
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from cranetwin.physics.chain import HEADER, JOINT_BLOCK, PRISMATIC, ChainParams

Ex = float | str
Vec = list[Ex]


class _Tracer:
    """Records straight-line code for arithmetic on numbers (folded) and variable names."""

    def __init__(self) -> None:
        self.lines: list[str] = []
        self._n = 0

    def _new(self, expr: str) -> str:
        name = f"t{self._n}"
        self._n += 1
        self.lines.append(f"{name} = {expr}")
        return name

    @staticmethod
    def _fmt(a: Ex) -> str:
        return a if isinstance(a, str) else f"({a!r})"

    def add(self, a: Ex, b: Ex) -> Ex:
        if isinstance(a, float) and isinstance(b, float):
            return a + b
        if a == 0.0:
            return b
        if b == 0.0:
            return a
        return self._new(f"{self._fmt(a)} + {self._fmt(b)}")

    def sub(self, a: Ex, b: Ex) -> Ex:
        if isinstance(a, float) and isinstance(b, float):
            return a - b
        if b == 0.0:
            return a
        if a == 0.0:
            return self.neg(b)
        return self._new(f"{self._fmt(a)} - {self._fmt(b)}")

    def neg(self, a: Ex) -> Ex:
        if isinstance(a, float):
            return -a
        return self._new(f"-{a}")

    def mul(self, a: Ex, b: Ex) -> Ex:
        if isinstance(a, float) and isinstance(b, float):
            return a * b
        if a == 0.0 or b == 0.0:
            return 0.0
        if a == 1.0:
            return b
        if b == 1.0:
            return a
        if a == -1.0:
            return self.neg(b)
        if b == -1.0:
            return self.neg(a)
        return self._new(f"{self._fmt(a)} * {self._fmt(b)}")

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


def trace_rnea(chain: np.ndarray, qd: list[Ex] | None = None, qdd: list[Ex] | None = None,
               gravity: bool = True) -> tuple[list[str], list[Ex], list[list[Ex]]]:
    """Trace the RNEA of :func:`kernels.rnea_into` for one sample on symbols.

    Inputs are the names ``q{i}``, ``qd{i}``, ``qdd{i}``, ``c{i}``/``s{i}`` (cos/sin of q{i})
    and ``pl`` (payload [kg]); ``qd``/``qdd`` replace the velocity/acceleration names by
    values (numbers fold away) and ``gravity=False`` leaves gravity out, e.g. a column of the
    mass matrix is the trace with qd = 0, qdd = e_j and no gravity. Returns (code lines, tau
    expressions, wrench expressions).
    """
    tr = _Tracer()
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
            c, s = f"c{i}", f"s{i}"
            v = tr.sub(1.0, c)
            kx, ky, kz = (float(x) for x in chain[o + 1:o + 4])
            rq: list[Ex] = [
                tr.add(c, tr.mul(kx * kx, v)),
                tr.sub(tr.mul(kx * ky, v), tr.mul(kz, s)),
                tr.add(tr.mul(kx * kz, v), tr.mul(ky, s)),
                tr.add(tr.mul(ky * kx, v), tr.mul(kz, s)),
                tr.add(c, tr.mul(ky * ky, v)),
                tr.sub(tr.mul(ky * kz, v), tr.mul(kx, s)),
                tr.sub(tr.mul(kz * kx, v), tr.mul(ky, s)),
                tr.add(tr.mul(kz * ky, v), tr.mul(kx, s)),
                tr.add(c, tr.mul(kz * kz, v)),
            ]
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
                           "pl")
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
    return tr.lines, taus, wrenches


def _ex(a: Ex) -> str:
    return a if isinstance(a, str) else repr(a)


def generate_source(chain: np.ndarray) -> str:
    """Python source of ``rnea_batch(q, qd, qdd, payload, tau, wrench)`` and
    ``rnea_tau_batch(q, qd, qdd, payload, tau)`` specialised to ``chain``, the two-pass
    ``rnea_tau_pair_batch``, ``mass_matrix_batch`` and the fused replay grid pass
    (:func:`cranetwin.physics.gridpass.grid_pass`) with the RNEA inlined."""
    nj = int(chain[0])
    lines, taus, wrenches = trace_rnea(chain)
    rev = [i for i in range(nj) if chain[HEADER + i * JOINT_BLOCK] != PRISMATIC]
    head = []
    for i in range(nj):
        head += [f"q{i} = q[k, {i}]", f"qd{i} = qd[k, {i}]", f"qdd{i} = qdd[k, {i}]"]
    for i in rev:
        head += [f"c{i} = math.cos(q{i})", f"s{i} = math.sin(q{i})"]
    body = head + ["pl = payload[k]"] + lines
    ind = " " * 8
    out_tau = [f"tau[k, {i}] = {_ex(t)}" for i, t in enumerate(taus)]
    out_w = [f"wrench[k, {i}, {j}] = {_ex(x)}" for i, wr in enumerate(wrenches)
             for j, x in enumerate(wr)]
    from cranetwin.physics import gridpass

    src = [
        '"""Generated by cranetwin.physics.codegen: RNEA specialised to one machine."""',
        "import math",
        "from numba import njit",
        "",
        "",
        "@njit(cache=True)",
        "def rnea_batch(q, qd, qdd, payload, tau, wrench):",
        "    for k in range(q.shape[0]):",
        *[ind + x for x in body + out_tau + out_w],
        "",
        "",
        "@njit(cache=True)",
        "def rnea_tau_batch(q, qd, qdd, payload, tau):",
        "    for k in range(q.shape[0]):",
        *[ind + x for x in body + out_tau],
        "",
        "",
        "@njit(cache=True)",
        inline_rnea(PAIR_TEMPLATE, nj, rev, lines, taus, wrenches),
        "",
        "",
        "@njit(cache=True)",
        mass_matrix_source(chain, rev),
        "",
        "",
        gridpass.IMPORTS,
        "",
        "",
        "@njit(cache=True, error_model=\"numpy\")",
        inline_rnea(gridpass.template_source(), nj, rev, lines, taus, wrenches),
    ]
    return "\n".join(src)


def mass_matrix_source(chain: np.ndarray, revolute: list[int]) -> str:
    """Source of ``mass_matrix_batch(q, payload, mm)``: M(q) with the payload, column j as the
    RNEA traced with qd = 0, qdd = e_j and no gravity (numbers folded, so each column keeps
    only what its unit acceleration reaches), all columns in one loop sharing cos/sin."""
    nj = int(chain[0])
    body = [f"rq{i} = q[g, {i}]" for i in range(nj)]
    for i in revolute:
        body += [f"rc{i} = math.cos(rq{i})", f"rs{i} = math.sin(rq{i})"]
    body.append("pl = payload[g]")
    for j in range(nj):
        unit: list[Ex] = [1.0 if i == j else 0.0 for i in range(nj)]
        lines, taus, _ = trace_rnea(chain, qd=[0.0] * nj, qdd=unit, gravity=False)
        ren = _renamer(f"m{j}_")
        body += [ren(x) for x in lines]
        body += [f"mm[g, {i}, {j}] = {ren(_ex(t))}" for i, t in enumerate(taus)]
    return "\n".join(["def mass_matrix_batch(q, payload, mm):",
                      "    for g in range(q.shape[0]):", *["        " + x for x in body]])


PAIR_TEMPLATE = """def rnea_tau_pair_batch(q, qd, qdd, qdd2, pl_a, pl_b, tau_a, tau_b):
    for g in range(q.shape[0]):
        pass  # @RNEA_HEAD@
        pl = pl_a[g]
        x  # @RNEA qdd tau_a -@
        pl = pl_b[g]
        x  # @RNEA qdd2 tau_b -@
"""
"""Two inverse-dynamics passes per sample that share q and qd — (qdd, pl_a) into tau_a,
(qdd2, pl_b) into tau_b — in one loop, so that the compiler computes what they share once
(the payload regression's tau at 0 and 1 kg; a column of M as tau(q, 0, e_j) − tau(q, 0, 0))."""

_NAME = re.compile(r"\b(t|qdd|qd|q|c|s)(\d+)\b|\bpl\b")


def _renamer(pre: str) -> Callable[[str], str]:
    """Renames the traced names of one pass: temporaries and accelerations get the pass's
    prefix, q/qd/cos/sin the shared ``r`` prefix of the head; ``pl`` stays."""

    def one(m: re.Match[str]) -> str:
        if m.group(0) == "pl":
            return "pl"
        kind, i = m.group(1), m.group(2)
        return f"{pre}{kind}{i}" if kind in ("t", "qdd") else f"r{kind}{i}"

    return lambda line: _NAME.sub(one, line)


def inline_rnea(template: str, nj: int, revolute: list[int], lines: list[str], taus: list[Ex],
                wrenches: list[list[Ex]]) -> str:
    """``template`` with its RNEA marker lines replaced by the traced straight-line code.

    ``pass  # @RNEA_HEAD@`` becomes the loads of q, qd at row ``g`` and the cos/sin of the
    revolute angles (shared by the passes that follow); ``<call>  # @RNEA qdd tau wrench@``
    becomes one RNEA reading accelerations from array ``qdd`` (row g) and writing ``tau`` and
    ``wrench``, each unless it is ``-``. Names are prefixed per pass so the passes do not collide
    with each other or the template; no call, no array arguments, nothing to reference-count.
    """
    out: list[str] = []
    n_pass = 0
    for line in template.split("\n"):
        stripped = line.strip()
        ind = line[: len(line) - len(line.lstrip())]
        if stripped.endswith("# @RNEA_HEAD@"):
            for i in range(nj):
                out += [f"{ind}rq{i} = q[g, {i}]", f"{ind}rqd{i} = qd[g, {i}]"]
            for i in revolute:
                out += [f"{ind}rc{i} = math.cos(rq{i})", f"{ind}rs{i} = math.sin(rq{i})"]
            continue
        marker = stripped.rsplit("# @RNEA ", 1)
        if len(marker) == 2 and marker[1].endswith("@"):
            acc, tau, wrench = marker[1][:-1].split()
            pre = f"r{n_pass}_"
            n_pass += 1

            ren = _renamer(pre)
            body = [f"{pre}qdd{i} = {acc}[g, {i}]" for i in range(nj)]
            body += [ren(x) for x in lines]
            if tau != "-":
                body += [f"{tau}[g, {i}] = {ren(_ex(t))}"
                         for i, t in enumerate(taus)]
            if wrench != "-":
                body += [f"{wrench}[g, {i}, {j}] = {ren(_ex(x))}"
                         for i, wr in enumerate(wrenches) for j, x in enumerate(wr)]
            out += [ind + x for x in body]
            continue
        out.append(line)
    return "\n".join(out)


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


def specialised_kernels(params: ChainParams) -> tuple[Callable[..., None], Callable[..., None]]:
    """(rnea_batch, rnea_tau_batch) generated for ``params.chain``; loaded once per process.

    ``rnea_batch(q, qd, qdd, payload, tau, wrench)`` has the meaning of
    :func:`kernels.rnea_batch` without the ``chain`` argument. Both are compiled (or loaded
    from numba's on-disk cache) here, before they are returned; a cache that cannot be loaded
    is deleted and the kernels compiled afresh.
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
    return mod.rnea_batch, mod.rnea_tau_batch


def specialised_module(params: ChainParams) -> Any:
    """The generated module of ``params.chain`` (loaded as :func:`specialised_kernels`); it
    also holds ``grid_pass``, compiled on its first call (then cached on disk)."""
    specialised_kernels(params)
    return _MODULES[_source(params.chain)[1]]


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
