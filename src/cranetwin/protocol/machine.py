"""A machine model as registered, checked once: what registration (CLI and API) accepts, the
daemon can serve — the description loads and validates, and its channels give a wire layout.

The wire layout is derived from the machine description's sensor channels, so this is where
``protocol`` meets ``model``.
"""

from __future__ import annotations

import tomllib

from cranetwin.errors import CraneTwinError, MachineFileError
from cranetwin.model import builtin_machines, load_machine, machine_from_dict
from cranetwin.model.schema import Machine
from cranetwin.protocol.wire import Layout


def check_model(model: str, source: str = "machine model") -> tuple[Machine, Layout]:
    """Load and validate a machine model as registered: a built-in name or description TOML text.

    The one check used when a machine is registered (CLI and API) and when the daemon loads its
    keys, so that what registration accepts the daemon can serve.

    Returns:
        The machine description and its wire channel layout.

    Raises:
        MachineFileError: The model does not load; ``problems`` lists ``"field.path: message"``.
    """
    if model in builtin_machines():
        machine = load_machine(model)
    else:
        try:
            data = tomllib.loads(model)
        except tomllib.TOMLDecodeError as exc:
            known = ", ".join(builtin_machines())
            hint = "" if "\n" in model or "=" in model else f" (and not a built-in: {known})"
            raise MachineFileError(source, [f"(file): TOML syntax error: {exc}{hint}"]) from None
        machine = machine_from_dict(data, source)
    try:
        layout = Layout.from_channels(machine.channels)
    except (CraneTwinError, ValueError, TypeError) as exc:
        raise MachineFileError(source, [f"channels: {exc}"]) from exc
    return machine, layout


def layout_of(model: str) -> Layout:
    """Channel layout of a machine model: a built-in name or machine-description TOML text.

    Raises:
        MachineFileError: The model does not load.
    """
    return check_model(model, "<stored model>")[1]
