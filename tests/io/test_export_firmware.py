"""Exports write everything a fit found, and only numbers (issue 30 item 4; issue 33 item 3).

- A firmware-space fit (``fit --target``) exports exactly its parameters (orientation, offsets, matrix, motor term
  and its type); a general calibration's rotation and current/throttle terms become ``COMPASS_ORIENT`` /
  ``COMPASS_MOT`` + ``COMPASS_MOTCT`` and ``CAL_MAGn_ROT`` / ``CAL_MAGn_xCOMP`` + ``CAL_MAG_COMP_TYP``; every
  writer's parameters, put through the firmware's formula in its order, give what ``Calibration.apply`` gives.
- What the firmware cannot load (out of limits, a rotation it cannot represent, a term it does not have, a unit it
  does not use) is refused (exit 2, no file), naming the parameter and the limit.
- No text of the calibration file reaches an output: each output loads in the target's own parser (pymavlink's
  ``.param`` reader, ``yaml.safe_load``, ``json``, a C compiler, ``scipy.io.loadmat``) with exactly the numbers.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from trimag.calibration import Calibration
from trimag.errors import TrimagInputError
from trimag.io.export import export_calibration, export_calibrations
from trimag.models.firmware import ArduPilotCompass, PX4Magnetometer, rotation_matrix

from _helpers import run_trimag

RNG = np.random.default_rng(11)
RAW_mG = RNG.normal(size=(100, 3)) * 400.0 + [50.0, -30.0, 80.0]
AMPS = RNG.uniform(0.0, 30.0, 100)


def _param_reader(path: Path) -> dict[str, float]:
    """pymavlink's own .param loader (MAVProxy's `param load`)."""
    from pymavlink.mavparm import MAVParmDict

    params = MAVParmDict()
    assert params.load(str(path))
    return {str(k): float(v) for k, v in params.items()}


def _firmware_fit_calibration(target: str = "ardupilot") -> Calibration:
    """A calibration as `trimag fit --target` writes it: W, b and a current term with the exact parameters."""
    from trimag.fields.attitude import body_field
    from trimag.simulate import current_profile
    from trimag.vehicle.firmware import firmware_calibration, fit_firmware

    truth = (ArduPilotCompass(orientation=6, offsets=[120.0, -80.0, 40.0], scale=1.05, diagonal=[1.02, 0.97, 1.01],
                              offdiagonal=[0.02, -0.01, 0.03], motor=[2.0, -1.5, 3.0], motor_type="current")
             if target == "ardupilot" else
             PX4Magnetometer(orientation=2, offsets=[0.12, -0.08, 0.04], diagonal=[1.07, 1.02, 1.06],
                             offdiagonal=[0.02, -0.01, 0.03], motor=[-0.3, 0.5, 1.1], motor_type="current"))
    unit = 1.0 if target == "ardupilot" else 1e-3
    n = 1500
    rng = np.random.default_rng(1)
    att = Rotation.from_euler("ZYX", np.column_stack([rng.uniform(0, 360, n), rng.uniform(-40, 40, n),
                                                      rng.uniform(-40, 40, n)]), degrees=True)
    amps = current_profile(n, 2, max_current=30.0)
    h = body_field(att, np.array([200.0, 10.0, 450.0]) * unit)
    raw = truth.uncorrect(h, amps) + rng.normal(0, 1.0 * unit, (n, 3))
    fit = fit_firmware(target, raw, field_body=h, motor_values={"current": amps})
    return firmware_calibration(fit, units=truth.unit, motor_channel="current_A")


def test_a_firmware_fit_exports_its_orientation_motor_term_and_type_through_the_formula(tmp_path: Path):
    cal = _firmware_fit_calibration("ardupilot")
    exp = export_calibration(cal, "ardupilot", instance=1)
    p = exp.parameters
    assert p["COMPASS_ORIENT2"] == 6 and p["COMPASS_MOTCT"] == 2
    compass = ArduPilotCompass.from_parameters({**p, "COMPASS_EXTERN2": 1}, 1)
    firmware = compass.correct(RAW_mG, AMPS)  # AP_Compass_Backend: rotate, OFS, SCALE, DIA/ODI, + MOT x current
    assert np.allclose(firmware, cal.apply(RAW_mG, regressors={"current_A": AMPS}), rtol=1e-9, atol=1e-6)
    path = tmp_path / "compass.param"
    path.write_text(exp.text)
    assert _param_reader(path) == pytest.approx(p)


def test_px4_export_writes_rot_comp_and_comp_typ_through_magnetometer_correct():
    cal = _firmware_fit_calibration("px4")
    p = export_calibration(cal, "px4", instance=1).parameters
    assert p["CAL_MAG1_ROT"] == 2 and p["CAL_MAG_COMP_TYP"] == 2 and "CAL_MAG1_ZCOMP" in p
    compass = PX4Magnetometer.from_parameters(p, 1)
    raw_G = RAW_mG / 1000.0
    assert np.allclose(compass.correct(raw_G, AMPS), cal.apply(raw_G, regressors={"current_A": AMPS}), atol=1e-9)


def test_a_general_calibrations_rotation_and_current_term_become_orient_and_mot():
    R = rotation_matrix("ardupilot", 2)  # the sensor is mounted yawed 90 deg
    W = np.array([[1.03, 0.02, 0.0], [0.02, 0.98, -0.01], [0.0, -0.01, 1.01]]) @ R
    k = np.array([[-0.5, 0.2, 0.4]])  # mG per A, subtracted from the raw reading
    cal = Calibration.from_matrix_offset(W, [30.0, -20.0, 10.0], units="mG", model="interference12",
                                         regressors={"names": ["current_A"], "means": [10.0], "coefficients": k})
    for target, unit in (("ardupilot", 1.0), ("px4", 1e-3)):
        exp = export_calibration(cal, target)
        klass = ArduPilotCompass if target == "ardupilot" else PX4Magnetometer
        compass = klass.from_parameters({**exp.parameters, "COMPASS_EXTERNAL": 1}, 0)
        assert compass.orientation == 2 and compass.motor_type == "current"
        expected = cal.apply(RAW_mG, regressors={"current_A": AMPS}) * unit
        assert np.allclose(compass.correct(RAW_mG * unit, AMPS), expected, rtol=1e-9, atol=1e-6 * unit)


def test_what_the_firmware_cannot_load_is_refused_naming_parameter_and_limit(tmp_path: Path):
    # the finding: a wrong reference made COMPASS_DIA_X 927, written with exit 0
    wrong = Calibration.from_matrix_offset(np.eye(3) * 927.0, [1.0, 2.0, 3.0], units="mG")
    with pytest.raises(TrimagInputError, match=r"COMPASS_DIA_X = 927 is outside \(0\.2, 5\)"):
        export_calibration(wrong, "ardupilot")
    big = Calibration.from_matrix_offset(np.eye(3), [300.0, 0.0, 0.0], units="uT")
    with pytest.raises(TrimagInputError, match=r"COMPASS_OFFS_MAX = 1800"):
        export_calibration(big, "ardupilot")
    tilted = Calibration.from_matrix_offset(Rotation.from_euler("z", 20, degrees=True).as_matrix(), [1.0, 2.0, 3.0],
                                            units="mG", model="interference12")
    with pytest.raises(TrimagInputError, match=r"20\.0 deg from the nearest standard orientation"):
        export_calibration(tilted, "px4")
    temp = Calibration.from_matrix_offset(np.eye(3), [1.0, 2.0, 3.0], units="mG",
                                          regressors={"names": ["temperature_C"], "means": [20.0],
                                                      "coefficients": [[0.1, 0.0, 0.0]]})
    with pytest.raises(TrimagInputError, match=r"no temperature_C term"):
        export_calibration(temp, "ardupilot")
    cal_path = wrong.to_file(tmp_path / "cal.json")
    out = tmp_path / "compass.param"
    r = run_trimag("export", cal_path, "--to", "ardupilot", "-o", out)
    assert r.returncode == 2 and not out.exists() and "COMPASS_DIA_X" in r.stderr


def test_one_file_for_several_compasses_and_a_conflicting_global_parameter_is_refused():
    cal = _firmware_fit_calibration("ardupilot")
    plain = Calibration.from_matrix_offset(np.eye(3), [10.0, 0.0, 0.0], units="mG")
    exp = export_calibrations([(cal, 0), (plain, 1)], "ardupilot")
    assert "COMPASS_OFS_X" in exp.parameters and exp.parameters["COMPASS_OFS2_X"] == -10.0
    assert exp.text.count("COMPASS_MOTCT") == 1
    throttle = Calibration.from_matrix_offset(np.eye(3), [1.0, 0.0, 0.0], units="mG",
                                              regressors={"names": ["throttle"], "means": [0.5],
                                                          "coefficients": [[1.0, 0.0, 0.0]]})
    with pytest.raises(TrimagInputError, match="COMPASS_MOTCT"):
        export_calibrations([(cal, 0), (throttle, 1)], "ardupilot")
    with pytest.raises(TrimagInputError, match="instance 2 twice"):
        export_calibrations([(plain, 1), (plain, 1)], "ardupilot")


# ------------------------------------------------------------------ issue 33 item 3: numbers only
INJECTED = {"created": "x\nCOMPASS_USE,0\n#", "method": "ml */ int evil; /* \r\x1b[2J"}


def _injected(tmp_path: Path) -> Path:
    data = Calibration.from_matrix_offset(np.diag([1.02, 0.98, 1.0]), [12.0, -7.0, 20.0], units="uT").as_dict()
    data.update(INJECTED)
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(data))
    return path


def _no_injection(text: str) -> None:
    assert "COMPASS_USE" not in text and "evil" not in text and "\x1b" not in text and "\r" not in text
    assert all(line.count("*/") <= (1 if line.rstrip().endswith("*/") else 0) for line in text.splitlines())


def test_ardupilot_and_px4_files_carry_no_text_of_the_calibration(tmp_path: Path):
    cal = Calibration.from_file(_injected(tmp_path))
    exp = export_calibration(cal, "ardupilot")
    _no_injection(exp.text)
    path = tmp_path / "c.param"
    path.write_text(exp.text)
    assert set(_param_reader(path)) == set(exp.parameters)
    px4 = export_calibration(cal, "px4").text
    _no_injection(px4)
    commands = [ln for ln in px4.splitlines() if ln and not ln.startswith("#")]
    assert all(ln.split()[:2] == ["param", "set"] and len(ln.split()) == 4 for ln in commands)


def test_c_header_compiles_with_the_numbers(tmp_path: Path):
    gcc = shutil.which("gcc")
    if gcc is None:
        pytest.skip("gcc not installed")
    cal = Calibration.from_file(_injected(tmp_path))
    header = export_calibration(cal, "c-header").text
    _no_injection(header)
    (tmp_path / "mag_cal.h").write_text(header)
    (tmp_path / "main.c").write_text(
        '#include <stdio.h>\n#include "mag_cal.h"\nint main(void) { printf("%.9g %.9g %s\\n", '
        "MAG_CAL_OFFSET[0], MAG_CAL_MATRIX[1][1], MAG_CAL_UNIT); return 0; }\n")
    build = subprocess.run([gcc, "-Wall", "-Werror", "-o", str(tmp_path / "main"), str(tmp_path / "main.c")],
                           capture_output=True, text=True)
    assert build.returncode == 0, build.stderr
    out = subprocess.run([str(tmp_path / "main")], capture_output=True, text=True).stdout.split()
    assert float(out[0]) == pytest.approx(12.0) and float(out[1]) == pytest.approx(0.98) and out[2] == "uT"


def test_yaml_and_json_load_with_exactly_the_numbers(tmp_path: Path):
    import yaml

    cal = Calibration.from_file(_injected(tmp_path))
    text = export_calibration(cal, "ros-yaml").text
    _no_injection(text)
    d = yaml.safe_load(text)["magnetometer_calibration"]
    assert set(d) == {"unit", "offset", "matrix"} and d["offset"] == [12, -7, 20]
    j = json.loads(export_calibration(cal, "json").text)
    _no_injection(json.dumps(j))
    assert j["offset"] == [12.0, -7.0, 20.0]


def test_matlab_mat_file_loads_in_scipy_and_m_text_has_no_injection(tmp_path: Path):
    from scipy.io import loadmat

    cal_path = _injected(tmp_path)
    out = tmp_path / "cal.mat"
    r = run_trimag("export", cal_path, "--to", "matlab", "-o", out)
    assert r.returncode == 0, r.stderr
    mat = loadmat(str(out))
    cal = Calibration.from_file(cal_path)
    assert np.allclose((RAW_mG - mat["b"].ravel()) @ mat["A"], cal.apply(RAW_mG))
    text = export_calibration(cal, "matlab").text
    _no_injection(text)
    assert all(ln.startswith("%") or ln.startswith(("A = ", "b = ", "     ")) for ln in text.splitlines())


def _internal_fit_calibration(target: str) -> Calibration:
    """A firmware fit of an internal compass: its orientation is the board's (AHRS_ORIENTATION / SENS_BOARD_ROT)."""
    from trimag.fields.attitude import body_field
    from trimag.vehicle.firmware import firmware_calibration, fit_firmware

    unit = 1.0 if target == "ardupilot" else 1e-3
    klass = ArduPilotCompass if target == "ardupilot" else PX4Magnetometer
    truth = klass(orientation=4, offsets=np.array([60.0, -40.0, 30.0]) * unit)
    rng = np.random.default_rng(3)
    n = 800
    att = Rotation.from_euler("ZYX", np.column_stack([rng.uniform(0, 360, n), rng.uniform(-60, 60, n),
                                                      rng.uniform(-60, 60, n)]), degrees=True)
    h = body_field(att, np.array([200.0, 10.0, 450.0]) * unit)
    raw = truth.uncorrect(h) + rng.normal(0, 1.0 * unit, (n, 3))
    held = klass(orientation=4)
    fit = fit_firmware(target, raw, field_body=h, held=held, external=False, level="offsets")
    return firmware_calibration(fit, units=truth.unit)


