"""Streaming ``apply`` / ``evaluate`` over files larger than one chunk (small ``chunk_rows`` exercise chunking).

Every row and every column is kept, in order and unchanged; rows with unusable x/y/z are kept with empty
corrected cells and counted; statistics computed chunk by chunk equal the whole-array ones; the output file
appears only when complete.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from trimag import Calibration
from trimag.app import apply_to_file, evaluate_file
from trimag.errors import TrimagInputError
from trimag.io import MagnitudeAccumulator, apply_file, iter_chunks, open_chunks

from _helpers import restore_sigint, simulate_ellipsoid

N = 103  # not a multiple of the chunk sizes used below
BAD = {7: "nan", 20: "", 41: "abc", 66: "inf"}  # row -> bad x cell


@pytest.fixture
def cal(tmp_path: Path) -> tuple[Calibration, Path]:
    W = np.array([[1.02, 0.01, 0.0], [0.0, 0.97, -0.02], [0.0, 0.0, 1.01]])
    c = Calibration.from_matrix_offset(W, [100.0, -50.0, 25.0], model="ellipsoid", units="nT")
    path = tmp_path / "cal.json"
    c.to_file(path)
    return c, path


def _rows(seed: int = 0) -> tuple[list[list[str]], np.ndarray]:
    """Cells as text (time, quoted label with a comma, x, y, z with some oddly formatted numbers)."""
    raw = simulate_ellipsoid(N, noise=5.0, seed=seed)
    rows = []
    for i, (x, y, z) in enumerate(raw):
        label = f"pass {i // 10}, leg {i % 3}" if i % 5 == 0 else f"p{i}"
        xs = BAD.get(i, f"{x:.3f}")
        rows.append([f"{i * 0.02:.2f}", label, xs, f"{y:.4e}" if i % 4 == 0 else f"{y:.3f}", f"{z:.3f}"])
    return rows, raw


def _write_csv(path: Path, rows: list[list[str]], *, preamble: tuple[str, ...] = (), header: bool = True,
               delimiter: str = ",") -> None:
    with path.open("w", encoding="utf-8", newline="") as fh:
        for line in preamble:
            fh.write(line + "\n")
        w = csv.writer(fh, delimiter=delimiter, lineterminator="\n")
        if header:
            w.writerow(["time", "label", "bx", "by", "bz"])
        w.writerows(rows)


def _expected_corrected(c: Calibration, rows: list[list[str]]) -> np.ndarray:
    xyz = np.array([[float(v) if v not in ("", "abc") else np.nan for v in r[2:]] for r in rows])
    ok = np.isfinite(xyz).all(axis=1)
    out = np.full_like(xyz, np.nan)
    out[ok] = c.apply(xyz[ok])
    return out


@pytest.mark.parametrize("chunk_rows", [1, 10, 50, 1000])
def test_apply_csv_keeps_every_row_and_cell(tmp_path: Path, cal: tuple[Calibration, Path], chunk_rows: int) -> None:
    c, _ = cal
    rows, _ = _rows()
    src = tmp_path / "log.csv"
    _write_csv(src, rows, preamble=("Fs,50.00", "sensor,QMC5883L"))
    out = tmp_path / "out" / "log_cal.csv"
    seen: list[int] = []
    res = apply_file(c.apply, src, out, chunk_rows=chunk_rows, progress=seen.append)
    assert res["n_rows"] == N and res["n_uncorrected"] == len(BAD)
    assert res["output_columns"] == ["bx_cal", "by_cal", "bz_cal"]
    assert seen[-1] == N and seen == sorted(seen) and len(seen) == -(-N // chunk_rows)
    with out.open(encoding="utf-8", newline="") as fh:
        lines = fh.read().split("\n")
    assert lines[:2] == ["Fs,50.00", "sensor,QMC5883L"]  # preamble kept
    got = list(csv.reader(lines[2:-1]))
    assert lines[-1] == ""
    assert got[0] == ["time", "label", "bx", "by", "bz", "bx_cal", "by_cal", "bz_cal"]
    assert len(got) == N + 1
    assert [r[:5] for r in got[1:]] == rows  # every input cell unchanged, in order
    cor = np.array([[float(v) if v else np.nan for v in r[5:]] for r in got[1:]])
    np.testing.assert_array_equal(np.isnan(cor), np.isnan(_expected_corrected(c, rows)))
    np.testing.assert_allclose(cor, _expected_corrected(c, rows), rtol=1e-15, equal_nan=True)
    assert all(r[5:] == ["", "", ""] for i, r in enumerate(got[1:]) if i in BAD)
    assert not list(out.parent.glob(".*.tmp"))


def test_apply_headerless_semicolon_and_whitespace(tmp_path: Path, cal: tuple[Calibration, Path]) -> None:
    c, _ = cal
    raw = simulate_ellipsoid(37, seed=3)
    rows = [[f"{v:.2f}" for v in r] for r in raw]
    src = tmp_path / "semi.csv"
    _write_csv(src, rows, header=False, delimiter=";")
    out = tmp_path / "semi_out.csv"
    res = apply_file(c.apply, src, out, chunk_rows=8)
    got = list(csv.reader(out.read_text(encoding="utf-8").splitlines()))
    assert res["n_rows"] == 37 and len(got) == 37  # no header in, none out
    assert [r[:3] for r in got] == rows
    np.testing.assert_allclose(np.array(got, dtype=float)[:, 3:], c.apply(raw.round(2)), rtol=1e-12)
    txt = tmp_path / "ws.txt"
    txt.write_text("x y z\n" + "\n".join("  ".join(r) for r in rows) + "\n", encoding="utf-8")
    out_txt = tmp_path / "ws_out.txt"
    res = apply_file(c.apply, txt, out_txt, chunk_rows=8)
    lines = out_txt.read_text(encoding="utf-8").splitlines()
    # whitespace-delimited input is written comma-separated
    assert res["n_rows"] == 37 and len(lines) == 38 and lines[0] == "x,y,z,x_cal,y_cal,z_cal"
    assert [ln.split(",")[:3] for ln in lines[1:]] == rows
    np.testing.assert_allclose(np.array([ln.split(",")[3:] for ln in lines[1:]], dtype=float),
                               c.apply(raw.round(2)), rtol=1e-12)


def test_apply_parquet_in_and_out(tmp_path: Path, cal: tuple[Calibration, Path]) -> None:
    c, _ = cal
    raw = simulate_ellipsoid(N, seed=4)
    raw[[5, 60]] = np.nan
    table = pa.table({"t": np.arange(N) * 0.5, "label": [f"r{i}" for i in range(N)],
                      "x": raw[:, 0], "y": raw[:, 1], "z": raw[:, 2]})
    src = tmp_path / "log.parquet"
    pq.write_table(table, src, row_group_size=30)
    for out_name in ("out.parquet", "out.csv"):
        out = tmp_path / out_name
        res = apply_file(c.apply, src, out, chunk_rows=16)
        assert res["n_rows"] == N and res["n_uncorrected"] == 2
        df = pd.read_parquet(out) if out_name.endswith("parquet") else pd.read_csv(out)
        assert list(df.columns) == ["t", "label", "x", "y", "z", "x_cal", "y_cal", "z_cal"]
        np.testing.assert_array_equal(df["t"], np.arange(N) * 0.5)
        assert list(df["label"]) == [f"r{i}" for i in range(N)]
        ok = np.isfinite(raw).all(axis=1)
        cor = df[["x_cal", "y_cal", "z_cal"]].to_numpy(dtype=float)
        assert np.isnan(cor[~ok]).all()
        np.testing.assert_allclose(cor[ok], c.apply(raw[ok]), rtol=1e-15)


def test_apply_npz_output(tmp_path: Path, cal: tuple[Calibration, Path]) -> None:
    c, _ = cal
    rows, _ = _rows()
    src = tmp_path / "log.csv"
    _write_csv(src, rows)
    out = tmp_path / "out.npz"
    apply_file(c.apply, src, out, chunk_rows=10)
    with np.load(out) as z:
        assert z["raw"].shape == (N, 3)
        np.testing.assert_allclose(z["corrected"], _expected_corrected(c, rows), rtol=1e-15, equal_nan=True)


class _Boom(RuntimeError):
    pass


def test_apply_is_atomic(tmp_path: Path, cal: tuple[Calibration, Path]) -> None:
    c, _ = cal
    rows, _ = _rows()
    src = tmp_path / "log.csv"
    _write_csv(src, rows)
    out = tmp_path / "out.csv"
    out.write_text("previous result\n", encoding="utf-8")
    calls = []

    def failing(xyz: np.ndarray) -> np.ndarray:
        calls.append(len(xyz))
        if len(calls) == 3:  # fail in the middle of the file
            raise _Boom("disk full")
        return c.apply(xyz)

    with pytest.raises(_Boom):
        apply_file(failing, src, out, chunk_rows=20)
    assert out.read_text(encoding="utf-8") == "previous result\n"  # untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cal.json", "log.csv", "out.csv"]  # no temp left
    with pytest.raises(TrimagInputError, match="cannot write"):
        apply_file(c.apply, src, tmp_path / "out.mat", chunk_rows=20)
    assert not (tmp_path / "out.mat").exists() and not list(tmp_path.glob(".*.tmp"))


def test_chunks_cover_the_file_in_order(tmp_path: Path) -> None:
    rows, _ = _rows()
    src = tmp_path / "log.csv"
    _write_csv(src, rows)
    source, chunks = open_chunks(src, chunk_rows=25)
    assert source.columns == ("bx", "by", "bz") and source.has_header
    parts = list(chunks)
    assert [p.start for p in parts] == [0, 25, 50, 75, 100]
    assert [len(p.xyz) for p in parts] == [25, 25, 25, 25, 3]
    table = pd.concat([p.table for p in parts], ignore_index=True)
    assert table.values.tolist() == rows  # text cells, unchanged
    xyz = np.vstack([p.xyz for p in parts])
    assert (~np.isfinite(xyz).all(axis=1)).sum() == len(BAD)
    assert sum(len(p.xyz) for p in iter_chunks(src, chunk_rows=7)) == N


def test_evaluate_streamed_equals_whole(tmp_path: Path, cal: tuple[Calibration, Path]) -> None:
    c, cal_path = cal
    rows, _ = _rows()
    src = tmp_path / "log.csv"
    _write_csv(src, rows)
    xyz = np.array([[float(v) if v not in ("", "abc") else np.nan for v in r[2:]] for r in rows])
    ok = np.isfinite(xyz).all(axis=1)
    after = np.linalg.norm(c.apply(xyz[ok]), axis=1)
    before = np.linalg.norm(xyz[ok], axis=1)
    results = [evaluate_file(cal_path, src, chunk_rows=k, reference=48000.0) for k in (1, 9, 1000)]
    for r in results:
        assert r["n_samples"] == N and r["n_dropped"] == len(BAD) and r["n_used"] == N - len(BAD)
        assert r["rms_after"] == pytest.approx(np.sqrt(np.mean((after - 48000.0) ** 2)), rel=1e-12)
        assert r["rms_before"] == pytest.approx(np.sqrt(np.mean((before - 48000.0) ** 2)), rel=1e-12)
        assert r["max_abs_after"] == pytest.approx(np.max(np.abs(after - 48000.0)), rel=1e-12)
    # unknown reference: errors against the mean corrected magnitude, from running sums
    r = evaluate_file(cal_path, src, chunk_rows=10)
    assert r["rms_after"] == pytest.approx(np.std(after), rel=1e-9)
    assert r["reference"]["value"] == pytest.approx(after.mean(), rel=1e-12)
    # selection across chunk borders
    r = evaluate_file(cal_path, src, chunk_rows=10, rows="15:95", where="label!=p33")
    assert r["n_samples"] == 79 and r["n_dropped"] == 3  # rows 20, 41, 66 are in range; 7 is not


def test_apply_to_file_wrapper(tmp_path: Path, cal: tuple[Calibration, Path]) -> None:
    _, cal_path = cal
    rows, _ = _rows()
    src = tmp_path / "log.csv"
    _write_csv(src, rows)
    res = apply_to_file(cal_path, src, tmp_path / "o.csv", chunk_rows=11)
    assert res["units"] == "nT" and res["n_rows"] == N and res["n_uncorrected"] == len(BAD)


def test_accumulator_matches_numpy() -> None:
    rng = np.random.default_rng(0)
    norms = rng.normal(100.0, 3.0, size=1000)
    ref = rng.normal(100.0, 0.1, size=1000)
    acc, acc_ref = MagnitudeAccumulator(), MagnitudeAccumulator()
    for part, rpart in zip(np.array_split(norms, 7), np.array_split(ref, 7), strict=True):
        acc.add(part, None)
        acc_ref.add(part, rpart)
    acc.add(np.empty(0), None)
    r = acc.result()
    assert r["mean_norm"] == pytest.approx(norms.mean(), rel=1e-12)
    assert r["std_norm"] == pytest.approx(norms.std(), rel=1e-9)
    assert r["rms"] == pytest.approx(norms.std(), rel=1e-9)
    assert r["peak_to_peak"] == pytest.approx(np.ptp(norms), rel=1e-12)
    r = acc_ref.result()
    assert r["rms"] == pytest.approx(np.sqrt(np.mean((norms - ref) ** 2)), rel=1e-12)
    assert r["max_abs"] == pytest.approx(np.max(np.abs(norms - ref)), rel=1e-12)


def test_short_row_mid_file_falls_back_without_losing_rows(tmp_path: Path, cal: tuple[Calibration, Path]) -> None:
    """A row with a missing field after the first read block: pyarrow refuses it, pandas continues from the
    first row not yet delivered; every row is kept once, in order, the short one counted as uncorrected."""
    c, _ = cal
    n, short = 4000, 3500  # ~150 kB: the short row lies beyond the first 64 kB read block
    raw = simulate_ellipsoid(n, seed=6)
    lines = ["t,bx,by,bz"] + [f"{i},{x:.2f},{y:.2f},{z:.2f}" for i, (x, y, z) in enumerate(raw)]
    lines[short + 1] = ",".join(lines[short + 1].split(",")[:3])
    src = tmp_path / "ragged.csv"
    src.write_text("\n".join(lines) + "\n", encoding="utf-8")
    parts = list(iter_chunks(src, chunk_rows=500))
    assert parts[0].has_arrow and not parts[-1].has_arrow  # fast path first, then the fallback
    assert [p.start for p in parts] == list(range(0, n, 500)) and sum(len(p) for p in parts) == n
    out = tmp_path / "ragged_out.csv"
    res = apply_file(c.apply, src, out, chunk_rows=500)
    assert res["n_rows"] == n and res["n_uncorrected"] == 1
    got = out.read_text(encoding="utf-8").splitlines()
    assert len(got) == n + 1 and [g.split(",")[0] for g in got[1:]] == [str(i) for i in range(n)]
    assert got[short + 1].endswith(",,,,")  # missing z kept empty, no corrected values
    cor = np.array([g.split(",")[4:] for i, g in enumerate(got[1:]) if i != short], dtype=float)
    np.testing.assert_allclose(cor, c.apply(np.delete(raw.round(2), short, axis=0)), rtol=1e-12)


def test_apply_copies_header_comments_and_untouched_cells_byte_for_byte(
    tmp_path: Path, cal: tuple[Calibration, Path]
) -> None:
    """Findings (issue 22): `apply` stripped header names (`' mag_Y'`), padded comment lines with commas and
    rewrote other cells. Comma CSV in, CSV out: every input line is copied as it is, the corrected cells appended
    (CRLF line endings, quoted cells, oddly written numbers and a short row included)."""
    c, _ = cal
    raw = simulate_ellipsoid(60, noise=5.0, seed=9)
    lines = ["# sensor: X", "# site: field 2, north pad", "t, mag_X, mag_Y ,mag_Z,note"]
    for i, (x, y, z) in enumerate(raw):
        note = '"a,b"' if i % 7 == 0 else ("" if i % 5 == 0 else f" p{i} ")
        lines.append(f"{i:.1f},{x:.3f}, {y:.10g},{float(z)!r},{note}")
    lines[30] = lines[30].rsplit(",", 1)[0]  # a short row: no note cell
    src = tmp_path / "log.csv"
    src.write_bytes(("\r\n".join(lines) + "\r\n").encode())
    out = tmp_path / "log_cal.csv"
    res = apply_file(c.apply, src, out, columns="1,2,3", chunk_rows=16)
    assert res["n_rows"] == 60 and res["n_uncorrected"] == 0
    got = out.read_bytes().decode().split("\r\n")
    assert got[-1] == "" and len(got) == len(lines) + 1
    assert got[:2] == lines[:2]  # comment lines unchanged, not padded
    assert got[2] == lines[2] + ",mag_X_cal,mag_Y_cal,mag_Z_cal"  # header names byte for byte
    for k in range(3, len(lines)):
        assert got[k].startswith(lines[k] + ("," if k != 30 else ",,"))  # every input cell byte-identical
    cor = np.array([g.rsplit(",", 3)[1:] for g in got[3:-1]], dtype=float)
    np.testing.assert_allclose(cor, c.apply(np.array([[float(v) for v in ln.split(",")[1:4]] for ln in lines[3:]])),
                               rtol=1e-15)


@pytest.mark.parametrize("compressed", [False, True])
def test_sigint_during_apply_leaves_no_temporary_or_partial_file(
    tmp_path: Path, cal: tuple[Calibration, Path], compressed: bool
) -> None:
    """Ctrl-C during `apply` of a large file: exit 130, one line on stderr, no output and no temporary file (nor the
    decompressed copy of a gzip'ed input)."""
    import gzip
    import os
    import signal
    import subprocess
    import sys
    import time

    _, cal_path = cal
    raw = simulate_ellipsoid(20_000, seed=4)
    block = "".join(f"{i},{x:.3f},{y:.3f},{z:.3f}\n" for i, (x, y, z) in enumerate(raw))
    src = tmp_path / "big.csv"
    with src.open("w", encoding="utf-8") as fh:
        fh.write("t,bx,by,bz\n")
        for _ in range(100):  # 2e6 rows, ~70 MB: seconds to apply at chunk_rows 1000
            fh.write(block)
    if compressed:
        with src.open("rb") as fin, gzip.open(tmp_path / "big.csv.gz", "wb", compresslevel=1) as fz:
            fz.write(fin.read())
        src.unlink()
        src = tmp_path / "big.csv.gz"
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    scratch = tmp_path / "scratch"  # TMPDIR: where a decompressed copy goes
    scratch.mkdir()
    out = out_dir / "big_cal.csv"
    proc = subprocess.Popen(
        [sys.executable, "-m", "trimag", "apply", str(cal_path), str(src), "-o", str(out), "--chunk-rows", "1000"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        env={**os.environ, "PYTHONUNBUFFERED": "1", "TMPDIR": str(scratch)}, preexec_fn=restore_sigint,
    )
    deadline = time.monotonic() + 60
    while not list(out_dir.glob(".*.tmp")) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert proc.poll() is None, "apply finished before it could be interrupted"
    assert bool(list(scratch.iterdir())) == compressed  # the decompressed copy exists while apply runs
    time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130
    assert "Traceback" not in err.decode() and len(err.decode().strip().splitlines()) == 1
    assert not out.exists() and not list(out_dir.iterdir()) and not list(scratch.iterdir())
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([src.name, "cal.json", "out", "scratch"])


@pytest.mark.parametrize("text", [
    "x,y,z,n\n1,2,3,a\n\n   \n \t \n4,5,6,b\n",  # blank and whitespace-only lines: skipped by the readers
    "x,y,z,n\r\n1,2,3,a\r\n4,5,6,b",  # no line break after the last row
    "\ufeffx,y,z,n\n1,2,3,a\n4,5,6,b\n",  # a byte-order mark
])
@pytest.mark.parametrize("chunk_rows", [1, 10])
def test_apply_byte_copy_keeps_rows_aligned(tmp_path: Path, text: str, chunk_rows: int) -> None:
    c = Calibration.from_matrix_offset(np.eye(3) * 1.01, [1.0, 2.0, 3.0], model="ellipsoid", units="nT")
    src = tmp_path / "in.csv"
    src.write_bytes(text.encode())
    out = tmp_path / "out.csv"
    res = apply_file(c.apply, src, out, chunk_rows=chunk_rows)
    rows = out.read_bytes().decode().splitlines()
    assert res["n_rows"] == 2 and len(rows) == 3
    assert rows[0].endswith("x,y,z,n,x_cal,y_cal,z_cal") and rows[0].startswith(text[:1])
    assert rows[1].startswith("1,2,3,a,") and rows[2].startswith("4,5,6,b,")
    np.testing.assert_allclose(np.array([r.split(",")[4:] for r in rows[1:]], dtype=float),
                               c.apply(np.array([[1.0, 2, 3], [4, 5, 6]])), rtol=1e-15)


def test_apply_on_text_the_reader_cannot_parse_exits_2(tmp_path: Path, cal: tuple[Calibration, Path]) -> None:
    """A quoted cell with a line break before the data made `apply` exit 1 (pandas' EmptyDataError)."""
    from _helpers import run_trimag

    src = tmp_path / "q.csv"
    src.write_text('x,y,z,n\n1,2,3,"a\nb"\n4,5,6,b\n', encoding="utf-8")
    r = run_trimag("apply", cal[1], src, "-o", tmp_path / "out.csv")
    assert r.returncode == 2 and "cannot parse as delimited text" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "out.csv").exists()


def test_evaluate_and_apply_take_one_request(tmp_path: Path, cal: tuple[Calibration, Path]) -> None:
    """The app layer's entry points take one typed request; the flat arguments build the same request, and a
    request given with arguments, or an argument no request has, is refused naming the known ones."""
    from trimag.app.requests import ApplyRequest, EvaluateRequest, InputSpec, ReferenceSpec
    from trimag.errors import TrimagInputError

    _, cal_path = cal
    rows, _ = _rows()
    src = tmp_path / "log.csv"
    _write_csv(src, rows)
    req = EvaluateRequest(cal_path, InputSpec(src, rows="15:95", where="label!=p33"),
                          reference=ReferenceSpec(reference=48000.0), chunk_rows=10)
    assert EvaluateRequest.of(cal_path, src, rows="15:95", where="label!=p33", reference=48000.0,
                              chunk_rows=10) == req
    r = evaluate_file(req)
    assert r == evaluate_file(cal_path, src, rows="15:95", where="label!=p33", reference=48000.0, chunk_rows=10)
    assert r["n_samples"] == 79 and r["reference"]["source"] == "given"
    with pytest.raises(TrimagInputError, match="not both"):
        evaluate_file(req, chunk_rows=5)
    with pytest.raises(TrimagInputError, match=r"unknown evaluate argument 'chunk'; known: .*chunk_rows"):
        evaluate_file(cal_path, src, chunk=5)
    res = apply_to_file(ApplyRequest(cal_path, InputSpec(src), tmp_path / "o.csv", chunk_rows=11))
    assert res["n_rows"] == N and res["n_uncorrected"] == len(BAD)
    with pytest.raises(TrimagInputError, match="unknown apply argument 'bogus'; known: chunk_rows, columns"):
        apply_to_file(cal_path, src, tmp_path / "o2.csv", chunk_rows=11, bogus=1)
    assert not (tmp_path / "o2.csv").exists()
