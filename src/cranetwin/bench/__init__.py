"""Benchmarks. Each module registers one ``cranetwin bench NAME`` command that prints measured
figures, and ratios against a baseline measured in the same run, as JSON with ``--json``."""

from typing import Any


def emit(figures: dict[str, Any], as_json: bool) -> None:
    """Print a benchmark's figures: one JSON object, or one aligned ``key  value`` line each
    (floats to 6 significant digits)."""
    import json

    import typer

    if as_json:
        typer.echo(json.dumps(figures))
        return
    width = max((len(k) for k in figures), default=0)
    for key, value in figures.items():
        typer.echo(f"{key:<{width}}  {value:.6g}" if isinstance(value, float)
                   else f"{key:<{width}}  {value}")
