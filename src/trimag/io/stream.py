"""Chunked reading for ``apply`` and ``evaluate``: memory stays bounded whatever the file size.

CSV/text and Parquet files are read ``chunk_rows`` rows at a time; NPZ and MAT files are loaded whole (they are
single arrays in memory by nature). Text cells are kept as strings so ``apply`` writes every input row and
column back unchanged, and appends the corrected columns.

Speed (docs/performance.md): delimited text is parsed by pyarrow's streaming CSV reader with every column typed
as a string (the cells are kept exactly), x/y/z are converted with one vectorised cast, and CSV output is
written by pyarrow's CSV writer. Whitespace-delimited text, rows pyarrow refuses (e.g. a row with a different
number of fields) and cells that need quoting on output fall back to pandas, which gives the same rows and
cells. A :class:`Chunk` converts between its Arrow and pandas forms only when asked.

pyarrow is optional (the ``parquet`` extra): without it text files are read and written by pandas alone (same
rows and cells, slower), and Parquet input or output is refused with one line naming the extra.
"""

from __future__ import annotations

import csv
import io
import itertools
import re
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from .._core.chunks import DEFAULT_CHUNK_ROWS, read_block_bytes
from .._core.extras import available, require
from .._core.stats import StreamingMoments
from ..errors import TrimagInputError
from .atomic import atomic_path
from .tables import (
    _numeric,
    check_row_range,
    check_sensor,
    detect_csv_layout,
    detect_format,
    guess_format,
    read_table,
    resolve_columns,
)

if TYPE_CHECKING:
    import pyarrow as pa

    from .logs.base import SensorChoice

__all__ = ["Chunk", "ChunkSource", "MagnitudeAccumulator", "apply_file", "iter_chunks", "open_chunks"]



class Chunk:
    """One block of rows: the original cells, the x/y/z values (NaN where unusable) and the global row offset.

    Attributes
    ----------
    table : pandas.DataFrame
        The rows' cells (text files: strings, exactly as in the file).
    arrow : pyarrow.Table
        The same cells as an Arrow table.
    xyz : ndarray, shape (n, 3)
        x, y, z as floats; NaN where a cell is missing or not a number.
    start : int
        Index of the chunk's first row among the data rows of the file (0-based).
    """

    def __init__(
        self,
        table: pd.DataFrame | None,
        xyz: NDArray[np.float64],
        start: int,
        *,
        arrow: pa.Table | None = None,
    ) -> None:
        if table is None and arrow is None:
            raise ValueError("a Chunk needs its cells as a pandas DataFrame or a pyarrow Table")
        self._table = table
        self._arrow = arrow
        self.xyz = xyz
        self.start = start

    @property
    def table(self) -> pd.DataFrame:
        if self._table is None:
            assert self._arrow is not None
            self._table = self._arrow.to_pandas()
        return self._table

    @property
    def arrow(self) -> pa.Table:
        if self._arrow is None:
            assert self._table is not None
            pa = require("pyarrow", "converting a chunk to an Arrow table")
            self._arrow = pa.Table.from_pandas(self._table, preserve_index=False)
        return self._arrow

    @property
    def has_arrow(self) -> bool:
        """True when the cells are already held as an Arrow table (no conversion needed)."""
        return self._arrow is not None

    def __len__(self) -> int:
        return len(self.xyz)


@dataclass
class ChunkSource:
    """What :func:`iter_chunks` found out about the file before streaming it."""

    fmt: str
    columns: tuple[str, str, str]
    column_note: str
    preamble: tuple[str, ...] = ()
    has_header: bool = True
    delimiter: str | None = ","
    all_columns: list[str] = field(default_factory=list)
    #: delimited text: the file read (after any decompression), the lines before the header, the number of fields
    raw_path: Path | None = None
    skip: int = 0
    n_fields: int = 0
    #: an autopilot log: what it told of the magnetometer read (``Samples.log_info``), else None
    log_info: dict[str, Any] | None = None
    #: the variable of an NPZ or MAT file the samples are read from (``imu_mag``), empty for other files
    variable: str = ""


