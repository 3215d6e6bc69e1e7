"""``geometric``: the blocked fit (every sum over samples in blocks, Gauss-Newton through a blocked QR)."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from trimag.estimators import geometric
from trimag.estimators.geometric import Geometric, solve_geometric
from trimag.estimators.pairwise import params_covariance
from trimag.models.ortho_gain import OrthoGain, OrthoGainBias
from trimag.quality.diagnostics import design_condition

GAIN = OrthoGain(theta=0.06, phi=0.08, psi=-0.04, kxz=0.95, kyz=1.05)
GAIN_BIAS = OrthoGainBias(**GAIN.as_dict(), bx=300.0, by=-250.0, bz=400.0)
FIELD = 50_000.0


def raw_log(n: int, noise: float, bias: bool, seed: int = 0) -> np.ndarray:
    """Raw samples of a sensor with paper A's errors (plus offsets with ``bias``) turned through uniform random
    directions in a field of magnitude :data:`FIELD`, with white noise of ``noise`` per axis."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    raw = (GAIN_BIAS if bias else GAIN).distort(FIELD * u)
    return raw + rng.normal(scale=noise, size=raw.shape) if noise else raw


def params(sol: geometric.GeometricSolution) -> np.ndarray:
    return np.concatenate([sol.q, sol.b, [sol.h]])


@pytest.mark.parametrize("bias", [False, True])
@pytest.mark.parametrize(("n", "noise"), [(200, 0.0), (1000, 20.0), (20_000, 200.0)])
def test_blocked_equals_one_block(small_chunks, bias, n, noise):
    """Blocks of 97 samples give the result of a single block, to rounding (the same Gauss-Newton steps)."""
    B = raw_log(n, noise, bias, seed=n)
    one = solve_geometric(B, bias=bias)  # n < 65 536: one chunk at the default setting
    small_chunks(97)
    blocked = solve_geometric(B, bias=bias)
    np.testing.assert_allclose(params(blocked), params(one), rtol=1e-9)
    assert blocked.result.method == one.result.method == "gauss-newton"
    assert blocked.result.nfev == one.result.nfev
    assert blocked.start_cond == pytest.approx(one.start_cond, rel=1e-9)
    assert blocked.rss == pytest.approx(one.rss, rel=1e-6, abs=1e-20)
    # R stands for the Jacobian: R^T R = J^T J, whatever the blocks
    scale = np.abs(one.R).max() ** 2
    np.testing.assert_allclose(blocked.R.T @ blocked.R, one.R.T @ one.R, rtol=1e-8, atol=1e-8 * scale)
    assert blocked.n == one.n == n


def full_jacobian(B: np.ndarray, sol: geometric.GeometricSolution) -> tuple[np.ndarray, np.ndarray]:
    """The residuals (N,) and Jacobian (N, 9) of the ``ortho-gain-bias`` fit at ``sol``, on whole arrays."""
    u = (B - sol.centre) / sol.scale
    e = u - (sol.b - sol.centre) / sol.scale
    y = e @ sol.C.T
    mag = np.linalg.norm(y, axis=1)
    nvec = y / mag[:, None]
    rows, cols = np.array([0, 0, 0, 1, 1]), np.array([0, 1, 2, 1, 2])
    J = np.column_stack([nvec[:, rows] * e[:, cols], -(nvec @ sol.C), -np.ones(len(B))])
    return mag - sol.h / sol.scale, J


def test_solution_R_and_rss_describe_the_whole_jacobian():
    """``R`` has the singular values of the full (N, p) Jacobian at the solution and ``rss`` is ``sum r^2``."""
    B = raw_log(3000, 50.0, True, seed=7)
    sol = solve_geometric(B, bias=True)
    r, J = full_jacobian(B, sol)
    assert sol.rss == pytest.approx(float(r @ r), rel=1e-9)
    np.testing.assert_allclose(np.linalg.svd(sol.R, compute_uv=False), np.linalg.svd(J, compute_uv=False), rtol=1e-9)
    np.testing.assert_allclose(sol.R.T @ sol.R, J.T @ J, rtol=1e-9, atol=1e-9 * len(B))


