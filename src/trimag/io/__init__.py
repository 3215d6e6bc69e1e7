"""Reading and writing magnetometer logs and calibration files (I/O lives only here and in the CLI)."""

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
