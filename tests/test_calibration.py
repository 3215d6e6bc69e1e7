"""The Calibration result: construction, apply/inverse/composition, JSON round trip, versioning."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from trimag import Calibration
from trimag.calibration import FORMAT_VERSION
from trimag.errors import CalibrationFormatError, TrimagInputError, UnitMismatchError

finite = st.floats(min_value=-10, max_value=10, allow_nan=False, allow_infinity=False)


def _well_conditioned(m: np.ndarray) -> np.ndarray:
    # strictly diagonally dominant (diagonal >= 2.1, off-diagonal row sums <= 1.8), so always invertible: the
    # earlier `3 I + 0.5 m` could draw a singular matrix, which Calibration rightly refuses
    return np.eye(3) * 3.0 + m * 0.09


@st.composite
def calibrations(draw: st.DrawFn) -> Calibration:
    m = draw(arrays(np.float64, (3, 3), elements=finite))
    b = draw(arrays(np.float64, (3,), elements=st.floats(-1e5, 1e5, allow_nan=False)))
    return Calibration.from_matrix_offset(_well_conditioned(m), b, units="nT", model="affine")


@given(calibrations())
@settings(max_examples=60, deadline=None)
def test_json_round_trip_is_exact(cal: Calibration) -> None:
    back = Calibration.from_json(cal.to_json())
    assert back == cal
    B = np.random.default_rng(0).normal(size=(50, 3)) * 1e4
    assert np.array_equal(back.apply(B), cal.apply(B))


@given(calibrations(), arrays(np.float64, (20, 3), elements=st.floats(-1e5, 1e5, allow_nan=False)))
@settings(max_examples=60, deadline=None)
def test_inverse_undoes_apply(cal: Calibration, B: np.ndarray) -> None:
    np.testing.assert_allclose(cal.inv().apply(cal.apply(B)), B, atol=1e-6 * (1 + np.abs(B).max()))
    np.testing.assert_allclose(cal.apply(cal.apply(B), inverse=True), B, atol=1e-6 * (1 + np.abs(B).max()))


@given(calibrations(), calibrations())
@settings(max_examples=40, deadline=None)
def test_composition_order(a: Calibration, b: Calibration) -> None:
    B = np.random.default_rng(1).normal(size=(10, 3)) * 100
    np.testing.assert_allclose((a * b).apply(B), a.apply(b.apply(B)), rtol=1e-9, atol=1e-6)


def test_apply_shapes() -> None:
    cal = Calibration.from_matrix_offset(np.diag([2.0, 1.0, 0.5]), [1.0, 2.0, 3.0])
    assert cal.apply([1.0, 2.0, 3.0]).shape == (3,)
    assert cal.apply(np.ones((1, 3))).shape == (1, 3)
    assert cal.apply(np.ones((7, 3))).shape == (7, 3)
    np.testing.assert_allclose(cal.apply([2.0, 3.0, 4.0]), [2.0, 1.0, 0.5])
    with pytest.raises(TrimagInputError, match="shape"):
        cal.apply(np.ones((4, 2)))


def test_immutable() -> None:
    cal = Calibration.from_matrix_offset(np.eye(3), [0, 0, 0])
    with pytest.raises(ValueError):
        cal.matrix[0, 0] = 5.0
    with pytest.raises(AttributeError):
        cal.units = "nT"  # type: ignore[misc]


def test_singular_matrix_refused() -> None:
    with pytest.raises(TrimagInputError, match="singular"):
        Calibration.from_matrix_offset(np.zeros((3, 3)), [0, 0, 0])


def test_unit_mismatch_raises() -> None:
    cal = Calibration.from_matrix_offset(np.eye(3), [0, 0, 0], units="uT")
    cal.apply(np.ones(3), units="µT")
    with pytest.raises(UnitMismatchError, match="'uT'"):
        cal.apply(np.ones(3), units="nT")


def test_file_carries_required_entries(tmp_path) -> None:
    cal = Calibration.from_matrix_offset(np.eye(3) * 1.1, [1, 2, 3], units="G", model="ellipsoid", method="ml",
                                         stats={"n_used": 5})
    path = cal.to_file(tmp_path / "sub" / "cal.json")
    data = json.loads(path.read_text())
    for key in ("format_version", "trimag_version", "created", "model", "method", "units", "input_unit",
                "output_unit", "matrix", "offset", "params", "reference", "stats", "uncertainty", "diagnostics"):
        assert key in data
    assert data["format_version"] == FORMAT_VERSION
    assert not list(tmp_path.glob("sub/.*.tmp"))
    assert Calibration.from_file(path) == cal


def test_newer_major_version_refused() -> None:
    data = Calibration.from_matrix_offset(np.eye(3), [0, 0, 0]).as_dict()
    data["format_version"] = "3.0.0"  # 2.0.0 is the format of calibrations with regressor terms
    with pytest.raises(CalibrationFormatError, match="newer"):
        Calibration.from_dict(data)


def test_older_major_version_refused_with_reason() -> None:
    data = Calibration.from_matrix_offset(np.eye(3), [0, 0, 0]).as_dict()
    data["format_version"] = "0.3.0"
    with pytest.raises(CalibrationFormatError, match="older"):
        Calibration.from_dict(data)


def test_foreign_json_refused() -> None:
    with pytest.raises(CalibrationFormatError, match="not a trimag calibration"):
        Calibration.from_json('{"A": [[1,0,0],[0,1,0],[0,0,1]], "b": [0,0,0]}')
    with pytest.raises(CalibrationFormatError, match="not valid JSON"):
        Calibration.from_json("{nope")


def test_repr_rebuilds() -> None:
    cal = Calibration.from_matrix_offset(np.diag([1.5, 1.0, 0.25]), [1.0, -2.0, 0.5], units="nT", model="ellipsoid")
    rebuilt = eval(repr(cal), {"Calibration": Calibration})
    assert rebuilt.approx_equal(cal, atol=0)
    assert rebuilt.model == "ellipsoid"


@pytest.mark.parametrize(("matrix", "offset", "units", "words"), [
    (np.eye(3), [1e308, 0.0, 0.0], "nT", "offset"),               # applied and exported as 1e+308f (issue 41, item 8)
    (np.eye(3), [2e7, 0.0, 0.0], "nT", "offset"),                 # 20 mT: no Earth-field magnetometer reads that
    (np.eye(3), [0.0, 3e5, 0.0], "G", "offset"),
    (np.eye(3), [1e13, 0.0, 0.0], "counts", "offset"),
    (1e300 * np.eye(3), [1.0, 2.0, 3.0], "nT", "matrix"),         # overflow warnings on apply
    (np.diag([1.0, 1.0, 1e-9]), [1.0, 2.0, 3.0], "nT", "matrix"),  # flattens one axis 1e9 times
    (np.diag([1.0, 1.0, 1e-7]), [1.0, 2.0, 3.0], "uT", "matrix"),  # invertible, condition number 1e7
])
def test_a_calibration_file_out_of_physical_range_is_refused_on_load(tmp_path, matrix, offset, units, words) -> None:
    """Issue 41, item 8: a calibration file's numbers are checked on load (finite, an offset within a magnetometer's
    range for its unit, a well-conditioned invertible matrix of a plausible gain); the command exits 2 with one line
    and no numpy warning, nothing written."""
    from _helpers import run_trimag

    data = json.loads(Calibration.from_matrix_offset(np.eye(3), [1, 2, 3], units=units).to_json())
    data["matrix"], data["offset"] = np.asarray(matrix, dtype=float).tolist(), list(offset)
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(data))
    with pytest.raises(CalibrationFormatError, match=words):
        Calibration.from_file(path)
    out = tmp_path / "cal.h"
    r = run_trimag("export", path, "--to", "c-header", "-o", out)
    assert r.returncode == 2 and not out.exists(), r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "Warning" not in r.stderr, r.stderr


def test_plausible_calibrations_still_load() -> None:
    """The bounds leave real calibrations alone: a counts calibration fitted to a unit sphere (gain 1e-6), a
    weak offset in gauss, a soft iron of condition number 20."""
    for matrix, offset, units in [(1e-6 * np.eye(3), [5e5, -2e5, 1e6], "counts"), (np.eye(3), [0.4, -0.2, 1.5], "G"),
                                  (np.diag([2.0, 1.0, 0.1]), [1200.0, -800.0, 300.0], "nT")]:
        cal = Calibration.from_matrix_offset(matrix, offset, units=units)
        assert Calibration.from_json(cal.to_json()).approx_equal(cal)


def test_a_number_of_5000_digits_in_a_calibration_file_is_refused_in_the_users_words(tmp_path):
    """Issue 41 item 4: Python refuses integers of more than 4300 digits with a ValueError that was not JSON's
    (exit 1, "use sys.set_int_max_str_digits()")."""
    from trimag.cli import main

    cal = Calibration.from_matrix_offset(np.eye(3), np.zeros(3), units="uT")
    text = cal.to_json().replace('"offset": [', '"offset": [' + "1" * 5000 + ", ", 1)
    assert text != cal.to_json()
    path = tmp_path / "cal.json"
    path.write_text(text)
    with pytest.raises(CalibrationFormatError, match="a number with more than 4300 digits"):
        Calibration.from_file(path)
    assert main(["export", str(path), "--to", "ardupilot", "-o", str(tmp_path / "x.param")]) == 2
    assert not (tmp_path / "x.param").exists()
