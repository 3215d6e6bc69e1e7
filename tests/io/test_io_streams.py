"""A pipe, a FIFO or standard input given as a log is refused in the user's words (issue 41, item 17): ``fit
/dev/stdin`` said "cannot read or write: lseek failed", ``fit -`` "-: no such file", and a FIFO hung."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from trimag.cli import main

from _helpers import trimag_command


def test_a_pipe_on_standard_input_is_named_a_pipe(tmp_path: Path) -> None:
    r = subprocess.run([*trimag_command(), "fit", "/dev/stdin"], input="x,y,z\n1,2,3\n", capture_output=True,
                       text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    line = r.stderr.strip()
    assert len(line.splitlines()) == 1 and "pipe" in line and "save the data to a file" in line, line


def test_a_dash_and_a_fifo_are_refused_before_anything_is_read(tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["fit", "-"]) == 2
    assert "standard input" in capsys.readouterr().err
    fifo = tmp_path / "stream.csv"
    os.mkfifo(fifo)
    assert main(["fit", str(fifo)]) == 2  # no writer: reading it would block forever
    err = capsys.readouterr().err
    assert "pipe (FIFO)" in err and "trimag live --stdin" in err


def test_an_npy_whose_header_claims_more_than_the_file_holds_is_called_damaged(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A 3xx-byte .npy declaring 240 GB said "not enough memory for the data ... fit part of it with --rows"."""
    import numpy as np

    path = tmp_path / "small.npy"
    np.save(path, np.zeros((10, 3)))
    path.write_bytes(path.read_bytes().replace(b"(10, 3)", b"(10000000000, 3)"))
    assert main(["fit", str(path)]) == 2
    err = capsys.readouterr().err
    assert "truncated or damaged" in err and "memory" not in err, err


def test_a_rate_of_zero_is_refused_in_the_user_s_words(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--rate 0`` with a gyroscope reached a division by zero and "`B` is empty: no samples to work with"."""
    import numpy as np

    from _helpers import simulate_ellipsoid

    path = tmp_path / "lab.csv"
    raw = simulate_ellipsoid(300, noise=20.0, seed=7) / 100
    np.savetxt(path, np.column_stack([raw, raw * 0.001]), delimiter=",", header="x,y,z,gx,gy,gz", comments="",
               fmt="%.4f")
    assert main(["fit", str(path), "--units", "mG", "--columns", "x,y,z", "--gyro-columns", "gx,gy,gz",
                 "--rate", "0"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "--rate" in err and "sample rate" in err, err
