"""Paper A's error model (methods.md, paper A): Gamma, Gamma^-1, q1..q5 and the exact conversions."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trimag.calibration import Calibration
from trimag.errors import TrimagInputError
from trimag.models import get_model
from trimag.models.ortho_gain import OrthoGain, OrthoGainBias, normalised_upper, params_from_q, q_from_params

PAPER = OrthoGain(theta=0.06, phi=0.08, psi=-0.04, kxz=0.95, kyz=1.05)

angles = st.floats(-1.2, 1.2)
gains = st.floats(0.3, 3.0)


def test_registry_names_and_counts():
    assert get_model("ortho-gain") is OrthoGain
    assert get_model("ortho-gain-bias") is OrthoGainBias
    assert OrthoGain.param_names() == ("theta", "phi", "psi", "kxz", "kyz")
    assert OrthoGainBias.param_names() == ("theta", "phi", "psi", "kxz", "kyz", "bx", "by", "bz")
    assert (OrthoGain.n_identifiable, OrthoGainBias.n_identifiable) == (5, 8)


def test_gamma_matches_paper_definition():
    t, p, s, kx, ky = 0.06, 0.08, -0.04, 0.95, 1.05
    expected = np.array(
        [
            [np.cos(t) * np.cos(p) / kx, np.cos(t) * np.sin(p) / kx, np.sin(t) / kx],
            [0, np.cos(s) / ky, np.sin(s) / ky],
            [0, 0, 1],
        ]
    )
    np.testing.assert_allclose(PAPER.gamma(), expected, rtol=0, atol=1e-15)


def test_gamma_inv_is_the_inverse_and_q2_uses_kyz():
    """The paper prints k'XZ in q2; inverting Gamma gives k'YZ (methods.md). kxz != kyz tells them apart."""
    np.testing.assert_allclose(PAPER.gamma_inv() @ PAPER.gamma(), np.eye(3), atol=1e-15)
    q2 = -PAPER.kyz * np.tan(PAPER.phi) / np.cos(PAPER.psi)
    assert PAPER.q()[1] == pytest.approx(q2, rel=1e-15)
    assert PAPER.q()[1] != pytest.approx(-PAPER.kxz * np.tan(PAPER.phi) / np.cos(PAPER.psi), rel=1e-3)


@settings(max_examples=200, deadline=None)
@given(angles, angles, angles, gains, gains)
def test_params_q_round_trip_exact(t, p, s, kx, ky):
    v = np.array([t, p, s, kx, ky])
    back = params_from_q(q_from_params(*v))
    np.testing.assert_allclose(back, v, rtol=1e-12, atol=1e-13)
    # and the other way round
    q = q_from_params(*v)
    np.testing.assert_allclose(q_from_params(*params_from_q(q)), q, rtol=1e-12, atol=1e-13)


def test_vectorised_conversions_shape():
    v = np.tile(PAPER.as_vector(), (4, 1))
    assert q_from_params(*v.T).shape == (4, 5)
    assert params_from_q(q_from_params(*v.T)).shape == (4, 5)


def test_matrix_offset_round_trip_and_distort_correct():
    m, b = PAPER.correction()
    np.testing.assert_allclose(OrthoGain.from_matrix_offset(m, b).as_vector(), PAPER.as_vector(), rtol=1e-14)
    biased = OrthoGainBias(**PAPER.as_dict(), bx=0.3, by=-0.2, bz=0.1)
    m, b = biased.correction()
    np.testing.assert_allclose(OrthoGainBias.from_matrix_offset(m, b).as_vector(), biased.as_vector(), rtol=1e-14)
    B = np.random.default_rng(0).normal(size=(50, 3))
    np.testing.assert_allclose(biased.correct(biased.distort(B)), B, atol=1e-13)
    np.testing.assert_allclose(biased.distort(B), B @ PAPER.gamma().T + [0.3, -0.2, 0.1], atol=1e-15)


def test_calibration_from_params_round_trip_json():
    cal = Calibration.from_params("ortho-gain", PAPER.as_dict())
    np.testing.assert_allclose(cal.matrix, PAPER.gamma_inv())
    again = Calibration.from_json(cal.to_json())
    assert again.approx_equal(cal, atol=1e-15)
    assert again.params == pytest.approx(PAPER.as_dict())


def test_rejects_matrices_outside_the_model():
    m = PAPER.gamma_inv()
    bad = m.copy()
    bad[2, 0] = 0.1
    with pytest.raises(TrimagInputError, match="upper-triangular"):
        OrthoGain.from_matrix_offset(bad)
    with pytest.raises(TrimagInputError, match="upper-triangular"):
        OrthoGain.from_matrix_offset(2 * m)
    with pytest.raises(TrimagInputError, match="no offsets"):
        OrthoGain.from_matrix_offset(m, [1.0, 0, 0])
    with pytest.raises(TrimagInputError, match="q1 and q4"):
        OrthoGain.from_q([-1.0, 0, 0, 1.0, 0])


@pytest.mark.parametrize(
    "kwargs",
    [
        pytest.param({"theta": 2.0}, id="theta-out-of-range"),
        pytest.param({"psi": float("nan")}, id="psi-nan"),
        pytest.param({"kxz": 0.0}, id="zero-gain"),
        pytest.param({"kyz": -1.0}, id="negative-gain"),
    ],
)
def test_invalid_parameters(kwargs):
    with pytest.raises(TrimagInputError):
        OrthoGain(**kwargs)


def test_normalised_upper_preserves_magnitudes_up_to_scale():
    rng = np.random.default_rng(3)
    A = np.eye(3) + 0.2 * rng.normal(size=(3, 3))
    C, s = normalised_upper(A)
    assert C[2, 2] == 1.0 and np.allclose(np.tril(C, -1), 0)
    v = rng.normal(size=(20, 3))
    np.testing.assert_allclose(np.linalg.norm(v @ A.T, axis=1), s * np.linalg.norm(v @ C.T, axis=1), rtol=1e-12)
    OrthoGain.from_matrix_offset(C)  # a valid Gamma^-1
