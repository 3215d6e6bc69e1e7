"""Acceptance policy (exit 4) and the heading error a calibration predicts (issue 20, items 3-4)."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

import trimag
from trimag.vehicle.heading import predicted_heading_sigma

from _helpers import ellipsoid_truth, run_trimag, simulate_ellipsoid

IGRF = "52.5,13.4,40,2024-06-01"


def _log(tmp_path: Path, n: int = 800, noise: float = 50.0) -> Path:
    from trimag.fields.reference import igrf

    F = igrf(52.5, 13.4, 40.0, "2024-06-01").total_nT
    p = tmp_path / "log.csv"
    np.savetxt(p, simulate_ellipsoid(n, noise=noise, seed=2, F=F), delimiter=",", header="x,y,z", comments="")
    return p


def test_policy_failures_exit_4_listing_each_rule_and_still_write_the_calibration(tmp_path: Path):
    policy = tmp_path / "strict.toml"
    policy.write_text("[limits]\nmax_rms_after = 1.0\nmin_coverage = 0.1\nmax_heading_sigma_deg = 0.001\n")
    out = tmp_path / "cal.json"
    r = run_trimag("fit", _log(tmp_path), "--units", "nT", "--igrf", IGRF, "--policy", policy, "-o", out)
    assert r.returncode == 4, r.stderr
    assert "max_rms_after" in r.stderr and "max_heading_sigma_deg" in r.stderr and "min_coverage" not in r.stderr
    verdict = json.loads(out.read_text())["diagnostics"]["acceptance"]
    assert verdict["accepted"] is False and {f["rule"] for f in verdict["failed"]} == {"max_rms_after",
                                                                                   "max_heading_sigma_deg"}


def test_default_policy_accepts_a_good_calibration_and_unmeasurable_rules_are_said(tmp_path: Path):
    log = _log(tmp_path)
    r = run_trimag("fit", log, "--units", "nT", "--igrf", IGRF, "--policy", "default")
    assert r.returncode == 0, r.stderr
    r = run_trimag("fit", log, "--units", "nT", "--policy", "default", "--json")
    assert r.returncode in (0, 4)
    verdict = json.loads(r.stdout)["acceptance"]
    assert "max_heading_sigma_deg" in verdict["not_evaluated"]  # no --igrf: no inclination, no F
    assert "max_field_error_pct" in verdict["not_evaluated"]


@pytest.mark.parametrize("text", ["[limits]\nmax_speed = 3\n", "not toml ===", "[other]\nx = 1\n"])
def test_bad_policy_files_exit_2(tmp_path: Path, text: str):
    policy = tmp_path / "p.toml"
    policy.write_text(text)
    r = run_trimag("fit", _log(tmp_path), "--units", "nT", "--policy", policy)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1


def test_predicted_heading_sigma_matches_monte_carlo_spread():
    """The 1-sigma heading error predicted from the covariance against the spread of 60 refits (fixed seeds)."""
    W, b = ellipsoid_truth()
    F, inc = 48000.0, 65.0
    psi = np.radians(np.arange(0.0, 360.0, 30.0))
    n = F * np.column_stack([np.cos(np.radians(inc)) * np.cos(psi), -np.cos(np.radians(inc)) * np.sin(psi),
                             np.full(len(psi), np.sin(np.radians(inc)))])
    raw_level = np.linalg.solve(W, n.T).T + b
    errors, predicted = [], []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for seed in range(60):
            cal = trimag.fit(simulate_ellipsoid(300, noise=150.0, seed=seed, F=F), model="ellipsoid",
                             reference=F, units="nT")
            y = cal.apply(raw_level)
            errors.append(np.degrees(np.angle(np.exp(1j * (np.arctan2(-y[:, 1], y[:, 0]) - psi)))))
            predicted.append(predicted_heading_sigma(cal, inc, np.degrees(psi))["sigma_deg"])
    observed = np.sqrt(np.mean(np.square(errors), axis=0))
    ratio = observed / np.mean(predicted, axis=0)
    assert 0.7 < np.median(ratio) < 1.4
