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

import typer

from cranetwin import __version__
from cranetwin.errors import CraneTwinError

# commands whose module is not named after them (``store-writer`` → ``store_writer`` is the rule)
_MODULE_OF = {"import": "importer", "machines": "ingest", "keys": "serve",
              "mqtt-ingest": "mqtt", "mqtt-send": "mqtt", "web-preview": "web"}
_BENCH_MODULE_OF = {"import": "importer"}


def _version(value: bool) -> None:
    if value:
        typer.echo(f"cranetwin {__version__}")
        raise typer.Exit()


def _root(
    version: bool = typer.Option(
        False, "--version", callback=_version, is_eager=True, help="Print the version and exit."
    ),
) -> None:
    """cranetwin: camera-less remote surveillance of hydraulic heavy equipment."""


def _submodules(package: str) -> list[str]:
    pkg = importlib.import_module(package)
    return [f"{package}.{i.name}" for i in sorted(pkgutil.iter_modules(pkg.__path__),
                                                  key=lambda i: i.name)
            if not i.name.startswith("_")]


def _module_for(package: str, command: str, aliases: dict[str, str]) -> str | None:
    """The module of ``package`` that defines ``command`` by the naming rule, if it exists."""
    name = aliases.get(command, command.replace("-", "_"))
    if not name.isidentifier() or name.startswith("_"):
        return None
    return f"{package}.{name}" if f"{package}.{name}" in _submodules(package) else None


def _register(target: typer.Typer, modules: list[str]) -> None:
    for name in modules:
        mod = importlib.import_module(name)
        if hasattr(mod, "register"):
            mod.register(target)


def build_app(argv: list[str] | None = None) -> typer.Typer:
    """The ``cranetwin`` command line.

    Every command module is imported and registered, unless ``argv`` (the arguments after the
    program name) names one command whose module follows the naming rule: then only that
    module is imported. The command modules import numpy, scipy, SQLAlchemy and the rest at
    module level, and importing all of them took 1.9 s at every start of every command.

    Args:
        argv: The command line to run, or None for the whole application (tests, help).
    """
    app = typer.Typer(
        name="cranetwin",
        help="Digital twin of hydraulic cranes: simulate, ingest, replay, serve, report.",
        no_args_is_help=True,
        add_completion=False,
        pretty_exceptions_enable=False,
        # plain help texts: with Rich markup, units in brackets ("Payload [kg]") vanish as tags
        rich_markup_mode=None,
    )
    app.callback()(_root)
    bench_app = typer.Typer(help="Benchmarks: print measured figures (and ratios to a baseline).",
                            no_args_is_help=True)
    app.add_typer(bench_app, name="bench")
    if argv == ["--version"]:
        return app
    words = [a for a in argv or [] if not a.startswith("-")]
    one = None
    if argv is not None and words and not argv[0].startswith("-"):
        if words[0] == "bench":
            if len(words) > 1:
                one = _module_for("cranetwin.bench", words[1], _BENCH_MODULE_OF)
                if one is not None:
                    _register(bench_app, [one])
                    if _defines(bench_app, words[1]):
                        return app
        else:
            one = _module_for("cranetwin.cli", words[0], _MODULE_OF)
            if one is not None:
                _register(app, [one])
                if _defines(app, words[0]):
                    return app
        return build_app(None)  # not found by the rule: everything, as help and errors expect
    _register(app, _submodules("cranetwin.cli"))
    _register(bench_app, _submodules("cranetwin.bench"))
    return app


def _defines(app: typer.Typer, command: str) -> bool:
    names = {c.name or (c.callback.__name__.replace("_", "-") if c.callback else "")
             for c in app.registered_commands}
    return command in names | {g.name for g in app.registered_groups}


_app: typer.Typer | None = None


def __getattr__(name: str) -> typer.Typer:
    """``cranetwin.cli.app``: the whole application, built on first use."""
    global _app
    if name == "app":
        if _app is None:
            _app = build_app()
        return _app
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def main() -> None:
    """Console-script entry point: run the app, turning cranetwin errors into clean exits."""
    try:
        build_app(sys.argv[1:])()
    except CraneTwinError as exc:
        typer.echo(f"error: {exc}", err=True)
        sys.exit(2)
