"""The firmwares' own parameters and formulas (issue 30; trimag.models.firmware): each ``correct`` is checked against
a line-by-line transcription of the firmware's code, in its order, and the rotation enums against the firmware's
own constants."""

from __future__ import annotations

import numpy as np
import pytest

from trimag.errors import TrimagInputError
from trimag.models.firmware import (
    ARDUPILOT_ROTATIONS,
    ArduPilotCompass,
    FirmwareCompass,
    PX4Magnetometer,
    euler_matrix,
    rotation_matrix,
)

RNG = np.random.default_rng(7)
RAW = RNG.normal(size=(50, 3)) * 300.0 + [40.0, -20.0, 100.0]
CURRENT = RNG.uniform(0.0, 30.0, 50)

AP = ArduPilotCompass(orientation=6, offsets=[120.0, -80.0, 40.0], scale=1.05, diagonal=[1.02, 0.97, 1.01],
                      offdiagonal=[0.02, -0.01, 0.03], motor=[2.0, -1.5, 3.0], motor_type="current")
PX4 = PX4Magnetometer(orientation=2, offsets=[0.12, -0.08, 0.04], diagonal=[1.07, 1.02, 1.06],
                      offdiagonal=[0.02, -0.01, 0.03], motor=[-0.3, 0.5, 1.1], motor_type="current")


def _rotate_ap(v: np.ndarray, roll: float, pitch: float, yaw: float) -> np.ndarray:
    """ArduPilot Vector3::rotate through Matrix3::from_euler (libraries/AP_Math/matrix3.cpp), written out."""
    cr, sr = np.cos(np.radians(roll)), np.sin(np.radians(roll))
    cp, sp = np.cos(np.radians(pitch)), np.sin(np.radians(pitch))
    cy, sy = np.cos(np.radians(yaw)), np.sin(np.radians(yaw))
    a = [cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy]
    b = [cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy]
    c = [-sp, sr * cp, cr * cp]
    return np.array([np.dot(a, v), np.dot(b, v), np.dot(c, v)])


def test_ardupilot_correct_is_correct_field_in_its_order():
    # AP_Compass_Backend::rotate_field then correct_field: rotate, += offsets, *= scale, = mat * mag, += mot * I
    p = AP.parameters(0)
    out = []
    for v, amps in zip(RAW, CURRENT, strict=True):
        mag = _rotate_ap(v, 0.0, 0.0, 270.0)  # COMPASS_ORIENT 6 = ROTATION_YAW_270
        mag = mag + np.array([p["COMPASS_OFS_X"], p["COMPASS_OFS_Y"], p["COMPASS_OFS_Z"]])
        mag = mag * p["COMPASS_SCALE"]
        mat = np.array([[p["COMPASS_DIA_X"], p["COMPASS_ODI_X"], p["COMPASS_ODI_Y"]],
                        [p["COMPASS_ODI_X"], p["COMPASS_DIA_Y"], p["COMPASS_ODI_Z"]],
                        [p["COMPASS_ODI_Y"], p["COMPASS_ODI_Z"], p["COMPASS_DIA_Z"]]])
        mag = mat @ mag
        mag = mag + np.array([p["COMPASS_MOT_X"], p["COMPASS_MOT_Y"], p["COMPASS_MOT_Z"]]) * amps
        out.append(mag)
    assert np.allclose(AP.correct(RAW, CURRENT), np.array(out), rtol=0, atol=1e-9)
    assert p["COMPASS_MOTCT"] == 2 and p["COMPASS_ORIENT"] == 6


def test_ardupilot_scale_outside_its_window_and_zero_diagonal_are_ignored_as_the_firmware_does():
    off = ArduPilotCompass(offsets=[10.0, 0.0, 0.0], scale=1.6, diagonal=[0.0, 0.0, 0.0])  # have_scale_factor false
    assert np.allclose(off.correct(RAW), RAW + np.array([10.0, 0.0, 0.0]))
    assert ArduPilotCompass(scale=0.0).effective_scale == 1.0