def test_an_internal_px4_magnetometer_is_written_rot_minus_one_as_px4_saves_it():
    """PX4 rotates an internal magnetometer by SENS_BOARD_ROT and stores CAL_MAGn_ROT = -1 (ParametersSave): a
    board rotation written into CAL_MAGn_ROT is read as the sensor's own once the device is external."""
    exp = export_calibration(_internal_fit_calibration("px4"), "px4", instance=0)
    assert exp.parameters["CAL_MAG0_ROT"] == -1
    assert any("SENS_BOARD_ROT" in n for n in exp.notes)
    compass = PX4Magnetometer.from_parameters({**exp.parameters, "SENS_BOARD_ROT": 4}, 0)
    assert compass.orientation == 4


def test_an_internal_ardupilot_compass_gets_no_compass_orient():
    """ArduPilot ignores COMPASS_ORIENTn of an internal compass (AHRS_ORIENTATION rotates it): not written."""
    exp = export_calibration(_internal_fit_calibration("ardupilot"), "ardupilot", instance=0)
    assert "COMPASS_ORIENT" not in exp.parameters
    assert any("AHRS_ORIENTATION" in n for n in exp.notes)


def test_a_held_matrix_seen_in_a_new_orientation_is_written_without_rounding_noise():
    """A guard (the issue 30 notes saw `COMPASS_ODI_X,-2.55e-17` once; not reproduced on this path, which passes on
    the tree it was written on): the held identity, turned into the orientation the fit chose by rotation matrices
    whose cos(90 deg) is 6e-17, is written as exact zeros and ones."""
    from trimag.fields.attitude import body_field
    from trimag.vehicle.firmware import firmware_calibration, fit_firmware

    truth = ArduPilotCompass(orientation=6, offsets=[60.0, -40.0, 30.0], diagonal=[1.0, 1.0, 1.0])
    rng = np.random.default_rng(5)
    n = 800
    att = Rotation.from_euler("ZYX", np.column_stack([rng.uniform(0, 360, n), rng.uniform(-60, 60, n),
                                                      rng.uniform(-60, 60, n)]), degrees=True)
    h = body_field(att, np.array([200.0, 10.0, 450.0]))
    raw = truth.uncorrect(h) + rng.normal(0, 1.0, (n, 3))
    held = ArduPilotCompass(orientation=0, diagonal=[1.0, 1.0, 1.0], offdiagonal=[0.0, 0.0, 0.0])
    fit = fit_firmware("ardupilot", raw, field_body=h, held=held, level="offsets")
    p = export_calibration(firmware_calibration(fit, units="mG"), "ardupilot").parameters
    assert p["COMPASS_ORIENT"] == 6
    assert [p[f"COMPASS_ODI_{a}"] for a in "XYZ"] == [0.0, 0.0, 0.0], p
    assert [p[f"COMPASS_DIA_{a}"] for a in "XYZ"] == [1.0, 1.0, 1.0], p


