"""Stale numba caches: dropped when any compiled source changed.

numba keys a cached function (``@njit(cache=True)``) on its own source file only. A compiled
function that calls or inlines a function of another module (the twin's stages call the linkage
dispatchers of :mod:`cranetwin.physics.linkage`, the simulator's loop inlines the physics
kernels, the generated RNEA kernels call the joint transforms) keeps running the callee's old
machine code from the cache after that module changed: an upgrade in place over an old checkout
then computes with the old physics, silently (seen: NaN kinematics for a newly added linkage
kind until ``__pycache__`` was cleared).

:func:`drop_stale` keeps one stamp, a SHA-256 of every source of the packages that hold numba
code (:data:`PACKAGES`), next to each cache, and deletes that cache's ``*.nbi``/``*.nbc`` files
when the stamp differs. It runs once per process, when this module is first imported: the
packages of :data:`PACKAGES` import it first, so it runs before any compiled function is first
called (numba reads its cache at the first call, not at import).
Reading the sources costs ≈ 1 ms; a change anywhere in them costs one recompilation.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterable
from pathlib import Path

PACKAGES = ("physics", "signal", "sim", "twin")
"""Sub-packages of ``cranetwin`` whose modules hold or are called by numba-compiled code."""

STAMP = "cranetwin.jit-stamp"
"""Name of the stamp file kept in each cache directory."""

_done = False


def sources(root: Path | None = None) -> list[Path]:
    """Every ``.py`` file of :data:`PACKAGES` under the package ``root`` (default: this
    installation's ``cranetwin``), sorted."""
    base = Path(__file__).resolve().parent if root is None else root
    return sorted(p for pkg in PACKAGES for p in (base / pkg).rglob("*.py"))


def digest(files: Iterable[Path]) -> str:
    """SHA-256 (hex) over the paths (relative names) and contents of ``files``."""
    h = hashlib.sha256()
    for p in files:
        h.update(p.name.encode())
        h.update(p.read_bytes())
    return h.hexdigest()


def cache_dirs(root: Path | None = None) -> list[Path]:
    """The directories numba and the kernel generator cache compiled code in: each package's
    ``__pycache__`` folders (made and stamped before numba first writes there), ``NUMBA_CACHE_DIR``
    if set, and the generated kernels' folder (``CRANETWIN_CACHE_DIR``/physics)."""
    out = sorted({p.parent / "__pycache__" for p in sources(root)})
    if os.environ.get("NUMBA_CACHE_DIR"):
        out.append(Path(os.environ["NUMBA_CACHE_DIR"]))
    env = os.environ.get("CRANETWIN_CACHE_DIR")
    out.append((Path(env) if env else Path.home() / ".cache" / "cranetwin") / "physics")
    return out


def drop_stale(root: Path | None = None, dirs: Iterable[Path] | None = None) -> int:
    """Delete the numba cache files of every cache directory whose stamp is not the current
    sources' digest, then stamp it. Returns the number of files deleted. Never raises for a
    directory it cannot write (a read-only install: numba then compiles in memory)."""
    want = digest(sources(root))
    dropped = 0
    for d in (cache_dirs(root) if dirs is None else dirs):
        stamp = d / STAMP
        try:
            if stamp.exists() and stamp.read_text() == want:
                continue
            for f in [*d.rglob("*.nbi"), *d.rglob("*.nbc")]:
                f.unlink(missing_ok=True)
                dropped += 1
            d.mkdir(parents=True, exist_ok=True)
            stamp.write_text(want)
        except OSError:
            continue
    return dropped


def drop_stale_once() -> None:
    """:func:`drop_stale` the first time it is called in this process."""
    global _done
    if _done:
        return
    _done = True
    drop_stale()


drop_stale_once()  # on first import (see the module docstring)
