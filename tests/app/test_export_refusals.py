"""Export refuses the parameters of a fit trimag itself rejected (issue 41, item 9): a calibration the acceptance
policy rejected (exit 4), or one whose fit said its numbers look like another unit (exit 2), is not written as
firmware parameters unless ``--force`` (named in the refusal) says so."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from _helpers import run_trimag, simulate_ellipsoid


def _csv(path: Path, raw: np.ndarray) -> Path:
    np.savetxt(path, raw, delimiter=",", header="mx,my,mz", comments="", fmt="%.6f")
    return path


def test_export_refuses_a_calibration_the_policy_rejected(tmp_path: Path) -> None:
    data = _csv(tmp_path / "lab.csv", simulate_ellipsoid(n=600, noise=20.0, seed=4))  # nT, offsets ~1200 nT
    policy = tmp_path / "strict.toml"
    policy.write_text("[limits]\nmax_offset = 100\n")
    cal = tmp_path / "cal.json"
    r = run_trimag("fit", data, "--units", "nT", "--policy", policy, "-o", cal, "-q")
    assert r.returncode == 4 and cal.exists(), r.stderr  # written, marked rejected
    out = tmp_path / "compass.param"
    r = run_trimag("export", cal, "--to", "ardupilot", "-o", out)
    assert r.returncode == 4, r.stderr
    assert not out.exists()
    line = r.stderr.strip()
    assert len(line.splitlines()) == 1 and "rejected" in line and "max_offset" in line and "--force" in line
    r = run_trimag("export", cal, "--to", "ardupilot", "-o", out, "--force")
    assert r.returncode == 0 and out.exists(), r.stderr
    assert "rejected" in r.stderr  # still said


def test_export_refuses_a_calibration_whose_unit_the_fit_doubted(tmp_path: Path) -> None:
    """µT numbers declared nT: the fit warns "the numbers look like uT"; the offsets exported would be 1000x too
    small."""
    data = _csv(tmp_path / "lab.csv", simulate_ellipsoid(n=600, noise=0.02, seed=5, F=48.0) / 1.0)
    cal = tmp_path / "cal.json"
    r = run_trimag("fit", data, "--units", "nT", "-o", cal, "-q")
    assert r.returncode == 0 and "look like" in r.stderr, r.stderr
    out = tmp_path / "compass.param"
    r = run_trimag("export", cal, "--to", "ardupilot", "-o", out)
    assert r.returncode == 2, r.stderr
    assert not out.exists()
    line = r.stderr.strip()
    assert len(line.splitlines()) == 1 and "uT" in line and "--force" in line, line
    r = run_trimag("export", cal, "--to", "ardupilot", "-o", out, "--force")
    assert r.returncode == 0 and out.exists(), r.stderr
