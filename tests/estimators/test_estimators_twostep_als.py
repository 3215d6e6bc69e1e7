"""``twostep`` (Alonso & Shuster 2002) and ``als`` (adjusted least squares, Markovsky et al. 2004)."""

from __future__ import annotations

import numpy as np
import pytest

import trimag
from trimag.errors import TrimagInputError
from trimag.estimators.als import AdjustedLeastSquares, als_scatter, als_solve
from trimag.estimators.ellipsoid_fit import EllipsoidFit
from trimag.estimators.twostep import TwoStep
from trimag.models.ellipsoid import Ellipsoid, to_upper
from trimag.quality.crlb import UPPER, crlb
from trimag.simulate import hemisphere_directions, uniform_directions

D = np.array([[1.08, 0.03, -0.02], [0.0, 0.93, 0.04], [0.0, 0.0, 1.0]])
B0 = np.array([0.2, -0.1, 0.15])
THETA = np.concatenate([to_upper(np.linalg.inv(D))[UPPER], B0])


def _params(cal):
    return np.concatenate([to_upper(cal.matrix)[UPPER], cal.offset])


def test_als_scatter_is_unbiased():
    """E[Psi_als(sigma^2)] over the noise equals the noise-free scatter (Hermite corrections), to Monte Carlo
    accuracy: 40 points x 5000 noise draws."""
    rng = np.random.default_rng(0)
    x = rng.normal(size=(40, 3))
    sigma = 0.3
    clean = als_scatter(x)[0]
    noisy = np.repeat(x, 5000, axis=0) + rng.normal(scale=sigma, size=(200000, 3))
    P0, P1, P2 = als_scatter(noisy)
    corrected = (P0 + sigma**2 * P1 + sigma**4 * P2) / 5000
    uncorrected = P0 / 5000
    scale = np.abs(clean).max()
    assert np.abs(corrected - clean).max() < 0.02 * scale
    assert np.abs(uncorrected - clean).max() > 0.1 * scale  # the correction matters at this noise


def test_als_recovers_noise_level_and_is_consistent():
    """sigma/F = 5e-2, N = 20000 (one fixed trial): ALS estimates sigma to 2 % and every parameter within 4
    CRLB standard deviations; the algebraic fit's scale is off by more than 4 (its bias)."""
    u = uniform_directions(20000, seed=11)
    raw = u @ D.T + B0 + np.random.default_rng(12).normal(scale=0.05, size=u.shape)
    bound = crlb(Ellipsoid.from_matrix_offset(np.linalg.inv(D), B0), u, 0.05)
    als = AdjustedLeastSquares().fit(raw, 1.0).calibration_
    assert als.diagnostics["als_noise_std"] == pytest.approx(0.05, rel=0.02)
    assert np.all(np.abs(_params(als) - THETA) < 4 * bound.std)
    alg = EllipsoidFit().fit(raw, 1.0).calibration_
    assert np.max(np.abs(_params(alg) - THETA)[[0, 3, 5]] / bound.std[[0, 3, 5]]) > 4


def test_als_solve_noise_free_gives_zero_noise():
    u = uniform_directions(500, seed=1) @ D.T + B0
    v, s = als_solve(u)
    assert s < 1e-8
    x, y, z = u.T
    xi = np.column_stack([x * x, y * y, z * z, 2 * y * z, 2 * x * z, 2 * x * y, 2 * x, 2 * y, 2 * z, np.ones_like(x)])
    assert np.abs(xi @ v).max() < 1e-8


def test_twostep_varying_magnitude_uses_the_centred_linear_step():
    """Per-sample reference magnitudes (as on an orbit): the centred linear step is used, and noise-free
    data are fitted exactly."""
    rng = np.random.default_rng(4)
    u = uniform_directions(800, seed=4)
    F = 1.0 + 0.2 * rng.uniform(size=800)
    raw = (u * F[:, None]) @ D.T + B0
    cal = TwoStep().fit(raw, F).calibration_
    np.testing.assert_allclose(_params(cal), THETA, atol=1e-8)
    np.testing.assert_allclose(np.linalg.norm(cal.apply(raw), axis=1), F, rtol=1e-9)


def test_twostep_strong_noise_close_to_crlb():
    """sigma/F = 1e-2, N = 2000: within 4 CRLB standard deviations, noise estimated to 5 %."""
    u = uniform_directions(2000, seed=21)
    raw = u @ D.T + B0 + np.random.default_rng(22).normal(scale=0.01, size=u.shape)
    cal = TwoStep().fit(raw, 1.0).calibration_
    bound = crlb(Ellipsoid.from_matrix_offset(np.linalg.inv(D), B0), u, 0.01)
    assert np.all(np.abs(_params(cal) - THETA) < 4 * bound.std)
    assert cal.uncertainty["noise_std"] == pytest.approx(0.01, rel=0.05)


