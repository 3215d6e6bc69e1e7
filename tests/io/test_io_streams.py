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
