"""check_field: validation of every field array that enters trimag."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from trimag.errors import TrimagInputError
from trimag.validation import check_field


def test_huge_finite_values_are_refused_and_non_finite_ones_are_caught_whatever_their_sum() -> None:
    big = np.ones((10, 3))
    big[:2, 0] = 1e308  # the sum overflows to inf, yet every value is finite: not a reading (issue 33, item 7)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(TrimagInputError, match="not a magnetometer reading"):
            check_field(big)
        assert check_field(np.full((10, 3), 1e150)).shape == (10, 3)  # large, finite, and its squares too
    for bad in (np.nan, np.inf, -np.inf):
        arr = np.ones((10, 3))
        arr[7, 2] = bad
        with pytest.raises(TrimagInputError, match="1 row\\(s\\) with NaN or inf \\(first at row 7\\)"):
            check_field(arr)
    arr = np.ones((10, 3))
    arr[3, 0], arr[4, 1] = np.inf, -np.inf  # inf - inf: a NaN sum
    with pytest.raises(TrimagInputError, match="2 row"):
        check_field(arr)


def test_float64_c_ordered_input_is_a_read_only_view_and_anything_else_a_copy() -> None:
    B = np.random.default_rng(0).normal(size=(50, 3))
    view = check_field(B)
    assert np.shares_memory(view, B) and not view.flags.writeable and B.flags.writeable
    with pytest.raises(ValueError, match="read-only"):
        view[0, 0] = 1.0  # the caller's array cannot be written through it
    for other in (np.asfortranarray(B), B.astype(np.float32), B[::2], B.tolist()):
        arr = check_field(other)
        assert arr.flags.c_contiguous and arr.dtype == np.float64 and arr.flags.writeable
        assert not isinstance(other, np.ndarray) or not np.shares_memory(arr, other)


# ------------------------------------------------------------------ wild rows (issue 33, item 7)
def _sphere(n: int = 600, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    return 48000.0 * u / np.linalg.norm(u, axis=1, keepdims=True) + [900.0, -300.0, 400.0]


def test_a_wild_row_is_named_not_fitted() -> None:
    """One row 1000x the others gave "condition number inf" and advice to turn the sensor; 1e308 a LinAlgError."""
    from trimag.validation import wild_rows

    B = _sphere()
    B[123] *= 1000.0
    assert np.flatnonzero(wild_rows(B)).tolist() == [123]
    with pytest.raises(TrimagInputError, match=r"1 row\(s\) .*row 123.*\d+x the median"):
        check_field(B)
    B = _sphere()
    B[[7, 8]] = 1e308
    with pytest.raises(TrimagInputError, match=r"2 row\(s\) .*row 7"):
        check_field(B)
    assert not wild_rows(_sphere()).any()
    assert not wild_rows(np.zeros((20, 3))).any()  # a stuck sensor is not wild (it is refused elsewhere)


def test_the_wild_row_screen_keeps_real_logs_whatever_their_iron() -> None:
    """Hard iron as large as the field (|B| from 0 to 2F), soft iron of 10:1 gains: nothing is wild."""
    from trimag.validation import wild_rows

    u = _sphere(5000) - [900.0, -300.0, 400.0]
    assert not wild_rows(u + u[0]).any()  # hard iron = the field: |B| in [0, 2F]
    assert not wild_rows(u * [10.0, 1.0, 1.0] + [3000.0, 0.0, 0.0]).any()
    assert check_field(u * [10.0, 1.0, 1.0]).shape == (5000, 3)