def test_twostep_falls_back_when_step_two_runs_away():
    """One hemisphere at sigma/F = 5e-2 and N = 400: the result stays near the truth (step 1 kept if step 2
    fits worse)."""
    u = hemisphere_directions(400, seed=1)
    raw = u @ D.T + B0 + np.random.default_rng(0).normal(scale=0.05, size=u.shape)
    cal = TwoStep().fit(raw).calibration_
    assert np.all(np.abs(cal.offset - B0) < 0.2)


@pytest.mark.parametrize("cls", [TwoStep, AdjustedLeastSquares])
def test_bad_form(cls):
    raw = uniform_directions(100, seed=0) @ D.T
    with pytest.raises(TrimagInputError, match="form"):
        cls(form="diagonal").fit(raw, 1.0)


def test_twostep_noise_option():
    raw = uniform_directions(300, seed=0) @ D.T + B0
    with pytest.raises(TrimagInputError, match="noise_std"):
        TwoStep(noise_std=float("nan")).fit(raw, 1.0)
    cal = TwoStep(noise_std=0.0).fit(raw, 1.0).calibration_
    np.testing.assert_allclose(_params(cal), THETA, atol=1e-8)


def test_twostep_step2_on_sufficient_statistics_matches_levenberg_marquardt(monkeypatch):
    """Step 2 by Gauss-Newton on 9 x 9 sufficient statistics gives the calibration MINPACK's
    Levenberg-Marquardt gives on the (N, 9) residuals (forced here by making the fast path decline)."""
    import trimag.estimators.twostep as twostep_module

    rng = np.random.default_rng(21)
    W = np.array([[1.08, 0.04, -0.02], [0.0, 0.96, 0.03], [0.0, 0.0, 1.01]])
    X = uniform_directions(3000, seed=22) @ np.linalg.inv(W).T * 5e4 + [900.0, -400.0, 250.0]
    X += 300.0 * rng.standard_normal(X.shape)
    fast = trimag.fit(X, method="twostep", units="nT")
    assert "sufficient statistics" in fast.diagnostics["optimizer"]
    monkeypatch.setattr(twostep_module, "_gauss_newton_step2", lambda *a, **k: None)
    slow = trimag.fit(X, method="twostep", units="nT")
    assert "sufficient statistics" not in slow.diagnostics["optimizer"]
    np.testing.assert_allclose(fast.matrix, slow.matrix, rtol=1e-9, atol=1e-14)
    np.testing.assert_allclose(fast.offset, slow.offset, rtol=0, atol=1e-6)


def test_twostep_blocked_statistics_do_not_depend_on_the_block_size(small_chunks):
    """Weights, step-1 residuals and step 2's sufficient statistics are accumulated in blocks of samples: many
    small blocks give the calibration that one block gives."""

    rng = np.random.default_rng(23)
    X = uniform_directions(3000, seed=24) @ D.T + B0 + 0.01 * rng.standard_normal((3000, 3))
    one = trimag.fit(X, method="twostep", reference=1.0)
    small_chunks(256)
    many = trimag.fit(X, method="twostep", reference=1.0)
    np.testing.assert_allclose(many.matrix, one.matrix, rtol=1e-11, atol=1e-14)
    np.testing.assert_allclose(many.offset, one.offset, rtol=0, atol=1e-12)
    assert many.uncertainty["noise_std"] == pytest.approx(one.uncertainty["noise_std"], rel=1e-10)


def test_twostep_block_sums_on_raw_samples_equal_those_on_the_normalised_copy() -> None:
    """With one magnitude for all samples ``twostep`` reads raw samples, normalises each block as it reads it and
    computes the weights and ``z`` per block: the same sums as on a normalised copy with per-sample arrays."""
    from trimag.estimators import twostep as ts
    from trimag.estimators._common import normalisation_stats, normalise

    rng = np.random.default_rng(9)
    u0 = uniform_directions(3000, seed=4)
    raw = (u0 @ D.T + B0 + rng.normal(scale=0.02, size=u0.shape)) * 480.0 + [300.0, -200.0, 100.0]
    u, _ = normalise(raw)
    stats = normalisation_stats(raw)
    b = np.array([0.1, -0.05, 0.02])
    M = np.array([[1.1, 0.02, 0.01], [0.02, 0.95, -0.03], [0.01, -0.03, 1.0]])
    w = ts._weights(u, b, M)
    F = 1.3
    x = np.concatenate([rng.normal(scale=0.1, size=9), [0.2]])
    on_copy = ts._step2_statistics(u, w, np.full(len(u), F))
    streamed = ts._step2_statistics(raw, (b, M), F, stats)
    for a, c in zip(on_copy, streamed, strict=True):
        np.testing.assert_allclose(c, a, rtol=1e-10, atol=1e-9 * np.max(np.abs(a)))
    assert ts._weighted_residual_sum(raw, (b, M), F, x, stats) == pytest.approx(
        ts._weighted_residual_sum(u, w, np.full(len(u), F), x), rel=1e-10
    )
    A = np.eye(3) * 1.02
    assert ts._magnitude_misfit(raw, A, b, F, stats) == pytest.approx(
        ts._magnitude_misfit(u, A, b, np.full(len(u), F)), rel=1e-10
    )
