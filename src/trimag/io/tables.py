"""Readers for magnetometer logs: CSV, whitespace text, NPZ, MAT (v5 and v7.3/HDF5), Parquet.

:func:`read_samples` returns the field samples (N, 3) together with the full table (for attitude, reference and
label columns), which columns were used and why, and how many rows were dropped (non-numeric, NaN or inf in
the field columns) — rows are never lost silently.
"""

from __future__ import annotations

import csv
import dataclasses
import io as _stdio
import math
import re
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from .._core.chunks import read_block_bytes
from .._core.extras import available, require
from .._core.rowwise import count_duplicate_rows
from ..errors import TrimagInputError

if TYPE_CHECKING:
    from .logs.base import SensorChoice

__all__ = [
    "FORMATS",
    "CsvLayout",
    "Samples",
    "detect_csv_layout",
    "guess_format",
    "read_samples",
    "read_table",
    "resolve_columns",
    "select_rows",
]

FORMATS = ("csv", "txt", "xyz", "npz", "mat", "parquet", "dataflash", "tlog", "ulog", "px4log", "rosbag", "phone")
LOG_KINDS = ("dataflash", "tlog", "ulog", "px4log", "rosbag", "phone")

_AXIS_RE = re.compile(
    r"^(?:(?:imu[\s_\-.]*)?(?:mag(?:netometer|netic)?|compass|field|m|b|h)[\s_\-.]*)?([xyz])(?:[\s_\-.(\[].*)?$"
)
_TIME_NAMES = {"t", "time", "timestamp", "ts", "seconds", "sec", "ms", "us"}


@dataclass
class Samples:
    """Field samples read from a file.

    Attributes
    ----------
    field : ndarray, shape (N, 3)
        Finite field samples (rows with NaN/inf/non-numeric field cells removed).
    table : pandas.DataFrame
        The kept rows with all the file's columns (same order as ``field``); its index holds their 0-based
        data-row numbers in the file.
    columns : tuple of 3 str
        Names of the x, y, z columns used.
    column_note : str
        How the columns were chosen (for the user), empty when given explicitly.
    n_rows : int
        Data rows read (after any row selection).
    n_dropped : int
        Rows dropped because a field cell was missing, non-numeric, NaN or inf.
    dropped_index : list of int
        0-based data-row numbers of the dropped rows (first 1000).
    n_duplicates : int
        Rows whose x, y, z repeat an earlier row exactly (kept; reported because a stuck or repeating
        logger shows up here).
    selection : str
        Row selection applied (``--rows`` / ``--where``), empty when none.
    """

    field: NDArray[np.float64]
    table: pd.DataFrame
    columns: tuple[str, str, str]
    column_note: str = ""
    n_rows: int = 0
    n_dropped: int = 0
    dropped_index: list[int] = dataclasses.field(default_factory=list)
    n_duplicates: int = 0
    selection: str = ""
    source: str = ""
    n_total_rows: int = 0
    #: what an autopilot log told (unit, magnetometer, GPS, messages), None for other files
    log_info: dict[str, Any] | None = None
    #: what the file's format told besides the rows (e.g. a Geosoft XYZ file's line records and `*` nulls)
    format_note: str = ""
    #: rows dropped as wild (:func:`trimag.validation.wild_rows`: a glitch, not a field; counted in ``n_dropped``),
    #: their 0-based data-row numbers (first 1000) and what they were
    n_wild: int = 0
    wild_index: list[int] = dataclasses.field(default_factory=list)
    wild_note: str = ""
    #: the variable of an NPZ or MAT file the samples were taken from (``imu_mag``), empty for other files
    variable: str = ""
    #: the unit the file states besides its column names (a ``trimag live`` recording's first line), empty if none
    stated_unit: str = ""


def detect_format(path: str | Path, fmt: str | None = None) -> str:
    """:func:`guess_format`, and a text file whose first record starts with ``/`` is Geosoft XYZ; a trimag
    calibration or compensation file given as a log is refused, naming the commands that take it."""
    kind = guess_format(path, fmt)
    if kind in ("csv", "txt"):
        refuse_calibration_file(path)
    if kind in ("csv", "txt") and fmt is None:
        from .geosoft import is_geosoft_xyz

        if is_geosoft_xyz(path):
            return "xyz"
    return kind


_CALIBRATION_FILE = re.compile(rb'"format"\s*:\s*"trimag-(calibration|compensation)"')


def refuse_calibration_file(path: str | Path) -> None:
    """Refuse a trimag calibration (or Tolles–Lawson compensation) file given where a log is expected: its
    ``"format"`` entry is on one of its first lines (:meth:`trimag.Calibration.to_json`)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(512)
    except OSError:
        return  # the reader says what is wrong with the path
    found = _CALIBRATION_FILE.search(head)
    if found is not None:
        kind = found.group(1).decode()
        takes = ("`trimag apply` or `trimag evaluate`" if kind == "compensation"  # (export has no compensation)
                 else "`trimag apply`, `trimag evaluate` or `trimag export`")
        raise TrimagInputError(
            f"{path}: this is a {kind} file, not a log of x, y, z samples: give it to {takes} (e.g. `trimag apply "
            f"{Path(path).name} LOG.csv -o OUT.csv`)"
        )


def guess_format(path: str | Path, fmt: str | None = None) -> str:
    """The format named by ``fmt`` or, when None, by the file's extension (autopilot logs included)."""
    from .logs import log_format

    kind = log_format(path, fmt.lower().lstrip(".") if fmt else None)
    if kind is not None:
        return kind
    if fmt:
        f = fmt.lower().lstrip(".")
        if f not in FORMATS:
            raise TrimagInputError(f"unknown `fmt` {fmt!r}; choose one of {', '.join(FORMATS)}")
        return f
    ext = Path(path).suffix.lower().lstrip(".")
    mapping = {"csv": "csv", "txt": "txt", "xyz": "xyz", "dat": "txt", "tsv": "txt", "log": "txt", "npz": "npz",
               "npy": "npz", "mat": "mat", "parquet": "parquet", "pq": "parquet"}
    if ext in mapping:
        return mapping[ext]
    return "csv"


@dataclass(frozen=True)
class CsvLayout:
    """Where the data start in a delimited text file: ``skip`` preamble lines, then a header (or not)."""

    skip: int
    has_header: bool
    delimiter: str | None  # None = whitespace
    preamble: tuple[str, ...] = ()
    n_fields: int = 0
    #: every field of the data lines read while sniffing is a plain number (no spaces, not empty): the reader
    #: may then try typed float columns first
    all_numeric: bool = False
    #: the header's fields as written, when they are distinct and non-empty (the column names pandas would give
    #: them); None otherwise (no header, or names pandas would rename: the reader then asks pandas)
    header: tuple[str, ...] | None = None


def _is_number(tok: str) -> bool:
    tok = tok.strip()
    if tok == "":
        return False
    try:
        float(tok)
    except ValueError:
        return tok.lower() in {"nan", "inf", "-inf", "+inf"}
    return True


#: A number as Python's ``float`` and Arrow's float columns read it (optional sign, digits, point, exponent; ``nan``,
#: ``inf``), no spaces. Only decides which read is tried first (:attr:`CsvLayout.all_numeric`): a token Arrow then
#: refuses costs a second read, never a different result.
_PLAIN_NUMBER = re.compile(r"[+-]?(?:(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?|nan|inf(?:inity)?)", re.IGNORECASE)


