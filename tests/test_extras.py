"""pyproject.toml declares what the code imports, and optional dependencies stay optional.

* Every third-party module imported anywhere in ``src/cranetwin`` belongs to a distribution that
  ``pyproject.toml`` declares, in the core dependencies or in an extra.
* Imports at module level (what ``import cranetwin.x`` runs) use core dependencies only.
* An import of an extra's distribution sits inside a function, in a ``try`` that turns the
  ``ImportError`` into :class:`~cranetwin.errors.MissingExtraError` (or falls back).
* Removed dependencies stay removed; a missing extra names itself.
"""

from __future__ import annotations

import ast
import re
import sys
import tomllib
from dataclasses import dataclass
from importlib.metadata import packages_distributions
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "cranetwin"
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))


def _dist_name(requirement: str) -> str:
    name = re.match(r"[A-Za-z0-9._-]+", requirement)
    assert name, requirement
    return re.sub(r"[-_.]+", "-", name.group(0)).lower()


CORE = {_dist_name(r) for r in PYPROJECT["project"]["dependencies"]}
EXTRAS = {extra: {_dist_name(r) for r in reqs if not r.startswith("cranetwin")}
          for extra, reqs in PYPROJECT["project"]["optional-dependencies"].items()}
DIST_OF = {module: {re.sub(r"[-_.]+", "-", d).lower() for d in dists}
           for module, dists in packages_distributions().items()}
# Pinocchio's wheel (`pin`) installs through cmeel, outside the records packages_distributions reads
DIST_OF.setdefault("pinocchio", {"pin"})


@dataclass(frozen=True)
class Use:
    path: Path
    line: int
    module: str  # top-level module name
    in_function: bool
    guarded: bool  # inside a try whose handlers catch ImportError
    type_only: bool  # under `if TYPE_CHECKING:`


def _catches_import_error(node: ast.Try) -> bool:
    for h in node.handlers:
        names = [h.type] if not isinstance(h.type, ast.Tuple) else list(h.type.elts)
        if h.type is None or any(isinstance(n, ast.Name) and n.id in
                                 ("ImportError", "ModuleNotFoundError", "Exception")
                                 for n in names):
            return True
    return False


def uses(path: Path) -> list[Use]:
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    out: list[Use] = []

    def visit(node: ast.AST, in_function: bool, guarded: bool, type_only: bool) -> None:
        if isinstance(node, ast.Import | ast.ImportFrom):
            if isinstance(node, ast.ImportFrom):
                mods = [] if node.level else [node.module or ""]
            else:
                mods = [a.name for a in node.names]
            out.extend(Use(path, node.lineno, m.split(".")[0], in_function, guarded, type_only)
                       for m in mods)
            return
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            in_function = True
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for child in node.body:
                visit(child, in_function, guarded, True)
            for child in node.orelse:
                visit(child, in_function, guarded, type_only)
            return
        if isinstance(node, ast.Try):
            for child in node.body:
                visit(child, in_function, guarded or _catches_import_error(node), type_only)
            for part in (node.handlers, node.orelse, node.finalbody):
                for child in part:
                    visit(child, in_function, guarded, type_only)
            return
        for child in ast.iter_child_nodes(node):
            visit(child, in_function, guarded, type_only)

    visit(tree, False, False, False)
    return out


def third_party(u: Use) -> bool:
    return u.module not in sys.stdlib_module_names and u.module not in ("cranetwin", "__future__")


USES = [u for p in sorted(SRC.rglob("*.py")) for u in uses(p) if third_party(u)]


def _where(u: Use) -> str:
    return f"{u.path.relative_to(ROOT)}:{u.line}: {u.module}"


def test_every_imported_distribution_is_declared() -> None:
    declared = CORE.union(*EXTRAS.values())
    problems = []
    for u in USES:
        dists = DIST_OF.get(u.module)
        if not dists:
            problems.append(f"{_where(u)} (not installed: which distribution is it?)")
        elif not dists & declared:
            problems.append(f"{_where(u)} from {sorted(dists)}: not in pyproject.toml")
    assert not problems, "\n".join(problems)


def test_module_level_imports_use_core_dependencies_only() -> None:
    problems = [f"{_where(u)} from {sorted(DIST_OF.get(u.module, ()))}" for u in USES
                if not u.in_function and not u.type_only
                and not DIST_OF.get(u.module, set()) & CORE]
    assert not problems, ("module-level imports of optional dependencies (import them inside "
                          "the function that needs them):\n" + "\n".join(problems))


def test_optional_imports_raise_missing_extra_or_fall_back() -> None:
    problems = [_where(u) for u in USES
                if u.in_function and not u.type_only and not u.guarded
                and not DIST_OF.get(u.module, set()) & CORE]
    assert not problems, ("optional dependencies imported without a try/except ImportError "
                          "that raises MissingExtraError naming the extra:\n" + "\n".join(problems))


def test_dropped_dependencies_stay_dropped() -> None:
    assert "msgpack" not in CORE.union(*EXTRAS.values())
    assert {"fatpack", "tomli-w"} <= EXTRAS["dev"] and not {"fatpack", "tomli-w"} & CORE
    assert {"postgres", "redis", "reports", "web", "ingest", "dev"} <= set(EXTRAS)
    dev = PYPROJECT["project"]["optional-dependencies"]["dev"]
    everything = next(r for r in dev if r.startswith("cranetwin["))
    assert set(everything[len("cranetwin["):-1].split(",")) == set(EXTRAS) - {"dev"}


def test_constraints_pin_every_declared_distribution() -> None:
    pins = {}
    for line in (ROOT / "constraints.txt").read_text(encoding="utf-8").splitlines():
        if line and not line.startswith("#"):
            name, _, version = line.partition("==")
            assert version, f"constraints.txt: {line!r} is not an exact pin"
            pins[re.sub(r"[-_.]+", "-", name).lower()] = version
    declared = CORE.union(*EXTRAS.values())
    assert declared <= set(pins), f"not pinned: {sorted(declared - set(pins))}"
    assert "cranetwin" not in pins


def test_reports_without_the_extra_name_it(monkeypatch: pytest.MonkeyPatch) -> None:
    from cranetwin.errors import MissingExtraError
    from cranetwin.reports import check_format

    monkeypatch.setitem(sys.modules, "reportlab", None)  # `import reportlab` raises ImportError
    with pytest.raises(MissingExtraError, match=r"cranetwin\[reports\]"):
        check_format("pdf")
    check_format("html")  # HTML needs matplotlib only
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    with pytest.raises(MissingExtraError, match="HTML reports"):
        check_format("html")
    check_format("csv")  # CSV needs neither
