"""Findings of issue 22 ("Trust at the data boundary"), each reproduced before its fix."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import trimag

from _helpers import ellipsoid_truth, simulate_ellipsoid


def _cone(n: int, half_deg: float, seed: int = 0, F: float = 50_000.0, noise: float = 5.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    z = rng.uniform(np.cos(np.radians(half_deg)), 1, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    s = np.sqrt(1 - z**2)
    u = np.column_stack([s * np.cos(phi), s * np.sin(phi), z])
    W, b = ellipsoid_truth()
    return np.linalg.solve(W, (F * u).T).T + b + rng.normal(scale=noise, size=u.shape)


def test_uncertainty_is_the_same_relative_size_in_nT_and_uT():
    """Finding: every parameter was +-inf in nT, finite for the same data in uT (an unscaled eigenvalue threshold)."""
    raw = _cone(3000, 40.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal_nT = trimag.fit(raw, model="ellipsoid", reference=50_000.0, units="nT")
        cal_uT = trimag.fit(raw / 1000.0, model="ellipsoid", reference=50.0, units="uT")
    s_nT, s_uT = cal_nT.uncertainty["param_std"], cal_uT.uncertainty["param_std"]
    assert s_nT["w11"] is not None and np.isfinite(s_nT["w11"])
    assert s_nT["w11"] == pytest.approx(s_uT["w11"], rel=1e-6)
    assert s_nT["hard_iron_x"] == pytest.approx(1000.0 * s_uT["hard_iron_x"], rel=1e-6)


def test_duplicating_every_row_does_not_shrink_the_sigmas():
    """Finding: duplicating every row shrank every sigma by sqrt(2)."""
    B = simulate_ellipsoid(3000, noise=20.0, seed=1)
    base = trimag.fit(B, model="ellipsoid", units="nT").uncertainty["param_std"]
    for doubled in (np.repeat(B, 2, axis=0), np.vstack([B, B])):
        std = trimag.fit(doubled, model="ellipsoid", units="nT").uncertainty["param_std"]
        assert std["w11"] == pytest.approx(base["w11"], rel=0.05)
        assert std["hard_iron_x"] == pytest.approx(base["hard_iron_x"], rel=0.05)


def test_as_many_samples_as_parameters_reports_unknown_uncertainty():
    """Finding: 9 samples reported c3 = -40719.9 +- 2.89e-09 nT (no degree of freedom left for the noise)."""
    from trimag.calibration import Calibration
    from trimag.honesty import honest_uncertainty

    X = simulate_ellipsoid(9, noise=0.0, seed=2)
    cal = Calibration.from_matrix_offset(np.eye(3), [0, 0, 0], units="nT", model="scalar9",
                                         uncertainty={"param_std": {f"p{k}": 1e-9 for k in range(9)}})
    out = honest_uncertainty(cal, X)
    assert all(v is None for v in out.uncertainty["param_std"].values())
    assert any("no degree of freedom" in w for w in out.diagnostics["warnings"])


def test_correlated_residuals_inflate_and_white_noise_does_not():
    from trimag.honesty import correlation_time

    rng = np.random.default_rng(0)
    white = rng.normal(size=5000)
    assert correlation_time(white) < 1.1
    ar = np.zeros(5000)
    for k in range(1, 5000):  # AR(1), rho = 0.9: tau = (1 + rho) / (1 - rho) = 19
        ar[k] = 0.9 * ar[k - 1] + white[k]
    assert 12 < correlation_time(ar) < 26


def test_a_log_whose_offset_changes_halfway_is_flagged_with_the_size_of_the_change():
    """Finding: the first and second halves of some logs disagree (RMS z up to 31) and nothing says so."""
    B = simulate_ellipsoid(4000, noise=20.0, seed=1)
    stable = trimag.fit(B, model="ellipsoid", units="nT")
    assert stable.diagnostics["drift"]["drift"] is False
    B[2000:] += np.array([150.0, 0.0, 0.0])
    moved = trimag.fit(B, model="ellipsoid", units="nT")
    assert moved.diagnostics["drift"]["drift"] is True
    assert moved.diagnostics["drift"]["offset_change"][0] == pytest.approx(150.0, rel=0.1)
    assert any("changed during the log" in w for w in moved.diagnostics["warnings"])