#: Data lines :func:`_plain_numbers` looks at.
_PLAIN_LINES = 50


def _plain_numbers(lines: list[str], delimiter: str | None) -> bool:
    """Every non-blank line is plain numbers joined by ``delimiter`` (whitespace when None): one match per line."""
    num = _PLAIN_NUMBER.pattern
    if delimiter is None:
        line_re = re.compile(rf"\s*{num}(?:\s+{num})*\s*", re.IGNORECASE)
    else:  # a cell may be quoted, as the csv module and Arrow read it
        cell = f'(?:{num}|"{num}")'
        line_re = re.compile(f"{cell}(?:{re.escape(delimiter)}{cell})*", re.IGNORECASE)
    return all(line_re.fullmatch(ln) is not None for ln in lines if ln.strip())


def _split(line: str, delimiter: str | None) -> list[str]:
    if delimiter is None:
        return line.split()
    try:
        return next(csv.reader([line], delimiter=delimiter))
    except csv.Error:  # a quote never closed (binary bytes): a cell longer than the csv module's limit is no number
        return line.split(delimiter)


def detect_csv_layout(path: str | Path, *, fmt: str = "csv") -> CsvLayout:
    """Find the delimiter, any preamble lines (e.g. ``Fs,50.00``) and whether a header row names the columns.

    The data block starts at the first line with >= 3 fields that is followed by a line with the same number of
    fields, mostly numeric; the line before the numbers is a header if it is not numeric itself. The preamble and
    the header must be UTF-8, as the rows must (every reader skips them undecoded: ``fit`` took a header that
    ``apply`` and ``evaluate`` refused, issue 41 item 17).
    """
    layout = _detect_csv_layout(path, fmt=fmt)
    _check_utf8_head(Path(path), layout.skip + int(layout.has_header))
    return layout


def _check_utf8_head(path: Path, n_lines: int) -> None:
    """Refuse (:class:`TrimagInputError`, :func:`not_utf8`) a file whose first ``n_lines`` lines are not UTF-8."""
    from .limits import current_limits
    from .normalise import source_name

    cap = current_limits().max_line_bytes
    with path.open("rb") as fh:
        for _ in range(n_lines):
            try:
                fh.readline(cap + 1).decode("utf-8")
            except UnicodeDecodeError as exc:
                raise TrimagInputError(f"{source_name(path)}: {not_utf8(exc)}") from None


