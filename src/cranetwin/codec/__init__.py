"""Integer codec shared by the wire protocol and storage: one place for each transformation.

The data path is float → integer steps → bits → integer steps (→ float only for callers that
want channel units). Every stage is a pure numpy function:

* :mod:`~cranetwin.codec.quantise`: values ↔ integer steps k = round(v / resolution), with a
  missing-sample mask (NaN);
* :mod:`~cranetwin.codec.delta`: zigzag mapping (scalar and array), per-channel deltas and
  their inverse, carrying the previous step through gaps;
* :mod:`~cranetwin.codec.bitpack`: frame-of-reference bit packing (the wire's data datagram)
  and byte-plane shuffling (storage's blocks).

``protocol`` frames the wire format (varints, HMAC, headers) around these; ``storage`` frames
its blob (header, zlib) around them. Imports numpy only.
"""

from __future__ import annotations

from cranetwin.codec.bitpack import (
    block_byte_planes,
    byte_planes,
    byte_width,
    from_byte_planes,
    pack_rows,
    row_widths,
    unpack_rows,
)
from cranetwin.codec.delta import (
    carry_through_gaps,
    deltas,
    undelta,
    unzigzag,
    unzigzag_array,
    zigzag,
    zigzag_array,
)
from cranetwin.codec.quantise import (
    EXACT_STEPS,
    QuantiseError,
    dequantise,
    on_grid,
    quantise,
)

__all__ = [
    "EXACT_STEPS", "QuantiseError", "block_byte_planes", "byte_planes", "byte_width",
    "carry_through_gaps", "deltas", "dequantise", "from_byte_planes", "on_grid", "pack_rows",
    "quantise", "row_widths", "undelta", "unpack_rows", "unzigzag", "unzigzag_array", "zigzag",
    "zigzag_array",
]
