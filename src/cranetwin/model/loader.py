"""Load and validate machine description files (TOML)."""

from __future__ import annotations

import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from cranetwin.errors import MachineFileError
from cranetwin.model.schema import Machine, reference_problems


def builtin_machines() -> list[str]:
    """Names of the machine descriptions shipped with cranetwin."""
    folder = resources.files("cranetwin") / "machines"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def _format_loc(loc: tuple[int | str, ...]) -> str:
    return ".".join(str(x) for x in loc) if loc else "(file)"


def problems_from_validation(exc: ValidationError) -> list[str]:
    """One ``"field.path: message"`` line per pydantic error.

    Cross-reference problems found by :class:`Machine` arrive as one error at the top level,
    joined by ``"; "``, each already prefixed with its own field path.
    """
    out: list[str] = []
    for err in exc.errors():
        loc = _format_loc(tuple(err["loc"]))
        msg = str(err["msg"]).removeprefix("Value error, ")
        if loc == "(file)" and err["type"] == "value_error":
            out.extend(msg.split("; "))
        else:
            out.append(f"{loc}: {msg}")
    return out


def machine_from_dict(data: dict[str, Any], source: str = "<dict>") -> Machine:
    """Validate a parsed description; raise :class:`MachineFileError` listing every problem."""
    try:
        return Machine.model_validate(data)
    except ValidationError as exc:
        problems = problems_from_validation(exc)
        # field errors stop pydantic before the cross-reference check: run it on the raw data too
        problems += [p for p in reference_problems(data) if p not in problems]
        raise MachineFileError(source, problems) from exc


def load_machine(source: str | Path) -> Machine:
    """Load a machine by built-in name (e.g. ``"patu655"``) or TOML file path.

    Raises:
        MachineFileError: unreadable file, TOML syntax error, or schema violations (all listed).
    """
    text: str
    name = str(source)
    if isinstance(source, str) and source in builtin_machines():
        text = (resources.files("cranetwin") / "machines" / f"{source}.toml").read_text("utf-8")
    else:
        path = Path(source)
        try:
            text = path.read_text("utf-8")
        except FileNotFoundError as exc:
            known = ", ".join(builtin_machines())
            raise MachineFileError(
                name, [f"(file): no such file, and not a built-in machine ({known})"]
            ) from exc
        except (OSError, UnicodeDecodeError) as exc:
            raise MachineFileError(name, [f"(file): cannot read: {exc}"]) from exc
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise MachineFileError(name, [f"(file): TOML syntax error: {exc}"]) from exc
    return machine_from_dict(data, name)
