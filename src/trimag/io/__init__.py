"""Reading and writing magnetometer logs and calibration files (I/O lives only here and in the CLI): table and
vehicle-log readers, streamed apply/evaluate, firmware writers and the one atomic writer.

The readers are imported on first use (pandas and pyarrow take ~0.3 s to import), so ``trimag.io.atomic`` and
``trimag.io.export`` stay light.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .stream import MagnitudeAccumulator, apply_file, iter_chunks, open_chunks
    from .tables import FORMATS, Samples, column_values, read_samples, read_table, resolve_columns, select_rows

__all__ = [
    "FORMATS",
    "MagnitudeAccumulator",
    "Samples",
    "apply_file",
    "column_values",
    "iter_chunks",
    "open_chunks",
    "read_samples",
    "read_table",
    "resolve_columns",
    "select_rows",
]

_HOME = {
    "MagnitudeAccumulator": "stream", "apply_file": "stream", "iter_chunks": "stream", "open_chunks": "stream",
    "FORMATS": "tables", "Samples": "tables", "column_values": "tables", "read_samples": "tables",
    "read_table": "tables", "resolve_columns": "tables", "select_rows": "tables",
}


def __getattr__(name: str) -> Any:
    if name in _HOME:
        return getattr(importlib.import_module(f".{_HOME[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
