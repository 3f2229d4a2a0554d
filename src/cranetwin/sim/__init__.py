"""Machine-side simulator: hydraulic + multibody model of any machine description (crane,
excavator, ...) producing realistic sensor streams.

Modules: :mod:`~cranetwin.sim.recording` (the output type), :mod:`~cranetwin.sim.scenario`
(valve-voltage scenarios per actuator, payload, contact force), :mod:`~cranetwin.sim.layout`
(the flat arrays' blocks for any topology), :mod:`~cranetwin.sim.hydraulics` (valve, chambers,
relief, end stops, torque drives), :mod:`~cranetwin.sim.sensors` (sampling, quantisation,
noise, bias, dropouts, jitter), :mod:`~cranetwin.sim.engine` (the compiled fixed-step loop on the
``physics.kernels``), :mod:`~cranetwin.sim.runner` (:func:`simulate`) and
:mod:`~cranetwin.sim.energy` (energy bookkeeping for checks). See docs/SIMULATOR.md.

Typical use::

    from cranetwin.model import load_machine
    from cranetwin.sim import load_scenario, simulate

    rec = simulate(load_machine("patu655"), load_scenario("fig3"))
    rec.save("fig3.npz")
"""

from __future__ import annotations

from cranetwin.sim.hydraulics import HydraulicSettings
from cranetwin.sim.recording import Recording, Truth, truth_columns
from cranetwin.sim.runner import Prepared, Session, SimOptions, prepare, simulate
from cranetwin.sim.scenario import (
    BUILTIN,
    Scenario,
    ScenarioFileError,
    builtin_scenario,
    load_scenario,
    scenario_from_dict,
)
from cranetwin.sim.sensors import SensorModel

__all__ = [
    "BUILTIN",
    "HydraulicSettings",
    "Prepared",
    "Recording",
    "Scenario",
    "ScenarioFileError",
    "SensorModel",
    "Session",
    "SimOptions",
    "Truth",
    "builtin_scenario",
    "load_scenario",
    "prepare",
    "scenario_from_dict",
    "simulate",
    "truth_columns",
]
