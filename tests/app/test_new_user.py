"""What a new user hits first (issue 32, item 8): a calibration file given as the log, `simulate` with only the
parameters that differ from the identity, `apply` / `export` to standard output."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from _helpers import run_trimag


def _sphere_log(path: Path, n: int = 500, seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    B = 50.0 * u + [5.0, -3.0, 2.0] + rng.normal(scale=0.1, size=(n, 3))
    np.savetxt(path, B, delimiter=",", header="x,y,z", comments="", fmt="%.6f")
    return path


@pytest.fixture
def cal_and_log(tmp_path: Path) -> tuple[Path, Path]:
    log = _sphere_log(tmp_path / "log.csv")
    cal = tmp_path / "cal.json"
    r = run_trimag("fit", log, "--units", "uT", "-o", cal, "-q")
    assert r.returncode == 0, r.stderr
    return cal, log


@pytest.mark.parametrize("command", ["fit", "evaluate", "apply"])
def test_a_calibration_file_given_as_the_log_is_named_as_such(cal_and_log: tuple[Path, Path], command: str,
                                                               tmp_path: Path):
    """Finding: `trimag fit cal.json` said "rows have only 1 numeric column(s)"."""
    cal, _ = cal_and_log
    args = {"fit": ("fit", cal), "evaluate": ("evaluate", cal, cal),
            "apply": ("apply", cal, cal, "-o", tmp_path / "o.csv")}[command]
    r = run_trimag(*args)
    assert r.returncode == 2
    line = r.stderr.strip()
    assert len(line.splitlines()) == 1 and "is a calibration file" in line, line
    assert "apply" in line and "evaluate" in line and "export" in line


def test_simulate_defaults_the_parameters_not_given_to_the_identity(tmp_path: Path):
    """Finding: `trimag simulate` needed all 12 matrix and offset entries of the ellipsoid model."""
    params = tmp_path / "p.json"
    params.write_text(json.dumps({"hard_iron_x": 5.0, "w11": 1.1}))
    out, truth = tmp_path / "sim.csv", tmp_path / "truth.json"
    r = run_trimag("simulate", "--model", "ellipsoid", "--params", params, "--n", "200", "--field", "50", "-o", out,
                   "--truth", truth)
    assert r.returncode == 0, r.stderr
    t = json.loads(truth.read_text())["params"]
    assert t["hard_iron_x"] == 5.0 and t["w11"] == 1.1 and t["hard_iron_y"] == 0.0 and t["w22"] == 1.0
    assert t["w12"] == 0.0
    assert "hard_iron_y" in r.stdout and "defaults" in r.stdout  # says which ones it defaulted
    params.write_text(json.dumps({"hard_iron_q": 5.0}))
    r = run_trimag("simulate", "--model", "ellipsoid", "--params", params, "--n", "20", "-o", out)
    assert r.returncode == 2 and "hard_iron_q" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_apply_and_export_write_to_standard_output(cal_and_log: tuple[Path, Path], tmp_path: Path):
    """Finding: `apply` and `export` could not write to standard output (`-o -`)."""
    cal, log = cal_and_log
    r = run_trimag("apply", cal, log, "-o", "-")
    assert r.returncode == 0, r.stderr
    lines = r.stdout.strip().splitlines()
    assert lines[0].split(",")[:3] == ["x", "y", "z"] and "x_cal" in lines[0] and len(lines) == 501
    corrected = np.loadtxt(lines[1:], delimiter=",")[:, 3:6]
    assert abs(np.linalg.norm(corrected, axis=1).mean() - 50.0) < 0.5
    assert not list(Path(".").glob("-*"))
    r = run_trimag("export", cal, "--to", "ardupilot", "-o", "-")
    assert r.returncode == 0, r.stderr
    assert "COMPASS_OFS_X" in r.stdout and "wrote" not in r.stdout
