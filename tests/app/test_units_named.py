"""The unit refusals name the command line's flag (`--units uT`), never the Python argument (`units=`) (issue 39,
item 8)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from trimag.cli import main

from _helpers import simulate_ellipsoid


def _one_line(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def _write(path: Path, header: str, scale: float = 1.0) -> Path:
    np.savetxt(path, simulate_ellipsoid(600, noise=20.0, seed=2) * scale, delimiter=",", header=header, comments="",
               fmt="%.3f")
    return path


def test_a_target_fit_without_a_unit_names_the_units_flag(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = _write(tmp_path / "log.csv", "x,y,z", scale=0.01)
    assert main(["fit", str(path), "--target", "ardupilot", "-q"]) == 2
    line = _one_line(capsys)
    assert "--units mG" in line and "units=" not in line and "--target ardupilot" in line


def test_a_unit_against_the_headers_names_the_units_flag(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = _write(tmp_path / "log.csv", "x_nT,y_nT,z_nT")
    assert main(["fit", str(path), "--units", "uT", "-q"]) == 2
    line = _one_line(capsys)
    assert "--units uT" in line and "units=" not in line


def test_exporting_a_unitless_calibration_names_the_units_flag(tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    path = _write(tmp_path / "log.csv", "x,y,z")
    assert main(["fit", str(path), "-o", str(tmp_path / "cal.json"), "-q"]) == 0
    assert main(["export", str(tmp_path / "cal.json"), "--to", "ardupilot", "-o", str(tmp_path / "c.param")]) == 2
    line = _one_line(capsys)
    assert "--units" in line and "units=" not in line
    assert not (tmp_path / "c.param").exists()
