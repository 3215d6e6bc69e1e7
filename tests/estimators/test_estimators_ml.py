"""``ml``: bias-corrected magnitude maximum likelihood, its uncertainty and identifiability diagnostics."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import scipy.stats

import trimag
from trimag.errors import IdentifiabilityError, IdentifiabilityWarning, TrimagInputError
from trimag.estimators.ml import MaximumLikelihood, geometric_residual
from trimag.models.ellipsoid import Ellipsoid, to_upper
from trimag.quality.crlb import UPPER, crlb
from trimag.simulate import uniform_directions

D = np.array([[1.08, 0.03, -0.02], [0.0, 0.93, 0.04], [0.0, 0.0, 1.0]])
B0 = np.array([0.2, -0.1, 0.15])
TRUTH = Ellipsoid.from_matrix_offset(np.linalg.inv(D), B0)
THETA = np.concatenate([to_upper(np.linalg.inv(D))[UPPER], B0])


def _trials(sigma, n, k, **options):
    """k fits with known F = 1 on uniform directions; returns errors (k, 9), reported std (k, 9), noise."""
    errs, stds, noise = [], [], []
    for t in range(k):
        u = uniform_directions(n, seed=100 + t)
        raw = u @ D.T + B0 + np.random.default_rng(200 + t).normal(scale=sigma, size=(n, 3))
        cal = MaximumLikelihood(**options).fit(raw, 1.0).calibration_
        errs.append(np.concatenate([to_upper(cal.matrix)[UPPER], cal.offset]) - THETA)
        stds.append(list(cal.uncertainty["param_std"].values()))
        noise.append(cal.uncertainty["noise_std"])
    return np.array(errs), np.array(stds), np.array(noise)


@pytest.fixture(scope="module")
def strong_noise():
    """sigma/F = 5e-2, N = 2000, 16 trials (fixed seeds), with and without bias correction."""
    return _trials(0.05, 2000, 16), _trials(0.05, 2000, 16, bias_correction=False)


def test_geometric_residual_jacobian_is_exact():
    rng = np.random.default_rng(0)
    u = rng.normal(size=(40, 3))
    p = np.array([1.1, 0.1, -0.05, 0.9, 0.08, 1.0, 0.1, 0.2, -0.1])
    t = np.ones(40)
    _, J = geometric_residual(u, p, t)
    num = np.empty_like(J)
    for k in range(9):
        d = np.zeros(9)
        d[k] = 1e-6
        num[:, k] = (geometric_residual(u, p + d, t)[0] - geometric_residual(u, p - d, t)[0]) / 2e-6
    np.testing.assert_allclose(J, num, atol=1e-7)


def test_blocked_normal_equations_equal_the_full_jacobian(small_chunks) -> None:
    """``_normal_equations`` (blocks of reused buffers, several blocks here) gives J^T J, J^T r and r^T r of the
    full residual and Jacobian, also with a per-sample target."""
    import trimag.estimators.ml as ml_module

    small_chunks(8 * 64)  # the residual passes take 1/8 the rows: 64
    rng = np.random.default_rng(4)
    u = rng.normal(size=(300, 3))
    p = np.array([1.1, 0.1, -0.05, 0.9, 0.08, 1.0, 0.1, 0.2, -0.1])
    t = rng.uniform(0.9, 1.1, 300)
    r, J = geometric_residual(u, p, t)
    JtJ, Jtr, ss = ml_module._normal_equations(u, p, t)
    np.testing.assert_allclose(JtJ, J.T @ J, rtol=1e-12)
    np.testing.assert_allclose(Jtr, J.T @ r, rtol=1e-10, atol=1e-12)
    assert ss == pytest.approx(float(r @ r), rel=1e-12)
    assert ml_module._normal_equations(u, p, t, hessian=False)[0] is None


def test_normal_equations_on_raw_samples_and_a_constant_target(small_chunks) -> None:
    """The polish of long logs passes the raw samples with their normalisation (normalised block by block, no copy)
    and, without a reference, one number as the target: the same sums as on the normalised copy with a target
    array, to rounding."""
    import trimag.estimators.ml as ml_module
    from trimag.estimators._common import normalisation_stats, normalise

    small_chunks(8 * 64)  # the residual passes take 1/8 the rows: 64
    rng = np.random.default_rng(5)
    raw = rng.normal(size=(300, 3)) * [300.0, 250.0, 200.0] + [1500.0, -800.0, 400.0]  # far from the origin
    u, norm = normalise(raw)
    stats = normalisation_stats(raw)
    np.testing.assert_allclose(stats.centre, norm.centre, rtol=1e-14)
    assert stats.scale == pytest.approx(norm.scale, rel=1e-14)
    p = np.array([1.1, 0.1, -0.05, 0.9, 0.08, 1.0, 0.1, 0.2, -0.1])
    JtJ, Jtr, ss = ml_module._normal_equations(u, p, np.ones(300))
    JtJ_raw, Jtr_raw, ss_raw = ml_module._normal_equations(raw, p, 1.0, norm=stats)
    np.testing.assert_allclose(JtJ_raw, JtJ, rtol=1e-11)
    np.testing.assert_allclose(Jtr_raw, Jtr, rtol=1e-8, atol=1e-10 * np.abs(Jtr).max())
    assert ss_raw == pytest.approx(ss, rel=1e-11)


def test_tetrahedral_bias_correction_equals_central_differences():
    """The bias correction's Laplacian on a tetrahedron (5 evaluations) equals the central-difference Laplacian
    (7 evaluations), computed here from the residual directly, to 1e-3 of the correction."""
    from trimag.estimators.ml import bias_correction

    rng = np.random.default_rng(5)
    u = uniform_directions(3000, seed=5) @ D.T + B0 + rng.normal(scale=0.05, size=(3000, 3))
    p = np.concatenate([to_upper(np.linalg.inv(D))[UPPER], B0])
    t = np.ones(len(u))
    sigma2 = 0.05**2
    r0, J = geometric_residual(u, p, t)
    h = 1e-3
    lap = np.zeros(9)
    for k in range(3):
        for sign in (1.0, -1.0):
            q = p.copy()
            q[6 + k] -= sign * h
            r, Jq = geometric_residual(u, q, t)
            lap += Jq.T @ r - J.T @ r0
    central = -np.linalg.solve(J.T @ J, 0.5 * sigma2 * lap / h**2)
    corr = bias_correction(u, p, t, sigma2)
    assert np.linalg.norm(central) > 0
    np.testing.assert_allclose(corr, central, atol=1e-3 * np.linalg.norm(central))
    # given the normal equations at p (as ml passes its last Gauss-Newton evaluation), the same correction
    given = bias_correction(u, p, t, sigma2, normal_equations=(J.T @ J, J.T @ r0))
    np.testing.assert_allclose(given, corr, rtol=1e-9, atol=1e-12 * np.linalg.norm(corr))


def test_bias_correction_removes_the_scale_bias(strong_noise):
    """Without correction the mean diagonal of W is biased by about (sigma/F)^2 (more than 4 standard errors
    of the mean over 16 trials); with it the mean error is within 2.5 standard errors."""
    (e_bc, _, _), (e_raw, _, _) = strong_noise
    d_bc = e_bc[:, [0, 3, 5]].mean(axis=1)
    d_raw = e_raw[:, [0, 3, 5]].mean(axis=1)
    sem = d_bc.std(ddof=1) / np.sqrt(len(d_bc))
    assert abs(d_raw.mean()) > 4 * sem
    assert abs(d_bc.mean()) < 2.5 * sem


def test_noise_is_estimated_from_the_data(strong_noise):
    (_, _, noise), _ = strong_noise
    np.testing.assert_allclose(noise, 0.05, rtol=0.05)


def test_reported_uncertainty_covers_about_68_percent(strong_noise):
    """1-sigma coverage over 16 trials x 9 parameters (144 cases, binomial sd 4 %): within 55-81 %; the
    benchmark (docs/accuracy.md) validates 60-76 % on many more trials."""
    (e, s, _), _ = strong_noise
    frac = float(np.mean(np.abs(e) <= s))
    assert 0.55 <= frac <= 0.81


def test_reported_std_matches_the_crlb():
    """The Fisher covariance at the estimate equals the CRLB at the truth to a few percent; so does the
    predicted RMS error of the corrected magnitude."""
    u = uniform_directions(3000, seed=5)
    raw = u @ D.T + B0 + np.random.default_rng(6).normal(scale=0.01, size=u.shape)
    cal = MaximumLikelihood().fit(raw, 1.0).calibration_
    bound = crlb(TRUTH, u, 0.01)
    np.testing.assert_allclose(list(cal.uncertainty["param_std"].values()), bound.std, rtol=0.05)
    assert cal.uncertainty["predicted_magnitude_rms"] == pytest.approx(bound.magnitude_rms, rel=0.05)
    assert cal.uncertainty["predicted_field_rms"] == pytest.approx(bound.field_rms, rel=0.05)


def test_unknown_magnitude_gauge_and_symmetric_form():
    u = uniform_directions(1000, seed=1)
    raw = 48000.0 * u @ D.T + 1000 * B0
    cal = MaximumLikelihood(form="symmetric").fit(raw, units="nT").calibration_
    assert np.linalg.det(cal.matrix) == pytest.approx(1.0, rel=1e-9)
    np.testing.assert_allclose(cal.matrix, cal.matrix.T, atol=1e-12)
    mags = np.linalg.norm(cal.apply(raw), axis=1)
    np.testing.assert_allclose(mags, mags.mean(), rtol=1e-8)
    assert cal.uncertainty["covariance_order"][-1] == "F"
    assert cal.reference["value"] == pytest.approx(mags.mean(), rel=1e-8)


def test_diagnostics_name_the_poorly_determined_parameters():
    """Samples within 35 degrees of one direction: a warning naming poorly determined parameters."""
    rng = np.random.default_rng(3)
    u = uniform_directions(4000, seed=3)
    u = u[u[:, 2] > np.cos(np.radians(35))][:600]
    raw = u @ D.T + B0 + rng.normal(scale=1e-3, size=u.shape)
    with pytest.warns(IdentifiabilityWarning, match="poorly determined"):
        cal = MaximumLikelihood().fit(raw, 1.0).calibration_
    ident = cal.diagnostics["identifiability"]
    assert "hard_iron_z" in ident["poorly_determined"]
    assert ident["coverage_fraction"] < 0.25
    u_full = uniform_directions(600, seed=4)
    with warnings.catch_warnings():
        warnings.simplefilter("error", IdentifiabilityWarning)
        full = MaximumLikelihood().fit(u_full @ D.T + B0, 1.0).calibration_
    assert full.diagnostics["identifiability"]["poorly_determined"] == []


def test_single_plane_is_unidentifiable():
    t = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    u = np.column_stack([np.cos(t), np.sin(t), np.zeros_like(t)])
    with pytest.raises(IdentifiabilityError, match="plane"):
        MaximumLikelihood().fit(u @ D.T + B0, 1.0)


def test_bad_options():
    raw = uniform_directions(100, seed=0) @ D.T
    with pytest.raises(TrimagInputError, match="form"):
        MaximumLikelihood(form="lower").fit(raw, 1.0)
    with pytest.raises(TrimagInputError, match="noise_std"):
        MaximumLikelihood(noise_std=-1.0).fit(raw, 1.0)


@pytest.mark.parametrize(("sigma", "polish_steps"), [(0.01, 1), (0.02, 2)])
def test_large_log_path_matches_full_solve(monkeypatch: pytest.MonkeyPatch, sigma: float, polish_steps: int) -> None:
    """Above LARGE_N samples, ml solves on a spread subsample and polishes on all samples (normal
    equations); the result must equal the full solve to within POLISH_TOLERANCE of its standard deviations."""
    import trimag.estimators.ml as ml_module

    rng = np.random.default_rng(11)
    n = 80_000
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    D = np.array([[1.08, 0.03, -0.02], [0.0, 0.93, 0.04], [0.0, 0.0, 1.0]])
    raw = u @ D.T + [0.2, -0.1, 0.15] + rng.normal(scale=sigma, size=(n, 3))
    polish = ml_module.gauss_newton_polish
    evaluations: list[int] = []

    def counted(*args, **kwargs):
        out = polish(*args, **kwargs)
        evaluations.append(out[3])
        return out

    monkeypatch.setattr(ml_module, "gauss_newton_polish", counted)
    fast = trimag.fit(raw, method="ml", reference=1.0)
    assert fast.stats["iterations"] >= 1
    # at sigma/F = 1e-2 the contraction measured on the subsample predicts convergence after one step on all
    # samples; at 2e-2 Gauss-Newton contracts more slowly and the polish checks with a second evaluation
    assert evaluations == [polish_steps]
    monkeypatch.setattr(ml_module, "LARGE_N", 10 * n)
    full = trimag.fit(raw, method="ml", reference=1.0)
    assert evaluations == [polish_steps]  # the full solve does not polish
    std = np.array(list(full.uncertainty["param_std"].values()))[:9]
    diff = np.concatenate([(fast.matrix - full.matrix)[np.triu_indices(3)], fast.offset - full.offset])
    assert np.all(np.abs(diff) < ml_module.POLISH_TOLERANCE * std)


def test_large_log_path_converges_on_a_hemisphere_at_strong_noise(monkeypatch: pytest.MonkeyPatch) -> None:
    """On poorly conditioned data (one hemisphere, sigma/F = 5e-2) Gauss-Newton contracts slowly (~0.1 per
    step); the polish keeps stepping until the predicted remaining error is below POLISH_TOLERANCE standard
    deviations, so the subsample-and-polish path still lands on the full solve (two fixed steps left up to 0.06
    standard deviations here)."""
    import trimag.estimators.ml as ml_module
    from trimag.simulate import hemisphere_directions

    n = 20_000
    raw = hemisphere_directions(n, seed=0) @ D.T + B0 + np.random.default_rng(50).normal(scale=0.05, size=(n, 3))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentifiabilityWarning)
        fast = trimag.fit(raw, method="ml", reference=1.0)
        monkeypatch.setattr(ml_module, "LARGE_N", 10 * n)
        full = trimag.fit(raw, method="ml", reference=1.0)
    std = np.array(list(full.uncertainty["param_std"].values()))[:9]
    diff = np.concatenate([(fast.matrix - full.matrix)[np.triu_indices(3)], fast.offset - full.offset])
    assert np.all(np.abs(diff) < 1e-2 * std)


# ---- balanced sampling: the sample mean as the offset (docs/method-ml.md, "Balanced sampling") -------------
def _circle_fits(n, sigma, k, balance, *, directions=None):
    """k fits (unknown F) of three complete, evenly sampled great circles; returns offset errors (k, 3),
    reported offset std (k, 3) and the balance diagnostics."""
    from trimag.simulate import great_circle_directions

    u = great_circle_directions(n) if directions is None else directions
    errs, stds, tests = [], [], []
    for t in range(k):
        raw = u @ D.T + B0 + np.random.default_rng(300 + t).normal(scale=sigma, size=u.shape)
        cal = trimag.fit(raw, method="ml", balance=balance)
        errs.append(cal.offset - B0)
        stds.append([cal.uncertainty["param_std"][f"hard_iron_{a}"] for a in "xyz"])
        tests.append(cal.diagnostics.get("balanced_offset"))
    return np.array(errs), np.array(stds), tests


def test_balanced_turns_use_the_sample_mean_and_beat_the_unknown_direction_bound():
    n, sigma, k = 600, 0.05, 24
    err_auto, std_auto, tests = _circle_fits(n, sigma, k, "auto")
    err_ml, _, none = _circle_fits(n, sigma, k, "never")
    assert all(t is None for t in none)  # "never": no test, plain ML
    accepted = np.array([t["applied"] for t in tests])
    assert accepted.mean() >= 0.85  # the test keeps its level (1 %) on balanced data; a few misses allowed
    # accepted: the offset is the sample mean and its reported std is sigma / sqrt(N) per axis
    for t in tests:
        if t["applied"]:
            assert t["balanced"] and t["dof"] == 3 and t["p_value"] > t["alpha"]
            # the closed-form chi-square tail against scipy's
            assert t["p_value"] == pytest.approx(scipy.stats.chi2.sf(t["chi2"], t["dof"]), rel=1e-9, abs=1e-300)
    np.testing.assert_allclose(std_auto[accepted], sigma / np.sqrt(n), rtol=0.15)
    # the mean's error is ~ sigma / sqrt(N); the ML's (unknown directions) ~ sqrt(3) sigma / sqrt(N)
    rms_auto = np.sqrt(np.mean(err_auto**2))
    rms_ml = np.sqrt(np.mean(err_ml**2))
    assert rms_auto < 0.8 * rms_ml
    assert rms_auto < 1.3 * sigma / np.sqrt(n)


def test_unbalanced_data_keep_the_ml_offset():
    from trimag.simulate import hemisphere_directions

    u = hemisphere_directions(600, seed=4)
    raw = u @ D.T + B0 + np.random.default_rng(5).normal(scale=0.05, size=u.shape)
    auto = trimag.fit(raw, method="ml")  # balance="auto" is the default
    plain = trimag.fit(raw, method="ml", balance="never")
    test = auto.diagnostics["balanced_offset"]
    assert not test["balanced"] and not test["applied"] and test["p_value"] < 1e-6
    np.testing.assert_array_equal(auto.offset, plain.offset)
    forced = trimag.fit(raw, method="ml", balance="always")  # the magcal assumption, wrong here
    np.testing.assert_allclose(forced.offset, raw.mean(axis=0), rtol=0, atol=1e-12)
    assert np.linalg.norm(forced.offset - B0) > 10 * np.linalg.norm(plain.offset - B0)


def test_balance_statistic_is_chi2_with_3_dof_under_balance():
    """Mean of the statistic over balanced trials ~ 3 (its expectation), not inflated by a wrong covariance."""
    _, _, tests = _circle_fits(300, 0.02, 40, "auto")
    chi2 = np.array([t["chi2"] for t in tests])
    assert 2.0 < chi2.mean() < 4.2  # standard error of the mean ~ 0.39 over 40 trials


def test_bad_balance_option():
    raw = uniform_directions(100, seed=0) @ D.T + B0
    with pytest.raises(TrimagInputError, match="balance"):
        trimag.fit(raw, method="ml", balance="sometimes")


def test_real_hand_rotated_log_is_not_taken_for_balanced():
    """The bundled QMC5883L log (hand-rotated): the test must reject balance by far and keep the ML offset."""
    from importlib import resources

    with resources.as_file(resources.files("trimag") / "data" / "qmc5883l_noisy_raw_data.csv") as path:
        raw = np.loadtxt(path, delimiter=",", skiprows=3)
    cal = trimag.fit(raw, units="counts")
    test = cal.diagnostics["balanced_offset"]
    assert not test["applied"] and test["chi2"] > 1e3  # measured: 1.66e5
    np.testing.assert_array_equal(cal.offset, trimag.fit(raw, units="counts", balance="never").offset)


def test_balance_always_applies_to_noise_free_data_too():
    from trimag.simulate import great_circle_directions

    u = great_circle_directions(300)
    raw = u @ D.T + B0  # noise-free, noise given as 0: no covariance, so no test; "always" still takes the mean
    cal = trimag.fit(raw, method="ml", balance="always", noise_std=0.0)
    assert cal.diagnostics["balanced_offset"]["applied"] and cal.diagnostics["balanced_offset"]["balanced"] is None
    np.testing.assert_allclose(cal.offset, raw.mean(axis=0), atol=1e-12)
    np.testing.assert_allclose(cal.offset, B0, atol=1e-12)  # balanced design: the mean is the offset


def test_gauss_newton_reaches_the_levenberg_marquardt_minimum_and_declines_bad_starts():
    """From the algebraic start, undamped Gauss-Newton reaches the minimum MINPACK's Levenberg-Marquardt finds
    (to 1e-10); from a start where a full step raises the cost it returns None, so the fit falls back to LM."""
    from scipy.optimize import least_squares

    from trimag.estimators._common import normalise
    from trimag.estimators.ellipsoid_fit import algebraic_ellipsoid
    from trimag.estimators.ml import gauss_newton_solve

    rng = np.random.default_rng(11)
    W = np.array([[1.1, 0.05, -0.03], [0.0, 0.95, 0.02], [0.0, 0.0, 1.02]])
    X = uniform_directions(1500, seed=12) @ np.linalg.inv(W).T + [0.2, -0.1, 0.3]
    X += 0.03 * rng.standard_normal(X.shape)
    u, _ = normalise(X)
    W0, c0, _ = algebraic_ellipsoid(u)
    p0 = np.concatenate([W0[UPPER], c0])
    target = np.ones(len(u))
    gn = gauss_newton_solve(u, p0, target)
    assert gn is not None and gn.nfev <= 10
    lm = least_squares(lambda p: geometric_residual(u, p, target)[0], p0,
                       jac=lambda p: geometric_residual(u, p, target)[1], method="lm",
                       xtol=1e-12, ftol=1e-12, gtol=1e-12)
    np.testing.assert_allclose(gn.x, lm.x, rtol=0, atol=1e-10)
    far = p0.copy()
    far[6:] += 3.0  # the offset three radii away: Gauss-Newton's first step overshoots
    assert gauss_newton_solve(u, far, target) is None


@pytest.mark.parametrize("n", [5000, 30_000])
@pytest.mark.parametrize("sigma", [0.0, 0.01])
def test_two_great_circles_are_refused_or_flagged_never_a_crash(n, sigma):
    """Turning the sensor about two axes only puts the samples on two planar sections of the ellipsoid, which
    every quadric of a one-parameter family passes through: ``ml`` must raise IdentifiabilityError or warn,
    on both the small and the large-log path (it used to fail with LinAlgError or a complex scale)."""
    rng = np.random.default_rng(7)
    t = rng.uniform(0.0, 2.0 * np.pi, n)
    half = n // 2
    u = np.zeros((n, 3))
    u[:half, 0], u[:half, 1] = np.cos(t[:half]), np.sin(t[:half])
    u[half:, 1], u[half:, 2] = np.cos(t[half:]), np.sin(t[half:])
    raw = u @ D.T + B0 + rng.normal(scale=sigma, size=(n, 3))
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            cal = MaximumLikelihood().fit(raw).calibration_
    except IdentifiabilityError:
        return
    assert any(issubclass(w.category, IdentifiabilityWarning) for w in caught)
    assert np.linalg.det(cal.matrix) > 0


def test_information_relative_to_a_full_sphere_flags_two_great_circles():
    """Two noisy great circles leave one combination of parameters to the noise: every ellipsoid method warns
    (the column-normalised condition number and the variance inflation factors do not see it), while a full
    sphere keeps ~1x and one hemisphere ~10x the full-sphere standard deviation, without that warning."""
    rng = np.random.default_rng(12)
    n = 5000
    t = rng.uniform(0.0, 2.0 * np.pi, n)
    u = np.zeros((n, 3))
    u[: n // 2, 0], u[: n // 2, 1] = np.cos(t[: n // 2]), np.sin(t[: n // 2])
    u[n // 2 :, 1], u[n // 2 :, 2] = np.cos(t[n // 2 :]), np.sin(t[n // 2 :])
    noise = rng.normal(scale=0.01, size=(n, 3))
    fitted = 0
    for method in ("ml", "ellipsoid-fit", "twostep", "als"):
        try:  # refusing the data (exit 3) is also an answer; a calibration must come with the warning
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                cal = trimag.fit(u @ D.T + B0 + noise, method=method)
        except IdentifiabilityError:
            continue
        fitted += 1
        assert any(issubclass(w.category, IdentifiabilityWarning) and "full sphere" in str(w.message) for w in caught)
        assert cal.diagnostics["identifiability"]["std_inflation_vs_full_sphere"] > 30
        assert "w13" in cal.diagnostics["identifiability"]["weakest_combination"]
    assert fitted >= 2
    from trimag.simulate import hemisphere_directions

    cases = ((uniform_directions(n, seed=12), 0.9, 1.5), (hemisphere_directions(n, seed=12), 5, 20))
    for directions, low, high in cases:
        with warnings.catch_warnings():
            warnings.simplefilter("error", IdentifiabilityWarning)
            cal = trimag.fit(directions @ D.T + B0 + noise, method="ml")
        assert low < cal.diagnostics["identifiability"]["std_inflation_vs_full_sphere"] < high


@pytest.mark.parametrize(("cap", "exact_path"), [(0.5, False), (0.05, True)])
def test_condition_number_from_the_gram_matrix_equals_the_qr_one(
    monkeypatch: pytest.MonkeyPatch, cap: float, exact_path: bool
) -> None:
    """``ml`` takes the condition number from ``J^T J`` and repeats it on ``J`` (QR) only above
    GRAM_CONDITION_EXACT: the reported value is the QR one either way (to 1e-6 relative)."""
    import trimag.estimators.ml as ml_module

    rng = np.random.default_rng(2)
    u = rng.normal(size=(3000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u = u[u[:, 2] > 1 - cap][:800]  # a cap of directions: the smaller, the worse the conditioning
    raw = u @ np.diag([1.05, 0.97, 1.0]).T + [0.1, -0.05, 0.02] + rng.normal(scale=1e-3, size=u.shape)
    calls: list[float] = []
    design = ml_module.design_condition

    def spy(J):
        out = design(J)
        calls.append(out[0])
        return out

    monkeypatch.setattr(ml_module, "design_condition", spy)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cond = trimag.fit(raw, method="ml", reference=1.0).diagnostics["condition_number"]
        assert bool(calls) == exact_path and (cond > ml_module.GRAM_CONDITION_EXACT) == exact_path
        monkeypatch.setattr(ml_module, "GRAM_CONDITION_EXACT", 0.0)  # always QR
        qr = trimag.fit(raw, method="ml", reference=1.0).diagnostics["condition_number"]
    np.testing.assert_allclose(cond, qr, rtol=1e-6)


def test_chi2_survival_equals_scipy() -> None:
    """The balance test's closed-form chi-square tail equals scipy.stats.chi2.sf for 1-3 degrees of freedom."""
    from scipy.stats import chi2

    from trimag.estimators._finish import chi2_survival

    for dof in (1, 2, 3):
        for x in (0.0, 1e-12, 0.3, 1.0, 3.0, 7.8, 20.0, 60.0, 300.0, np.inf):
            np.testing.assert_allclose(chi2_survival(x, dof), chi2.sf(x, dof), rtol=1e-12, atol=1e-300)
    assert np.isnan(chi2_survival(np.nan, 3))
    with pytest.raises(ValueError, match="dof"):
        chi2_survival(1.0, 4)


def test_a_default_fit_does_not_load_scipy_optimize_or_stats() -> None:
    """``ml`` needs scipy.optimize only when Levenberg-Marquardt takes over, and scipy.stats not at all: a plain
    fit does not import them (together ~0.5 s of every ``trimag fit`` run and of every batch worker's start)."""
    import subprocess
    import sys

    code = (
        "import sys, numpy as np, trimag\n"
        "u = np.random.default_rng(0).normal(size=(2000, 3)); u /= np.linalg.norm(u, axis=1, keepdims=True)\n"
        "raw = u * [1.05, 0.97, 1.0] + [0.1, -0.05, 0.02] + np.random.default_rng(1).normal(scale=1e-3, size=u.shape)\n"
        "trimag.fit(raw, method='ml', reference=1.0)\n"
        "print(sorted(m for m in ('scipy.optimize', 'scipy.stats') if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
