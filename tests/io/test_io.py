"""Reading logs: formats, column choice, and every bad-input case of the foundation issue."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import pytest
import scipy.io

from trimag.errors import TrimagInputError
from trimag.io import read_samples, read_table

from _helpers import SHARED_DATA, requires_shared, run_trimag, simulate_ellipsoid


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_csv_with_preamble_and_header(tmp_path: Path) -> None:
    p = _write(tmp_path / "a.csv", "Fs,50.00\nInitialization time,60\nmx,my,mz\n1,2,3\n4,5,6\n7,8,9\n")
    s = read_samples(p)
    assert s.columns == ("mx", "my", "mz")
    np.testing.assert_array_equal(s.field, [[1, 2, 3], [4, 5, 6], [7, 8, 9]])
    assert "recognised" in s.column_note


@pytest.mark.parametrize(
    "header,expected",
    [
        ("ax,ay,az,mx,my,mz", ("mx", "my", "mz")),
        ("time,mag_x,mag_y,mag_z", ("mag_x", "mag_y", "mag_z")),
        ("Bx (nT),By (nT),Bz (nT)", ("Bx (nT)", "By (nT)", "Bz (nT)")),
        ("x,y,z,t", ("x", "y", "z")),
    ],
)
def test_header_recognition(tmp_path: Path, header: str, expected: tuple[str, str, str]) -> None:
    ncol = len(header.split(","))
    rows = "\n".join(",".join(str(i * 10 + j) for j in range(ncol)) for i in range(5))
    s = read_samples(_write(tmp_path / "h.csv", f"{header}\n{rows}\n"))
    assert s.columns == expected


def test_three_candidate_columns_skip_time_and_four_are_not_guessed(tmp_path: Path) -> None:
    # issue 22: columns are never guessed silently; with four candidates the user chooses (exit 2)
    data = np.column_stack([np.arange(20) * 0.1, np.random.default_rng(0).normal(size=(20, 4))])
    p = tmp_path / "n.csv"
    np.savetxt(p, data, delimiter=",", header="time,a,b,c,d", comments="")
    with pytest.raises(TrimagInputError, match=r"several columns could be .*a, b, c, d.*`columns=X,Y,Z`"):
        read_samples(p)
    np.savetxt(p, data[:, :4], delimiter=",", header="time,a,b,c", comments="")
    s = read_samples(p)
    assert s.columns == ("a", "b", "c")
    assert "only three" in s.column_note and "time" in s.column_note


def test_columns_by_name_and_index(tmp_path: Path) -> None:
    p = _write(tmp_path / "c.csv", "t,p,q,r\n0,1,2,3\n1,4,5,6\n2,7,8,9\n")
    assert read_samples(p, columns="r,q,p").columns == ("r", "q", "p")
    assert read_samples(p, columns="1,2,3").columns == ("p", "q", "r")
    with pytest.raises(TrimagInputError, match="no column 'w'"):
        read_samples(p, columns="p,q,w")
    with pytest.raises(TrimagInputError, match="out of range"):
        read_samples(p, columns="1,2,9")
    with pytest.raises(TrimagInputError, match="exactly three"):
        read_samples(p, columns="p,q")


def test_whitespace_text(tmp_path: Path) -> None:
    p = _write(tmp_path / "w.txt", "# x y z\n1 2 3\n4 5 6\n7 8 9\n")
    assert read_samples(p).field.shape == (3, 3)


def test_npz_mat_parquet(tmp_path: Path) -> None:
    raw = simulate_ellipsoid(50)
    np.savez(tmp_path / "a.npz", mag=raw, other=np.ones(5))
    np.testing.assert_array_equal(read_samples(tmp_path / "a.npz").field, raw)
    scipy.io.savemat(tmp_path / "a.mat", {"imu_mag": raw, "imu_acc": raw * 0})
    np.testing.assert_array_equal(read_samples(tmp_path / "a.mat").field, raw)
    with pytest.raises(TrimagInputError, match="`var`"):
        scipy.io.savemat(tmp_path / "b.mat", {"a": raw, "b": raw})
        read_samples(tmp_path / "b.mat")
    np.testing.assert_array_equal(read_samples(tmp_path / "b.mat", var="b").field, raw)
    with h5py.File(tmp_path / "c.mat", "w") as h5:  # MATLAB v7.3 layout: 4 x N, rows t, x, y, z
        h5["compassBuffer"] = np.vstack([np.arange(50.0), raw.T])
    s = read_samples(tmp_path / "c.mat")
    np.testing.assert_array_equal(s.field, raw)
    pd.DataFrame(raw, columns=["bx", "by", "bz"]).to_parquet(tmp_path / "a.parquet")
    np.testing.assert_array_equal(read_samples(tmp_path / "a.parquet").field, raw)


# ---- the bad-input cases of the foundation issue, one test each -------------------------------------------
def test_empty_file(tmp_path: Path) -> None:
    with pytest.raises(TrimagInputError, match="empty"):
        read_samples(_write(tmp_path / "e.csv", ""))


def test_header_only(tmp_path: Path) -> None:
    with pytest.raises(TrimagInputError, match="no data rows"):
        read_samples(_write(tmp_path / "h.csv", "bx,by,bz\n"))


def test_non_numeric_cells_dropped_and_counted(tmp_path: Path) -> None:
    p = _write(tmp_path / "n.csv", "bx,by,bz\n1,2,3\n4,oops,6\n7,8,9\n10,11,\n13,14,15\n")
    s = read_samples(p)
    assert s.n_rows == 5 and s.n_dropped == 2 and s.dropped_index == [1, 3]
    assert s.field.shape == (3, 3)
    with pytest.raises(TrimagInputError, match="2 row"):
        read_samples(p, strict=True)


def test_fewer_than_three_numeric_columns(tmp_path: Path) -> None:
    with pytest.raises(TrimagInputError, match="three"):
        read_samples(_write(tmp_path / "two.csv", "x,y\n1,2\n3,4\n5,6\n"))
    with pytest.raises(TrimagInputError, match="three"):
        read_samples(_write(tmp_path / "txt.csv", "a,b,c\n1,2,x\n3,4,y\n5,6,z\n"))


def test_nan_inf_rows_dropped_and_counted(tmp_path: Path) -> None:
    p = _write(tmp_path / "nan.csv", "bx,by,bz\n1,2,3\nnan,5,6\n7,inf,9\n10,11,12\n13,14,15\n")
    s = read_samples(p)
    assert s.n_dropped == 2 and s.field.shape == (3, 3)
    with pytest.raises(TrimagInputError, match="`strict`"):
        read_samples(p, strict=True)


def test_duplicate_rows_counted_and_kept(tmp_path: Path) -> None:
    s = read_samples(_write(tmp_path / "d.csv", "bx,by,bz\n1,2,3\n1,2,3\n4,5,6\n1,2,3\n"))
    assert s.n_duplicates == 2 and s.field.shape == (4, 3)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(TrimagInputError, match="no such file"):
        read_samples(tmp_path / "nope.csv")


def test_all_rows_bad(tmp_path: Path) -> None:
    with pytest.raises(TrimagInputError, match="none of the"):
        read_samples(_write(tmp_path / "bad.csv", "bx,by,bz\n1,2,nan\nx,5,6\n1,2,3x\n"))


def test_row_selection(tmp_path: Path) -> None:
    p = _write(tmp_path / "s.csv", "axis,bx,by,bz\nx,1,2,3\ny,4,5,6\nx,7,8,9\nz,1,1,1\n")
    assert read_samples(p, rows="1:3").field.tolist() == [[4, 5, 6], [7, 8, 9]]
    assert read_samples(p, where="axis==x").field.tolist() == [[1, 2, 3], [7, 8, 9]]
    assert read_samples(p, where="axis!=x").n_rows == 2
    with pytest.raises(TrimagInputError, match="matched no rows"):
        read_samples(p, where="axis==w")
    with pytest.raises(TrimagInputError, match="START:STOP"):
        read_samples(p, rows="a-b")


@requires_shared
@pytest.mark.parametrize(
    "rel,kwargs,n",
    [
        ("qmc5883l-suarez/noisy_raw_data.csv", {}, 22743),
        ("ck-explorer-accmag/acc_mag_log.csv", {}, 12000),
        ("smartphone-kritiksoman/data_mag.txt", {}, 1266),
        ("hmc5883l-sunsided/full-sphere_hmc5883l_compass.mat", {}, 8190),
        ("broad/01_undisturbed_slow_rotation_A.mat", {"var": "imu_mag"}, 56940),
    ],
)
def test_shared_real_logs(rel: str, kwargs: dict[str, str], n: int) -> None:
    s = read_samples(SHARED_DATA / rel, **kwargs)
    assert s.field.shape == (n, 3) and s.n_dropped == 0


def test_count_duplicate_rows_matches_pandas_and_ignores_hash_collisions(monkeypatch):
    """The hashed duplicate count equals pandas' exact one (``-0.0 == 0.0`` included); rows whose hashes
    collide but differ are not counted (forced here by a constant hash)."""
    import pandas as pd

    import trimag.io.tables as tables

    rng = np.random.default_rng(0)
    for trial in range(60):
        a = rng.integers(-2, 3, (int(rng.integers(1, 200)), 3)).astype(float)
        if trial % 2:
            a[a == 0] = -0.0
        assert tables.count_duplicate_rows(a) == int(pd.DataFrame(a + 0.0).duplicated().sum())
    distinct = rng.standard_normal((50, 3))
    assert tables.count_duplicate_rows(distinct) == 0
    monkeypatch.setattr(tables.pd.util, "hash_array", lambda values, *a, **k: np.zeros(len(values), np.uint64))
    assert tables.count_duplicate_rows(distinct) == 0
    assert tables.count_duplicate_rows(np.vstack([distinct, distinct[:7]])) == 7


def test_csv_reader_arrow_and_pandas_paths_agree(tmp_path, monkeypatch):
    """The pyarrow reader (every cell a string) gives the same samples, table and counts as the pandas one,
    with a preamble, quoted cells, empty and non-numeric field cells."""
    import trimag.io.tables as tables

    text = "Fs,50.00\nt,bx,by,bz,note\n" + "".join(
        f'{i * 0.02:.2f},{1000 + i},{-200 + 3 * i},{50 - i},"a, {i}"\n' for i in range(40)
    )
    text += '0.80,,5,6,x\n0.82,abc,1,2,y\n0.84,1001,-197,49,"a, 1"\n'
    path = tmp_path / "log.csv"
    path.write_text(text)
    fast = read_samples(path)
    monkeypatch.setattr(tables, "_read_delimited_arrow", lambda *a, **k: None)
    slow = read_samples(path)
    np.testing.assert_array_equal(fast.field, slow.field)
    assert fast.table.astype(str).equals(slow.table.astype(str))
    assert (fast.n_rows, fast.n_dropped, fast.n_duplicates) == (slow.n_rows, slow.n_dropped, slow.n_duplicates)
    assert (fast.n_dropped, fast.n_duplicates) == (2, 1)
    assert fast.columns == ("bx", "by", "bz")


@pytest.mark.parametrize(
    ("bad_row", "dropped"),
    [(None, 0), ("1.5,,3.0", 1), ("nan,2,3", 1), ("1.0,NA,3.0", 1), ("1.0,abc,3.0", 1), (" 1.0, 2.0, 3.0", 0)],
)
def test_numeric_csv_reads_as_floats_with_the_same_rows_as_the_text_path(
    tmp_path: Path, bad_row: str | None, dropped: int
) -> None:
    """A CSV whose sniffed lines are plain numbers is read into float columns (no string per cell). Cells that
    are not plain numbers (empty, NA, text, spaces) either become NaN and are dropped and counted, or send the
    reader back to the text path: the same samples, drops and duplicates as a file that can only be read as
    text (here: the same rows with a text column appended)."""
    rng = np.random.default_rng(12)
    rows = [",".join(f"{v:.3f}" for v in r) for r in rng.normal(size=(400, 3)) * 300]
    rows += rows[:5]  # 5 duplicate rows
    if bad_row is not None:
        rows[350] = bad_row  # far below the sniffed head: only the reader sees it
    numeric = _write(tmp_path / "numeric.csv", "x,y,z\n" + "\n".join(rows) + "\n")
    text = _write(tmp_path / "text.csv", "x,y,z,label\n" + "\n".join(r + ",run-a" for r in rows) + "\n")
    a, b = read_samples(numeric), read_samples(text)
    if bad_row is None:
        assert a.table["x"].dtype == np.float64  # the typed fast path
    assert b.table["label"].dtype != np.float64  # the text path
    np.testing.assert_array_equal(a.field, b.field)
    assert (a.n_dropped, a.n_duplicates, a.dropped_index) == (b.n_dropped, b.n_duplicates, b.dropped_index)
    assert a.n_dropped == dropped


@pytest.mark.parametrize(
    "header",
    ["x,y,z", " x , y , z", '"mag x","mag y","mag z"', "x,x,y", "x,,z", "\ufeffx,y,z", "t,bx,by,bz", None],
)
def test_csv_column_names_are_those_pandas_gives(tmp_path: Path, header: str | None) -> None:
    """The column names come from the sniffed header line when pandas would keep them as written, and from pandas
    otherwise (duplicate or empty names, a byte-order mark): the table has pandas' names either way."""
    width = 4 if header is not None and header.startswith("t,") else 3
    rng = np.random.default_rng(3)
    body = "\n".join(",".join(f"{v:.2f}" for v in r) for r in rng.normal(size=(30, width)) * 100) + "\n"
    path = tmp_path / "log.csv"
    path.write_text(("" if header is None else header + "\n") + body, encoding="utf-8")
    expected = pd.read_csv(path, header=0 if header is not None else None, dtype=str)
    names = [f"col{i}" for i in range(width)] if header is None else [str(c).strip() for c in expected.columns]
    df = read_table(path)
    assert list(df.columns) == names
    np.testing.assert_array_equal(df.to_numpy(dtype=float), expected.to_numpy(dtype=float))


