"""Stale numba caches are dropped when any compiled source changes (cranetwin.jitcache)."""

from __future__ import annotations

from pathlib import Path

import pytest

from cranetwin import jitcache


def _tree(root: Path) -> Path:
    for pkg in jitcache.PACKAGES:
        (root / pkg / "sub").mkdir(parents=True)
        (root / pkg / "a.py").write_text("x = 1\n")
        (root / pkg / "sub" / "b.py").write_text("y = 2\n")
    return root


def _caches(root: Path) -> list[Path]:
    out = []
    for d in (root / "physics" / "__pycache__", root / "twin" / "sub" / "__pycache__"):
        d.mkdir(parents=True, exist_ok=True)
        for name in ("f.py311.nbi", "f.f-1.py311.1.nbc"):
            (d / name).write_text("compiled")
            out.append(d / name)
    return out


@pytest.mark.timeout(30)
def test_caches_survive_while_sources_are_unchanged_and_go_when_one_changes(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setenv("CRANETWIN_CACHE_DIR", str(tmp_path / "cache"))
    root = _tree(tmp_path / "cranetwin")
    jitcache.drop_stale(root)  # first run: every cache folder made and stamped
    stamps = list(root.rglob(jitcache.STAMP))
    assert len(stamps) == 2 * len(jitcache.PACKAGES)  # each package and its sub-package
    assert (tmp_path / "cache" / "physics" / jitcache.STAMP).exists()
    files = _caches(root)
    assert jitcache.drop_stale(root) == 0 and all(f.exists() for f in files)
    (root / "physics" / "sub" / "b.py").write_text("y = 3\n")  # a callee changed
    assert jitcache.drop_stale(root) == len(files)
    assert not any(f.exists() for f in files)  # the callers' caches too
    files = _caches(root)
    assert jitcache.drop_stale(root) == 0 and all(f.exists() for f in files)


@pytest.mark.timeout(30)
def test_the_installed_package_is_stamped_with_its_sources() -> None:
    root = Path(jitcache.__file__).resolve().parent
    want = jitcache.digest(jitcache.sources())
    stamp = root / "physics" / "__pycache__" / jitcache.STAMP
    assert stamp.read_text() == want  # importing cranetwin.physics stamped it
    assert any(p.name == "linear.py" for p in jitcache.sources())