def test_px4_correct_is_magnetometer_correct_with_current_in_kA():
    # Magnetometer::Correct: _rotation * (_scale * ((data + _power * _power_compensation) - _offset)),
    # _power = current_a * 0.001 (VehicleMagnetometer::UpdatePowerCompensation, CAL_MAG_COMP_TYP 2)
    p = PX4.parameters(0)
    S = np.array([[p["CAL_MAG0_XSCALE"], p["CAL_MAG0_XODIAG"], p["CAL_MAG0_YODIAG"]],
                  [p["CAL_MAG0_XODIAG"], p["CAL_MAG0_YSCALE"], p["CAL_MAG0_ZODIAG"]],
                  [p["CAL_MAG0_YODIAG"], p["CAL_MAG0_ZODIAG"], p["CAL_MAG0_ZSCALE"]]])
    comp = np.array([p["CAL_MAG0_XCOMP"], p["CAL_MAG0_YCOMP"], p["CAL_MAG0_ZCOMP"]])
    off = np.array([p["CAL_MAG0_XOFF"], p["CAL_MAG0_YOFF"], p["CAL_MAG0_ZOFF"]])
    raw_G = RAW / 1000.0
    expected = np.array([_rotate_ap(S @ ((v + (amps * 0.001) * comp) - off), 0.0, 0.0, 90.0)
                         for v, amps in zip(raw_G, CURRENT, strict=True)])  # CAL_MAG0_ROT 2 = ROTATION_YAW_90
    assert np.allclose(PX4.correct(raw_G, CURRENT), expected, rtol=0, atol=1e-12)
    assert p["CAL_MAG_COMP_TYP"] == 2 and p["CAL_MAG0_ROT"] == 2


@pytest.mark.parametrize("compass", [AP, PX4], ids=["ardupilot", "px4"])
def test_uncorrect_inverts_correct_and_the_algebra_round_trips(compass: FirmwareCompass):
    raw = RAW / (1.0 if compass.unit == "mG" else 1000.0)
    assert np.allclose(compass.uncorrect(compass.correct(raw, CURRENT), CURRENT), raw, atol=1e-9)
    A, o, m = compass.algebra()
    back = type(compass).from_algebra(A, o, m, orientation=compass.orientation, motor_type=compass.motor_type)
    assert np.allclose(back.correct(raw, CURRENT), compass.correct(raw, CURRENT), atol=1e-9)
    # the shared algebra: R^T B (PX4) or B (ArduPilot) = A (u + o) + m x with u the raw in the firmware's frame
    u = raw @ compass.rotation.T if compass.target == "ardupilot" else raw
    B = compass.correct(raw, CURRENT)
    Bt = B if compass.target == "ardupilot" else B @ compass.rotation
    assert np.allclose(Bt, (u + o) @ A.T + CURRENT[:, None] * m, atol=1e-9)


def test_rotation_38_is_ardupilots_hard_coded_matrix_and_px4s_integer_angles():
    # libraries/AP_Math/vector3.cpp, ROTATION_ROLL_90_PITCH_68_YAW_293: the literal matrix
    exact = np.array([[0.143038972, 0.368776487, -0.918446381], [-0.332132778, -0.856289421, -0.395545503],
                      [-0.932323801, 0.361624570, 0.0]])
    assert np.allclose(rotation_matrix("ardupilot", 38), exact, atol=2e-6)
    px4 = rotation_matrix("px4", 38)
    angle = np.degrees(np.arccos((np.trace(px4 @ exact.T) - 1) / 2))
    assert 0.8 < angle < 0.9  # PX4's rot_lookup uses 68 / 293 degrees
    with pytest.raises(TrimagInputError, match=r"0\.\.40"):
        rotation_matrix("px4", 42)
    assert set(ARDUPILOT_ROTATIONS) == set(range(44))
    assert np.allclose(euler_matrix(0, 0, 90) @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])


