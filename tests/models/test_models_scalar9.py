"""The ``scalar9`` model (paper B): convention, exact conversion to and from (matrix, offset), gauge."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trimag.calibration import Calibration
from trimag.errors import TrimagInputError
from trimag.models import get_model
from trimag.models.scalar9 import Scalar9, lq_gauge, t_matrix, t_matrix_derivatives

angles = st.floats(min_value=-0.5, max_value=0.5)
scales = st.floats(min_value=0.5, max_value=2.0)
biases = st.floats(min_value=-1e3, max_value=1e3)


@settings(max_examples=60, deadline=None)
@given(b1=biases, b2=biases, b3=biases, k1=scales, k2=scales, k3=scales,
       alpha=angles, beta=angles, gamma=angles)
def test_round_trip_matrix_offset_is_exact(**params: float) -> None:
    m = Scalar9(**params)
    matrix, offset = m.correction()
    back = Scalar9.from_matrix_offset(matrix, offset)
    np.testing.assert_allclose(back.as_vector(), m.as_vector(), rtol=1e-11, atol=1e-12)


def test_convention_of_the_spec() -> None:
    """methods.md paper B: B_m = K T B + b, rows of T are unit vectors, correction T^-1 K^-1 (B_m - b)."""
    m = Scalar9(b1=10.0, b2=-5.0, b3=2.0, k1=1.1, k2=0.9, k3=1.05, alpha=0.1, beta=-0.2, gamma=0.3)
    T = m.T
    expected = np.array([
        [1, 0, 0],
        [math.sin(0.1), math.cos(0.1), 0],
        [math.sin(-0.2), math.sin(0.3) * math.cos(-0.2), math.cos(0.3) * math.cos(-0.2)],
    ])
    np.testing.assert_allclose(T, expected, atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(T, axis=1), 1.0, atol=1e-15)
    B = np.array([[1.0, 2.0, 3.0], [-4.0, 0.5, 2.0]])
    raw = m.distort(B)
    np.testing.assert_allclose(raw, B @ (np.diag([1.1, 0.9, 1.05]) @ T).T + [10.0, -5.0, 2.0], atol=1e-13)
    np.testing.assert_allclose(m.correct(raw), B, atol=1e-12)
    matrix, offset = m.correction()
    np.testing.assert_allclose(matrix, np.linalg.inv(T) @ np.diag(1 / np.array([1.1, 0.9, 1.05])), atol=1e-14)
    np.testing.assert_array_equal(offset, [10.0, -5.0, 2.0])


def test_degrees_helpers() -> None:
    m = Scalar9.from_degrees(alpha=0.5, beta=-0.25, gamma=1.0)
    assert m.alpha == pytest.approx(math.radians(0.5))
    assert m.angles_deg() == pytest.approx({"alpha": 0.5, "beta": -0.25, "gamma": 1.0})


def test_derivatives_of_T_match_finite_differences() -> None:
    ang = np.array([0.1, -0.2, 0.3])
    h = 1e-7
    for j, dT in enumerate(t_matrix_derivatives(*ang)):
        step = np.zeros(3)
        step[j] = h
        num = (t_matrix(*(ang + step)) - t_matrix(*(ang - step))) / (2 * h)
        np.testing.assert_allclose(dT, num, atol=1e-8)


def test_magnitude_gauge_keeps_corrected_magnitudes() -> None:
    rng = np.random.default_rng(3)
    matrix = np.eye(3) + 0.05 * rng.normal(size=(3, 3))
    offset = rng.normal(size=3) * 100
    with pytest.raises(TrimagInputError, match="not of the scalar9 form"):
        Scalar9.from_matrix_offset(matrix, offset)
    m = Scalar9.from_matrix_offset(matrix, offset, gauge="magnitude")
    raw = rng.normal(size=(50, 3)) * 1000
    np.testing.assert_allclose(
        np.linalg.norm(m.correct(raw), axis=1), np.linalg.norm((raw - offset) @ matrix.T, axis=1), rtol=1e-12
    )
    L = lq_gauge(np.linalg.inv(matrix))
    assert np.allclose(np.triu(L, 1), 0) and (np.diag(L) > 0).all()


@pytest.mark.parametrize(
    ("params", "match"),
    [
        ({"k1": 0.0}, "scale factor `k1`"),
        ({"k3": -1.0}, "scale factor `k3`"),
        ({"alpha": 2.0}, "angle `alpha` must be in radians"),
        ({"b2": float("nan")}, "bias `b2`"),
    ],
)
def test_invalid_parameters_are_refused(params: dict[str, float], match: str) -> None:
    with pytest.raises(TrimagInputError, match=match):
        Scalar9(**params)


def test_bad_shapes_and_gauge_name() -> None:
    with pytest.raises(TrimagInputError, match="matrix must be"):
        Scalar9.from_matrix_offset(np.eye(2), [0, 0, 0])
    with pytest.raises(TrimagInputError, match="gauge must be"):
        Scalar9.from_matrix_offset(np.eye(3), [0, 0, 0], gauge="other")


def test_registry_and_calibration_from_params() -> None:
    assert get_model("scalar9") is Scalar9
    params = Scalar9(b1=100.0, k2=1.01, gamma=0.01).as_dict()
    cal = Calibration.from_params("scalar9", params, units="nT")
    assert cal.model == "scalar9"
    back = Calibration.from_json(cal.to_json())
    assert back.approx_equal(cal, atol=0) and back.params == pytest.approx(params)
