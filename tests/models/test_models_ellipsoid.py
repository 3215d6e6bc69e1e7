"""The ellipsoid (hard + soft iron) model: parameters <-> matrices, distort/correct, gauges."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from trimag import Calibration
from trimag.errors import TrimagInputError
from trimag.models import available_models, get_model
from trimag.models.ellipsoid import Ellipsoid, to_symmetric, to_upper


@given(
    arrays(np.float64, (3, 3), elements=st.floats(-0.3, 0.3)),
    arrays(np.float64, (3,), elements=st.floats(-1e4, 1e4)),
)
@settings(max_examples=50, deadline=None)
def test_matrix_offset_round_trip_exact(dm: np.ndarray, b: np.ndarray) -> None:
    W = np.eye(3) + dm
    model = Ellipsoid.from_matrix_offset(W, b)
    W2, b2 = model.correction()
    assert np.array_equal(W2, W) and np.array_equal(b2, b)
    assert Ellipsoid.from_dict(model.as_dict()) == model
    assert Ellipsoid.from_vector(model.as_vector()) == model


def test_distort_then_correct_is_identity() -> None:
    model = Ellipsoid.from_matrix_offset([[1.1, 0.02, 0.0], [0.0, 0.9, 0.01], [0.0, 0.0, 1.05]], [10.0, -5.0, 3.0])
    B = np.random.default_rng(0).normal(size=(100, 3))
    np.testing.assert_allclose(model.correct(model.distort(B)), B, atol=1e-12)


def test_gauges_preserve_magnitudes() -> None:
    rng = np.random.default_rng(2)
    M = np.eye(3) + 0.2 * rng.normal(size=(3, 3))
    e = rng.normal(size=(50, 3))
    U, S = to_upper(M), to_symmetric(M)
    assert np.allclose(np.tril(U, -1), 0) and np.all(np.diag(U) > 0)
    assert np.allclose(S, S.T)
    for G in (U, S):
        np.testing.assert_allclose(np.linalg.norm(e @ G.T, axis=1), np.linalg.norm(e @ M.T, axis=1), rtol=1e-12)


def test_from_params_calibration() -> None:
    params = Ellipsoid(hard_iron_x=1.0, w11=2.0).as_dict()
    cal = Calibration.from_params("ellipsoid", params, units="uT")
    np.testing.assert_allclose(cal.apply([2.0, 1.0, 1.0]), [2.0, 1.0, 1.0])
    assert cal.params == params


def test_bad_params_rejected() -> None:
    with pytest.raises(TrimagInputError, match="missing"):
        Ellipsoid.from_dict({"w11": 1.0})
    with pytest.raises(TrimagInputError, match="unknown model"):
        get_model("sphere")
    assert "ellipsoid" in available_models()


def test_every_model_declares_the_kind_of_each_parameter():
    """Reports and the generic estimator checks read the declared kinds (no guessing from names): every
    parameter has one of the known kinds, and e.g. scalar9's ``beta`` is an angle, ``b1`` an offset."""
    from trimag.models import MODELS, get_model
    from trimag.models.base import PARAM_KINDS

    for name in MODELS:
        cls = get_model(name)
        assert set(cls.kinds) == set(cls.param_names()), name
        assert set(cls.kinds.values()) <= set(PARAM_KINDS), name
    scalar9 = get_model("scalar9")
    assert (scalar9.kind_of("beta"), scalar9.kind_of("b1"), scalar9.kind_of("k1")) == ("angle", "offset", "gain")
    assert get_model("interference12").kind_of("c2") == "offset"
