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