def _parse_rows(rows: str | None) -> tuple[int, int | None]:
    if not rows:
        return 0, None
    m = re.fullmatch(r"\s*(\d*)\s*:\s*(\d*)\s*", rows)
    if not m:
        raise TrimagInputError(f"`rows` takes START:STOP with non-negative integers, e.g. 0:5000; got {rows!r}")
    start, stop = (int(m.group(1)) if m.group(1) else 0), (int(m.group(2)) if m.group(2) else None)
    check_row_range(rows, start, stop)
    return start, stop


def _arrow_numeric(col: pa.ChunkedArray | pa.Array) -> NDArray[np.float64]:
    """Column -> float64 (NaN for null, empty or non-numeric cells): one Arrow cast, pandas when it refuses."""
    import pyarrow as pa
    import pyarrow.compute as pc

    try:
        return np.asarray(pc.cast(col, pa.float64()).to_numpy(zero_copy_only=False), dtype=np.float64)
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError):
        return _numeric(pd.Series(col.to_pandas()))


def _xyz(table: pa.Table, cols: tuple[str, str, str]) -> NDArray[np.float64]:
    out = np.empty((table.num_rows, 3))
    for j, c in enumerate(cols):
        out[:, j] = _arrow_numeric(table.column(c))
    return out


def chunk_columns(chunk: Chunk, names: Sequence[str], path: str | Path = "the data") -> NDArray[np.float64]:
    """The numeric values of the columns ``names`` in one chunk, shape (n, m); NaN where a cell is missing or not a
    number. A column that is not there raises :class:`TrimagInputError` naming it and ``path``."""
    present = chunk.arrow.column_names if chunk.has_arrow else [str(c) for c in chunk.table.columns]
    missing = [n for n in names if n not in present]
    if missing:
        raise TrimagInputError(
            f"{path}: no column {missing[0]!r} (a regressor of the calibration); the columns are {', '.join(present)}"
        )
    out = np.empty((len(chunk), len(names)))
    for j, name in enumerate(names):
        out[:, j] = _arrow_numeric(chunk.arrow.column(name)) if chunk.has_arrow else _numeric(chunk.table[name])
    return out


def _rechunk(batches: Iterable[pa.RecordBatch], rows: int) -> Iterator[pa.Table]:
    """Regroup record batches into tables of exactly ``rows`` rows (the last one shorter); zero-copy slices."""
    import pyarrow as pa

    buf: list[pa.RecordBatch] = []
    n = 0
    for batch in batches:
        if batch.num_rows == 0:
            continue
        buf.append(batch)
        n += batch.num_rows
        while n >= rows:
            table = pa.Table.from_batches(buf)
            yield table.slice(0, rows)
            rest = table.slice(rows)
            buf = rest.to_batches()
            n = rest.num_rows
    if n:
        yield pa.Table.from_batches(buf)


def _bytes_per_row(path: Path, skip: int) -> float:
    with path.open("rb") as fh:
        head = fh.read(1 << 16)
    lines = head.split(b"\n")[skip + 1 : -1]
    return max(sum(len(ln) + 1 for ln in lines) / len(lines), 8.0) if lines else 64.0


