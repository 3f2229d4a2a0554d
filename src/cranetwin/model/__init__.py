"""Machine descriptions: bodies, joints, actuators, sensors and ratings, loaded from TOML."""

from __future__ import annotations

from cranetwin.model.loader import builtin_machines, load_machine, machine_from_dict
from cranetwin.model.schema import (
    WORLD,
    Body,
    Channel,
    Classification,
    Cylinder,
    FatigueDetail,
    FourBar,
    Friction,
    Hydraulics,
    Joint,
    LinearActuator,
    LoadPoint,
    Machine,
    RatedLoad,
    TorqueDrive,
    Valve,
    Visual,
)

__all__ = [
    "WORLD",
    "Body",
    "Channel",
    "Classification",
    "Cylinder",
    "FatigueDetail",
    "FourBar",
    "Friction",
    "Hydraulics",
    "Joint",
    "LinearActuator",
    "LoadPoint",
    "Machine",
    "RatedLoad",
    "TorqueDrive",
    "Valve",
    "Visual",
    "builtin_machines",
    "load_machine",
    "machine_from_dict",
]
