"""Chunked reading for ``apply`` and ``evaluate``: memory stays bounded whatever the file size.

CSV/text and Parquet files are read ``chunk_rows`` rows at a time; NPZ and MAT files are loaded whole (they are
single arrays in memory by nature). Text cells are kept as strings so ``apply`` writes every input row and
column back unchanged, and appends the corrected columns.
"""

from __future__ import annotations

import os
import re
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from ..errors import TrimagInputError
from .tables import _numeric, detect_csv_layout, guess_format, read_table, resolve_columns

__all__ = ["Chunk", "MagnitudeAccumulator", "apply_file", "iter_chunks"]

DEFAULT_CHUNK_ROWS = 200_000


@dataclass
class Chunk:
    """One block of rows: the original cells, the x/y/z values (NaN where unusable) and the global row offset."""

    table: pd.DataFrame
    xyz: NDArray[np.float64]
    start: int


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


def _parse_rows(rows: str | None) -> tuple[int, int | None]:
    if not rows:
        return 0, None
    m = re.fullmatch(r"\s*(\d*)\s*:\s*(\d*)\s*", rows)
    if not m:
        raise TrimagInputError(f"--rows takes START:STOP with non-negative integers, e.g. 0:5000; got {rows!r}")
    return (int(m.group(1)) if m.group(1) else 0), (int(m.group(2)) if m.group(2) else None)


def open_chunks(
    path: str | Path,
    *,
    fmt: str | None = None,
    columns: str | None = None,
    var: str | None = None,
    chunk_rows: int = DEFAULT_CHUNK_ROWS,
) -> tuple[ChunkSource, Iterator[Chunk]]:
    """Inspect ``path`` and return its description and an iterator over :class:`Chunk` s."""
    p = Path(path)
    if not p.exists():
        raise TrimagInputError(f"{p}: no such file")
    kind = guess_format(p, fmt)
    if kind in ("csv", "txt"):
        layout = detect_csv_layout(p, fmt=kind)
        kwargs: dict[str, Any] = {
            "skiprows": layout.skip,
            "header": 0 if layout.has_header else None,
            "dtype": str,
            "keep_default_na": False,
            "sep": r"\s+" if layout.delimiter is None else layout.delimiter,
        }
        head = pd.read_csv(p, nrows=2000, **kwargs)
        if not layout.has_header:
            head.columns = [f"col{i}" for i in range(head.shape[1])]
        head.columns = [str(c).strip() for c in head.columns]
        if len(head) == 0:
            raise TrimagInputError(f"{p}: the file has a header but no data rows")
        cols, note = resolve_columns(head, columns)
        names = list(head.columns)
        source = ChunkSource(kind, cols, note, layout.preamble, layout.has_header, layout.delimiter, names)

        def gen_text() -> Iterator[Chunk]:
            start = 0
            reader = pd.read_csv(p, chunksize=chunk_rows, **kwargs)
            for df in reader:
                df.columns = names
                xyz = np.column_stack([_numeric(df[c]) for c in cols])
                yield Chunk(df, xyz, start)
                start += len(df)

        return source, gen_text()
    if kind == "parquet":
        import pyarrow.parquet as pq

        try:
            pf = pq.ParquetFile(p)
        except Exception as exc:
            raise TrimagInputError(f"{p}: not a readable Parquet file ({exc})") from None
        names = list(pf.schema_arrow.names)
        head = pf.read_row_group(0).to_pandas().head(2000) if pf.num_row_groups else pd.DataFrame(columns=names)
        if len(head) == 0:
            raise TrimagInputError(f"{p}: the file has no data rows")
        cols, note = resolve_columns(head, columns)
        source = ChunkSource(kind, cols, note, all_columns=names)

        def gen_parquet() -> Iterator[Chunk]:
            start = 0
            for batch in pf.iter_batches(batch_size=chunk_rows):
                df = batch.to_pandas()
                xyz = np.column_stack([_numeric(df[c]) for c in cols])
                yield Chunk(df, xyz, start)
                start += len(df)

        return source, gen_parquet()
    df = read_table(p, fmt=kind, var=var)
    cols, note = resolve_columns(df, columns)
    source = ChunkSource(kind, cols, note, all_columns=list(df.columns))

    def gen_whole() -> Iterator[Chunk]:
        yield Chunk(df, np.column_stack([_numeric(df[c]) for c in cols]), 0)

    return source, gen_whole()


