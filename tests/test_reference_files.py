"""Calibration files written by an earlier trimag still read, and still correct data the same (issue 24, item 6).

``tests/data/calibrations/`` holds one calibration file per registered error model and one Tolles–Lawson
compensation file, written by ``tests/data/calibrations/make.py`` from fixed-seed simulated data, each with a few
raw rows (``NAME.in.csv``) and what ``apply`` gave for them when the file was written (``NAME.out.csv``). Today's
code must accept each file's format version, read it, and map ``in`` to ``out`` to 1e-9 relative. A failure here
means the JSON schema or ``apply``'s maths changed in a way that changes what the files users already have do: fix
the code (or add a migration with a new format version), do not regenerate the files to make it pass.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from numpy.typing import NDArray

from trimag import Calibration
from trimag.aircraft.compensation import COMPENSATION_FORMAT_VERSION, ScalarCompensation
from trimag.calibration import FORMAT_VERSION
from trimag.cli import main as trimag_main
from trimag.models import available_models

DATA = Path(__file__).resolve().parent / "data" / "calibrations"
COMPENSATION = "tolles-lawson"
REGRESSORS = "ellipsoid-regressors"  # an ellipsoid calibration with regressor terms (format 2.0.0)
MODELS = available_models()
RTOL = 1e-9


def read_rows(path: Path) -> NDArray[np.float64]:
    """A ``NAME.in.csv`` / ``NAME.out.csv`` file: a header, then numbers (each parsed exactly)."""
    return np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)


def assert_rows_close(actual: NDArray[np.float64], expected: NDArray[np.float64], what: str) -> None:
    """Every row within ``RTOL`` of the expected row's size (its norm): relative, yet defined for a component
    that happens to be near zero."""
    actual = np.asarray(actual, dtype=np.float64).reshape(len(expected), -1)
    expected = expected.reshape(len(expected), -1)
    assert actual.shape == expected.shape, f"{what}: shape {actual.shape}, expected {expected.shape}"
    scale = np.linalg.norm(expected, axis=1, keepdims=True)
    rel = np.abs(actual - expected) / scale
    assert np.all(rel <= RTOL), f"{what}: relative error up to {np.nanmax(rel):.3g} (> {RTOL:g})"


def _major(version: str) -> int:
    parts = version.split(".")
    assert len(parts) == 3 and all(p.isdigit() for p in parts), f"format_version {version!r} is not semver"
    return int(parts[0])


def test_every_registered_model_has_a_reference_file() -> None:
    """A newly registered model needs its reference file: ``python tests/data/calibrations/make.py``."""
    missing = [f"{name}{ext}" for name in [*MODELS, REGRESSORS, COMPENSATION]
               for ext in (".json", ".in.csv", ".out.csv") if not (DATA / f"{name}{ext}").is_file()]
    assert not missing, f"run `python tests/data/calibrations/make.py` to write {', '.join(missing)}"


@pytest.mark.parametrize("model", MODELS)
def test_calibration_file_reads_and_applies_as_written(model: str) -> None:
    path = DATA / f"{model}.json"
    data = json.loads(path.read_text(encoding="utf-8"))
    assert data["format"] == "trimag-calibration"
    assert _major(data["format_version"]) <= _major(FORMAT_VERSION), "a format this trimag does not accept"
    cal = Calibration.from_file(path)
    assert (cal.model, cal.units) == (model, "nT")
    raw, expected = read_rows(DATA / f"{model}.in.csv"), read_rows(DATA / f"{model}.out.csv")
    assert_rows_close(cal.apply(raw), expected, f"{model}: apply")
    # more than 1000 rows take the blocked path of apply: the same numbers
    assert_rows_close(cal.apply(np.tile(raw, (200, 1)))[-len(raw):], expected, f"{model}: apply of 1200 rows")
    assert_rows_close(cal.apply(expected, inverse=True), raw, f"{model}: apply(inverse=True)")
    # the model's named parameters in the file still mean the same correction
    from_params = Calibration.from_params(model, cal.params, units=cal.units)
    assert_rows_close(from_params.apply(raw), expected, f"{model}: Calibration.from_params(params)")
    # and today's writer gives a file today's reader maps the same way, bit for bit
    np.testing.assert_array_equal(Calibration.from_json(cal.to_json()).apply(raw), cal.apply(raw))


def test_compensation_file_reads_and_applies_as_written() -> None:
    path = DATA / f"{COMPENSATION}.json"
    data = json.loads(path.read_text(encoding="utf-8"))
    assert data["format"] == "trimag-compensation"
    assert _major(data["format_version"]) <= _major(COMPENSATION_FORMAT_VERSION)
    comp = ScalarCompensation.from_file(path)
    rows, expected = read_rows(DATA / f"{COMPENSATION}.in.csv"), read_rows(DATA / f"{COMPENSATION}.out.csv")
    vector, scalar = rows[:, 1:4], rows[:, 4]
    assert_rows_close(comp.interference(vector, scalar), expected[:, 0], "Tolles–Lawson interference")
    assert_rows_close(comp.apply(vector, scalar), expected[:, 1], "Tolles–Lawson compensated scalar")
    np.testing.assert_array_equal(ScalarCompensation.from_json(comp.to_json()).apply(vector, scalar),
                                  comp.apply(vector, scalar))


def test_calibration_file_with_regressor_terms_reads_and_applies_as_written() -> None:
    """Format 2.0.0: the offset moves with the rows' ``current`` and ``temperature`` (docs/vehicle.md)."""
    data = json.loads((DATA / f"{REGRESSORS}.json").read_text(encoding="utf-8"))
    assert _major(data["format_version"]) == 2 and data["regressors"]["names"] == ["current", "temperature"]
    cal = Calibration.from_file(DATA / f"{REGRESSORS}.json")
    rows = read_rows(DATA / f"{REGRESSORS}.in.csv")
    raw, u = rows[:, :3], {"current": rows[:, 3], "temperature": rows[:, 4]}
    expected = read_rows(DATA / f"{REGRESSORS}.out.csv")
    assert_rows_close(cal.apply(raw, regressors=u), expected, "ellipsoid with regressors: apply")
    assert_rows_close(cal.apply(raw, regressors=rows[:, 3:]), expected, "ellipsoid with regressors: (N, m) array")
    assert_rows_close(cal.apply(expected, inverse=True, regressors=u), raw, "ellipsoid with regressors: inverse")
    back = Calibration.from_json(cal.to_json())
    assert json.loads(back.to_json())["format_version"] == data["format_version"]
    np.testing.assert_array_equal(back.apply(raw, regressors=u), cal.apply(raw, regressors=u))


@pytest.mark.parametrize("name", [*MODELS, REGRESSORS, COMPENSATION])
def test_trimag_apply_on_the_reference_rows(name: str, tmp_path: Path) -> None:
    """The same through the command a user runs: ``trimag apply FILE NAME.in.csv -o OUT.csv``."""
    out = tmp_path / "out.csv"
    assert trimag_main(["apply", str(DATA / f"{name}.json"), str(DATA / f"{name}.in.csv"), "-o", str(out),
                        "-q"]) == 0
    table = pd.read_csv(out)
    expected = read_rows(DATA / f"{name}.out.csv")
    if name == COMPENSATION:
        assert_rows_close(table["scalar_compensated"].to_numpy(), expected[:, 1], f"trimag apply {name}")
    else:
        assert_rows_close(table[["bx_cal", "by_cal", "bz_cal"]].to_numpy(), expected, f"trimag apply {name}")