def test_from_parameters_reads_a_logs_parameters_per_instance():
    params = {"COMPASS_OFS2_X": 10.0, "COMPASS_OFS2_Y": -5.0, "COMPASS_OFS2_Z": 3.0, "COMPASS_DIA2_X": 1.1,
              "COMPASS_DIA2_Y": 0.9, "COMPASS_DIA2_Z": 1.0, "COMPASS_ODI2_X": 0.01, "COMPASS_SCALE2": 1.02,
              "COMPASS_ORIENT2": 6, "COMPASS_EXTERN2": 1, "COMPASS_MOTCT": 2, "COMPASS_MOT2_Z": 4.0,
              "AHRS_ORIENTATION": 2}
    c = ArduPilotCompass.from_parameters(params, 1)
    assert c.orientation == 6 and c.motor_type == "current" and c.motor[2] == 4.0 and c.scale == 1.02
    assert ArduPilotCompass.from_parameters({**params, "COMPASS_EXTERN2": 0}, 1).orientation == 2  # internal
    assert c.parameters(1)["COMPASS_OFS2_X"] == 10.0
    px = PX4Magnetometer.from_parameters({"CAL_MAG1_ROT": -1, "SENS_BOARD_ROT": 4, "CAL_MAG1_XSCALE": 1.1,
                                          "CAL_MAG_COMP_TYP": 1}, 1)
    assert px.orientation == 4 and px.diagonal[0] == 1.1 and px.motor_type == "throttle"


def test_violations_name_the_parameter_and_the_limit():
    bad = ArduPilotCompass(offsets=[1500.0, -1200.0, 0.0], scale=1.7, diagonal=[5.5, 1.0, 1.0],
                           offdiagonal=[1.2, 0.0, 0.0], motor=[1200.0, 0.0, 0.0], motor_type="throttle")
    text = " | ".join(str(v) for v in bad.violations(instance=1))
    for expected in ("|COMPASS_OFS2_X..Z| = 1920.94", "COMPASS_OFFS_MAX = 1800", "COMPASS_DIA2_X = 5.5",
                     "COMPASS_ODI2_X = 1.2", "COMPASS_SCALE2 = 1.7", "COMPASS_MOT2_X = 1200"):
        assert expected in text
    assert not bad.violations(offsets_max=3000.0)[0].parameter.startswith("|")
    assert "CAL_MAG0_YSCALE" in str(PX4Magnetometer(diagonal=[1.0, 3.5, 1.0]).violations()[0])
    assert not AP.violations() and not PX4.violations()


def test_ardupilot_dia_all_zero_is_the_firmwares_no_matrix_not_a_violation():
    """Found on an unseen ArduCopter 3.3 log (erle-copter 218.BIN, COMPASS_DIA_X..Z = 0): ``correct_field`` applies
    the DIA/ODI matrix only when a DIA is non-zero, so all-zero DIA is the identity; every level that held it was
    called 'outside (0.2, 5)' and auto fell back to a level that fits the scale."""
    held = ArduPilotCompass(offsets=[10.0, -20.0, 30.0], diagonal=[0.0, 0.0, 0.0])
    assert held.violations() == []
    assert np.allclose(held.correct([[100.0, 0.0, 0.0]]), [[110.0, -20.0, 30.0]])
    one_zero = ArduPilotCompass(diagonal=[1.0, 0.0, 1.0])
    assert [v.parameter for v in one_zero.violations()][:1] == ["COMPASS_DIA_Y"]


def test_a_matrix_whose_mean_gain_is_beyond_compass_scale_keeps_the_rest_in_dia():
    """Same log: the full level's matrix has a mean diagonal of 1.505, which from_algebra put whole into
    COMPASS_SCALE (loadable up to 1.5), so the level was 'outside' although DIA (up to 5) can carry the rest."""
    A = np.array([[1.62, 0.02, 0.0], [0.02, 1.48, 0.01], [0.0, 0.01, 1.42]])
    compass = ArduPilotCompass.from_algebra(A, [5.0, 6.0, 7.0], np.zeros(3), orientation=0, motor_type=None)
    assert compass.violations() == []
    assert compass.scale == pytest.approx(1.5)
    raw = np.array([[100.0, -50.0, 300.0], [-200.0, 10.0, 40.0]])
    assert np.allclose(compass.correct(raw), (raw + np.array([5.0, 6.0, 7.0])) @ A.T)