def open_chunks(
    path: str | Path,
    *,
    fmt: str | None = None,
    columns: str | None = None,
    var: str | None = None,
    chunk_rows: int = DEFAULT_CHUNK_ROWS,
    sensor: SensorChoice = None,
) -> tuple[ChunkSource, Iterator[Chunk]]:
    """Inspect ``path`` and return its description and an iterator over :class:`Chunk` s of ``chunk_rows`` rows
    (the last one shorter); ``sensor``: which magnetometer of an autopilot log (refused for other files)."""
    p = Path(path)
    if not p.exists():
        raise TrimagInputError(f"{p}: no such file")
    if fmt is None or fmt in ("csv", "txt"):
        from .normalise import plain_path

        p = plain_path(p)  # compressed text, decimal commas
    if chunk_rows < 1:
        raise TrimagInputError(f"`chunk_rows` must be a positive number of rows; got {chunk_rows}")
    kind = detect_format(p, fmt)
    check_sensor(kind, sensor, path)
    if kind in ("csv", "txt"):
        return _open_text(p, str(path), kind, columns, chunk_rows)
    if kind == "parquet":
        return _open_parquet(p, str(path), columns, chunk_rows)
    df = read_table(p, fmt=kind, var=var, sensor=sensor)
    cols, note = resolve_columns(df, columns, str(path))
    source = ChunkSource(kind, cols, note, all_columns=list(df.columns), log_info=df.attrs.get("trimag_log"),
                         variable=str(df.attrs.get("trimag_variable", "")))
    return source, iter([Chunk(df, np.column_stack([_numeric(df[c]) for c in cols]), 0)])


def _open_text(
    p: Path, name: str, kind: str, columns: str | None, chunk_rows: int
) -> tuple[ChunkSource, Iterator[Chunk]]:
    """:func:`open_chunks` of delimited text ``p`` (``name``: the path as given, for messages)."""
    layout = detect_csv_layout(p, fmt=kind)
    kwargs: dict[str, Any] = {
        "skiprows": layout.skip,
        "header": 0 if layout.has_header else None,
        "dtype": str,
        "keep_default_na": False,
        "sep": r"\s+" if layout.delimiter is None else layout.delimiter,
    }
    try:
        head = pd.read_csv(p, nrows=2000, **kwargs)
    except (pd.errors.EmptyDataError, pd.errors.ParserError) as exc:  # e.g. a quoted cell with a line break
        raise TrimagInputError(f"{p}: cannot parse as delimited text: {str(exc).splitlines()[0]}") from None
    except UnicodeDecodeError as exc:
        from .tables import not_utf8

        raise TrimagInputError(f"{name}: {not_utf8(exc)}") from None
    if not layout.has_header:
        head.columns = [f"col{i}" for i in range(head.shape[1])]
    head.columns = [str(c).strip() for c in head.columns]
    if len(head) == 0:
        raise TrimagInputError(f"{p}: the file has a header but no data rows")
    cols, note = resolve_columns(head, columns, name)
    names = list(head.columns)
    source = ChunkSource(kind, cols, note, layout.preamble, layout.has_header, layout.delimiter, names,
                         raw_path=p, skip=layout.skip, n_fields=len(names))
    # pyarrow (the `parquet` extra) reads delimited text faster; pandas gives the same rows and cells
    if layout.delimiter is not None and available("pyarrow"):
        return source, _text_chunks_arrow(p, source, kwargs, chunk_rows)
    return source, _text_chunks_pandas(p, source, kwargs, chunk_rows)


def _text_chunks_pandas(
    p: Path, source: ChunkSource, kwargs: dict[str, Any], chunk_rows: int, skip_rows: int = 0
) -> Iterator[Chunk]:
    """The chunks of delimited text read by pandas (``kwargs`` of :func:`pandas.read_csv`), after the first
    ``skip_rows`` data rows (already delivered by the Arrow reader)."""
    start = 0
    for df in pd.read_csv(p, chunksize=chunk_rows, **kwargs):
        if skip_rows >= len(df):  # rows already delivered by the Arrow reader
            skip_rows -= len(df)
            start += len(df)
            continue
        if skip_rows:
            df = df.iloc[skip_rows:].reset_index(drop=True)
            start += skip_rows
            skip_rows = 0
        df.columns = source.all_columns
        xyz = np.column_stack([_numeric(df[c]) for c in source.columns])
        yield Chunk(df, xyz, start)
        start += len(df)


