"""Machine-side simulator: hydraulic + multibody crane producing realistic sensor streams.

Modules: :mod:`~cranetwin.sim.recording` (the output type), :mod:`~cranetwin.sim.scenario`
(valve-voltage scenarios), :mod:`~cranetwin.sim.hydraulics` (valve, chambers, relief, end stops,
friction, slewing drive), :mod:`~cranetwin.sim.sensors` (sampling, quantisation, noise, bias,
dropouts, jitter) and :mod:`~cranetwin.sim.engine` (the fixed-step integration loop).
"""

from __future__ import annotations

from cranetwin.sim.recording import Recording, Truth, truth_columns

__all__ = ["Recording", "Truth", "truth_columns"]
