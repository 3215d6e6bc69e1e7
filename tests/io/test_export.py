"""Firmware exports (issue 19): each writer's parameters, put through the firmware's own published formula, give
what :meth:`Calibration.apply` gives (to 1e-6 relative)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from trimag.calibration import Calibration
from trimag.errors import TrimagInputError
from trimag.io.export import export_calibration, symmetric_polar

from _helpers import run_trimag

RNG = np.random.default_rng(3)
RAW_uT = RNG.normal(size=(200, 3)) * 40.0 + np.array([12.0, -7.0, 20.0])


def _cal(symmetric: bool = True, units: str = "uT", model: str = "ellipsoid") -> Calibration:
    A = np.array([[1.05, 0.03, -0.02], [0.03, 0.96, 0.04], [-0.02, 0.04, 1.01]])
    if not symmetric:
        A = np.array([[1.05, 0.03, -0.02], [0.0, 0.96, 0.04], [0.0, 0.0, 1.01]])
    return Calibration.from_matrix_offset(A, [12.0, -7.0, 20.0], units=units, model=model)


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a - b).max() / np.abs(b).max())


def test_ardupilot_params_through_correct_field_equal_apply():
    cal = _cal()
    p = export_calibration(cal, "ardupilot").parameters
    # libraries/AP_Compass/AP_Compass_Backend.cpp, correct_field: mag += offsets; mag *= scale; mag = mat * mag
    ofs = np.array([p["COMPASS_OFS_X"], p["COMPASS_OFS_Y"], p["COMPASS_OFS_Z"]])
    M = np.array([[p["COMPASS_DIA_X"], p["COMPASS_ODI_X"], p["COMPASS_ODI_Y"]],
                  [p["COMPASS_ODI_X"], p["COMPASS_DIA_Y"], p["COMPASS_ODI_Z"]],
                  [p["COMPASS_ODI_Y"], p["COMPASS_ODI_Z"], p["COMPASS_DIA_Z"]]])
    raw_mG = RAW_uT * 10.0
    firmware = ((raw_mG + ofs) * p["COMPASS_SCALE"]) @ M.T
    assert _rel(firmware, cal.apply(RAW_uT) * 10.0) < 1e-6
    assert p["COMPASS_OFS_X"] == pytest.approx(-120.0)  # mGauss, added to the reading


def test_ardupilot_second_compass_names_and_param_file(tmp_path: Path):
    exp = export_calibration(_cal(), "ardupilot", instance=1)
    assert "COMPASS_OFS2_X" in exp.parameters and "COMPASS_DIA2_Z" in exp.parameters
    lines = [ln for ln in exp.text.splitlines() if not ln.startswith("#")]
    assert all(len(ln.split(",")) == 2 for ln in lines)  # NAME,VALUE as MAGFit's .param files


def test_px4_params_through_sensor_calibration_equal_apply():
    cal = _cal()
    p = export_calibration(cal, "px4", instance=0).parameters
    # src/lib/sensor_calibration/Magnetometer.cpp: _rotation * (_scale * ((data + _power * _power_compensation)
    # - _offset)), _scale = [[XSCALE, XODIAG, YODIAG], [XODIAG, YSCALE, ZODIAG], [YODIAG, ZODIAG, ZSCALE]]
    off = np.array([p["CAL_MAG0_XOFF"], p["CAL_MAG0_YOFF"], p["CAL_MAG0_ZOFF"]])
    S = np.array([[p["CAL_MAG0_XSCALE"], p["CAL_MAG0_XODIAG"], p["CAL_MAG0_YODIAG"]],
                  [p["CAL_MAG0_XODIAG"], p["CAL_MAG0_YSCALE"], p["CAL_MAG0_ZODIAG"]],
                  [p["CAL_MAG0_YODIAG"], p["CAL_MAG0_ZODIAG"], p["CAL_MAG0_ZSCALE"]]])
    raw_G = RAW_uT / 100.0
    firmware = (raw_G - off) @ S.T
    assert _rel(firmware, cal.apply(RAW_uT) / 100.0) < 1e-6
    assert p["CAL_MAG0_XOFF"] == pytest.approx(0.12)  # gauss, subtracted


def test_non_symmetric_matrix_exports_polar_factor_with_same_magnitude():
    cal = _cal(symmetric=False)
    exp = export_calibration(cal, "ardupilot")
    p = exp.parameters
    M = np.array([[p["COMPASS_DIA_X"], p["COMPASS_ODI_X"], p["COMPASS_ODI_Y"]],
                  [p["COMPASS_ODI_X"], p["COMPASS_DIA_Y"], p["COMPASS_ODI_Z"]],
                  [p["COMPASS_ODI_Y"], p["COMPASS_ODI_Z"], p["COMPASS_DIA_Z"]]])
    ofs = np.array([p[f"COMPASS_OFS_{a}"] for a in "XYZ"])
    firmware = (RAW_uT * 10.0 + ofs) @ M.T
    assert _rel(np.linalg.norm(firmware, axis=1), np.linalg.norm(cal.apply(RAW_uT) * 10.0, axis=1)) < 1e-6
    assert any("symmetric polar factor" in n for n in exp.notes)
    P, angle = symmetric_polar(np.asarray(cal.matrix))
    assert np.allclose(P, P.T) and angle > 0.5


def test_attitude_fit_rotation_is_refused_for_autopilots_but_kept_elsewhere():
    R = np.array([[np.cos(0.1), -np.sin(0.1), 0], [np.sin(0.1), np.cos(0.1), 0], [0, 0, 1]])
    cal = Calibration.from_matrix_offset(R, [1.0, 2.0, 3.0], units="nT", model="interference12")
    with pytest.raises(TrimagInputError, match="heading"):
        export_calibration(cal, "px4")
    exp = export_calibration(cal, "matlab")
    assert "A = [" in exp.text


def test_matlab_magcal_convention_equals_apply():
    cal = _cal(symmetric=False)
    ns: dict[str, np.ndarray] = {}
    text = export_calibration(cal, "matlab").text
    for name in ("A", "b"):
        line = text.split(f"{name} = [")[1].split("];")[0]
        ns[name] = np.array([[float(v) for v in row.split()] for row in line.split(";")])
    # MATLAB magcal: C = (D - b) * A
    assert _rel((RAW_uT - ns["b"]) @ ns["A"], cal.apply(RAW_uT)) < 1e-9


def test_json_c_header_ros_yaml_carry_full_matrix_and_offset():
    cal = _cal(symmetric=False)
    d = json.loads(export_calibration(cal, "json").text)
    assert _rel((RAW_uT - np.array(d["offset"])) @ np.array(d["matrix"]).T, cal.apply(RAW_uT)) < 1e-12
    header = export_calibration(cal, "c-header").text
    assert "MAG_CAL_OFFSET[3]" in header and "MAG_CAL_MATRIX[3][3]" in header and '"uT"' in header
    yaml_text = export_calibration(cal, "ros-yaml").text
    assert "offset: [12, -7, 20]" in yaml_text


def test_limits_are_refused_and_counts_refused():
    big = Calibration.from_matrix_offset(np.eye(3), [300.0, 0.0, 0.0], units="uT")
    with pytest.raises(TrimagInputError, match="COMPASS_OFFS_MAX"):  # issue 30: refused, no longer a warning
        export_calibration(big, "ardupilot")
    with pytest.raises(TrimagInputError, match="unit"):
        export_calibration(Calibration.from_matrix_offset(np.eye(3), [1, 2, 3], units="counts"), "ardupilot")


def test_cli_export(tmp_path: Path):
    cal_path = _cal().to_file(tmp_path / "cal.json")
    out = tmp_path / "compass.param"
    r = run_trimag("export", cal_path, "--to", "ardupilot", "--instance", "2", "-o", out)
    assert r.returncode == 0, r.stderr
    assert "COMPASS_OFS2_X,-120" in out.read_text()
    r = run_trimag("export", cal_path, "--to", "nope", "-o", out)
    assert r.returncode == 2


@pytest.mark.parametrize("entry", ["method", "trimag_version"])
def test_a_trailing_newline_in_method_or_version_cannot_split_the_c_header_comment(tmp_path: Path, entry: str):
    """Issue 41, item 16: ``"method": "given\\n"`` passed the check (``$`` matches before a final newline) and broke
    the header's comment line in two, the second half C code."""
    data = json.loads(_cal().to_json())
    data[entry] = {"method": "given", "trimag_version": "0.1.0"}[entry] + "\n"
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(data))
    text = export_calibration(Calibration.from_file(path), "c-header").text
    lines = text.splitlines()
    assert lines[0].startswith("/* trimag ") and lines[0].endswith(" */"), lines[:2]
    assert all(line.startswith(("/*", "#", "static", "    {", "};")) for line in lines), lines