def _text_chunks_arrow(p: Path, source: ChunkSource, kwargs: dict[str, Any], chunk_rows: int) -> Iterator[Chunk]:
    """The chunks of delimited text read by pyarrow's streaming reader, every cell a string; from a row it refuses
    (e.g. one with a different number of fields) on, pandas reads the rest as before."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    assert source.delimiter is not None
    names = source.all_columns
    block = read_block_bytes(int(chunk_rows * _bytes_per_row(p, source.skip)))
    start = 0
    try:
        reader = pacsv.open_csv(
            p,
            read_options=pacsv.ReadOptions(
                skip_rows=source.skip + int(source.has_header), column_names=names, block_size=block
            ),
            parse_options=pacsv.ParseOptions(delimiter=source.delimiter),
            convert_options=pacsv.ConvertOptions(
                column_types=dict.fromkeys(names, pa.string()), strings_can_be_null=False,
                quoted_strings_can_be_null=False,
            ),
        )
        for table in _rechunk(reader, chunk_rows):
            yield Chunk(None, _xyz(table, source.columns), start, arrow=table)
            start += table.num_rows
        return
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError, pa.ArrowTypeError):
        pass  # e.g. a row with a different number of fields: pandas reads the rest as before
    yield from _text_chunks_pandas(p, source, kwargs, chunk_rows, skip_rows=start)


def _open_parquet(p: Path, name: str, columns: str | None, chunk_rows: int) -> tuple[ChunkSource, Iterator[Chunk]]:
    """:func:`open_chunks` of a Parquet file ``p``, read one batch of ``chunk_rows`` rows at a time."""
    pq = require("pyarrow.parquet", "reading Parquet files")

    try:
        # pre_buffer=False: reads column chunks page by page; with pre-buffering the memory pool peaked at
        # 252 MB (vs 53 MB) on a file with 1e6-row row groups (docs/performance.md)
        pf = pq.ParquetFile(p, pre_buffer=False)
    except Exception as exc:
        raise TrimagInputError(f"{p}: not a readable Parquet file ({exc})") from None
    names = list(pf.schema_arrow.names)
    first = next(pf.iter_batches(batch_size=2000), None) if pf.num_row_groups else None
    head = first.to_pandas() if first is not None else pd.DataFrame(columns=names)
    if len(head) == 0:
        raise TrimagInputError(f"{p}: the file has no data rows")
    cols, note = resolve_columns(head, columns, name)
    source = ChunkSource("parquet", cols, note, all_columns=names)

    def gen_parquet() -> Iterator[Chunk]:
        start = 0
        for table in _rechunk(pf.iter_batches(batch_size=chunk_rows), chunk_rows):
            yield Chunk(None, _xyz(table, cols), start, arrow=table)
            start += table.num_rows

    return source, gen_parquet()


def iter_chunks(path: str | Path, **kwargs: Any) -> Iterator[Chunk]:
    """Iterate over the :class:`Chunk` s of a file (see :func:`open_chunks`)."""
    return open_chunks(path, **kwargs)[1]


def _with_corrected(table: pa.Table, corrected: NDArray[np.float64], names: list[str]) -> pa.Table:
    import pyarrow as pa

    for j, name in enumerate(names):
        table = table.append_column(name, pa.array(corrected[:, j], from_pandas=True))  # NaN -> empty cell
    return table


def _write_csv_rows(fh: Any, table: pa.Table, sep: str) -> None:
    """Write the rows (no header) of ``table``: pyarrow's writer, or pandas when a cell needs quoting."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    buf = io.BytesIO()
    try:
        pacsv.write_csv(table, buf, write_options=pacsv.WriteOptions(
            include_header=False, delimiter=sep, quoting_style="none"))
    except pa.ArrowInvalid:  # a cell holds the delimiter, a quote or a line break: quote as pandas does
        fh.write(table.to_pandas().to_csv(index=False, header=False, sep=sep, lineterminator="\n"))
        return
    fh.write(buf.getvalue().decode("utf-8"))