@pytest.mark.parametrize("first_row", ["nan,1.0,2.0", "inf,1.0,2.0", '"1.5","2.5","3.5"', "+1.5,-2.5,3e2"])
def test_numbers_python_reads_keep_the_typed_read(tmp_path: Path, first_row: str) -> None:
    """``nan``, ``inf``, quoted numbers, signs and exponents in the sniffed lines still take the typed (float) read,
    with the samples and drops of the text read."""
    rng = np.random.default_rng(4)
    rows = [first_row] + [",".join(f"{v:.3f}" for v in r) for r in rng.normal(size=(50, 3))]
    typed = read_samples(_write(tmp_path / "typed.csv", "x,y,z\n" + "\n".join(rows) + "\n"))
    text = read_samples(_write(tmp_path / "text.csv", "x,y,z,k\n" + "\n".join(r + ",a" for r in rows) + "\n"))
    assert typed.table["x"].dtype == np.float64
    np.testing.assert_array_equal(typed.field, text.field)
    assert (typed.n_dropped, typed.n_duplicates) == (text.n_dropped, text.n_duplicates)


def test_count_duplicate_rows_with_a_block_transform_counts_the_transformed_rows(small_chunks):
    """``prepare`` is applied block by block (blocks of 5 here) and to the compared candidates: the count is that
    of the transformed array, without a transformed copy of the whole array."""
    from trimag._core import rowwise as _rowwise

    small_chunks(5)
    rng = np.random.default_rng(2)
    a = rng.normal(size=(40, 3))
    a[10:20] = a[:10] + 1e-12  # equal after rounding to 9 decimals, distinct before
    assert _rowwise.count_duplicate_rows(a) == 0
    rounded = np.round(a, 9)
    expected = int(pd.DataFrame(rounded + 0.0).duplicated().sum())
    assert expected == 10
    assert _rowwise.count_duplicate_rows(a, prepare=lambda rows: np.round(rows, 9)) == expected


