"""Bring a user's own recording in: CSV, Parquet (pyarrow) and ASAM MDF4 (asammdf) files, with a
mapping of columns, units, cylinder position convention and time (docs/IMPORT.md).

* :func:`import_file`: into storage through ``Store.write_batch`` (the ingest daemon's
  idempotent path: importing the same file twice stores it once);
* :func:`read_file` (a file), :func:`read_columns` (a dict of arrays or a DataFrame): into
  :class:`~cranetwin.samples.SampleArrays`, as storage would return them;
* :func:`check_rod_positions`: the convention check on any samples (pin-to-pin lengths or
  millimetres given as stroke positions are refused with a message naming the mix-up).

Parquet and MDF need the ``import`` extra (pyarrow, asammdf); CSV needs numpy only (pyarrow,
where installed, parses it faster).
"""

from __future__ import annotations

from cranetwin.importer.api import (
    ImportedFile,
    ImportSummary,
    import_file,
    iter_blocks,
    read_columns,
    read_file,
)
from cranetwin.importer.checks import check_rod_positions
from cranetwin.importer.mapping import (
    ChannelMap,
    ImportFileError,
    Mapping,
    load_mapping,
    mapping_from_dict,
)
from cranetwin.importer.pipeline import ImportReport, file_epoch
from cranetwin.importer.readers import Refusal

__all__ = [
    "ChannelMap", "ImportFileError", "ImportReport", "ImportSummary", "ImportedFile", "Mapping",
    "Refusal", "check_rod_positions", "file_epoch", "import_file", "iter_blocks",
    "load_mapping", "mapping_from_dict", "read_columns", "read_file",
]