def apply_file(
    calibrate: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    in_path: str | Path,
    out_path: str | Path,
    *,
    fmt: str | None = None,
    columns: str | None = None,
    var: str | None = None,
    suffix: str = "_cal",
    chunk_rows: int = DEFAULT_CHUNK_ROWS,
    progress: Callable[[int], None] | None = None,
    regressor_columns: Sequence[str] = (),
    sensor: SensorChoice = None,
    strict: bool = False,
) -> dict[str, Any]:
    """Correct every row of ``in_path`` and write all input columns plus the corrected x, y, z to ``out_path``.

    With ``regressor_columns`` (m names), ``calibrate`` is called as ``calibrate(xyz, u)`` with ``u`` the rows'
    values of those columns (n, m); a row whose value is missing is not corrected (counted in ``n_uncorrected``).

    The output format follows ``out_path``'s extension (``.csv``, ``.txt``, ``.parquet``, ``.npz``); CSV/text and
    Parquet are streamed in ``chunk_rows`` blocks. Rows whose x/y/z are missing, non-numeric or non-finite are
    kept, with empty corrected cells, and counted in ``n_uncorrected`` (with ``strict``, the first such row is
    refused and nothing is written). ``sensor``: which magnetometer of an autopilot log. The file appears only
    when complete (written to a temporary file, then renamed).

    Returns
    -------
    dict
        ``n_rows``, ``n_uncorrected``, ``columns`` (x, y, z used), ``output_columns`` (appended names), ``out``.
    """
    out = Path(out_path)
    out_kind = guess_format(out) if out.suffix else "csv"
    if out_kind not in ("csv", "txt", "parquet", "npz"):
        raise TrimagInputError(f"cannot write {out.suffix!r} files; use .csv, .parquet or .npz for -o")
    if out_kind == "parquet":
        require("pyarrow.parquet", "writing Parquet files")
    source, chunks = open_chunks(in_path, fmt=fmt, columns=columns, var=var, chunk_rows=chunk_rows, sensor=sensor)
    new_cols = [f"{c}{suffix}" for c in source.columns]
    tally = _Tally(progress)
    corrected = _corrected_chunks(calibrate, chunks, regressor_columns, in_path, strict=strict)
    with atomic_path(out) as tmp:  # renamed to `out` when complete, removed on error
        raw_copy = (out_kind in ("csv", "txt") and source.raw_path is not None and source.delimiter is not None
                    and (out_kind == "txt" or source.delimiter == ","))
        if raw_copy:  # delimited text in, same delimiter out: every input byte copied, corrected cells appended
            _write_raw_copy(tmp, source, corrected, new_cols, tally, in_path)
        elif out_kind in ("csv", "txt"):
            sep = "," if out_kind == "csv" or source.delimiter is None else source.delimiter
            _write_text(tmp, source, corrected, new_cols, tally, sep)
        elif out_kind == "parquet":
            _write_parquet(tmp, corrected, new_cols, tally)
        else:  # npz: arrays in memory by nature
            _write_npz(tmp, corrected, tally)
        if tally.n_rows and tally.n_bad == tally.n_rows:  # nothing corrected: no output (removed, not renamed)
            raise TrimagInputError(
                f"{in_path}: none of the {tally.n_rows} rows has three numeric, finite values in columns "
                f"{', '.join(map(str, source.columns))}: nothing to correct; check `columns` and the file")
    return {
        "n_rows": tally.n_rows,
        "n_uncorrected": tally.n_bad,
        "columns": list(source.columns),
        "column_note": source.column_note,
        "output_columns": new_cols,
        "out": str(out),
        "log_info": source.log_info,
        "variable": source.variable,
    }


@dataclass
class _Tally:
    """Rows written and rows left uncorrected so far; ``progress`` is told the rows written after each chunk."""

    progress: Callable[[int], None] | None
    n_rows: int = 0
    n_bad: int = 0

    def add(self, rows: int, bad: int) -> None:
        self.n_rows += rows
        self.n_bad += bad
        if self.progress:
            self.progress(self.n_rows)


