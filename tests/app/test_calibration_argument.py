"""The calibration argument of ``apply``, ``evaluate`` and ``fit --prior`` given a data file (issue 41, item 17):
the message names the file, says it is not a calibration and what is, and a log and a calibration given in the
wrong order are said to be swapped (before: "calibration file is not valid JSON: Expecting value: line 1 column 1
(char 0)", no file named)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from _helpers import run_trimag


@pytest.fixture()
def files(tmp_path: Path) -> tuple[Path, Path]:
    rng = np.random.default_rng(3)
    u = rng.normal(size=(300, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    log = tmp_path / "log.csv"
    np.savetxt(log, u * 500 + [30, -20, 10] + rng.normal(0, 2, (300, 3)), delimiter=",", header="x,y,z",
               comments="")
    cal = tmp_path / "cal.json"
    assert run_trimag("fit", log, "-o", cal, "-q").returncode == 0
    return log, cal


@pytest.mark.parametrize("command", ["apply", "evaluate"])
def test_a_log_and_a_calibration_in_the_wrong_order_are_said_to_be_swapped(files: tuple[Path, Path], command: str,
                                                                           tmp_path: Path) -> None:
    log, cal = files
    out = ["-o", str(tmp_path / "out.csv")] if command == "apply" else []
    r = run_trimag(command, log, cal, *out)
    assert r.returncode == 2
    assert f"{log} is a log and {cal} a calibration: the calibration comes first: `trimag {command} {cal} {log}`" \
        in r.stderr, r.stderr
    assert not (tmp_path / "out.csv").exists()


@pytest.mark.parametrize("command", ["apply", "evaluate", "prior"])
def test_a_data_file_as_the_calibration_is_named_and_the_calibration_explained(files: tuple[Path, Path],
                                                                              command: str, tmp_path: Path) -> None:
    log, _ = files
    other = tmp_path / "other.csv"
    other.write_text(log.read_text())
    if command == "prior":
        r = run_trimag("fit", log, "--prior", other, "-q")
    else:
        r = run_trimag(command, other, log, *(["-o", str(tmp_path / "out.csv")] if command == "apply" else []))
    assert r.returncode == 2
    assert f"{other} is not a calibration file (it is not JSON text)" in r.stderr, r.stderr
    assert "trimag fit LOG -o cal.json" in r.stderr and "char 0" not in r.stderr
