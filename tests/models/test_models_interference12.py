"""The interference12 model: H_m = K H_b + c, correction inv(K) (H_m - c)."""

from __future__ import annotations

import numpy as np
import pytest

from trimag.calibration import Calibration
from trimag.errors import TrimagInputError
from trimag.models import get_model
from trimag.models.interference12 import Interference12


def _model(seed: int = 0) -> Interference12:
    rng = np.random.default_rng(seed)
    return Interference12.from_K_c(np.eye(3) + 0.1 * rng.normal(size=(3, 3)), rng.normal(size=3) * 800)


def test_registry_and_names():
    assert get_model("interference12") is Interference12
    assert Interference12.param_names() == (
        "k11", "k12", "k13", "k21", "k22", "k23", "k31", "k32", "k33", "c1", "c2", "c3"
    )


def test_distort_is_K_Hb_plus_c_and_correct_inverts():
    m = _model()
    H_b = np.random.default_rng(1).normal(size=(50, 3)) * 30000
    np.testing.assert_allclose(m.distort(H_b), H_b @ m.K.T + m.c, rtol=1e-14)
    np.testing.assert_allclose(m.correct(m.distort(H_b)), H_b, atol=1e-8)


def test_affine_form_matrix_is_inverse_K_offset_is_c():
    m = _model(2)
    matrix, offset = m.correction()
    np.testing.assert_allclose(matrix, np.linalg.inv(m.K), rtol=1e-13)
    np.testing.assert_array_equal(offset, m.c)
    back = Interference12.from_matrix_offset(matrix, offset)
    np.testing.assert_allclose(back.as_vector(), m.as_vector(), atol=1e-12)
    cal = Calibration.from_matrix_offset(matrix, offset, units="nT", model="interference12")
    H = np.array([[1000.0, -2000.0, 45000.0]])
    np.testing.assert_allclose(cal.apply(H), m.correct(H), atol=1e-9)


def test_identity_default_and_bad_shapes():
    m = Interference12()
    np.testing.assert_array_equal(m.K, np.eye(3))
    with pytest.raises(TrimagInputError, match=r"\(3, 3\)"):
        Interference12.from_K_c(np.eye(2), [0, 0, 0])
    with pytest.raises(TrimagInputError, match="singular"):
        Interference12.from_K_c(np.zeros((3, 3))).correction()
