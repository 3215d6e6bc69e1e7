"""A large log's samples and its table hold x, y, z once (issue 41, item 10): the table's x, y, z columns are views
of ``Samples.field``, in their places among the other columns, with the same values; rows dropped as non-finite
or wild are gone from both. Small logs keep their own columns (cheaper to read)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from trimag.io import column_values, read_samples
from trimag.io.tables import SHARED_XYZ_ROWS


def _log(path: Path, n: int) -> np.ndarray:
    rng = np.random.default_rng(7)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    xyz = np.round(u * 500 + [30, -20, 10], 2)
    table = pd.DataFrame({"t": np.arange(n) * 0.01, "mx": xyz[:, 0], "temp": 20.0, "my": xyz[:, 1],
                          "mz": xyz[:, 2]})
    table.to_csv(path, index=False)
    text = path.read_text().splitlines()
    text[5] = text[5].replace(text[5].split(",")[1], "", 1)  # data row 4: an empty x cell, dropped and counted
    path.write_text("\n".join(text) + "\n")
    return xyz


def test_a_large_log_holds_its_samples_once_and_its_table_in_order(tmp_path: Path) -> None:
    n = SHARED_XYZ_ROWS + 5000
    xyz = _log(tmp_path / "big.csv", n)
    s = read_samples(tmp_path / "big.csv", columns="mx,my,mz")
    assert s.n_dropped == 1 and len(s.field) == n - 1
    assert list(s.table.columns) == ["t", "mx", "temp", "my", "mz"]
    assert np.array_equal(s.field, np.delete(xyz, 4, axis=0))
    for k, name in enumerate(("mx", "my", "mz")):
        values = s.table[name].to_numpy()
        assert np.shares_memory(values, s.field) and np.array_equal(values, s.field[:, k])
    assert np.array_equal(column_values(s, "t"), np.delete(np.arange(n) * 0.01, 4))
    assert s.table.index[4] == 5  # the index still numbers the data rows


def test_a_small_log_reads_the_same(tmp_path: Path) -> None:
    xyz = _log(tmp_path / "small.csv", 2000)
    s = read_samples(tmp_path / "small.csv", columns="mx,my,mz")
    assert list(s.table.columns) == ["t", "mx", "temp", "my", "mz"] and s.n_dropped == 1
    assert np.array_equal(s.field, np.delete(xyz, 4, axis=0))
    assert np.array_equal(s.table[["mx", "my", "mz"]].to_numpy(dtype=float), s.field)  # (cells as read: text here)
