"""Tests of ``trimag reproduce zhang2009`` (paper D)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from trimag.experiments import get_experiment
from trimag.experiments import zhang2009 as z

from _helpers import run_trimag


def test_registered() -> None:
    assert get_experiment("zhang2009") is z


def test_attitude_path_matches_the_paper() -> None:
    """40 samples; 5 deg heading steps from 0 (195 deg in all) and 3 deg about the sensor's Z (117 deg)."""
    from scipy.spatial.transform import Rotation

    att = z.paper_attitudes(40)
    k = np.arange(40)
    heading = Rotation.from_rotvec(np.radians(5.0 * k)[:, None] * [0, 0, 1])
    spin = Rotation.from_rotvec(np.radians(3.0 * k)[:, None] * [0, 0, 1])
    expected = heading * Rotation.from_rotvec([0, np.pi / 2, 0]) * spin
    assert np.all((att.inv() * expected).magnitude() < 1e-12)
    assert 5.0 * k[-1] == 195.0 and 3.0 * k[-1] == 117.0
    assert np.linalg.norm(z.FIELD_NAV) == pytest.approx(1.0)


def test_paper_case_numbers() -> None:
    case = z.paper_case()
    fits = case["fits"]
    assert fits["quadric"]["W_error"] < 1e-6
    assert fits["quadric"]["max_param_error"] < 1e-6  # angles in degrees here, stricter than radians
    assert fits["lms"]["W_error"] > 1e3 * fits["quadric"]["W_error"]
    assert fits["bfgs"]["W_error"] > 1e3 * fits["quadric"]["W_error"]
    assert case["identifiability"]["rank"] == 9 and case["identifiability"]["undetermined"] == []
    single = case["single_axis"]
    assert single["rank"] < 9 and "bz" in single["undetermined"]
    assert "cannot identify" in single["quadric_message"]


def test_run_quick_writes_outputs(tmp_path: Path) -> None:
    s = z.run(tmp_path, quick=True, trials=1, seed=3, sigmas=(0.0, 1e-4))
    json.dumps(s, allow_nan=False)
    for key in ("W_true", "W_quadric", "W_lms", "W_bfgs", "param_errors"):
        assert key in s
    np.testing.assert_allclose(s["W_quadric"], s["W_true"], atol=1e-6)
    np.testing.assert_allclose(s["W_true"][:3], s["W_paper_first3"], atol=2e-4)
    assert s["full_sphere"]["max_W_spread"] < 1e-6
    for name in s["outputs"]:
        assert (tmp_path / name).stat().st_size > 0
    rows = [r for r in s["noise_sweep"] if r["sigma"] == 0.0 and r["path"] == "sphere"]
    assert rows[0]["quadric_W_error_median"] < 1e-9
    assert "W on the paper's 40 noise-free samples" in s["text"]


@pytest.mark.slow
def test_cli_json(tmp_path: Path) -> None:
    proc = run_trimag("reproduce", "zhang2009", "--out", tmp_path, "--quick", "--trials", "1", "--json")
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert set(out) >= {"W_true", "W_quadric", "W_lms", "W_bfgs", "param_errors"}
    assert max(out["param_errors"]["quadric"].values()) < 1e-6
