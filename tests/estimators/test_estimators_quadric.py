"""Tests of ``quadric`` (paper D's linear method) and the identifiability report shared by paper D's methods."""

from __future__ import annotations

import numpy as np
import pytest

import trimag
from trimag.errors import IdentifiabilityError, NotFittedError, TrimagInputError
from trimag.estimators import get_estimator
from trimag.estimators._quadric import quadric_solve, quadric_terms
from trimag.estimators.quadric import Quadric, identifiability_report
from trimag.experiments.zhang2009 import FIELD_NAV, TRUTH, paper_attitudes
from trimag.models.zhang_cheng import ZhangCheng
from trimag.simulate import body_field, uniform_directions


def paper_samples(tilt_deg: float = 90.0) -> np.ndarray:
    return TRUTH.distort(body_field(paper_attitudes(40, tilt_deg=tilt_deg), FIELD_NAV))


def test_registered() -> None:
    assert get_estimator("quadric") is Quadric
    assert trimag.estimators.DEFAULT_METHOD["zhang-cheng"] == "quadric"


def test_paper_case_recovers_w_and_parameters() -> None:
    """Noise-free, the paper's 40 samples: W to 1e-6 and every parameter (angles in rad) to 1e-6."""
    cal = Quadric().fit(paper_samples(), 1.0).calibration_
    est = ZhangCheng.from_dict(cal.params)
    np.testing.assert_allclose(est.w_vector(), TRUTH.w_vector(), rtol=0, atol=1e-6)
    np.testing.assert_allclose(cal.diagnostics["w"], TRUTH.w_vector(), rtol=0, atol=1e-6)
    np.testing.assert_allclose(est.as_vector(), TRUTH.as_vector(), rtol=0, atol=1e-6)
    np.testing.assert_allclose(est.w_vector()[:3], [0.9616, 1.0209, 0.9806], atol=2e-4)  # the paper's print
    d = cal.diagnostics
    assert d["rank"] == 9 and d["undetermined"] == []
    assert 1.0 < d["condition_number"] < 1e4
    assert d["identifiability"]["physical_rank"] == 9
    assert d["params_display"]["alpha_deg"] == pytest.approx(0.8, abs=1e-9)
    assert cal.stats["rms_after"] < 1e-12 < cal.stats["rms_before"]


def test_ten_unknown_design_is_always_rank_deficient() -> None:
    """Why the solve fixes the trace: with a free constant, phi(V) W = F^2 has the null vector W - F^2 e10."""
    V = TRUTH.distort(uniform_directions(200, seed=0))
    P = quadric_terms(V)
    assert np.linalg.matrix_rank(P) == 9
    null = TRUTH.w_vector() - np.eye(10)[9]
    assert np.max(np.abs(P @ null)) < 1e-12


def test_single_axis_turn_refused_with_names() -> None:
    """Both turns about the vertical: the design is rank deficient, exit 3 with the parameters named."""
    V = paper_samples(tilt_deg=0.0)
    rep = identifiability_report(V, 1.0)
    assert rep.rank < 9 and rep.physical_rank < 9
    assert {"kz", "bz"} <= set(rep.undetermined)
    assert "gamma" not in rep.undetermined  # the in-plane angle shows in the ellipse's shape
    with pytest.raises(IdentifiabilityError, match=r"rank \d of 9.*undetermined: .*bz") as info:
        Quadric().fit(V, 1.0)
    assert info.value.exit_code == 3


def test_turn_about_x_keeps_beta() -> None:
    from scipy.spatial.transform import Rotation

    att = Rotation.from_euler("x", np.radians(9.0 * np.arange(40))[:, None])
    rep = identifiability_report(TRUTH.distort(body_field(att, FIELD_NAV)), 1.0)
    assert "beta" not in rep.undetermined and "bx" in rep.undetermined


def test_physical_units_and_large_offsets() -> None:
    F = 48193.0
    truth = ZhangCheng(0.004, -0.006, 0.008, 1.02, 0.97, 1.01, 1500.0, -900.0, 400.0)
    V = truth.distort(F * uniform_directions(300, seed=2))
    cal = trimag.fit(V, model="zhang-cheng", reference=F, units="nT")
    assert cal.method == "quadric" and cal.units == "nT"
    est = ZhangCheng.from_dict(cal.params)
    np.testing.assert_allclose(est.as_vector()[:6], truth.as_vector()[:6], atol=1e-9)
    np.testing.assert_allclose(est.as_vector()[6:], truth.as_vector()[6:], atol=1e-6)