def iter_chunks(path: str | Path, **kwargs: Any) -> Iterator[Chunk]:
    """Iterate over the :class:`Chunk` s of a file (see :func:`open_chunks`)."""
    return open_chunks(path, **kwargs)[1]


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
) -> dict[str, Any]:
    """Correct every row of ``in_path`` and write all input columns plus the corrected x, y, z to ``out_path``.

    The output format follows ``out_path``'s extension (``.csv``, ``.txt``, ``.parquet``, ``.npz``); CSV/text and
    Parquet are streamed in ``chunk_rows`` blocks. Rows whose x/y/z are missing, non-numeric or non-finite are
    kept, with empty corrected cells, and counted in ``n_uncorrected``. The file appears only when complete
    (written to a temporary file, then renamed).

    Returns
    -------
    dict
        ``n_rows``, ``n_uncorrected``, ``columns`` (x, y, z used), ``output_columns`` (appended names), ``out``.
    """
    out = Path(out_path)
    source, chunks = open_chunks(in_path, fmt=fmt, columns=columns, var=var, chunk_rows=chunk_rows)
    new_cols = [f"{c}{suffix}" for c in source.columns]
    out_kind = guess_format(out) if out.suffix else "csv"
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    n_rows = 0
    n_bad = 0
    try:
        if out_kind in ("csv", "txt"):
            sep = "," if out_kind == "csv" or source.delimiter is None else source.delimiter
            with tmp.open("w", encoding="utf-8", newline="") as fh:
                for line in source.preamble:
                    fh.write(line + "\n")
                first = True
                for chunk in chunks:
                    corrected, bad = _correct(calibrate, chunk.xyz)
                    df = chunk.table.copy()
                    for j, name in enumerate(new_cols):
                        df[name] = corrected[:, j]
                    df.to_csv(fh, index=False, header=first and source.has_header, sep=sep, lineterminator="\n")
                    first = False
                    n_rows += len(df)
                    n_bad += bad
                    if progress:
                        progress(n_rows)
        elif out_kind == "parquet":
            import pyarrow as pa
            import pyarrow.parquet as pq

            writer = None
            try:
                for chunk in chunks:
                    corrected, bad = _correct(calibrate, chunk.xyz)
                    df = chunk.table.copy()
                    for j, name in enumerate(new_cols):
                        df[name] = corrected[:, j]
                    table = pa.Table.from_pandas(df, preserve_index=False)
                    if writer is None:
                        writer = pq.ParquetWriter(tmp, table.schema)
                    writer.write_table(table)
                    n_rows += len(df)
                    n_bad += bad
                    if progress:
                        progress(n_rows)
            finally:
                if writer is not None:
                    writer.close()
        elif out_kind == "npz":
            parts = []
            for chunk in chunks:
                corrected, bad = _correct(calibrate, chunk.xyz)
                parts.append((chunk.xyz, corrected))
                n_rows += len(corrected)
                n_bad += bad
            raw = np.vstack([r for r, _ in parts])
            cor = np.vstack([c for _, c in parts])
            with tmp.open("wb") as fh:
                np.savez(fh, raw=raw, corrected=cor)
        else:
            raise TrimagInputError(f"cannot write {out.suffix!r} files; use .csv, .parquet or .npz for -o")
        os.replace(tmp, out)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return {
        "n_rows": n_rows,
        "n_uncorrected": n_bad,
        "columns": list(source.columns),
        "column_note": source.column_note,
        "output_columns": new_cols,
        "out": str(out),
    }


def _correct(
    calibrate: Callable[[NDArray[np.float64]], NDArray[np.float64]], xyz: NDArray[np.float64]
) -> tuple[NDArray[np.float64], int]:
    ok = np.isfinite(xyz).all(axis=1)
    corrected = np.full_like(xyz, np.nan)
    if ok.any():
        corrected[ok] = calibrate(xyz[ok])
    return corrected, int((~ok).sum())


class MagnitudeAccumulator:
    """One-pass statistics of ``|B| - F`` over chunks, for a known reference (scalar or per-row) or, with
    ``F = None``, against the mean magnitude of all rows (from running sums)."""

    def __init__(self) -> None:
        self.n = 0
        self.sum = 0.0
        self.sum_sq = 0.0
        self.min = np.inf
        self.max = -np.inf
        self.err_sq = 0.0
        self.err_min = np.inf
        self.err_max = -np.inf
        self.known = False

    def add(self, norms: NDArray[np.float64], reference: NDArray[np.float64] | float | None) -> None:
        if len(norms) == 0:
            return
        self.n += len(norms)
        self.sum += float(norms.sum())
        self.sum_sq += float((norms * norms).sum())
        self.min = min(self.min, float(norms.min()))
        self.max = max(self.max, float(norms.max()))
        if reference is not None:
            self.known = True
            err = norms - reference
            self.err_sq += float((err * err).sum())
            self.err_min = min(self.err_min, float(err.min()))
            self.err_max = max(self.err_max, float(err.max()))

    def result(self, reference_value: float | None = None) -> dict[str, float]:
        """Statistics: ``mean_norm``, ``std_norm``, ``rms``, ``max_abs``, ``peak_to_peak``; without a known reference
        the errors are taken against ``reference_value`` (e.g. the corrected mean)."""
        mean = self.sum / self.n
        var = max(self.sum_sq / self.n - mean * mean, 0.0)
        if self.known:
            rms = np.sqrt(self.err_sq / self.n)
            lo, hi = self.err_min, self.err_max
        else:
            F = mean if reference_value is None else reference_value
            rms = np.sqrt(max(self.sum_sq / self.n - 2 * F * mean + F * F, 0.0))
            lo, hi = self.min - F, self.max - F
        return {
            "mean_norm": float(mean),
            "std_norm": float(np.sqrt(var)),
            "rms": float(rms),
            "max_abs": float(max(abs(lo), abs(hi))),
            "peak_to_peak": float(hi - lo),
        }
