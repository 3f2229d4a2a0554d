"""The command line imports only the module of the command it runs (start-up time), and finds
every command that way: a new command whose module breaks the naming rule fails here until its
alias is added in ``cranetwin.cli``."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import typer

from cranetwin.cli import build_app

pytestmark = pytest.mark.timeout(120)


def _names(app: typer.Typer) -> set[str]:
    return ({c.name or (c.callback.__name__.replace("_", "-") if c.callback else "")
             for c in app.registered_commands} | {g.name or "" for g in app.registered_groups})


def _bench(app: typer.Typer) -> typer.Typer:
    (group,) = [g for g in app.registered_groups if g.name == "bench"]
    assert group.typer_instance is not None
    return group.typer_instance


def test_every_command_is_found_alone() -> None:
    full = build_app()
    top = _names(full) - {"bench"}
    bench = _names(_bench(full))
    assert {"import", "ingest", "worker", "store-writer", "export", "replay"} <= top
    assert {"fleet", "import", "replay"} <= bench
    for cmd in sorted(top):
        one = build_app([cmd, "--help"])
        got = _names(one) - {"bench"}
        assert cmd in got and len(got) < len(top), cmd  # that command, not everything
    for cmd in sorted(bench):
        one = _bench(build_app(["bench", cmd, "--json"]))
        assert _names(one) == {cmd} or (cmd in _names(one) and len(_names(one)) < len(bench))


def test_unknown_or_no_command_gets_the_whole_application() -> None:
    full = _names(build_app())
    assert _names(build_app([])) == full
    assert _names(build_app(["no-such-command"])) == full
    assert _names(build_app(["--help"])) == full


@pytest.mark.parametrize("argv", [["export", "--help"], ["send", "--help"], ["keys", "--help"],
                                  ["import", "--help"]])
def test_a_light_command_does_not_import_the_numerics(argv: list[str]) -> None:
    code = (f"import sys; from cranetwin.cli import build_app; build_app({argv!r}); "
            "print(sorted(m for m in ('scipy.signal', 'numba', 'cranetwin.signal', "
            "'cranetwin.physics') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60, check=True).stdout.strip()
    assert out == "[]", out


@pytest.mark.timeout(120)
def test_importing_a_file_into_storage_loads_no_twin_numerics(tmp_path: Path) -> None:
    """`cranetwin import` reads, checks and stores; the replay's smoothing (scipy.signal, numba)
    is not needed and cost 1–2 CPU s per command when the rod check lived in the twin."""
    code = ("import sys; from pathlib import Path;"
            " from cranetwin.bench.importer import write_files;"
            " from cranetwin.importer import import_file; from cranetwin.model import load_machine;"
            " from cranetwin.storage import Store; m = load_machine('patu655');"
            " d = Path(sys.argv[1]); csv_path, _ = write_files(m, 500, d);"
            " st = Store.open(f'sqlite:///{d}/a.db'); st.add_machine('a', 5, b'b' * 32);"
            " n = import_file(csv_path, m, st, 'a').samples_stored; st.close();"
            " print(n, sorted(k for k in ('scipy.signal', 'numba', 'cranetwin.signal',"
            " 'cranetwin.physics', 'cranetwin.twin') if k in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True,
                         text=True, timeout=100, check=True).stdout.strip()
    assert out == "500 []", out


def test_the_console_command_runs_through_the_lazy_path() -> None:
    out = subprocess.run([sys.executable, "-c", "from cranetwin.cli import main; main()",
                          "--version"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.startswith("cranetwin ")
    out = subprocess.run([sys.executable, "-c", "from cranetwin.cli import main; main()",
                          "keys", "--help"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "Usage" in out.stdout