def _geosoft_xyz(path: Path, n_per_line: int = 200, null_rows: tuple[int, ...] = (5, 250)) -> tuple[Path, np.ndarray]:
    """A Geosoft XYZ file: `/` comments, a `/` names record, `Line`/`Tie` records, `*` nulls in FLUX_Y."""
    B = simulate_ellipsoid(2 * n_per_line, noise=5.0, seed=11, F=50_000.0)
    out = ["/ ------------------------------------------", "/ XYZ EXPORT [03/14/2024]",
           "/ DATABASE   [.\\survey.gdb]", "/", "/          X          Y     FLUX_X     FLUX_Y     FLUX_Z        MAG"]
    for k in range(2 * n_per_line):
        if k % n_per_line == 0:
            out.append(["Line 1001", "Tie 2001"][k // n_per_line])
        fy = "*" if k in null_rows else f"{B[k, 1]:.2f}"
        out.append(f"  {500000 + 10 * k:10.1f} {6100000.0:12.1f} {B[k, 0]:10.2f} {fy:>10} {B[k, 2]:10.2f} "
                   f"{np.linalg.norm(B[k]):10.2f}")
    path.write_text("\n".join(out) + "\n", encoding="utf-8")
    return path, B


def test_geosoft_xyz_names_nulls_and_line_records(tmp_path: Path) -> None:
    """Finding (issue 22): Geosoft XYZ (`/` header lines, `*` nulls) was refused with a poor message."""
    path, B = _geosoft_xyz(tmp_path / "survey.xyz")
    s = read_samples(path, columns="FLUX_X,FLUX_Y,FLUX_Z")
    assert s.columns == ("FLUX_X", "FLUX_Y", "FLUX_Z") and s.n_rows == 400
    assert s.n_dropped == 2 and s.dropped_index == [5, 250]  # the `*` rows, counted
    np.testing.assert_allclose(s.field, np.delete(B, [5, 250], axis=0), atol=0.006)
    assert list(s.table["line"].unique()) == ["1001", "2001"]
    assert "2 line record(s)" in s.format_note and "2 row(s) with a `*` null" in s.format_note
    one_line = read_samples(path, columns="FLUX_X,FLUX_Y,FLUX_Z", where="line==2001")
    assert one_line.n_rows == 200 and one_line.n_dropped == 1
    # detected by the `/` header without the extension, and by its columns' names without `columns`
    other = tmp_path / "survey.dat"
    other.write_bytes(path.read_bytes())
    assert read_samples(other, columns="2,3,4").n_dropped == 2
    assert list(read_table(other).columns) == ["X", "Y", "FLUX_X", "FLUX_Y", "FLUX_Z", "MAG", "line"]
    # without `columns`: the line number, the total field MAG and the coordinates are not axes
    assert read_samples(path).columns == ("FLUX_X", "FLUX_Y", "FLUX_Z")


def test_geosoft_xyz_ragged_row_is_refused_with_its_line(tmp_path: Path) -> None:
    path = tmp_path / "bad.xyz"
    path.write_text("/ X Y Z\n1 2 3\n4 5\n", encoding="utf-8")
    with pytest.raises(TrimagInputError, match=r"line 3 has 2 fields where the data rows have 3"):
        read_samples(path)


def test_geosoft_xyz_data_row_that_is_not_utf8_is_refused_with_its_line(tmp_path: Path) -> None:
    """Found by test_fuzz_cli (``b'/\\n\\x80'``): a non-UTF-8 byte in a data row was an internal error (exit 1)."""
    path = tmp_path / "latin1.txt"
    path.write_bytes(b"/ X Y Z\n1 2 3\n4 5 \xb06\n")
    with pytest.raises(TrimagInputError, match=r"line 3 is not UTF-8 text \(byte 0xb0\)"):
        read_samples(path)
    comment = tmp_path / "comment.xyz"  # a non-UTF-8 byte in a comment is kept, not refused
    comment.write_bytes(b"/ survey at 45\xb0N\n/ X Y Z\n1 2 3\n4 5 6\n")
    assert len(read_samples(comment).field) == 2


def test_cli_non_utf8_geosoft_record_exits_2_with_one_line(tmp_path: Path) -> None:
    path = tmp_path / "fuzz.txt"
    path.write_bytes(b"/\n\x80")
    r = run_trimag("fit", str(path))
    assert r.returncode == 2, r.stderr
    assert r.stderr.count("\n") == 1 and "not UTF-8" in r.stderr


def test_wild_rows_are_dropped_counted_and_named(tmp_path: Path) -> None:
    """A row 1000x the others (a logger glitch) is dropped and counted like a NaN row, with its row number; `strict`
    refuses it (issue 33, item 7)."""
    rng = np.random.default_rng(0)
    u = rng.normal(size=(300, 3))
    B = 48000.0 * u / np.linalg.norm(u, axis=1, keepdims=True)
    B[57] *= 1000.0
    B[200] = [1e308, 0.0, 0.0]
    p = tmp_path / "wild.csv"
    np.savetxt(p, B, delimiter=",", header="x,y,z", comments="", fmt="%.6g")
    s = read_samples(p)
    assert s.n_rows == 300 and s.n_dropped == 2 and s.n_wild == 2 and s.wild_index == [57, 200]
    assert s.field.shape == (298, 3) and np.abs(s.field).max() < 50000
    with pytest.raises(TrimagInputError, match="data row 57"):
        read_samples(p, strict=True)