def _corrected_chunks(
    calibrate: Callable[..., NDArray[np.float64]], chunks: Iterable[Chunk], regressor_columns: Sequence[str],
    in_path: str | Path, *, strict: bool = False,
) -> Iterator[tuple[Chunk, NDArray[np.float64], int]]:
    """Each chunk with its corrected x, y, z (n, 3) (NaN where not corrected) and the number of rows not corrected;
    ``strict``: the first row that cannot be corrected raises."""
    for chunk in chunks:
        u = chunk_columns(chunk, regressor_columns, in_path) if regressor_columns else None
        corrected, bad = _correct(calibrate, chunk.xyz, u)
        if bad and strict:
            first = chunk.start + int(np.flatnonzero(~np.isfinite(corrected).all(axis=1))[0])
            raise TrimagInputError(
                f"{in_path}: data row {first} has a missing, non-numeric, NaN or inf value in its field (or "
                "regressor) columns; fix it, or drop `strict` to keep such rows uncorrected and count them"
            )
        yield chunk, corrected, bad


def _write_raw_copy(
    tmp: Path, source: ChunkSource, corrected: Iterable[tuple[Chunk, NDArray[np.float64], int]], new_cols: list[str],
    tally: _Tally, in_path: str | Path,
) -> None:
    """Delimited text in, the same delimiter out: every input byte copied, the corrected cells appended."""
    assert source.raw_path is not None and source.delimiter is not None
    sep_b = source.delimiter.encode()
    with tmp.open("wb") as fb, source.raw_path.open("rb") as fin:
        lines_in = _RawLines(fin, source, sep_b)
        for body, ending in lines_in.head():  # preamble and header, unchanged
            if ending is not None:  # the header: the corrected columns' names appended
                fb.write(body + sep_b + sep_b.join(n.encode() for n in new_cols) + ending)
            else:
                fb.write(body)
        for chunk, values, bad in corrected:
            cells = _corrected_cells(values, source.delimiter, arrow=chunk.has_arrow)
            block = lines_in.take(cells)
            if block is None:
                raise TrimagInputError(f"{in_path}: the rows read do not match the file's lines")
            fb.writelines(block)
            tally.add(len(chunk), bad)
        if not lines_in.at_end():  # never an output whose cells are not those of its rows
            raise TrimagInputError(f"{in_path}: the rows read do not match the file's lines")


def _write_text(
    tmp: Path, source: ChunkSource, corrected: Iterable[tuple[Chunk, NDArray[np.float64], int]], new_cols: list[str],
    tally: _Tally, sep: str,
) -> None:
    """Delimited text out, written from the cells (another delimiter, or a table read whole)."""
    with tmp.open("w", encoding="utf-8", newline="") as fh:
        for line in source.preamble:
            fh.write(line + "\n")
        first = True
        for chunk, values, bad in corrected:
            if first and source.has_header:
                header = chunk.arrow.column_names if chunk.has_arrow else [str(c) for c in chunk.table.columns]
                csv.writer(fh, delimiter=sep, lineterminator="\n").writerow(header + new_cols)
            first = False
            if chunk.has_arrow:
                _write_csv_rows(fh, _with_corrected(chunk.arrow, values, new_cols), sep)
            else:  # NPZ/MAT tables and pandas-read text: written by pandas
                df = chunk.table.copy()
                for j, name in enumerate(new_cols):
                    df[name] = values[:, j]
                df.to_csv(fh, index=False, header=False, sep=sep, lineterminator="\n")
            tally.add(len(chunk), bad)


def _write_parquet(
    tmp: Path, corrected: Iterable[tuple[Chunk, NDArray[np.float64], int]], new_cols: list[str], tally: _Tally
) -> None:
    import pyarrow.parquet as pq

    writer = None
    try:
        for chunk, values, bad in corrected:
            table = _with_corrected(chunk.arrow, values, new_cols)
            if writer is None:
                writer = pq.ParquetWriter(tmp, table.schema)
            elif not table.schema.equals(writer.schema):
                table = table.cast(writer.schema)
            writer.write_table(table)
            tally.add(table.num_rows, bad)
    finally:
        if writer is not None:
            writer.close()


