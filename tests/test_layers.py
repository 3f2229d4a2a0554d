"""No module imports across the layers documented in docs/ARCHITECTURE.md.

The layer table ("### Layers") is the single source: for each package, the ``cranetwin``
packages it may import (transitively: also what those may import; ``all below`` = every package
in an earlier row) and the modules it must never import. Every module's imports are read with
``ast`` — at module level, inside functions and under ``TYPE_CHECKING`` alike — and checked
against it. The physics core is also imported in a fresh interpreter to prove that no web
framework or database library comes along.
"""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "cranetwin"
ARCHITECTURE = ROOT / "docs" / "ARCHITECTURE.md"
ROOT_PACKAGE = "cranetwin"  # src/cranetwin/__init__.py: may import no cranetwin package


@dataclass(frozen=True)
class Layer:
    name: str
    may_import: frozenset[str]  # direct entries of the table (plus "all below" resolved)
    never_imports: frozenset[str]


def _names(cell: str) -> list[str]:
    return re.findall(r"`([^`]+)`", cell)


def parse_layers(text: str) -> dict[str, Layer]:
    """The "### Layers" table of ARCHITECTURE.md, in row order."""
    section = re.search(r"^### Layers\n(.*?)(?=^#)", text, re.MULTILINE | re.DOTALL)
    assert section, "docs/ARCHITECTURE.md has no '### Layers' section"
    rows = [line for line in section.group(1).splitlines() if line.startswith("|")]
    header = [c.strip() for c in rows[0].strip("|").split("|")]
    assert header == ["package", "may import", "never imports"], header
    layers: dict[str, Layer] = {}
    for line in rows[2:]:  # skip the header and the |---| line
        cells = [c.strip() for c in line.strip("|").split("|")]
        assert len(cells) == 3, line
        (name,) = _names(cells[0])
        assert name not in layers, f"{name} listed twice"
        if cells[1] == "all below":
            may = frozenset(layers)
        else:
            may = frozenset(_names(cells[1]))
            unknown = may - set(layers)
            assert not unknown, f"{name} may import {sorted(unknown)}: not in an earlier row"
        layers[name] = Layer(name, may, frozenset(_names(cells[2])))
    return layers


def allowed(layers: dict[str, Layer]) -> dict[str, frozenset[str]]:
    """Transitive closure of "may import" (rows only refer to earlier rows, so one pass)."""
    out: dict[str, frozenset[str]] = {}
    for name, layer in layers.items():
        reach = set(layer.may_import)
        for dep in layer.may_import:
            reach |= out[dep]
        out[name] = frozenset(reach)
    return out


@dataclass(frozen=True)
class Import:
    module: str  # absolute dotted name
    line: int


def module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _is_submodule(name: str) -> bool:
    return name in LAYERS or (SRC / name).is_dir() or (SRC / f"{name}.py").is_file()


