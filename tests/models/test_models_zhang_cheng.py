"""Tests of the paper-D model ``zhang-cheng``: conversions to and from (matrix, offset), Q and W."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trimag.calibration import Calibration
from trimag.errors import TrimagInputError
from trimag.estimators._quadric import quadric_terms
from trimag.models import get_model
from trimag.models.zhang_cheng import ZhangCheng, quadric_from_w, upper_from_quadric, w_from_quadric

PAPER = ZhangCheng(*np.radians([0.8, 0.5, 1.1]), 1.02, 0.99, 1.01, 0.03, 0.02, 0.01)

angles = st.floats(-0.6, 0.6)
gains = st.floats(0.5, 2.0)
offsets = st.floats(-5.0, 5.0)


def test_registered() -> None:
    assert get_model("zhang-cheng") is ZhangCheng
    assert ZhangCheng.param_names() == ("alpha", "beta", "gamma", "kx", "ky", "kz", "bx", "by", "bz")


def test_equations_match_spec() -> None:
    """V = K A B + b with Lx, Ly, Lz written out as in methods.md, paper D."""
    rng = np.random.default_rng(0)
    B = rng.normal(size=(20, 3))
    m = PAPER
    Lx = B[:, 0] * np.cos(m.gamma) * np.cos(m.alpha) + B[:, 1] * np.sin(m.gamma) + B[:, 2] * np.sin(m.alpha)
    Ly = B[:, 1] * np.cos(m.beta) + B[:, 2] * np.sin(m.beta)
    Lz = B[:, 2]
    V = np.column_stack([m.kx * Lx + m.bx, m.ky * Ly + m.by, m.kz * Lz + m.bz])
    np.testing.assert_allclose(m.distort(B), V, rtol=0, atol=1e-14)
    np.testing.assert_allclose(m.correct(V), B, rtol=0, atol=1e-13)


def test_paper_q_diagonal() -> None:
    """The true diagonal of Q is (0.96171, 1.02076, 0.98056); the paper prints 0.9616, 1.0209, 0.9806
    (rounded, within 2e-4 of it)."""
    w = PAPER.w_vector()
    np.testing.assert_allclose(w[:3], [0.96171, 1.02076, 0.98056], atol=5e-6)
    np.testing.assert_allclose(w[:3], [0.9616, 1.0209, 0.9806], atol=2e-4)
    assert w[3] < 0  # the paper's fourth value starts with "-0"


def test_w_reproduces_magnitude() -> None:
    rng = np.random.default_rng(1)
    B = rng.normal(size=(50, 3)) * 3.0
    V = PAPER.distort(B)
    np.testing.assert_allclose(quadric_terms(V) @ PAPER.w_vector(), np.sum(B * B, axis=1), rtol=1e-12)


def test_correction_is_upper_triangular() -> None:
    M, _ = PAPER.correction()
    assert np.all(M[np.tril_indices(3, -1)] == 0)
    assert np.all(np.diag(M) > 0)
    np.testing.assert_allclose(M.T @ M, PAPER.quadric(), atol=1e-15)


@settings(max_examples=60, deadline=None)
@given(st.tuples(angles, angles, angles, gains, gains, gains, offsets, offsets, offsets))
def test_round_trips(vals: tuple[float, ...]) -> None:
    m = ZhangCheng(*vals)
    v = m.as_vector()
    np.testing.assert_allclose(ZhangCheng.from_matrix_offset(*m.correction()).as_vector(), v, atol=1e-10)
    np.testing.assert_allclose(ZhangCheng.from_quadric(m.quadric(), v[6:]).as_vector(), v, atol=1e-9)
    np.testing.assert_allclose(ZhangCheng.from_w(m.w_vector()).as_vector(), v, atol=1e-8)
    Q, _, _ = quadric_from_w(m.w_vector())
    np.testing.assert_allclose(w_from_quadric(Q, v[6:]), m.w_vector(), atol=1e-12)


def test_from_w_rescales_to_the_known_magnitude() -> None:
    """A W scaled by any factor (the homogeneous form) comes back to the same parameters with F given."""
    F = 48000.0
    m = ZhangCheng(0.01, -0.02, 0.015, 1.01, 0.98, 1.02, 300.0, -200.0, 150.0)
    w = m.w_vector().copy()
    w[9] -= F**2  # phi(V) . w = 0
    w_scaled = 3.7 * w
    w_scaled[9] += F**2  # back to phi(V) . W = F^2, but with Q scaled by 3.7
    np.testing.assert_allclose(ZhangCheng.from_w(w_scaled, F).as_vector(), m.as_vector(), rtol=1e-9)


def test_gauge_cholesky() -> None:
    """M = cholesky(Q)^T is upper triangular; any rotated R M gives the same Q and the same parameters."""
    M, b = PAPER.correction()
    R = np.linalg.qr(np.random.default_rng(3).normal(size=(3, 3)))[0]
    Mr = R @ M
    np.testing.assert_allclose(upper_from_quadric(Mr.T @ Mr), M, atol=1e-14)
    with pytest.raises(TrimagInputError, match="upper-triangular"):
        ZhangCheng.from_matrix_offset(Mr, b)


def test_calibration_from_params() -> None:
    cal = Calibration.from_params("zhang-cheng", PAPER.as_dict(), units="uT")
    rng = np.random.default_rng(4)
    B = rng.normal(size=(10, 3))
    np.testing.assert_allclose(cal.apply(PAPER.distort(B)), B, atol=1e-13)
    assert Calibration.from_json(cal.to_json()).approx_equal(cal, atol=0)


def test_report_in_degrees() -> None:
    r = PAPER.as_report()
    assert r["alpha_deg"] == pytest.approx(0.8) and r["gamma_deg"] == pytest.approx(1.1)
    assert "alpha" not in r


@pytest.mark.parametrize(
    "kwargs, match",
    [({"kx": 0.0}, "positive"), ({"alpha": 1.6}, "90"), ({"bx": float("nan")}, "finite")],
)
def test_bad_params(kwargs: dict[str, float], match: str) -> None:
    with pytest.raises(TrimagInputError, match=match):
        ZhangCheng(**kwargs)


def test_not_positive_definite() -> None:
    with pytest.raises(TrimagInputError, match="positive definite"):
        upper_from_quadric(np.diag([1.0, -1.0, 1.0]))
