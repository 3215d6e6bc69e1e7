"""A large CSV of short plain-number rows is parsed block by block into one array (issue 41, item 10): what
``read_samples`` gives is the same as reading the file whole, cell for cell and count for count (dropped rows,
their numbers, duplicates, columns and how they were chosen), whatever the file holds past the lines the layout
was sniffed from (empty, `nan`, quoted or non-numeric cells, blank lines, CRLF, no final newline, a row of another
width); the samples are then held once, shared with the table."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import trimag.io.tables as tables
from trimag._core.chunks import working_memory_limit
from trimag.errors import TrimagInputError
from trimag.io import read_samples

N_ROWS = tables.SHARED_XYZ_ROWS + 2000


def _rows(n: int, seed: int = 5) -> list[str]:
    rng = np.random.default_rng(seed)
    xyz = rng.integers(-600, 600, size=(n, 3))
    xyz[::9] = xyz[1::9][: len(xyz[::9])]  # repeated rows: duplicates to count
    return [f"{a},{b},{c}" for a, b, c in xyz]


def _both(path: Path, monkeypatch: pytest.MonkeyPatch, *, by_blocks: bool = True
          ) -> tuple[tables.Samples, tables.Samples]:
    """The file read block by block (blocks of 4 KiB: many of them) and read whole; ``by_blocks``: whether the
    block reader took the file (or gave it back to the whole-file reader)."""
    read = tables._read_numeric_blocks
    taken: list[bool] = []

    def spy(*args: object) -> object:
        df = read(*args)  # type: ignore[arg-type]
        taken.append(df is not None)
        return df

    with monkeypatch.context() as m:
        m.setattr(tables, "NARROW_STREAM_BYTES", 0)
        m.setattr(tables, "_read_numeric_blocks", spy)
        with working_memory_limit(6144):  # blocks of 4 KiB of text
            blocks = read_samples(path)
    assert taken == [by_blocks]
    with monkeypatch.context() as m:
        m.setattr(tables, "NARROW_STREAM_BYTES", 1 << 62)
        whole = read_samples(path)
    return blocks, whole


def _same(a: tables.Samples, b: tables.Samples) -> None:
    assert np.array_equal(a.field, b.field)
    assert (a.n_rows, a.n_dropped, a.dropped_index, a.n_duplicates) == (b.n_rows, b.n_dropped, b.dropped_index,
                                                                        b.n_duplicates)
    assert (a.columns, a.column_note) == (b.columns, b.column_note)
    assert list(a.table.columns) == list(b.table.columns) and a.table.index.equals(b.table.index)
    for name in a.table.columns:
        assert np.array_equal(a.table[name].to_numpy(dtype=float), b.table[name].to_numpy(dtype=float),
                              equal_nan=True)


def test_a_large_log_read_by_blocks_is_the_log_read_whole(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    rows = _rows(N_ROWS)
    rows[70_000] = "5,,7"  # past the sniffed lines: an empty cell, a NaN, an inf, a quoted number
    rows[80_000] = "nan,1,2"
    rows[90_000] = "1,inf,2"
    rows[95_000] = '"12.5",3,4'
    rows.insert(60_000, "")  # a blank line
    path = tmp_path / "big.csv"
    path.write_bytes(("x,y,z\r\n" + "\r\n".join(rows)).encode())  # CRLF, no final newline
    blocks, whole = _both(path, monkeypatch)
    _same(blocks, whole)
    assert blocks.n_dropped == 3 and blocks.n_duplicates > 10_000
    assert blocks.field.flags.writeable and blocks.field.flags.c_contiguous
    for k, name in enumerate("xyz"):  # held once: the table's columns are views of the samples, in place
        assert np.shares_memory(blocks.table[name].to_numpy(), blocks.field[:, k])


@pytest.mark.parametrize("header", ["", "t,x,y,z\n", "z,x,y\n"])
def test_columns_are_chosen_the_same(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, header: str) -> None:
    """Without a header (a time column told by its numbers), with a time column named, with the axes out of order."""
    rows = _rows(N_ROWS)
    if header.count(",") == 3 or not header:
        rows = [f"{k * 0.01:.2f},{r}" for k, r in enumerate(rows)]
    path = tmp_path / "log.csv"
    path.write_text(header + "\n".join(rows) + "\n")
    blocks, whole = _both(path, monkeypatch)
    _same(blocks, whole)


def test_a_non_numeric_cell_past_the_sniffed_lines_is_dropped_and_counted(tmp_path: Path,
                                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    rows = _rows(N_ROWS)
    rows[50_000] = "1,abc,3"
    path = tmp_path / "text.csv"
    path.write_text("x,y,z\n" + "\n".join(rows) + "\n")
    blocks, whole = _both(path, monkeypatch, by_blocks=False)  # (read whole, the cells as text)
    _same(blocks, whole)
    assert blocks.n_dropped == 1 and blocks.dropped_index == [50_000]


def test_a_row_of_another_width_is_refused_the_same(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    rows = _rows(N_ROWS)
    rows[50_000] = "1,2,3,4"
    path = tmp_path / "wide.csv"
    path.write_text("x,y,z\n" + "\n".join(rows) + "\n")
    messages = []
    for stream_bytes in (0, 1 << 62):
        with monkeypatch.context() as m, pytest.raises(TrimagInputError) as err:
            m.setattr(tables, "NARROW_STREAM_BYTES", stream_bytes)
            read_samples(path)
        messages.append(str(err.value))
    assert messages[0] == messages[1] and "line" in messages[0]
