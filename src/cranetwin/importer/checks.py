"""Convention checks on samples from any source (a file, storage, a user's arrays)."""

from __future__ import annotations

from cranetwin.importer.mapping import unit_factor
from cranetwin.importer.pipeline import position_problem
from cranetwin.model import Machine
from cranetwin.samples import SampleArrays


def check_rod_positions(samples: SampleArrays, machine: Machine) -> list[str]:
    """Problems with the rod position channels of ``samples``, one line each (empty: none).

    A channel whose values mostly lie outside [0, stroke] (beyond 1 % of the stroke) holds
    something else than stroke positions — typically pin-to-pin lengths or millimetres — and
    the twin would clip every rod to an end of its stroke; the line names the likely mix-up.
    """
    cyl = {c.name: c for c in machine.cylinders}
    out: list[str] = []
    for ch in machine.channels:
        if ch.quantity != "position" or ch.source not in cyl or ch.name not in samples.channels:
            continue
        c = cyl[ch.source]
        msg = position_problem(ch.name, samples.column(ch.name), c.stroke_m, c.closed_length_m,
                               unit_factor(ch.unit, "m", ch.name))
        if msg is not None:
            out.append(msg)
    return out
