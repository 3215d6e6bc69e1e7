"""``ellipsoid-fit`` and ``ml`` on simulated data with known truth, and their failure modes."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import trimag
from trimag.errors import IdentifiabilityError, IdentifiabilityWarning, TrimagInputError
from trimag.estimators import DEFAULT_METHOD, get_estimator

from _helpers import ellipsoid_truth, simulate_ellipsoid

F = 48000.0


@pytest.mark.parametrize("method", ["ellipsoid-fit", "ml"])
def test_noise_free_recovery(method: str) -> None:
    raw = simulate_ellipsoid(500)
    W, b = ellipsoid_truth()
    cal = trimag.fit(raw, method=method, reference=F, units="nT")
    np.testing.assert_allclose(cal.offset, b, atol=1e-6)
    np.testing.assert_allclose(cal.matrix, W, atol=1e-9)
    assert cal.stats["rms_after"] < 1e-6
    assert cal.stats["rms_before"] > 1000


def test_ml_with_noise_reaches_noise_floor_and_reports_std() -> None:
    sigma = 30.0
    raw = simulate_ellipsoid(3000, noise=sigma, seed=3)
    cal = trimag.fit(raw, reference=F, units="nT")
    assert cal.method == DEFAULT_METHOD["ellipsoid"]
    # the magnitude residual of an isotropic 3-D noise is ~ sigma (its radial component)
    assert 0.9 * sigma < cal.stats["rms_after"] < 1.1 * sigma
    _, b = ellipsoid_truth()
    std = cal.uncertainty["param_std"]
    for k, axis in enumerate("xyz"):
        assert abs(cal.offset[k] - b[k]) < 5 * std[f"hard_iron_{axis}"]
    assert cal.uncertainty["noise_std"] == pytest.approx(sigma, rel=0.1)


def test_unknown_magnitude_keeps_shape() -> None:
    raw = simulate_ellipsoid(800)
    cal = trimag.fit(raw, units="nT")
    W, _ = ellipsoid_truth()
    assert np.linalg.det(cal.matrix) == pytest.approx(1.0)
    upper = np.triu_indices(3)
    ratio = cal.matrix[upper] / W[upper]
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-8)
    assert cal.reference["source"] == "mean"
    assert cal.stats["rms_after"] < 1e-6


def test_symmetric_form() -> None:
    raw = simulate_ellipsoid(500)
    cal = trimag.fit(raw, reference=F, units="nT", form="symmetric")
    assert np.allclose(cal.matrix, cal.matrix.T)
    assert cal.stats["rms_after"] < 1e-6


def test_planar_data_is_unidentifiable() -> None:
    t = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    raw = np.column_stack([F * np.cos(t) + 100, F * np.sin(t), np.full_like(t, 3000.0)])
    with pytest.raises(IdentifiabilityError, match="one plane"):
        trimag.fit(raw, reference=F)


def test_stuck_sensor_is_unidentifiable() -> None:
    with pytest.raises(IdentifiabilityError, match="identical"):
        trimag.fit(np.tile([100.0, 200.0, 300.0], (50, 1)))


def test_too_few_samples() -> None:
    with pytest.raises(IdentifiabilityError, match="too few"):
        trimag.fit(simulate_ellipsoid(8))


def test_small_arc_warns() -> None:
    rng = np.random.default_rng(4)
    u = rng.normal(size=(500, 3)) * [0.15, 0.15, 1.0] + [0, 0, 4]
    u /= np.linalg.norm(u, axis=1, keepdims=True)  # a cap of ~10 degrees around +z
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            trimag.fit(F * u + rng.normal(scale=20, size=u.shape), reference=F)
        except IdentifiabilityError:
            return  # also acceptable: refused outright
    assert any(issubclass(w.category, IdentifiabilityWarning) for w in caught)


def test_input_validation() -> None:
    raw = simulate_ellipsoid(100)
    bad = raw.copy()
    bad[3, 1] = np.nan
    with pytest.raises(TrimagInputError, match="NaN"):
        trimag.fit(bad)
    with pytest.raises(TrimagInputError, match=r"shape \(N, 3\)"):
        trimag.fit(raw[:, :2])
    with pytest.raises(TrimagInputError, match="unknown method"):
        trimag.fit(raw, method="magic")
    with pytest.raises(TrimagInputError, match="unknown unit"):
        trimag.fit(raw, units="furlongs")
    with pytest.raises(TrimagInputError, match="positive"):
        trimag.fit(raw, reference=-5.0)
    with pytest.raises(TrimagInputError, match="no option"):
        trimag.fit(raw, method="ml", bogus=1)


def test_estimator_contract_basics() -> None:
    est = get_estimator("ml")()
    assert not [k for k in vars(est) if k.endswith("_")]
    with pytest.raises(trimag.NotFittedError):
        est.transform(np.ones((2, 3)))
    raw = simulate_ellipsoid(300)
    copy = raw.copy()
    assert est.fit(raw, F) is est
    assert np.array_equal(raw, copy)
    assert est.residuals_.shape == (300,) and est.n_samples_ == 300
    np.testing.assert_allclose(est.transform(raw), est.calibration_.apply(raw))


def test_algebraic_fit_normalised_on_the_fly_equals_the_normalised_copy():
    """``algebraic_ellipsoid(B, norm)`` (normalised chunk by chunk, no copy) equals the fit of the copy."""
    from trimag.estimators._common import normalisation_of, normalise
    from trimag.estimators.ellipsoid_fit import algebraic_ellipsoid
    from trimag.simulate import uniform_directions

    rng = np.random.default_rng(4)
    B = uniform_directions(3000, seed=5) @ np.diag([1.1, 0.9, 1.05]) * 4e4 + [3e3, -2e3, 1e3]
    B += 50 * rng.standard_normal(B.shape)
    norm = normalisation_of(B)
    W1, c1, cond1 = algebraic_ellipsoid(B, norm)
    W2, c2, cond2 = algebraic_ellipsoid(norm.forward(B))
    np.testing.assert_allclose(W1, W2, rtol=1e-10)
    np.testing.assert_allclose(c1, c2, atol=1e-12)
    assert cond1 == pytest.approx(cond2, rel=1e-8)
    # and the fit does not depend on the normalisation (translation and scale invariance)
    u, norm_full = normalise(B)
    W3, c3, _ = algebraic_ellipsoid(u)
    np.testing.assert_allclose(W3 / norm_full.scale, W1 / norm.scale, rtol=1e-8)
    np.testing.assert_allclose(norm_full.centre + norm_full.scale * c3, norm.centre + norm.scale * c1, rtol=1e-8)


@pytest.mark.parametrize("method", ["ellipsoid-fit", "ml", "als", "twostep"])
def test_memory_layout_of_the_input_does_not_matter(method: str) -> None:
    """A Fortran-ordered (or transposed-view) input gives the same calibration and statistics as a C-ordered
    one, and is not modified (the component-major fast paths must never write through a view)."""
    rng = np.random.default_rng(8)
    raw = simulate_ellipsoid(800) + 30.0 * rng.standard_normal((800, 3))
    c_order = np.ascontiguousarray(raw)
    f_order = np.asfortranarray(raw)
    kept = f_order.copy()
    a = trimag.fit(c_order, method=method, units="nT")
    b = trimag.fit(f_order, method=method, units="nT")
    np.testing.assert_array_equal(f_order, kept)
    np.testing.assert_allclose(b.matrix, a.matrix, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(b.offset, a.offset, rtol=1e-12, atol=1e-9)
    for key in ("rms_before", "rms_after", "max_abs_after", "mean_norm_after"):
        assert b.stats[key] == pytest.approx(a.stats[key], rel=1e-12), key


def test_power_sums_equal_the_direct_sums_over_several_chunks() -> None:
    from itertools import product

    from trimag._core.chunks import chunk_rows
    from trimag._core.quadric import power_sums
    from trimag.estimators._common import normalisation_of

    rng = np.random.default_rng(3)
    raw = rng.normal(size=(chunk_rows() + 1234, 3)) * [2.0, 1.0, 0.5] + [100.0, -50.0, 20.0]  # > 1 chunk
    norm = normalisation_of(raw)
    u = (raw - norm.centre) / norm.scale
    sums = power_sums(raw, norm)
    direct = {(a, b, c): float(np.sum(u[:, 0] ** a * u[:, 1] ** b * u[:, 2] ** c))
              for a, b, c in product(range(5), repeat=3) if a + b + c <= 4}
    assert set(sums) == set(direct) and len(sums) == 35
    for key, value in direct.items():
        assert sums[key] == pytest.approx(value, rel=1e-10, abs=1e-8 * len(u)), key


def test_one_pass_of_moments_gives_the_scatter_and_the_power_sums() -> None:
    """``als`` takes the algebraic fit's scatter and its own power sums from one pass (``quadric_moments``)."""
    from trimag._core.quadric import (
        power_sums,
        power_sums_from_moments,
        quadric_moments,
        quadric_scatter,
        scatter_from_moments,
    )
    from trimag.estimators._common import normalisation_stats

    rng = np.random.default_rng(8)
    raw = rng.normal(size=(3000, 3)) * [2.0, 1.0, 0.5] + [100.0, -50.0, 20.0]
    norm = normalisation_stats(raw)
    moments = quadric_moments(raw, norm)
    np.testing.assert_array_equal(scatter_from_moments(moments), quadric_scatter(raw, norm))
    assert power_sums_from_moments(moments) == power_sums(raw, norm)