@pytest.mark.parametrize("bias", [False, True])
def test_noise_free_recovery_1e9(small_chunks, bias):
    small_chunks(97)
    B = raw_log(500, 0.0, bias, seed=3)
    model = "ortho-gain-bias" if bias else "ortho-gain"
    cal = Geometric(model).fit(B).calibration_
    truth = GAIN_BIAS if bias else GAIN
    est = np.array([cal.params[k] for k in truth.param_names()])
    np.testing.assert_allclose(est, truth.as_vector(), rtol=1e-9)
    assert cal.stats["fitted_magnitude"] == pytest.approx(FIELD, rel=1e-9)
    assert cal.diagnostics["optimizer"].startswith("Gauss-Newton converged")


def test_uncertainty_and_condition_match_full_jacobian():
    """``param_std``, ``noise_std`` and the condition number from ``R`` and ``rss`` are those of the full Jacobian
    (``cov = s^2 (J^T J)^-1``, ``s^2 = sum r^2 / (N - p)``)."""
    sigma = 30.0
    B = raw_log(5000, sigma, True, seed=11)
    cal = Geometric("ortho-gain-bias").fit(B).calibration_
    sol = solve_geometric(B, bias=True)
    r, J = full_jacobian(B, sol)
    s2 = float(r @ r) / (len(B) - J.shape[1])
    cov = params_covariance(sol.q, s2 * np.linalg.pinv(J.T @ J), np.full(4, sol.scale))
    std = dict(zip([*OrthoGainBias.param_names(), "h"], np.sqrt(np.diag(cov)), strict=True))
    assert cal.uncertainty["param_std"] == pytest.approx(std, rel=1e-7)
    assert cal.uncertainty["noise_std"] == pytest.approx(np.sqrt(s2) * sol.scale, rel=1e-9)
    assert cal.uncertainty["noise_std"] == pytest.approx(sigma, rel=0.05)  # the radial noise: one component
    assert cal.diagnostics["condition_number"] == pytest.approx(design_condition(J)[0], rel=1e-9)


def test_lm_fallback_still_works():
    """With a single Gauss-Newton step allowed the fit falls back to Levenberg-Marquardt on the full arrays and
    reaches the same minimum."""
    B = raw_log(2000, 100.0, True, seed=5)
    gn = solve_geometric(B, bias=True)
    lm = solve_geometric(B, bias=True, max_iter=1)
    assert lm.result.method == "levenberg-marquardt" and gn.result.method == "gauss-newton"
    np.testing.assert_allclose(params(lm), params(gn), rtol=1e-7)
    np.testing.assert_allclose(lm.R.T @ lm.R, gn.R.T @ gn.R, rtol=1e-6, atol=1e-6 * len(B))
    assert lm.rss == pytest.approx(gn.rss, rel=1e-9)


def traced_peak(B: np.ndarray) -> int:
    """tracemalloc peak (bytes) of ``solve_geometric(B, bias=True)``."""
    tracemalloc.start()
    try:
        sol = solve_geometric(B, bias=True)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert sol.result.method == "gauss-newton"
    return peak


def test_memory_well_below_one_n_by_9_array(small_chunks):
    """A fit of 300 000 samples in blocks of 8192 peaks far below one (N, 9) float64 array (the unblocked fit held
    several (N, p) Jacobians and residual arrays)."""
    n = 300_000
    B = raw_log(n, 20.0, True)  # (allocated before tracing)
    solve_geometric(B[:1000], bias=True)  # imports outside the measurement
    small_chunks(8192)
    peak = traced_peak(B)
    assert peak < 0.25 * n * 9 * 8, f"peak {peak / 1e6:.1f} MB"


def test_memory_independent_of_n(small_chunks):
    """The peak is a few blocks of ``[J | -r]`` (p + 1 = 10 columns), whatever N (blocks of 4096 samples here, to
    keep the test fast; the default block behaves alike: measured ~20 MB from N = 1.5e5 to 1e7)."""
    B = raw_log(120_000, 20.0, True)
    solve_geometric(B[:1000], bias=True)
    small_chunks(4096)
    peaks = [traced_peak(B[:n]) for n in (30_000, 120_000)]
    block_bytes = 4096 * 10 * 8
    assert peaks[1] <= 1.05 * peaks[0], f"peaks {[p / 1e6 for p in peaks]} MB"
    assert max(peaks) < 6 * block_bytes, f"peaks {[p / 1e6 for p in peaks]} MB"