def imports_of(path: Path, source: str | None = None) -> list[Import]:
    """Every import in the file (or in ``source`` as if it were that file), anywhere in it,
    in source order, with relative imports made absolute."""
    text = path.read_text(encoding="utf-8") if source is None else source
    tree = ast.parse(text, filename=str(path))
    package = module_name(path).split(".")
    if path.name != "__init__.py":
        package = package[:-1]
    out: list[Import] = []
    nodes = sorted((n for n in ast.walk(tree) if isinstance(n, ast.Import | ast.ImportFrom)),
                   key=lambda n: (n.lineno, n.col_offset))
    for node in nodes:
        if isinstance(node, ast.Import):
            out.extend(Import(a.name, node.lineno) for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[:len(package) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            # `from cranetwin import physics` imports the package cranetwin.physics;
            # `from cranetwin import __version__` only the root package
            if mod == ROOT_PACKAGE:
                out.extend(Import(f"{mod}.{a.name}" if _is_submodule(a.name) else mod,
                                  node.lineno) for a in node.names)
            else:
                out.append(Import(mod, node.lineno))
    return out


def package_of(module: str) -> str:
    """``cranetwin.physics.linkage.fourbar`` → ``physics``; ``cranetwin`` → ``cranetwin``."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ROOT_PACKAGE


LAYERS = parse_layers(ARCHITECTURE.read_text(encoding="utf-8"))
ALLOWED = allowed(LAYERS)
MODULES = sorted(SRC.rglob("*.py"))


def test_layer_table_is_well_formed() -> None:
    assert {"model", "physics", "signal", "twin", "sim", "codec", "protocol", "storage",
            "ingest", "analytics", "service", "reports", "api", "cli", "testing", "viz",
            "bench"} <= set(LAYERS)
    for name in ("physics", "signal", "twin", "sim", "protocol", "codec", "analytics"):
        assert {"fastapi", "sqlalchemy", "starlette", "socket"} <= LAYERS[name].never_imports
    # nothing low may reach the HTTP layer, and the CLI reaches everything
    assert all("api" not in ALLOWED[n] for n in ("service", "twin", "storage", "ingest"))
    assert ALLOWED["cli"] == frozenset(LAYERS) - {"cli"}


def test_every_package_is_in_the_layer_table() -> None:
    packages = {package_of(module_name(p)) for p in MODULES} - {ROOT_PACKAGE}
    missing = packages - set(LAYERS)
    assert not missing, f"packages missing from docs/ARCHITECTURE.md's layer table: {missing}"


def test_no_module_imports_across_layers() -> None:
    problems: list[str] = []
    for path in MODULES:
        here = package_of(module_name(path))
        may = ALLOWED.get(here, frozenset())
        for imp in imports_of(path):
            if imp.module.split(".")[0] != ROOT_PACKAGE:
                continue
            there = package_of(imp.module)
            if there in (here, ROOT_PACKAGE) and here != ROOT_PACKAGE:
                continue
            if there not in may:
                problems.append(f"{path.relative_to(ROOT)}:{imp.line}: {here} imports "
                                f"{imp.module} ({here} may import: {', '.join(sorted(may))})")
    assert not problems, "imports across layers:\n" + "\n".join(problems)


def test_core_packages_never_import_web_database_or_sockets() -> None:
    problems: list[str] = []
    for path in MODULES:
        here = package_of(module_name(path))
        layer = LAYERS.get(here)
        if layer is None:
            continue
        for imp in imports_of(path):
            if imp.module.split(".")[0] in layer.never_imports:
                problems.append(f"{path.relative_to(ROOT)}:{imp.line}: {here} imports "
                                f"{imp.module}")
    assert not problems, "forbidden imports:\n" + "\n".join(problems)


@pytest.mark.parametrize("package", ["physics", "twin"])
def test_importing_the_physics_core_loads_no_web_or_database_library(package: str) -> None:
    code = (f"import sys, cranetwin.{package}\n"
            "bad = sorted(m for m in ('fastapi', 'starlette', 'sqlalchemy', 'uvicorn')"
            " if m in sys.modules)\n"
            "print(','.join(bad))")
    env = {**os.environ,
           "PYTHONPATH": os.pathsep.join([str(SRC.parent), os.environ.get("PYTHONPATH", "")])}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=300, env=env)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "", f"importing cranetwin.{package} loaded {r.stdout.strip()}"


def test_the_checker_sees_imports_inside_functions_and_relative_ones() -> None:
    source = ("from __future__ import annotations\nfrom typing import TYPE_CHECKING\n"
              "if TYPE_CHECKING:\n    from cranetwin.sim import Recording\n"
              "def f():\n    from ..api import app\n    import sqlalchemy.orm\n"
              "    from . import kinematics\n    from cranetwin import service\n")
    found = [i.module for i in imports_of(SRC / "physics" / "probe.py", source)]
    assert found == ["__future__", "typing", "cranetwin.sim", "cranetwin.api", "sqlalchemy.orm",
                     "cranetwin.physics", "cranetwin.service"]