def test_parameters_the_logs_firmware_lacks_are_not_written():
    """Unseen ArduCopter 3.4.4 / 3.3-dev / 3.6 logs: COMPASS_SCALE (and DIA/ODI, MOT) lines were written for firmware
    that has no such parameter (a GCS refuses or ignores them; the offsets were fitted with them)."""
    from trimag.vehicle.firmware import firmware_calibration, fit_firmware

    raw, h = _internal_like_flight()
    for absent, gone in ((("scale",), ["COMPASS_SCALE"]),
                         (("scale", "matrix", "motor"),
                          ["COMPASS_SCALE", "COMPASS_DIA", "COMPASS_ODI", "COMPASS_MOT"])):
        fit = fit_firmware("ardupilot", raw, field_body=h, absent=absent)
        p = export_calibration(firmware_calibration(fit, units="mG"), "ardupilot").parameters
        assert not [k for k in p if k.startswith(tuple(gone))], p
        assert "COMPASS_OFS_X" in p


def _internal_like_flight() -> tuple[np.ndarray, np.ndarray]:
    from trimag.fields.attitude import body_field

    truth = ArduPilotCompass(orientation=0, offsets=[60.0, -40.0, 30.0], diagonal=[1.03, 0.98, 1.0],
                             offdiagonal=[0.01, 0.0, -0.02], scale=1.1)
    rng = np.random.default_rng(8)
    n = 900
    att = Rotation.from_euler("ZYX", np.column_stack([rng.uniform(0, 360, n), rng.uniform(-60, 60, n),
                                                      rng.uniform(-60, 60, n)]), degrees=True)
    h = body_field(att, np.array([200.0, 10.0, 450.0]))
    return truth.uncorrect(h) + rng.normal(0, 1.0, (n, 3)), h