def _write_npz(tmp: Path, corrected: Iterable[tuple[Chunk, NDArray[np.float64], int]], tally: _Tally) -> None:
    parts = []
    for chunk, values, bad in corrected:
        parts.append((chunk.xyz, values))
        tally.add(len(values), bad)
    raw = np.vstack([r for r, _ in parts])
    cor = np.vstack([c for _, c in parts])
    with tmp.open("wb") as fb:
        np.savez(fb, raw=raw, corrected=cor)


class _RawLines:
    """The raw lines of a delimited text file, for ``apply`` to copy byte for byte.

    :meth:`head` gives the preamble lines and the header as written; :meth:`take` the next ``n`` data records, each
    as ``(record, ending)``: the record padded with the delimiter to the file's number of fields when short (the
    corrected cells then land in their columns) and followed by one delimiter, and its line ending. Blank and
    whitespace-only lines are skipped (the readers skip them); a record whose quotes are unbalanced continues on
    the next line (a quoted cell with a line break). Blocks without quotes or blank lines take a vectorised path.
    """

    def __init__(self, fin: Any, source: ChunkSource, sep: bytes) -> None:
        self.fin = fin
        self.source = source
        self.sep = sep
        self.blank = bytes(c for c in b" \t\r\f\v" if bytes([c]) != sep)  # a line of only these is skipped
        self._blank_line = re.compile(rb"\n[" + re.escape(self.blank) + rb"]*\n")  # a blank line after the first
        self.pending: list[bytes] = []

    def head(self) -> list[tuple[bytes, bytes | None]]:
        """The preamble lines ``(line, None)`` (ending included), then ``(header, ending)`` when there is one."""
        out: list[tuple[bytes, bytes | None]] = [(self.fin.readline(), None) for _ in range(self.source.skip)]
        if self.source.has_header:
            out.append(_split_ending(self.fin.readline()))
        return out

    def _line(self) -> bytes:
        return self.pending.pop() if self.pending else self.fin.readline()

    def take(self, cells: list[bytes]) -> Iterable[bytes] | None:
        """The next ``len(cells)`` records with ``cells`` appended, one per record, as pieces of the output's bytes;
        None when the file has fewer records left."""
        n = len(cells)
        sep, n_fields = self.sep, self.source.n_fields
        lines = list(itertools.islice(self.fin, n)) if not self.pending else []
        if len(lines) == n and n:
            data = b"".join(lines)
            eol = b"\r\n" if data.endswith(b"\r\n") else b"\n"
            if (data.endswith(b"\n") and data.count(eol) == n and (eol == b"\r\n" or b"\r" not in data)
                    and b'"' not in data and data.count(sep) == n * (n_fields - 1)
                    and lines[0].strip(self.blank + b"\n") and self._blank_line.search(data) is None):
                # plain full rows: no per-line work in Python
                del lines
                bodies = data[: -len(eol)].split(eol)
                del data
                return itertools.chain.from_iterable(zip(bodies, itertools.repeat(sep), cells, itertools.repeat(eol)))
        self.pending.extend(reversed(lines))
        out = []
        for cell in cells:
            record = self._record()
            if record is None:
                return None
            out.append(record[0] + cell + record[1])
        return out

    def at_end(self) -> bool:
        """Whether no record is left."""
        return self._record() is None

    def _record(self) -> tuple[bytes, bytes] | None:
        sep, n_fields = self.sep, self.source.n_fields
        while True:
            line = self._line()
            if not line:
                return None
            body, ending = _split_ending(line)
            if body.strip(self.blank):
                break
        while body.count(b'"') % 2:  # a quoted cell spans lines
            more = self._line()
            if not more:
                break
            nxt, ending2 = _split_ending(more)
            body = body + (b"\r\n" if ending == b"\r\n" else b"\n") + nxt
            ending = ending2
        if b'"' in body:
            fields = len(next(csv.reader([body.decode("utf-8", "surrogateescape")], delimiter=sep.decode())))
        else:
            fields = body.count(sep) + 1
        return body + sep * max(n_fields - fields, 0) + sep, ending


