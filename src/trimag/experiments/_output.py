"""Output helpers shared by the experiments: atomic CSV tables, PNG figures, JSON-safe summaries."""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ..calibration import jsonable
from ..io.atomic import atomic_write_text
from ..quality.report import save_figure

__all__ = ["jsonable", "save_figure", "write_csv", "write_dict_csv"]


def _cell(value: Any, digits: int) -> Any:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.{digits}g}"
    return value


def write_csv(path: Path, header: Sequence[str], rows: Sequence[Sequence[Any]], *, digits: int = 10) -> Path:
    """Write a CSV table atomically; floats with ``digits`` significant digits, ``None`` as an empty cell."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(header)
    writer.writerows([_cell(v, digits) for v in row] for row in rows)
    return atomic_write_text(path, buf.getvalue())


def write_dict_csv(path: Path, rows: Sequence[dict[str, Any]], *, digits: int = 6) -> Path:
    """Write a list of same-keyed dicts as a CSV table atomically (columns in the first row's key order)."""
    header = list(rows[0]) if rows else []
    return write_csv(path, header, [[r.get(k) for k in header] for r in rows], digits=digits)
