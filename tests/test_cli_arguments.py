"""Loose argument checks (issue 41, item 14): each value that cannot be meant is refused before any work, with one
line (exit 2), and a message listing what the input holds stays a readable line."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from trimag.cli import main

from _helpers import TESTS_DIR, simulate_ellipsoid


@pytest.fixture
def lab(tmp_path: Path) -> Path:
    path = tmp_path / "lab.csv"
    np.savetxt(path, simulate_ellipsoid(300, noise=20.0, seed=7) / 100, delimiter=",", header="x,y,z", comments="",
               fmt="%.3f")
    return path


def _one_line(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err and "Warning" not in err, err
    return lines[0]


@pytest.mark.parametrize(("flags", "words"), [
    (["--heading", "1e308", "--igrf", "40,10,0,2024-01-01"], "heading"),
    (["--heading", "nan", "--igrf", "40,10,0,2024-01-01"], "heading"),
    (["--igrf", "40,1e308,0,2024-01-01"], "longitude"),
    (["--igrf", "40,10,1e12,2024-01-01"], "altitude"),
    (["--target", "ardupilot", "--reference", "-5"], "reference"),
    (["--target", "ardupilot", "--reference", "inf"], "reference"),
])
def test_a_value_that_cannot_be_meant_is_refused(tmp_path: Path, lab: Path, capsys: pytest.CaptureFixture[str],
                                                 flags: list[str], words: str) -> None:
    out = tmp_path / "cal.json"
    assert main(["fit", str(lab), "--units", "mG", "-o", str(out), *flags]) == 2
    assert words in _one_line(capsys)
    assert not out.exists()


def test_export_out_dash_is_refused_not_written_as_a_file_named_dash(tmp_path: Path, monkeypatch,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.chdir(tmp_path)
    log = TESTS_DIR / "data" / "logs" / "ardusub_small.BIN"
    code = main(["fit", str(log), "--sensor", "all", "--heading", "0", "--igrf", "40,-120,0,2023-01-01",
                 "--export-to", "px4", "--export-out", "-"])
    assert code == 2
    assert "--export-out" in _one_line(capsys)
    assert os.listdir(tmp_path) == []


def test_a_message_listing_100000_names_stays_a_short_line(lab: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """100 000 regressors named made a 1.6 MB error line."""
    names = ",".join(f"current{i % 50_000}" for i in range(100_000))  # each named twice
    assert main(["fit", str(lab), "--units", "mG", "--regressors", names]) == 2
    line = _one_line(capsys)
    assert len(line) < 2000 and "more" in line and "current0" in line, len(line)


def test_any_error_line_is_cut_to_a_readable_length(capsys: pytest.CaptureFixture[str]) -> None:
    """Whatever message a library error carries, the line printed keeps its start and its end, cut in the middle."""
    from trimag.cli import _err

    _err("error: the columns are " + ", ".join(f"c{i}" for i in range(100_000)) + "; give --columns")
    line = _one_line(capsys)
    assert len(line) < 4200 and line.endswith("; give --columns") and "more characters" in line