def _split_ending(line: bytes) -> tuple[bytes, bytes]:
    """A raw line without and with only its line ending (``\\n`` added when the last line has none)."""
    if line.endswith(b"\r\n"):
        return line[:-2], b"\r\n"
    if line.endswith(b"\n"):
        return line[:-1], b"\n"
    return line, b"\n"


def _corrected_cells(corrected: NDArray[np.float64], delimiter: str, *, arrow: bool) -> list[bytes]:
    """The corrected x, y, z of each row as delimited text (empty cells for NaN), one bytes line per row, formatted
    as the pyarrow or the pandas writer formats them (``arrow``)."""
    if arrow and available("pyarrow"):
        import pyarrow as pa
        import pyarrow.csv as pacsv

        table = pa.table({str(j): pa.array(corrected[:, j], from_pandas=True) for j in range(3)})
        buf = io.BytesIO()
        pacsv.write_csv(table, buf, write_options=pacsv.WriteOptions(
            include_header=False, delimiter=delimiter, quoting_style="none"))
        text = buf.getvalue()
    else:
        text = pd.DataFrame(corrected).to_csv(index=False, header=False, sep=delimiter, lineterminator="\n").encode()
    return text.split(b"\n")[: len(corrected)]


def _correct(
    calibrate: Callable[..., NDArray[np.float64]], xyz: NDArray[np.float64], u: NDArray[np.float64] | None = None
) -> tuple[NDArray[np.float64], int]:
    ok = np.isfinite(xyz).all(axis=1)
    if u is not None:
        ok &= np.isfinite(u).all(axis=1)
    extra = () if u is None else (u,)
    if ok.all():
        return np.asarray(calibrate(xyz, *extra), dtype=np.float64), 0
    corrected = np.full_like(xyz, np.nan)
    if ok.any():
        corrected[ok] = calibrate(xyz[ok], *(e[ok] for e in extra))
    return corrected, int((~ok).sum())


class MagnitudeAccumulator:
    """One-pass statistics of ``|B| - F`` over chunks, for a known reference (scalar or per-row) or, with
    ``F = None``, against the mean magnitude of all rows (:class:`~trimag._core.stats.StreamingMoments`: no
    cancellation when the field is large and its spread tiny)."""

    def __init__(self) -> None:
        self.norms = StreamingMoments()
        self.errors = StreamingMoments()
        self.known = False

    @property
    def n(self) -> int:
        """Rows added."""
        return self.norms.n

    def add(self, norms: NDArray[np.float64], reference: NDArray[np.float64] | float | None) -> None:
        if len(norms) == 0:
            return
        self.norms.add(norms)
        if reference is not None:
            self.known = True
            self.errors.add(norms - reference)

    def result(self, reference_value: float | None = None) -> dict[str, float]:
        """Statistics: ``mean_norm``, ``std_norm``, ``rms``, ``max_abs``, ``peak_to_peak``; without a known reference
        the errors are taken against ``reference_value`` (e.g. the corrected mean)."""
        norms = self.norms
        if self.known:
            rms = self.errors.rms_about(0.0)
            lo, hi = self.errors.lo, self.errors.hi
        else:
            F = norms.mean if reference_value is None else reference_value
            rms = norms.rms_about(F)
            lo, hi = norms.lo - F, norms.hi - F
        return {
            "mean_norm": float(norms.mean),
            "std_norm": float(np.sqrt(norms.variance)),
            "rms": float(rms),
            "max_abs": float(max(abs(lo), abs(hi))),
            "peak_to_peak": float(hi - lo),
        }
