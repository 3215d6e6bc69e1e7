"""An acceptance policy's limits are checked before the fit, and a policy nothing was checked against is not an
acceptance (issue 33, item 7)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from trimag.cli import main
from trimag.errors import TrimagInputError
from trimag.vehicle.policy import DEFAULT_LIMITS, check_policy, read_policy

from _helpers import simulate_ellipsoid


@pytest.fixture
def log(tmp_path: Path) -> Path:
    path = tmp_path / "log.csv"
    np.savetxt(path, simulate_ellipsoid(600, noise=30.0, seed=4), delimiter=",", header="x,y,z", comments="",
               fmt="%.3f")
    return path


def _policy(tmp_path: Path, body: str) -> Path:
    path = tmp_path / "policy.toml"
    path.write_text(f"[limits]\n{body}\n", encoding="utf-8")
    return path


def test_a_policy_no_rule_of_which_the_data_can_measure_is_not_an_acceptance(
    log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Only max_heading_sigma_deg (needs --igrf) and max_field_error_pct (needs a reference): nothing can be
    checked. It was reported accepted with exit 0."""
    policy = _policy(tmp_path, "max_heading_sigma_deg = 1.0\nmax_field_error_pct = 2.0")
    out = tmp_path / "cal.json"
    assert main(["fit", str(log), "--policy", str(policy), "-o", str(out), "-q"]) == 4
    err = capsys.readouterr().err
    assert "nothing was checked" in err and "max_heading_sigma_deg" in err and "Traceback" not in err
    verdict = json.loads(out.read_text())["diagnostics"]["acceptance"]
    assert verdict["accepted"] is False and not verdict["passed"] and not verdict["failed"]
    assert set(verdict["not_evaluated"]) == {"max_heading_sigma_deg", "max_field_error_pct"}


@pytest.mark.parametrize("body", [
    "max_rms_after = nan", "max_rms_after = -5.0", "max_offset = inf", "min_coverage = -inf",
    'max_rms_after = "150"', "max_offset = true", "min_coverage = 1.5", "max_rms_after = [1, 2]",
])
def test_a_limit_that_is_not_a_usable_number_is_refused_before_the_fit(
    body: str, log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "cal.json"
    assert main(["fit", str(log), "--policy", str(_policy(tmp_path, body)), "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and body.split()[0] in err[0], err
    assert not out.exists()
    with pytest.raises(TrimagInputError, match=body.split()[0]):
        read_policy(str(_policy(tmp_path, body)))


def test_integer_and_boundary_limits_are_accepted() -> None:
    from trimag import Calibration

    cal = Calibration.from_matrix_offset(np.eye(3), [1.0, 2.0, 3.0], stats={"rms_after": 0.0},
                                         diagnostics={"coverage": {"fraction": 1.0}})
    verdict = check_policy(cal, {"max_rms_after": 0, "min_coverage": 1, "max_offset": 3})
    assert verdict["accepted"] and len(verdict["passed"]) == 3
    assert read_policy("default") == DEFAULT_LIMITS