def test_per_sample_reference() -> None:
    V = paper_samples()
    cal = Quadric().fit(V, np.ones(len(V))).calibration_
    np.testing.assert_allclose(ZhangCheng.from_dict(cal.params).as_vector(), TRUTH.as_vector(), atol=1e-9)


def test_noise_full_sphere_error_scales_with_sigma() -> None:
    rng = np.random.default_rng(5)
    B = uniform_directions(400, seed=6)
    errs = []
    for sigma in (1e-4, 1e-3):
        V = TRUTH.distort(B) + rng.normal(scale=sigma, size=B.shape)
        est, _ = quadric_solve(V, 1.0)
        errs.append(np.max(np.abs(est.w_vector() - TRUTH.w_vector())))
    assert errs[0] < 1e-3 and 3 < errs[1] / errs[0] < 30


def test_needs_reference() -> None:
    with pytest.raises(TrimagInputError, match="field magnitude"):
        Quadric().fit(paper_samples())


def test_estimator_contract() -> None:
    est = Quadric()
    assert not hasattr(est, "calibration_")
    with pytest.raises(NotFittedError):
        est.transform(np.zeros((2, 3)))
    V = paper_samples()
    V_copy = V.copy()
    assert est.fit(V, 1.0) is est
    np.testing.assert_array_equal(V, V_copy)
    np.testing.assert_allclose(est.transform(V), body_field(paper_attitudes(40), FIELD_NAV), atol=1e-12)
    bad = V.copy()
    bad[3, 1] = np.nan
    with pytest.raises(TrimagInputError, match="NaN"):
        Quadric().fit(bad, 1.0)
    with pytest.raises(TrimagInputError, match="no option"):
        Quadric().set_params(step=1)


def test_noise_swamps_limited_path_as_non_ellipsoid_or_large_error() -> None:
    """With sigma = 1e-2 on the paper's path the linear method stops being enough: it either refuses (not an
    ellipsoid) or misses W by more than 1e-2."""
    rng = np.random.default_rng(7)
    V = paper_samples() + rng.normal(scale=1e-2, size=(40, 3))
    try:
        cal = Quadric().fit(V, 1.0).calibration_
    except IdentifiabilityError as exc:
        assert "ellipsoid" in str(exc)
    else:
        assert np.max(np.abs(np.array(cal.diagnostics["w"]) - TRUTH.w_vector())) > 1e-2


def test_blocked_design_gives_the_whole_log_solution(small_chunks) -> None:
    """The linear design and the physical Jacobian are factored block by block: tiny blocks give the same
    parameters, ranks, condition numbers and singular values as one block, on a full set of attitudes and on
    a single-axis turn (where the report names what is undetermined)."""

    rng = np.random.default_rng(8)
    full = TRUTH.distort(uniform_directions(3000, seed=8)) + rng.normal(scale=1e-3, size=(3000, 3))
    single = paper_samples(tilt_deg=0.0)
    whole = [identifiability_report(V, 1.0) for V in (full, single)]
    small_chunks(7)
    blocked = [identifiability_report(V, 1.0) for V in (full, single)]
    for w, b in zip(whole, blocked, strict=True):
        assert (b.rank, b.physical_rank, b.undetermined, b.undetermined_terms) == (
            w.rank, w.physical_rank, w.undetermined, w.undetermined_terms)
        np.testing.assert_allclose(b.singular_values, w.singular_values, rtol=1e-9, atol=1e-12)
        if w.condition_number < 1e9:
            np.testing.assert_allclose(b.condition_number, w.condition_number, rtol=1e-6)
        else:  # rank deficient: the condition number is rounding over rounding, only its size is meaningful
            assert b.condition_number > 1e9
    assert whole[0].estimate is not None and blocked[0].estimate is not None
    np.testing.assert_allclose(blocked[0].estimate.as_vector(), whole[0].estimate.as_vector(), rtol=1e-10, atol=1e-13)
    assert whole[1].undetermined  # the single-axis turn leaves parameters undetermined
