"""check_field: validation of every field array that enters trimag."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from trimag.errors import TrimagInputError
from trimag.validation import check_field


def test_huge_finite_values_pass_and_non_finite_ones_are_caught_whatever_their_sum() -> None:
    big = np.ones((10, 3))
    big[:2, 0] = 1e308  # the sum overflows to inf, yet every value is finite
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert check_field(big).shape == (10, 3)
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
