"""The ``cranetwin`` command.

Each area of the project owns one module under ``cranetwin.cli`` (commands) or ``cranetwin.bench``
(benchmarks) that defines ``register(app: typer.Typer) -> None``; this module finds and registers
them, so adding a command never means editing a shared file. Errors from cranetwin are printed as
one clear message (exit status 2), never as a traceback.
"""

from __future__ import annotations

import importlib
import pkgutil
import sys
from types import ModuleType

import typer

from cranetwin import __version__
from cranetwin.errors import CraneTwinError

app = typer.Typer(
    name="cranetwin",
    help="Digital twin of hydraulic cranes: simulate, ingest, replay, serve, report.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    # plain help texts: with Rich markup, units in brackets ("Payload [kg]") vanish as tags
    rich_markup_mode=None,
)
bench_app = typer.Typer(help="Benchmarks: print measured figures (and ratios to a baseline).",
                        no_args_is_help=True)
app.add_typer(bench_app, name="bench")


def _version(value: bool) -> None:
    if value:
        typer.echo(f"cranetwin {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(
        False, "--version", callback=_version, is_eager=True, help="Print the version and exit."
    ),
) -> None:
    """cranetwin: camera-less remote surveillance of hydraulic heavy equipment."""


def _submodules(package: str) -> list[ModuleType]:
    pkg = importlib.import_module(package)
    mods = []
    for info in sorted(pkgutil.iter_modules(pkg.__path__), key=lambda i: i.name):
        if not info.name.startswith("_"):
            mods.append(importlib.import_module(f"{package}.{info.name}"))
    return mods


for _mod in _submodules("cranetwin.cli"):
    if hasattr(_mod, "register"):
        _mod.register(app)
for _mod in _submodules("cranetwin.bench"):
    if hasattr(_mod, "register"):
        _mod.register(bench_app)


def main() -> None:
    """Console-script entry point: run the app, turning cranetwin errors into clean exits."""
    try:
        app()
    except CraneTwinError as exc:
        typer.echo(f"error: {exc}", err=True)
        sys.exit(2)
