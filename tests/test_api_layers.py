"""The service layer has no HTTP in it, and the synthetic data live in one package."""

from __future__ import annotations

import importlib
import pkgutil
import subprocess
import sys
import textwrap

import cranetwin.service


def test_service_imports_no_fastapi_or_starlette() -> None:
    mods = [f"cranetwin.service.{m.name}" for m in pkgutil.iter_modules(cranetwin.service.__path__)]
    code = textwrap.dedent(f"""
        import importlib, sys
        for name in {mods!r}:
            importlib.import_module(name)
        bad = sorted(m for m in sys.modules
                     if m.split('.')[0] in ('fastapi', 'starlette', 'uvicorn')
                     or m.startswith('cranetwin.api'))
        assert not bad, bad
        print("ok")
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=False)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"
    assert "cranetwin.service.worker" in mods and "cranetwin.service.fleet" in mods


def test_synthetic_generators_live_only_in_the_testing_package() -> None:
    for old in ("cranetwin.api.synthetic", "cranetwin.twin.synthetic",
                "cranetwin.analytics.synthetic", "cranetwin.viz.synthetic"):
        try:
            importlib.import_module(old)
        except ModuleNotFoundError:
            continue
        raise AssertionError(f"{old} still exists; synthetic data live in cranetwin.testing")
    for new in ("blocks", "histories", "recordings", "views"):
        importlib.import_module(f"cranetwin.testing.{new}")