def _detect_csv_layout(path: str | Path, *, fmt: str = "csv") -> CsvLayout:
    from .limits import current_limits, read_head_lines
    from .normalise import source_name

    p = Path(path)
    where = source_name(p)
    lines = [ln.rstrip("\r\n") for ln in read_head_lines(p, 200, where=where)]
    if not any(ln.strip() for ln in lines):
        raise TrimagInputError(f"{where}: the file is empty; it needs a header (optional) and rows of x, y, z values")
    sample = "\n".join(lines[:50])
    if fmt == "txt" and "," not in sample and ";" not in sample and "\t" not in sample:
        delimiter: str | None = None
    else:
        counts = {d: sample.count(d) for d in (",", ";", "\t")}
        best = max(counts, key=lambda d: counts[d])
        delimiter = best if counts[best] > 0 else None
    limits = current_limits()
    for k, line in enumerate(lines):  # a line of more fields than allowed is never made into columns
        if (line.count(delimiter) + 1 if delimiter else len(line.split())) > limits.max_fields:
            n_fields = len(_split(line, delimiter))
            if n_fields > limits.max_fields:
                raise limits.too_many_fields(where, k + 1, n_fields)
    # lines are split only as far as the search needs (the data usually start within the first few lines)
    split: list[list[str] | None] = [None] * len(lines)

    def row(k: int) -> list[str]:
        fields = split[k]
        if fields is None:
            fields = split[k] = _split(lines[k], delimiter) if lines[k].strip() else []
        return fields

    for i in range(len(lines)):
        fields = row(i)
        if not fields:
            continue
        numeric = [_is_number(t) for t in fields]
        nxt = next((r for r in map(row, range(i + 1, len(lines))) if r), None)
        same_width = nxt is None or len(nxt) == len(fields)
        if len(fields) >= 3 and sum(numeric) >= max(2, (len(fields) + 1) // 2) and same_width:
            # first data-like line; is the previous non-empty line a header of the same width?
            j = i - 1
            while j >= 0 and not row(j):
                j -= 1
            numeric_before = [k for k in range(i) if len(row(k)) >= 2 and all(_is_number(t) for t in row(k))]
            if numeric_before:  # rows of numbers before the data block: a malformed row, never skipped silently
                bad = next((k for k in range(numeric_before[0], i) if len(row(k)) != len(fields)), numeric_before[0])
                raise TrimagInputError(
                    f"{where}: line {bad + 1} has {len(row(bad))} fields where the data rows have {len(fields)}; "
                    "fix or remove that line"
                )
            plain = _plain_numbers(lines[i : i + _PLAIN_LINES], delimiter)
            if j >= 0 and len(row(j)) == len(fields) and not any(_is_number(t) for t in row(j)):
                names = tuple(row(j))
                distinct = len(set(names)) == len(names) and all(n.strip() and "\ufeff" not in n for n in names)
                return CsvLayout(j, True, delimiter, tuple(lines[:j]), len(fields), plain, names if distinct else None)
            return CsvLayout(i, False, delimiter, tuple(lines[:i]), len(fields), plain)
    rows = [row(k) for k in range(len(lines))]
    # no numeric line found: too few columns, header only, or no numbers at all
    narrow = [r for r in rows if r and all(_is_number(t) for t in r)]
    if narrow:
        raise TrimagInputError(
            f"{where}: rows have only {max(len(r) for r in narrow)} numeric column(s); a magnetometer log needs "
            "three (x, y, z)"
        )
    widths = [len(r) for r in rows if r]
    if len(rows) and widths and len([r for r in rows if r]) == 1:
        raise TrimagInputError(f"{where}: the file has a header but no data rows")
    raise TrimagInputError(f"{where}: no rows of numbers found; expected columns of x, y, z field values")


def not_utf8(exc: UnicodeDecodeError) -> str:
    """What a text file that is not UTF-8 is, in the user's words (the byte, not Python's codec message)."""
    bad = exc.object[exc.start:exc.start + 1]
    byte = f"byte 0x{bad[0]:02x}" if isinstance(bad, bytes | bytearray) and bad else "a byte"
    return (f"not UTF-8 text ({byte}, as a spreadsheet's Latin-1 or UTF-16 export writes): save it as UTF-8 "
            "text (in a spreadsheet: CSV UTF-8)")


def _read_delimited(path: Path, fmt: str) -> tuple[pd.DataFrame, CsvLayout]:
    layout = detect_csv_layout(path, fmt=fmt)
    kwargs: dict[str, Any] = {
        "skiprows": layout.skip,
        "header": 0 if layout.has_header else None,
        "skip_blank_lines": True,
        "dtype": str,
        "keep_default_na": False,
    }
    if layout.delimiter is None:
        kwargs["sep"] = r"\s+"
    else:
        kwargs["sep"] = layout.delimiter
    try:  # pyarrow's reader when the `parquet` extra is installed; pandas' otherwise (same rows and cells)
        if layout.delimiter is None or not available("pyarrow"):
            df = None
        elif layout.n_fields <= NARROW_ROW_FIELDS:  # short rows: the reader's memory would outweigh the data
            df = _arrow_system_pool(_read_narrow_rows, path, layout, kwargs)
        else:
            df = _read_delimited_arrow(path, layout, kwargs)
        if df is None:
            df = pd.read_csv(path, **kwargs)
    except UnicodeDecodeError as exc:
        from .normalise import source_name

        raise TrimagInputError(f"{source_name(path)}: {not_utf8(exc)}") from None
    except pd.errors.ParserError as exc:
        from .normalise import source_name

        raise TrimagInputError(f"{source_name(path)}: cannot parse as delimited text: {str(exc).splitlines()[0]}") \
            from None
    if not layout.has_header:
        df.columns = [f"col{i}" for i in range(df.shape[1])]
    df.columns = [str(c).strip() for c in df.columns]
    return df, layout


#: Fields per row up to which a CSV is read by :func:`_arrow_system_pool`: for rows of a few short numbers Arrow's
#: retained blocks were most of the peak (50 of 100 bytes per row of `1,2,3`) and the read is faster too; for
#: long rows they are a small share (2.6 -> 2.2 bytes per byte) and returning them cost 10-20 % of the read's CPU
NARROW_ROW_FIELDS = 6


def _arrow_system_pool(read: Callable[..., pd.DataFrame | None], *args: Any) -> pd.DataFrame | None:
    """``read(*args)`` with the C library's allocator as Arrow's memory pool, not Arrow's default (mimalloc): what
    Arrow frees (the parser's blocks, a column once copied into the samples) goes back to the process for numpy
    instead of staying in Arrow's pool (on a log of short rows the peak was 50 bytes per row higher). The default
    pool is restored after the read (buffers remember their pool); after a large read the freed memory is
    returned to the system (:func:`_return_freed_memory`)."""
    import pyarrow as pa

    before = pa.default_memory_pool()
    pa.set_memory_pool(pa.system_memory_pool())
    try:
        df = read(*args)
    finally:
        pa.set_memory_pool(before)
    if df is not None and len(df) >= SHARED_XYZ_ROWS:  # (1 ms a call: not for a small log)
        _return_freed_memory()
    return df


def _return_freed_memory() -> None:
    """Give the C library's freed memory back to the system (glibc's ``malloc_trim``): the parser's blocks, freed
    after the read, stay in the heap otherwise, under the arrays allocated next (30-40 bytes per row of a short-row
    log). Nothing where the C library has no such call."""
    import ctypes

    try:
        libc = ctypes.CDLL(None)  # the process' own C library (find_library ran `ldconfig -p` on every call)
        libc.malloc_trim(0)
    except (OSError, AttributeError):
        pass


#: Bytes from which a CSV of short plain-number rows is parsed block by block into one preallocated array
#: (:func:`_read_numeric_blocks`); smaller files are read whole (a batch of 5000-row logs)
NARROW_STREAM_BYTES = 2_000_000


def _read_narrow_rows(path: Path, layout: CsvLayout, kwargs: dict[str, Any]) -> pd.DataFrame | None:
    """A CSV of at most :data:`NARROW_ROW_FIELDS` fields per row: a large one of plain numbers parsed block by
    block into one float64 array (:func:`_read_numeric_blocks`), any other by :func:`_read_delimited_arrow`."""
    if layout.all_numeric and path.stat().st_size >= NARROW_STREAM_BYTES:
        df = _read_numeric_blocks(path, layout, kwargs)
        if df is not None:
            return df
        # a cell that is not a number, or a row of another width: the whole file as text (a typed read of it
        # would fail the same way, a third pass)
        layout = dataclasses.replace(layout, all_numeric=False)
    return _read_delimited_arrow(path, layout, kwargs)


def _column_names(path: Path, layout: CsvLayout, kwargs: dict[str, Any]) -> list[str]:
    """The names pandas gives the columns of a delimited file (``0, 1, ...`` without a header)."""
    if layout.header is not None:  # distinct, non-empty names: pandas would keep them as they are
        return list(layout.header)
    if not layout.has_header:
        return [str(k) for k in range(layout.n_fields)]
    return [str(c) for c in pd.read_csv(path, nrows=0, **kwargs).columns]  # pandas' renaming ("x.1", "Unnamed: 2")


def _line_count(path: Path) -> int:
    """Newlines in the file, plus one: at least its rows (1 GB/s; a block of 1 MB at a time)."""
    count = 1
    with path.open("rb") as fh:
        while block := fh.read(1 << 20):
            count += block.count(b"\n")
    return count


def _read_numeric_blocks(path: Path, layout: CsvLayout, kwargs: dict[str, Any]) -> pd.DataFrame | None:
    """Every column of the file as float64 (empty cells NaN), parsed by Arrow's streaming reader block by block
    into one preallocated (N, fields) array; the table's columns are views of it (issue 41, item 10: Arrow's
    whole-file table and its conversion to pandas held 2-3 copies of the numbers at the peak, 40-50 bytes per row
    of `1,2,3`; here the numbers are held once, plus one block). The array is sized by the file's newlines (pages
    never written cost no memory) and shrunk to the rows read. None when a cell is not a plain number (the caller
    then reads the file whole, as strings where needed)."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    names = _column_names(path, layout, kwargs)
    # 256 KiB of text a block at the default working memory (Arrow's streaming reader holds some 20-30 parsed blocks
    # ahead: 1 MiB blocks took 44 MB on 12 MB of `1,2,3` rows, 256 KiB ones 19 MB, and read as fast)
    reader_options = pacsv.ReadOptions(skip_rows=layout.skip + int(layout.has_header), column_names=names,
                                       block_size=read_block_bytes(1 << 18))
    convert = pacsv.ConvertOptions(column_types=dict.fromkeys(names, pa.float64()), null_values=[""],
                                   strings_can_be_null=False)
    # at most a row per newline, and per n_fields bytes (`,,` and its newline)
    capacity = min(_line_count(path), path.stat().st_size // len(names) + 1)
    # three columns: one (N, 3) array, the samples themselves when they are x, y, z in order (_held_xyz); more: an
    # array per column, so that x, y, z are each freed once copied into the samples (_take_xyz)
    try:
        values = np.empty((capacity, 3)) if len(names) == 3 else None
        columns = [] if values is not None else [np.empty(capacity) for _ in names]
    except MemoryError:  # (address space refused: the whole-file reader says what it can)
        return None
    n = 0
    try:
        reader = pacsv.open_csv(path, read_options=reader_options,
                                parse_options=pacsv.ParseOptions(delimiter=layout.delimiter),
                                convert_options=convert, memory_pool=pa.default_memory_pool())  # (the system's)
        for batch in reader:
            m = batch.num_rows
            if n + m > capacity:  # (never: a row ends at a newline or at the file's end)
                return None
            for k, column in enumerate(batch.columns):
                (values[:, k] if values is not None else columns[k])[n : n + m] = column.to_numpy(
                    zero_copy_only=False)
            n += m
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError, pa.ArrowTypeError):
        return None
    if n == 0:
        return None  # header only: pandas gives the same empty frame and the caller's message
    if values is not None:  # (no view of it is left: resized in place, the unused pages given back)
        values.resize((n, 3), refcheck=False)
        return pd.DataFrame(values, columns=names, copy=False)
    for array in columns:
        array.resize(n, refcheck=False)
    return pd.DataFrame(dict(zip(names, columns, strict=True)), copy=False)


def _read_delimited_arrow(path: Path, layout: CsvLayout, kwargs: dict[str, Any]) -> pd.DataFrame | None:
    """The whole file by pyarrow's multithreaded CSV reader (10x faster than pandas on 1e7 rows).

    When the sniffed data lines are all plain numbers (``layout.all_numeric``), every column is first read as
    float64, empty cells as NaN (dropped and counted later, as on the string path): no string per cell, about
    5x less memory. If any cell is not a plain number that read fails and the file is read again with every
    column typed as a string (as pandas reads it with ``dtype=str``); the numbers are the same either way
    (both use Arrow's string-to-double conversion). None when pyarrow refuses the file (e.g. a row with a
    different number of fields): the caller then uses pandas, whose messages name the problem."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    names = _column_names(path, layout, kwargs)
    read_options = pacsv.ReadOptions(skip_rows=layout.skip + int(layout.has_header), column_names=names)
    parse_options = pacsv.ParseOptions(delimiter=layout.delimiter)
    pool = pa.default_memory_pool()  # the system's: _arrow_system_pool
    table = None
    if layout.all_numeric:
        try:
            table = pacsv.read_csv(
                path, read_options=read_options, parse_options=parse_options,
                convert_options=pacsv.ConvertOptions(
                    column_types=dict.fromkeys(names, pa.float64()), null_values=[""], strings_can_be_null=False,
                ), memory_pool=pool,
            )
        except (pa.ArrowInvalid, pa.ArrowNotImplementedError, pa.ArrowTypeError):
            table = None
    if table is None:
        try:
            table = pacsv.read_csv(
                path, read_options=read_options, parse_options=parse_options,
                convert_options=pacsv.ConvertOptions(
                    column_types=dict.fromkeys(names, pa.string()), strings_can_be_null=False,
                    quoted_strings_can_be_null=False,
                ), memory_pool=pool,
            )
        except (pa.ArrowInvalid, pa.ArrowNotImplementedError, pa.ArrowTypeError):
            return None
    if table.num_rows == 0:
        return None  # header only: pandas gives the same empty frame and the caller's message
    # one block per column and Arrow's buffers freed as they are converted: no second copy of the log
    df = table.to_pandas(memory_pool=pool, split_blocks=True, self_destruct=True)
    del table
    if not all(dtype == np.float64 or pd.api.types.is_string_dtype(dtype) for dtype in df.dtypes):
        return None
    return df


def _array_table(arr: Any, name: str, path: Path) -> pd.DataFrame:
    a = np.asarray(arr)
    if a.dtype.kind not in "fiub":
        raise TrimagInputError(f"{path}: variable {name!r} is not numeric (dtype {a.dtype})")
    a = np.squeeze(a)
    if a.ndim != 2:
        raise TrimagInputError(f"{path}: variable {name!r} must be 2-D (N x 3 or 3 x N); got shape {a.shape}")
    if a.shape[1] > a.shape[0]:
        a = a.T
    df = pd.DataFrame(a.astype(np.float64), columns=[f"col{i}" for i in range(a.shape[1])])
    df.attrs["trimag_variable"] = name  # which variable of the file (said with the columns: issue 39)
    return df


def _pick_variable(candidates: dict[str, Any], var: str | None, path: Path) -> str:
    if var is not None:
        if var not in candidates:
            raise TrimagInputError(
                f"{path}: no variable {var!r}; variables are {', '.join(sorted(candidates)) or 'none'}"
            )
        return var
    usable = {}
    for k, v in candidates.items():
        shape = np.shape(v)
        squeezed = [s for s in shape if s != 1]
        if len(squeezed) == 2 and min(squeezed) >= 3 and np.asarray(v).dtype.kind in "fiu":
            usable[k] = v
    if not usable:
        raise TrimagInputError(f"{path}: no 2-D numeric variable with >= 3 columns; name one with `var`")
    preferred = [k for k in usable if re.search(r"mag|compass|field", k, re.I)]
    if len(preferred) == 1:
        return preferred[0]
    if len(usable) == 1:
        return next(iter(usable))
    raise TrimagInputError(
        f"{path}: several arrays could hold the field ({', '.join(sorted(usable))}); choose one with `var`"
    )


def _struct_table(value: Any, name: str, path: Path) -> pd.DataFrame:
    """A MATLAB struct's vector fields of the common (longest) length as columns ``NAME.FIELD``."""
    record = np.asarray(value).ravel()[0]
    fields: dict[str, NDArray[np.float64]] = {}
    for field_name in np.asarray(value).dtype.names or ():
        arr = np.asarray(record[field_name])
        if arr.dtype.kind not in "fiub":
            continue
        arr = np.squeeze(arr)
        if arr.ndim == 1 and len(arr) > 1:
            fields[f"{name}.{field_name}"] = arr.astype(np.float64)
    if not fields:
        raise TrimagInputError(f"{path}: struct {name!r} has no numeric vector fields")
    n = max(len(a) for a in fields.values())
    df = pd.DataFrame({k: a for k, a in fields.items() if len(a) == n})
    df.attrs["trimag_variable"] = name
    return df


_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def _is_hdf5(path: Path) -> bool:
    """True when the file carries the HDF5 signature where MATLAB v7.3 (after its 512-byte header) or a plain
    HDF5 file puts it."""
    with path.open("rb") as fh:
        head = fh.read(520)
    return head[:8] == _HDF5_SIGNATURE or head[512:520] == _HDF5_SIGNATURE


def _read_mat(path: Path, var: str | None) -> pd.DataFrame:
    import scipy.io

    try:
        with warnings.catch_warnings():  # "Duplicate variable name": scipy keeps the last one, as MATLAB does
            warnings.simplefilter("ignore", scipy.io.matlab.MatReadWarning)
            data = scipy.io.loadmat(path)
        candidates = {k: v for k, v in data.items() if not k.startswith("__")}
        structs = {k: v for k, v in candidates.items() if getattr(np.asarray(v).dtype, "names", None)}
        if structs and (var in structs or (var is None and len(structs) == len(candidates) == 1)):
            name = var if var is not None else next(iter(structs))
            return _struct_table(structs[name], name, path)
        name = _pick_variable(candidates, var, path)
        return _array_table(candidates[name], name, path)
    except NotImplementedError:
        pass  # MATLAB v7.3 = HDF5
    except ValueError as exc:
        if "Unknown mat file type" not in str(exc) and "Mat file appears to be truncated" not in str(exc):
            raise TrimagInputError(f"{path}: cannot read MAT file: {exc}") from None
    if not available("h5py"):
        if _is_hdf5(path):
            require("h5py", f"{path}: reading MATLAB v7.3 (HDF5) files")  # raises: the extra is missing
        raise TrimagInputError(f"{path}: not a readable MAT file (neither MATLAB v4-v7.2 nor v7.3/HDF5)")
    import h5py

    try:
        with h5py.File(path, "r") as h5:
            candidates = {k: h5[k] for k in h5.keys() if isinstance(h5[k], h5py.Dataset)}
            name = _pick_variable({k: np.empty(v.shape, dtype=v.dtype) for k, v in candidates.items()}, var, path)
            return _array_table(np.asarray(candidates[name]), name, path)
    except OSError as exc:
        raise TrimagInputError(f"{path}: not a readable MAT file ({exc})") from None


def file_variables(path: str | Path, fmt: str | None = None) -> dict[str, NDArray[Any]]:
    """Every numeric array variable of an NPZ or MAT file (v4-v7.2; v7.3 with the ``mat`` extra), by name; an
    empty dict for any other kind of file. What a gyroscope or a sample rate stored beside the magnetometer is
    read from (``imu_gyr``, ``sampling_rate``)."""
    p = Path(path)
    kind = detect_format(p, fmt)
    if kind == "npz" and p.suffix.lower() != ".npy":
        if _npz_size(p) > _limits().max_decompressed_bytes:
            raise _limits().too_large(str(p), "its arrays are decompressed")
        with np.load(p, allow_pickle=False) as data:
            found = {k: data[k] for k in data.files}
    elif kind == "mat":
        import scipy.io

        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", scipy.io.matlab.MatReadWarning)
                found = {k: v for k, v in scipy.io.loadmat(p).items() if not k.startswith("__")}
        except NotImplementedError:  # MATLAB v7.3 = HDF5
            h5py = require("h5py", f"{p}: reading MATLAB v7.3 (HDF5) files")
            with h5py.File(p, "r") as h5:
                found = {k: np.asarray(h5[k]) for k in h5.keys() if isinstance(h5[k], h5py.Dataset)}
    else:
        return {}
    return {k: np.asarray(v) for k, v in found.items() if np.asarray(v).dtype.kind in "fiub"}


def _limits() -> Any:
    from .limits import current_limits

    return current_limits()


def _npz_size(path: Path) -> int:
    """Bytes the arrays of an NPZ file (a zip archive) expand to, as its members declare (0 for an NPY file)."""
    import zipfile

    if not zipfile.is_zipfile(path):
        return 0
    try:
        with zipfile.ZipFile(path) as zf:
            return sum(member.file_size for member in zf.infolist())
    except (OSError, zipfile.BadZipFile):
        return 0  # np.load names the damage


def _check_npy_size(path: Path) -> None:
    """Refuse an NPY file whose header declares more data than the file holds (issue 41, item 17: a 368-byte file
    claiming 240 GB said "not enough memory ... fit part of it"): it is truncated or damaged."""
    from numpy.lib import format as npy_format

    try:
        with open(path, "rb") as fh:
            version = npy_format.read_magic(fh)
            read_header = npy_format.read_array_header_1_0 if version == (1, 0) else npy_format.read_array_header_2_0
            shape, _, dtype = read_header(fh)
            data_bytes = path.stat().st_size - fh.tell()
    except (OSError, ValueError):
        return  # np.load names the damage
    declared = math.prod(int(d) for d in shape) * dtype.itemsize
    if declared > data_bytes:
        raise TrimagInputError(f"{path}: its header declares an array of shape {tuple(shape)} "
                               f"({declared / 1e6:.4g} MB) but the file holds {data_bytes} bytes of data: the file is "
                               "truncated or damaged")


def _read_npz(path: Path, var: str | None) -> pd.DataFrame:
    from .limits import current_limits

    if _npz_size(path) > current_limits().max_decompressed_bytes:
        raise current_limits().too_large(str(path), "its arrays are decompressed")
    try:
        if path.suffix.lower() == ".npy":
            _check_npy_size(path)
            return _array_table(np.load(path, allow_pickle=False), "array", path)
        with np.load(path, allow_pickle=False) as data:
            candidates = {k: data[k] for k in data.files}
    except (OSError, ValueError) as exc:
        raise TrimagInputError(f"{path}: not a readable NPZ file ({exc})") from None
    name = _pick_variable(candidates, var, path)
    return _array_table(candidates[name], name, path)


def _read_vehicle_log(p: Path, kind: str, sensor: SensorChoice) -> pd.DataFrame:
    """An autopilot log as a table of one magnetometer with the other streams aligned (``io.logs``).

    ``df.attrs["trimag_log"]`` carries what the fit needs from the log: the unit, the magnetometer used, what was
    undone, the GPS fix (for IGRF) and the messages for the user.
    """
    from .logs import read_log

    log = read_log(p, kind)
    mag = log.choose(sensor)
    df, messages = log.table(sensor)
    df.attrs["trimag_log"] = {
        "format": log.format,
        "unit": mag.unit,
        "sensor": mag.name,
        "instance": mag.instance,
        "compass": mag.number,  # as the user numbers it (`sensor`, export's instance): from 1
        "compasses": [{"number": m.number, "name": m.name, "n_samples": len(m.time_s)} for m in log.magnetometers],
        "device_id": mag.device_id,
        "ekf_mag_device_ids": None if log.ekf_mag_device_ids is None else list(log.ekf_mag_device_ids),
        "gps": log.gps,
        "messages": log.summary_lines(sensor) + messages,
        "channels": [c for c in df.columns if c not in ("time_s",) and not c.startswith(("mag_", "yaw_g"))],
        "has_attitude": "yaw_deg" in df.columns,
        "attitude_source": None if log.attitude is None else log.attitude.source,
        "vehicle": log.vehicle,
        "parameters": dict(log.parameters),
        "yaw_sources": [c for c in ("yaw_gps_deg", "yaw_gsf_deg") if c in df.columns],
        "attitude_sources": {name: ch.source for name, ch in log.attitudes.items() if "yaw_dcm_deg" in df.columns},
        # the gyroscope (read again for the gyro-aided fit: a DataFlash log's IMU only then, docs/method-gyro.md)
        "gyro": log.gyro.source if log.gyro is not None else ("IMU (read on request)" if kind == "dataflash" else None),
    }
    return df


def strict_refusal(where: str, n_bad: int, values: str, first: str) -> TrimagInputError:
    """The one message of ``strict`` for rows that would be skipped: ``n_bad`` rows of ``where`` (a path and ": ",
    or "") have ``values`` missing, the first at ``first`` ("data row 17", "kept row 3")."""
    return TrimagInputError(f"{where}{n_bad} row(s) have {values} (first at {first}); fix them, or drop `strict` to "
                            "skip and count them")


def check_sensor(kind: str, sensor: SensorChoice, path: str | Path) -> None:
    """Refuse a ``sensor`` for a file that is not an autopilot log (a table has one magnetometer: its columns)."""
    if sensor is not None and kind not in LOG_KINDS:
        raise TrimagInputError(
            f"`sensor` picks a magnetometer of an autopilot log ({', '.join(LOG_KINDS)}); {path} is a {kind} file "
            "with one: drop `sensor` (choose its field with `columns`)"
        )


#: The first line of a ``trimag live`` samples file: ``# trimag live recording (SOURCE); unit G``.
_LIVE_UNIT = re.compile(r"^#\s*trimag live recording\b.*;\s*unit\s+(nT|uT|G|mG|counts)\s*$")


def refuse_stream(p: Path) -> None:
    """Refuse a pipe, a FIFO, a terminal or a device given as a log (issue 41, item 17: ``fit /dev/stdin`` said
    "cannot read or write: lseek failed", a FIFO hung): trimag reads a log more than once."""
    import stat

    try:
        mode = p.stat().st_mode
    except OSError:
        return  # the reader says what is wrong with the path
    if stat.S_ISREG(mode) or stat.S_ISDIR(mode):
        return
    kind = "a pipe (FIFO)" if stat.S_ISFIFO(mode) else "a socket" if stat.S_ISSOCK(mode) else "a device or terminal"
    raise TrimagInputError(f"{p} is {kind}, not a file: trimag reads a log more than once (its layout first); save "
                           "the data to a file (e.g. `my_logger > log.csv`) and give that file (for a live stream: "
                           "trimag live --stdin)")


def read_table(
    path: str | Path, *, fmt: str | None = None, var: str | None = None, sensor: SensorChoice = None
) -> pd.DataFrame:
    """Read a whole log into a DataFrame (text cells stay strings; see :func:`read_samples`)."""
    p = Path(path)
    if str(path).strip() == "-":
        raise TrimagInputError("standard input (-) is not read as a log: trimag reads a log more than once (its layout "
                               "first); save the data to a file (e.g. `my_logger > log.csv`) and give that file")
    if not p.exists():
        raise TrimagInputError(f"{p}: no such file")
    refuse_stream(p)
    if fmt is None or fmt in ("csv", "txt"):
        from .normalise import plain_path

        p = plain_path(p)  # compressed text, decimal commas
    kind = detect_format(p, fmt)
    if p.is_dir() and kind != "rosbag":
        raise TrimagInputError(f"{p}: is a folder; give a data file")
    if kind in LOG_KINDS:
        return _read_vehicle_log(p, kind, sensor)
    check_sensor(kind, sensor, p)
    if kind in ("csv", "txt"):
        df, layout = _read_delimited(p, kind)
        stated = next((m.group(1) for m in map(_LIVE_UNIT.search, layout.preamble) if m), None)
        if stated is not None:  # a `trimag live` recording states its unit on its first line
            df.attrs["trimag_stated_unit"] = stated
        return df
    if kind == "xyz":
        from .geosoft import read_xyz

        xyz = read_xyz(p)
        xyz.table.attrs["trimag_xyz"] = {"n_line_records": xyz.n_line_records, "line_column": xyz.line_column,
                                         "comments": list(xyz.comments)}
        return xyz.table
    if kind == "npz":
        return _read_npz(p, var)
    if kind == "mat":
        return _read_mat(p, var)
    require("pyarrow.parquet", "reading Parquet files")
    try:
        return pd.read_parquet(p, engine="pyarrow")
    except Exception as exc:  # pyarrow raises several types
        raise TrimagInputError(f"{p}: not a readable Parquet file ({exc})") from None


def _numeric(series: pd.Series) -> NDArray[np.float64]:
    if series.dtype.kind in "fiub":
        return series.to_numpy(dtype=np.float64)
    if isinstance(series.dtype, pd.StringDtype) and series.dtype.storage == "pyarrow":
        import pyarrow as pa
        import pyarrow.compute as pc

        try:  # every cell a number: one vectorised Arrow cast (10x numpy's conversion of Python strings)
            return np.asarray(
                pc.cast(pa.array(series.array), pa.float64()).to_numpy(zero_copy_only=False), dtype=np.float64
            )
        except (pa.ArrowInvalid, pa.ArrowNotImplementedError, pa.ArrowTypeError):
            pass  # an empty or non-numeric cell, or spaces: the general path below
    try:  # every cell a number (the usual case): one conversion, no per-cell cleaning
        return np.asarray(series.to_numpy(), dtype=np.float64)
    except (TypeError, ValueError):  # empty or non-numeric cells become NaN (dropped and counted by the caller)
        return pd.to_numeric(series.astype(str).str.strip(), errors="coerce").to_numpy(dtype=np.float64)


def resolve_columns(
    df: pd.DataFrame, columns: str | Sequence[str | int] | None, source: str | None = None
) -> tuple[tuple[str, str, str], str]:
    """Choose the x, y, z columns: given names or 0-based indices, else x/y/z-like header names, else the first
    three numeric non-time columns. Returns the names and a note saying how they were chosen."""
    names = [str(c) for c in df.columns]
    if columns is not None:
        items = [c.strip() for c in columns.split(",")] if isinstance(columns, str) else list(columns)
        if len(items) != 3:
            raise TrimagInputError(f"`columns` needs exactly three columns (x, y, z); got {len(items)}: {items}")
        chosen = []
        for item in items:
            if isinstance(item, str) and item in names:
                chosen.append(item)
            elif isinstance(item, int) or (isinstance(item, str) and item.lstrip("-").isdigit()):
                idx = int(item)
                if not 0 <= idx < len(names):
                    raise TrimagInputError(
                        f"`columns`: index {idx} is out of range; "
                        f"the file has {len(names)} columns (0-{len(names) - 1})"
                    )
                chosen.append(names[idx])
            else:
                raise TrimagInputError(
                    f"`columns`: no column {item!r}; the columns are {', '.join(names)}"
                )
        twice = sorted({c for c in chosen if chosen.count(c) > 1})
        if twice:  # the same column as two axes: the samples would lie on a line, refused as a sensor that never turned
            given = ", ".join(map(str, items))
            raise TrimagInputError(f"`columns` names the column {twice[0]!r} for more than one axis ({given}): give "
                                   "the x, y and z columns, three different ones")
        return (chosen[0], chosen[1], chosen[2]), ""
    by_axis: dict[str, list[str]] = {"x": [], "y": [], "z": []}
    for name in names:
        m = _AXIS_RE.match(name.strip().lower())
        if m:
            by_axis[m.group(1)].append(name)
    if all(len(v) == 1 for v in by_axis.values()):
        chosen3 = (by_axis["x"][0], by_axis["y"][0], by_axis["z"][0])
        return chosen3, f"using columns {', '.join(chosen3)} (recognised from the header)"
    return _columns_by_content(df, names, source)


#: header words that name something other than a magnetometer axis
_NOT_FIELD = re.compile(
    r"(acc|gyr|gyro|rate|temp|time|stamp|_ns\b|_us\b|_ms\b|index|idx|count|loop|step|seq|frame|lat|lon|alt|"
    r"roll|pitch|yaw|heading|quat|\bq[wxyz0-3]\b|volt|curr|press|baro|min\b|max\b|mean|std|var\b|\bg[xyz]\b|"
    r"^line(?:_record)?$|^fid(?:ucial)?$|^mag$|^tmi$|"
    r"\ba[xyz]\b|vel|pos|speed|gps|thr|pwm|rc)", re.I
)
_NOT_FIELD_FILE = re.compile(r"(accel|gyro|temperature|stats)", re.I)


def _columns_by_content(
    df: pd.DataFrame, names: list[str], source: str | None
) -> tuple[tuple[str, str, str], str]:
    """The x, y, z columns when the header does not name them: never a guess between several candidates.

    A column is excluded when its name says it is something else (accelerometer, gyroscope, time, counter,
    attitude, statistics...), or its numbers do: constant, mostly missing, increasing at every row (a clock or an
    index). Exactly three left: used, and said so. More: the user chooses (exit 2, candidates listed). Fewer: exit 2.
    """
    candidates: list[str] = []
    skipped: dict[str, list[str]] = {}

    def skip(name: str, why: str) -> None:
        skipped.setdefault(why, []).append(name)

    for name in names:
        values = _numeric(df[name])
        finite = values[np.isfinite(values)]
        if len(finite) < max(1, 0.5 * len(values)):
            continue  # not numeric
        label = name.strip().lower()
        if label in _TIME_NAMES or (len(finite) > 10 and np.all(np.diff(finite) > 0)):
            skip(name, "time or counter")
        elif not re.fullmatch(r"col\d+", label) and _NOT_FIELD.search(label):
            skip(name, "named as another quantity")
        elif len(finite) > 1 and np.ptp(finite) == 0:
            skip(name, "constant")
        else:
            candidates.append(name)
    skipped_txt = "; ".join(f"{why}: {', '.join(cols)}" for why, cols in skipped.items())
    headerless = all(re.fullmatch(r"col\d+", n) for n in names)
    if headerless and source and _NOT_FIELD_FILE.search(Path(source).name):
        raise TrimagInputError(
            f"the file name says this is not a magnetometer log ({Path(source).name}); if it is one, name the x, y, "
            "z columns with `columns`"
        )
    if len(candidates) == 3:
        chosen3 = (candidates[0], candidates[1], candidates[2])
        note = f"using columns {', '.join(chosen3)} (the only three that can be a field"
        note += f"; skipped {skipped_txt})" if skipped_txt else ")"
        return chosen3, note + "; choose others with `columns`"
    if len(candidates) > 3:
        raise TrimagInputError(
            f"several columns could be the magnetometer's x, y, z ({', '.join(candidates)}); "
            "name them with `columns=X,Y,Z`"
        )
    raise TrimagInputError(
        f"found {len(candidates)} column(s) that can be a magnetometer axis ({', '.join(candidates) or 'none'}"
        f"{'; skipped ' + skipped_txt if skipped_txt else ''}); a magnetometer log needs three (x, y, z): "
        "name them with `columns`"
    )


def check_row_range(rows: str, start: int | None, stop: int | None) -> None:
    """Refuse (:class:`TrimagInputError`) a ``rows`` range ``START:STOP`` that is empty whatever the file holds: START
    at or after STOP, both counted from the same end (both >= 0, or both < 0)."""
    if start is not None and stop is not None and (start >= 0) == (stop >= 0) and start >= stop:
        hint = f", e.g. {stop}:{start}" if stop < start else ""
        raise TrimagInputError(f"`rows` {rows.strip()} is empty: START ({start}) must be before STOP ({stop}; 0-based, "
                               f"STOP excluded){hint}")


def select_rows(df: pd.DataFrame, rows: str | None = None, where: str | None = None) -> tuple[pd.DataFrame, str]:
    """Select data rows by a 0-based half-open range ``"START:STOP"`` and/or ``"COLUMN==VALUE"`` (or ``!=``)."""
    notes = []
    if rows:
        m = re.fullmatch(r"\s*(-?\d*)\s*:\s*(-?\d*)\s*", rows)
        if not m:
            raise TrimagInputError(f"`rows` takes START:STOP (0-based, STOP excluded), e.g. 0:5000; got {rows!r}")
        start = int(m.group(1)) if m.group(1) else None
        stop = int(m.group(2)) if m.group(2) else None
        check_row_range(rows, start, stop)
        df = df.iloc[slice(start, stop)]
        notes.append(f"rows {rows}")
    if where:
        df = df[where_mask(df, where)]
        notes.append(f"where {where.strip()}")
    if (rows or where) and len(df) == 0:
        raise TrimagInputError(f"the row selection ({'; '.join(notes)}) matched no rows")
    return df, "; ".join(notes)


def where_mask(df: pd.DataFrame, where: str) -> NDArray[np.bool_]:
    """Boolean mask of the rows of ``df`` matching ``"COLUMN==VALUE"`` or ``"COLUMN!=VALUE"``."""
    m = re.fullmatch(r"\s*([^=!]+?)\s*(==|!=)\s*(.*?)\s*", where)
    if not m:
        raise TrimagInputError(f"`where` takes COLUMN==VALUE or COLUMN!=VALUE; got {where!r}")
    col, op, value = m.groups()
    if col not in df.columns:
        raise TrimagInputError(f"`where`: no column {col!r}; the columns are {', '.join(map(str, df.columns))}")
    series = df[col]
    if series.dtype.kind in "fiub":
        try:
            mask = np.isclose(series.to_numpy(dtype=float), float(value))
        except ValueError:
            mask = np.zeros(len(series), dtype=bool)
    else:
        text = series.astype(str).str.strip()
        mask = (text == value).to_numpy()
        if not mask.any():
            try:
                mask = np.isclose(pd.to_numeric(text, errors="coerce").to_numpy(dtype=float), float(value))
            except ValueError:
                pass
    return ~mask if op == "!=" else mask


def read_samples(
    path: str | Path,
    *,
    fmt: str | None = None,
    columns: str | Sequence[str | int] | None = None,
    var: str | None = None,
    rows: str | None = None,
    where: str | None = None,
    strict: bool = False,
    sensor: SensorChoice = None,
) -> Samples:
    """Read a magnetometer log and return its finite field samples with provenance.

    Parameters
    ----------
    path : str or Path
    fmt : {"csv", "txt", "npz", "mat", "parquet"}, optional
        By default from the extension.
    columns : str or sequence, optional
        ``"X,Y,Z"`` header names or 0-based indices.
    var : str, optional
        Variable name inside NPZ / MAT files.
    rows, where : str, optional
        Row selection, see :func:`select_rows`.
    strict : bool
        Raise instead of dropping rows with missing / non-numeric / non-finite field cells.

    Raises
    ------
    TrimagInputError
        Missing file, empty file, header only, fewer than 3 numeric columns, unknown columns, no valid rows.
    """
    p = Path(path)
    df = read_table(p, fmt=fmt, var=var, sensor=sensor)
    variable = str(df.attrs.get("trimag_variable", ""))
    stated_unit = str(df.attrs.get("trimag_stated_unit", ""))
    if not df.index.equals(pd.RangeIndex(len(df))):  # the index numbers the data rows (Samples.table)
        df = df.set_axis(pd.RangeIndex(len(df)), axis=0)
    log_info = df.attrs.get("trimag_log")
    n_total = len(df)
    if n_total == 0:
        raise TrimagInputError(f"{p}: the file has a header but no data rows")
    if log_info is not None and columns is None:
        cols = ("mag_x", "mag_y", "mag_z")
        note = f"using {log_info['sensor']} (calibration undone: mag_x, mag_y, mag_z)"
    else:
        cols, note = resolve_columns(df, columns, str(p))
    if variable:  # the variable of the file, as well as its columns
        note = f"variable {variable}: {note}" if note else f"variable {variable}: columns {', '.join(cols)}"
    df, selection = select_rows(df, rows, where)
    format_note = _xyz_note(df, cols, n_total) if "trimag_xyz" in df.attrs else ""
    xyz, df, order = _take_xyz(df, cols)
    ok = np.isfinite(xyz).all(axis=1)
    n_bad = int((~ok).sum())
    positions = np.nonzero(~ok)[0]
    if n_bad and strict:
        raise strict_refusal(f"{p}: ", n_bad, "missing, non-numeric, NaN or inf field values",
                             f"data row {int(df.index[positions[0]])}")
    if n_bad == len(df):
        raise TrimagInputError(
            f"{p}: none of the {len(df)} rows has three numeric, finite values in columns {', '.join(cols)}"
        )
    kept = df[ok] if n_bad else df
    field_arr = xyz[ok] if n_bad else xyz
    kept, field_arr, wild_index, wild_note = _drop_wild_rows(pd.DataFrame(kept), field_arr, strict, p)
    n_dup = count_duplicate_rows(field_arr)
    field_arr = np.ascontiguousarray(field_arr)
    return Samples(
        field=field_arr,
        table=_with_xyz(pd.DataFrame(kept), field_arr, cols, order),  # the index: the kept rows' data-row numbers
        columns=cols,
        column_note=note,
        n_rows=len(df),
        n_dropped=n_bad + len(wild_index),
        dropped_index=[int(df.index[i]) for i in positions[:1000]],
        n_duplicates=n_dup,
        selection=selection,
        source=str(p),
        n_total_rows=n_total,
        log_info=log_info,
        format_note=format_note,
        n_wild=len(wild_index),
        wild_index=wild_index[:1000],
        wild_note=wild_note,
        variable=variable,
        stated_unit=stated_unit,
    )


#: Rows from which the table's x, y, z columns are views of the samples (below, the 1 ms of rebuilding the table
#: costs more than the memory saved: a batch of 5000-row logs read 25 % slower)
SHARED_XYZ_ROWS = 100_000


def _take_xyz(df: pd.DataFrame, cols: tuple[str, str, str]
              ) -> tuple[NDArray[np.float64], pd.DataFrame, list[Any] | None]:
    """The x, y, z columns of ``df`` as one (N, 3) float64 array, each column dropped from ``df`` as soon as it is
    copied (the log is never held twice: 24 bytes per row less at the peak), and ``df``'s column order for
    :func:`_with_xyz`; ``order`` None (the columns kept) for a log of fewer than :data:`SHARED_XYZ_ROWS` rows or
    when ``df``'s names are not distinct."""
    if len(df) < SHARED_XYZ_ROWS or not df.columns.is_unique or len(set(cols)) < 3:
        return np.column_stack([_numeric(df[c]) for c in cols]), df, None
    held = _held_xyz(df, cols)
    if held is not None:  # the table's columns are views of it: kept as the samples, the table rebuilt on them
        return held, df.drop(columns=list(cols)), list(df.columns)
    xyz = np.empty((len(df), 3))
    order = list(df.columns)
    for k, c in enumerate(cols):
        xyz[:, k] = _numeric(df[c])
        df = df.drop(columns=[c])
    return xyz, df, order


def _held_xyz(df: pd.DataFrame, cols: tuple[str, str, str]) -> NDArray[np.float64] | None:
    """The (N, 3) array ``df``'s float64 columns ``cols`` (all its columns, in that order) are views of
    (:func:`_read_numeric_blocks`), writable, or None when they are not one such array."""
    if list(df.columns) != list(cols) or not all(dtype == np.float64 for dtype in df.dtypes):
        return None
    first = df[cols[0]].to_numpy()
    if not all(np.may_share_memory(first, df[c].to_numpy()) for c in cols[1:]):
        return None  # separate columns: df.to_numpy would copy them
    held = df.to_numpy(dtype=np.float64, copy=False)
    if not (held.flags.c_contiguous and np.may_share_memory(held, first)):
        return None
    try:
        held.flags.writeable = True  # (pandas' read-only view of the reader's array: the samples own it now)
    except ValueError:
        return None
    return held


def _with_xyz(table: pd.DataFrame, field: NDArray[np.float64], cols: tuple[str, str, str],
              order: list[Any] | None) -> pd.DataFrame:
    """``table`` (without its x, y, z columns, :func:`_take_xyz`) with them back in their places as views of
    ``field`` (N, 3): one copy of the samples, not two."""
    if order is None:
        return table
    views = {c: field[:, k] for k, c in enumerate(cols)}
    out = pd.DataFrame({c: views[c] if c in views else table[c] for c in order}, index=table.index, copy=False)
    out.attrs = dict(table.attrs)
    return out


def _drop_wild_rows(
    kept: pd.DataFrame, field: NDArray[np.float64], strict: bool, path: Path
) -> tuple[pd.DataFrame, NDArray[np.float64], list[int], str]:
    """``kept`` and ``field`` without their wild rows (:func:`trimag.validation.wild_rows`, screened again until
    none is left: the median moves as they go), the wild rows' data-row numbers and what they were; ``strict``
    refuses them."""
    from ..validation import describe_wild_rows, wild_rows

    wild_index: list[int] = []
    note = ""
    for _ in range(5):
        wild = wild_rows(field)
        if not wild.any():
            break
        rows = kept.index.to_numpy()[wild]
        if not note:
            note = describe_wild_rows(field, wild, "data row", int(rows[0]))
        if strict:
            raise TrimagInputError(f"{path}: {note}; fix them, or drop `strict` to skip and count them")
        wild_index += [int(r) for r in rows]
        kept, field = kept[~wild], field[~wild]
    return kept, field, sorted(wild_index), note


def _xyz_note(df: pd.DataFrame, cols: tuple[str, str, str], n_total: int) -> str:
    """What a Geosoft XYZ file held besides the rows used: line records and ``*`` null rows (for the user)."""
    info = df.attrs["trimag_xyz"]
    n_null = int(np.any(np.column_stack([df[c].astype(str).str.strip().to_numpy() == "*" for c in cols]), axis=1).sum())
    note = f"Geosoft XYZ: {n_total} data rows"
    if info["n_line_records"]:
        lines = pd.unique(df[info["line_column"]]) if info["line_column"] in df.columns else []
        note += (f", {info['n_line_records']} line record(s) skipped ({len(lines)} line(s) in the rows used, "
                 f"column {info['line_column']!r})")
    if n_null:
        note += f", {n_null} row(s) with a `*` null in {', '.join(cols)} (dropped and counted below)"
    return note


def column_values(samples: Samples, name: str) -> NDArray[np.float64]:
    """Numeric values (N,) of a column of the kept rows (e.g. a reference or attitude column)."""
    if name not in samples.table.columns:
        raise TrimagInputError(f"no column {name!r}; the columns are {', '.join(map(str, samples.table.columns))}")
    values = _numeric(samples.table[name])
    if not np.isfinite(values).all():
        bad = int((~np.isfinite(values)).sum())
        raise TrimagInputError(f"column {name!r} has {bad} missing or non-numeric value(s) in the rows used")
    return values


def read_csv_text(text: str) -> pd.DataFrame:
    """Parse CSV text (tests and small inputs)."""
    return pd.read_csv(_stdio.StringIO(text))
