"""Geosoft XYZ files (``.xyz``, the exchange format of airborne survey processing, Oasis montaj).

The layout read:

- comment and header records start with ``/``; the last ``/`` record before the first data row whose number of
  words equals the data rows' number of fields names the columns (``/ X Y FLUX_X FLUX_Y FLUX_Z MAG``);
- data rows are whitespace-separated; ``*`` is the null value (a dummy): such a cell reads as missing, and a row
  with a null in a column used is dropped and counted like any other non-numeric cell;
- ``Line 1001`` / ``Tie 2001`` records (also ``Trend``, ``Test``...) start a flight line: they are not data rows,
  they are counted, and each data row gets the number of its line in a ``line`` column (``line_record`` when the
  file already has a ``line`` column), so ``where="line==1001"`` selects one line.

The table keeps every cell as text (as the delimited-text reader does); :func:`is_geosoft_xyz` tells an XYZ file
from other text by its extension or its leading ``/`` record.
"""

from __future__ import annotations

import io as _stdio
import re
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from ..errors import TrimagInputError

__all__ = ["GeosoftTable", "is_geosoft_xyz", "read_xyz"]

#: records that start a line of the survey (Geosoft's line types), then the line's number
_LINE_RECORD = re.compile(r"^\s*(line|tie|trend|test|baseline|random|l|t)\s+(\S+)\s*$", re.IGNORECASE)


@dataclass
class GeosoftTable:
    """A Geosoft XYZ file read whole.

    Attributes
    ----------
    table : pandas.DataFrame
        The data rows (text cells, ``*`` kept as written: it reads as missing), with a ``line`` column when the
        file has line records.
    comments : tuple of str
        The ``/`` records other than the one naming the columns, as written.
    n_line_records : int
        ``Line`` / ``Tie`` records (not data rows).
    line_column : str or None
        The name of the added line column, None when the file has no line records.
    """

    table: pd.DataFrame
    comments: tuple[str, ...]
    n_line_records: int
    line_column: str | None


#: Surrogate code points: what a byte that is not UTF-8 reads as with ``errors="surrogateescape"``.
_SURROGATE = re.compile("[\udc80-\udcff]")


def is_geosoft_xyz(path: str | Path) -> bool:
    """True for an ``.xyz`` file, or a text file whose first non-blank line is a ``/`` record."""
    p = Path(path)
    if p.suffix.lower() == ".xyz":
        return True
    if not p.is_file():
        return False
    try:
        with p.open("r", encoding="utf-8", errors="replace") as fh:
            for _ in range(50):
                line = fh.readline(1 << 16)  # bounded: a line without end is not read whole (trimag.io.limits)
                if not line:
                    return False
                if line.strip():
                    return line.lstrip().startswith("/")
    except OSError:
        return False
    return False


def read_xyz(path: str | Path) -> GeosoftTable:
    """Read a Geosoft XYZ file (see the module docstring).

    Raises
    ------
    TrimagInputError
        No data rows, or data rows with different numbers of fields.
    """
    p = Path(path)
    with p.open("r", encoding="utf-8", errors="surrogateescape") as fh:
        text = fh.read()
    comments: list[str] = []
    data: list[str] = []
    line_of_row: list[str] = []
    current = ""
    n_line_records = 0
    names_before_data: list[str] | None = None
    width = 0
    for k, raw in enumerate(text.splitlines()):
        s = raw.strip()
        if not s:
            continue
        if s.startswith("/"):
            if not data:
                comments.append(raw)
            continue
        m = _LINE_RECORD.match(s)
        if m:
            current = m.group(2)
            n_line_records += 1
            continue
        bad = _SURROGATE.search(s)
        if bad:  # a byte that is not UTF-8 (kept as a surrogate so that comments may hold one)
            raise TrimagInputError(
                f"{p}: line {k + 1} is not UTF-8 text (byte 0x{ord(bad.group()) - 0xDC00:02x}); save the file as UTF-8"
            )
        n = len(s.split())
        if not data:
            width = n
        elif n != width:
            raise TrimagInputError(
                f"{p}: line {k + 1} has {n} fields where the data rows have {width}; fix or remove that line"
            )
        data.append(s)
        line_of_row.append(current)
    if not data:
        raise TrimagInputError(f"{p}: no data rows found in this Geosoft XYZ file (only `/` and line records)")
    for j in range(len(comments) - 1, -1, -1):
        words = comments[j].strip().lstrip("/").split()
        if len(words) == width and len(set(words)) == width:
            names_before_data = words
            del comments[j]
            break
    names = names_before_data or [f"col{i}" for i in range(width)]
    df = pd.read_csv(_stdio.StringIO("\n".join(data)), sep=r"\s+", header=None, names=names, dtype=str,
                     keep_default_na=False, engine="c")
    line_column = None
    if n_line_records:
        line_column = "line" if "line" not in names else "line_record"
        df[line_column] = line_of_row
    return GeosoftTable(df, tuple(comments), n_line_records, line_column)
