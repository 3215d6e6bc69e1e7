"""Firmware-space fits (issue 30, items 1 and 2; trimag.vehicle.firmware).

Simulated flights with known truth written in each firmware's own form (orientation, offsets, symmetric matrix,
current or throttle term): raw readings are the firmware's formula inverted (``uncorrect``) at the true attitudes,
plus 2 mGauss of sensor noise; the fit sees attitudes with 0.5 deg (roll, pitch) and 1 deg (yaw) errors, as an EKF
logs them. A second flight with its own attitudes and current profile judges the fitted parameters through the
firmware's formula against the noise floor (the true parameters on the same flight).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from trimag.errors import IdentifiabilityError, TrimagInputError
from trimag.fields.attitude import body_field, from_euler
from trimag.models.firmware import ArduPilotCompass, FirmwareCompass, PX4Magnetometer
from trimag.simulate import current_profile, random_attitudes
from trimag.vehicle.firmware import fit_firmware, level_table

FIELD_NED_mG = np.array([200.0, 10.0, 450.0])
NOISE_mG = 2.0
AP_TRUTH = ArduPilotCompass(orientation=6, offsets=[120.0, -80.0, 40.0], scale=1.05, diagonal=[1.02, 0.97, 1.01],
                            offdiagonal=[0.02, -0.01, 0.03], motor=[2.0, -1.5, 3.0], motor_type="current")
PX4_TRUTH = PX4Magnetometer(orientation=2, offsets=[0.12, -0.08, 0.04], diagonal=[1.07, 1.02, 1.06],
                            offdiagonal=[0.02, -0.01, 0.03], motor=[-0.03, 0.05, 0.11], motor_type="throttle")


def flight(n: int, seed: int, max_tilt_deg: float = 35.0, yaw_step_deg: float = 3.0) -> tuple[Rotation, Rotation]:
    """A flight's true attitudes (a random walk in yaw, pitch and roll within ``max_tilt_deg``) and the logged ones
    (0.5 deg roll/pitch and 1 deg yaw errors)."""
    rng = np.random.default_rng(seed)
    yaw = np.cumsum(rng.normal(0, yaw_step_deg, n)) % 360
    pitch = np.clip(np.cumsum(rng.normal(0, 2, n)), -max_tilt_deg, max_tilt_deg)
    roll = np.clip(np.cumsum(rng.normal(0, 2, n)), -max_tilt_deg, max_tilt_deg)
    true = Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll]), degrees=True)
    error = Rotation.from_rotvec(np.radians(rng.normal(0, [0.5, 0.5, 1.0], (n, 3))))
    return true, error * true


def throttle_profile(n: int, seed: int) -> np.ndarray:
    return np.clip(current_profile(n, seed, max_current=1.0), 0.05, 1.0)


def simulate(truth: FirmwareCompass, n: int, seed: int, **kw: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw readings (firmware unit), logged body field and the motor channel of a simulated flight."""
    true, logged = flight(n, seed, **kw)
    unit = 1.0 if truth.unit == "mG" else 1e-3
    x = current_profile(n, seed + 1, max_current=30.0) if truth.motor_type == "current" else \
        throttle_profile(n, seed + 1)
    raw = truth.uncorrect(body_field(true, FIELD_NED_mG * unit), x)
    raw += np.random.default_rng(seed + 2).normal(0, NOISE_mG * unit, raw.shape)
    return raw, body_field(logged, FIELD_NED_mG * unit), x


def _rms(B: np.ndarray, h: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((B - h) ** 2, axis=1))))


@pytest.mark.parametrize("truth", [AP_TRUTH, PX4_TRUTH], ids=["ardupilot-current", "px4-throttle"])
def test_flight_fit_reaches_the_noise_floor_on_a_second_flight_with_the_true_orientation(truth: FirmwareCompass):
    raw, h, x = simulate(truth, 2500, seed=1)
    fit = fit_firmware(truth.target, raw, field_body=h, motor_values={truth.motor_type: x})  # the log says ROT 0
    assert fit.compass.orientation == truth.orientation and fit.orientation["decision"] == "chosen"
    assert fit.level == "full" and fit.compass.motor_type == truth.motor_type
    raw2, h2, x2 = simulate(truth, 2500, seed=20, max_tilt_deg=45.0)  # its own attitudes and motor profile
    floor = _rms(truth.correct(raw2, x2), h2)
    assert _rms(fit.compass.correct(raw2, x2), h2) <= 1.3 * floor
    assert not fit.compass.violations()
    # every fitted parameter has a sigma, and the truth is within 5 of them
    fitted = fit.compass.parameters(0)
    true = truth.parameters(0)
    for name, std in fit.param_std.items():
        if name.endswith(("SCALE", "DIA_X", "DIA_Y", "DIA_Z")) and truth.target == "ardupilot":
            continue  # SCALE and DIA share the matrix's scale (MAGFit's gauge: mean DIA = 1): compared below
        assert abs(fitted[name] - true[name]) < 5 * std + 1e-9, (name, fitted[name], true[name], std)
    A_fit, A_true = fit.compass.algebra()[0], truth.algebra()[0]
    assert np.abs(A_fit - A_true).max() < 0.01


def test_a_tumble_without_attitudes_fits_the_magnitude_and_keeps_the_orientation():
    n = 2000
    att = random_attitudes(n, 3)
    amps = current_profile(n, 2, max_current=30.0)
    truth = ArduPilotCompass(orientation=0, offsets=[120.0, -80.0, 40.0], scale=1.05, diagonal=[1.02, 0.97, 1.01],
                             offdiagonal=[0.02, -0.01, 0.03], motor=[2.0, -1.5, 3.0], motor_type="current")
    raw = truth.uncorrect(body_field(att, FIELD_NED_mG), amps) + np.random.default_rng(5).normal(0, NOISE_mG, (n, 3))
    fit = fit_firmware("ardupilot", raw, magnitude=np.linalg.norm(FIELD_NED_mG), motor_values={"current": amps})
    assert fit.residual_kind == "magnitude" and fit.orientation["decision"] == "kept"
    assert fit.level == "full" and fit.compass.motor_type == "current"
    assert np.abs(fit.compass.offsets - truth.offsets).max() < 2.0
    assert np.abs(fit.compass.motor - truth.motor).max() < 0.1


def test_a_flight_that_mostly_yawed_gives_offsets_and_the_motor_term_and_says_what_it_held():
    held = ArduPilotCompass(orientation=6, offsets=[0.0, 0.0, 0.0], scale=1.05, diagonal=[1.02, 0.97, 1.01],
                            offdiagonal=[0.02, -0.01, 0.03])  # the earlier calibration's matrix, in the log
    raw, h, x = simulate(AP_TRUTH, 1500, seed=4, max_tilt_deg=1.0, yaw_step_deg=5.0)
    logged = raw @ AP_TRUTH.rotation.T  # an ArduPilot log holds the readings rotated by COMPASS_ORIENT
    fit = fit_firmware("ardupilot", logged, field_body=h, motor_values={"current": x}, held=held,
                       applied_orientation=6)
    assert fit.orientation["decision"] == "kept"
    assert any(not r["identified"] for r in fit.table)  # level flight: the vertical scale is not seen
    assert fit.level in ("offsets", "scale") and fit.compass.motor_type == "current"
    assert np.abs(fit.compass.offsets - AP_TRUTH.offsets).max() < 6.0
    assert "COMPASS_DIA_X" in fit.held and "COMPASS_ODI_Z" in fit.held
    text = level_table(fit.table, "mG")
    assert "held-out" in text and "<--" in text
    with pytest.raises(IdentifiabilityError, match="full level asked for is not identified"):
        fit_firmware("ardupilot", logged, field_body=h, motor_values={"current": x}, held=held,
                     applied_orientation=6, level="full")


def test_a_mounting_rotation_beyond_the_tolerance_is_refused_naming_the_angle():
    """Exit 3 (the data cannot support a firmware calibration of this mounting; issue 38, item 2: was exit 2), with
    the angle and what to check; heading-free too, where it was only reported and the parameters written (the
    real ardusub_small.BIN printed "leaves 150.2 +- 1.5 deg, left to the symmetric matrix" and exited 0)."""
    raw, h, x = simulate(AP_TRUTH, 1500, seed=5)
    tilted = raw @ Rotation.from_euler("X", 12.0, degrees=True).as_matrix().T  # a compass mounted 12 deg off
    refusal = (r"rotated 1[12]\.\d \+- \d\.\d deg from the compass's readings in the nearest standard orientation"
               r".*check the reference .*the log's orientation \(COMPASS_ORIENTn")
    with pytest.raises(IdentifiabilityError, match=refusal):
        fit_firmware("ardupilot", tilted, field_body=h, motor_values={"current": x})
    _, logged = flight(1500, seed=5)  # simulate's attitudes: the tilt of each sample, as app/_firmware.py builds it
    euler = logged.as_euler("ZYX", degrees=True)
    level = from_euler(np.zeros(len(euler)), euler[:, 1], euler[:, 2]).as_matrix()
    with pytest.raises(IdentifiabilityError, match=refusal + r".*the yaw is the EKF's"):
        fit_firmware("ardupilot", tilted, field_body=h, motor_values={"current": x}, heading_free=level)


def test_an_internal_compass_keeps_the_boards_orientation_and_says_which_fits_better():
    raw, h, x = simulate(AP_TRUTH, 1500, seed=6)  # mounted ROTATION_YAW_270, but the board says 0
    with pytest.raises(IdentifiabilityError, match=r"unexplained.*fits ROTATION_YAW_270 \(6\).*internal"):
        fit_firmware("ardupilot", raw, field_body=h, motor_values={"current": x}, external=False,
                     tolerance_deg=360.0)


def test_a_reference_the_data_contradict_is_refused_before_any_parameter():
    raw, h, _ = simulate(AP_TRUTH, 800, seed=7)
    with pytest.raises(TrimagInputError, match=r"(9\d\d|1e\+03)x the reference field"):
        fit_firmware("ardupilot", raw, field_body=h / 1000.0)
    with pytest.raises(TrimagInputError, match=r"0\.00\d+x the reference field"):
        fit_firmware("ardupilot", raw, magnitude=np.linalg.norm(FIELD_NED_mG) * 1000.0)


def test_offsets_the_firmware_cannot_load_are_refused_naming_the_parameter_and_limit():
    truth = ArduPilotCompass(offsets=[1500.0, -1200.0, 400.0])
    att = random_attitudes(800, 8)
    raw = truth.uncorrect(body_field(att, FIELD_NED_mG)) + np.random.default_rng(9).normal(0, NOISE_mG, (800, 3))
    with pytest.raises(TrimagInputError, match=r"\|COMPASS_OFS_X\.\.Z\| = 19\d\d.* COMPASS_OFFS_MAX = 1800"):
        fit_firmware("ardupilot", raw, magnitude=np.linalg.norm(FIELD_NED_mG))
    fit = fit_firmware("ardupilot", raw, magnitude=np.linalg.norm(FIELD_NED_mG), offsets_max=3000.0)
    assert np.abs(fit.compass.offsets - truth.offsets).max() < 2.0


def test_level_and_motor_can_be_asked_for():
    raw, h, x = simulate(AP_TRUTH, 1200, seed=10)
    fit = fit_firmware("ardupilot", raw, field_body=h, motor_values={"current": x}, level="scale", motor="none")
    assert fit.level == "scale" and fit.compass.motor_type is None and len(fit.table) == 1
    with pytest.raises(TrimagInputError, match="needs a logged throttle channel"):
        fit_firmware("ardupilot", raw, field_body=h, motor_values={"current": x}, motor="throttle")


def test_a_log_whose_own_calibration_is_right_is_told_to_keep_it():
    raw, h, x = simulate(AP_TRUTH, 1200, seed=12)
    logged = raw @ AP_TRUTH.rotation.T
    with pytest.raises(IdentifiabilityError, match="calibration in the log fits these data"):
        fit_firmware("ardupilot", logged, field_body=h, motor_values={"current": x}, held=AP_TRUTH,
                     applied_orientation=6)


def test_a_log_orientation_that_reverses_the_field_is_said_so_not_infinitely_worse():
    """An internal compass mounted ROTATION_YAW_180 on a board that says 0: the log's orientation sees the field
    reversed (a negative scale); the message says so. Before: 'fits ROTATION_YAW_180 (4) infx better'."""
    import dataclasses

    raw, h, x = simulate(dataclasses.replace(AP_TRUTH, orientation=4), 1500, seed=6)
    with pytest.raises(IdentifiabilityError) as info:
        fit_firmware("ardupilot", raw, field_body=h, motor_values={"current": x}, external=False, tolerance_deg=360.0)
    text = str(info.value)
    assert "inf" not in text and "ROTATION_YAW_180 (4)" in text and "reversed" in text


def test_a_fit_that_leaves_a_tenth_of_the_field_unexplained_is_written_with_a_warning():
    """Found at the 2026-11-27 review: compass 3 of the real log171 is fitted with 83 of 582 mG unexplained (14 %,
    a heading error of up to ~20 deg where the horizontal field is 236 mG) and was written with no word of it; under
    the 20 % refusal such a fit is kept (it is far better than the log's 717 mG) but now says it is poor."""
    raw, h, x = simulate(AP_TRUTH, 1500, seed=21)
    clean = fit_firmware("ardupilot", raw, field_body=h, motor_values={"current": x})
    assert not [m for m in clean.messages if "unexplained" in m]
    t = np.arange(len(raw))
    disturbance = 75.0 * np.column_stack([np.sin(t / 37.0), np.cos(t / 53.0), np.sin(t / 71.0 + 1.0)])
    fit = fit_firmware("ardupilot", raw + disturbance, field_body=h, motor_values={"current": x})
    said = [m for m in fit.messages if m.startswith("warning:") and "unexplained" in m]
    assert len(said) == 1 and "%" in said[0], fit.messages


def test_a_firmware_without_compass_scale_or_the_matrix_gets_only_what_it_has():
    """Found on unseen logs (ArduCopter 3.4.4: DIA/ODI but no COMPASS_SCALE; 3.3-dev: neither): the fit wrote
    COMPASS_SCALE (ignored by that firmware: a 9.6 % gain error once loaded) and DIA/ODI (absent) with offsets
    fitted together with them. The parameters a log's firmware lacks are now never fitted."""
    raw, h, x = simulate(AP_TRUTH, 1500, seed=3)
    no_scale = fit_firmware("ardupilot", raw, field_body=h, motor_values={"current": x}, absent=("scale",))
    assert no_scale.compass.scale == 0.0 and "scale" not in {r["level"] for r in no_scale.table}
    full = fit_firmware("ardupilot", raw, field_body=h, motor_values={"current": x})
    test_raw, test_h, test_x = simulate(AP_TRUTH, 1500, seed=4)
    assert _rms(no_scale.compass.correct(test_raw, test_x), test_h) < 1.05 * _rms(full.compass.correct(test_raw,
                                                                                                      test_x), test_h)
    offsets_only = fit_firmware("ardupilot", raw, field_body=h, motor_values={"current": x},
                                absent=("scale", "matrix", "motor"))
    assert {r["level"] for r in offsets_only.table} == {"offsets"} and offsets_only.compass.motor_type is None
    with pytest.raises(TrimagInputError, match="COMPASS_SCALE"):
        fit_firmware("ardupilot", raw, field_body=h, level="scale", absent=("scale",))


def test_a_level_whose_added_parameters_are_none_identified_is_not_chosen():
    """Found on an unseen log (beastayyg sample.bin, compass 2): auto chose `offsets + throttle` with m_x, m_y, m_z
    all not identified (held-out 24.59 -> 23.00 mG) and wrote COMPASS_MOT and COMPASS_MOTCT 1 (the log had 0)."""
    from types import SimpleNamespace

    from trimag.vehicle.firmware import _choose

    def cand(level: str, motor: str | None, heldout: float, weak: list[str], n: int) -> SimpleNamespace:
        names = ["o_x", "o_y", "o_z"] + (["m_x", "m_y", "m_z"] if motor else [])
        return SimpleNamespace(level=level, motor=motor, heldout_rms=heldout, weak=weak, identified=not weak,
                               n_identified=n - len(weak), violations=[], at_limit=[],
                               problem=SimpleNamespace(n_params=n, names=lambda names=names: names))

    plain = cand("offsets", None, 24.59, [], 3)
    unidentified_motor = cand("offsets", "throttle", 23.00, ["m_x", "m_y", "m_z"], 6)
    assert _choose("auto", [plain, unidentified_motor]) is plain
    identified_motor = cand("offsets", "throttle", 20.0, ["m_z"], 6)
    assert _choose("auto", [plain, identified_motor]) is identified_motor


@pytest.mark.parametrize(("target", "unit", "first", "own"), [("ardupilot", 1.0, "COMPASS_OFS_", "COMPASS_OFS2_"),
                                                              ("px4", 1e-3, "CAL_MAG0_", "CAL_MAG1_")])
def test_a_refusal_names_the_compass_s_own_parameters(target: str, unit: float, first: str, own: str):
    """Issue 39, item 2 (one naming everywhere): a vehicle that never turned is refused (NotExcited, exit 3)
    naming the second compass's parameters, as its result would; the same type, so the exit code stays."""
    from trimag.vehicle._firmware_trust import NotExcited

    h = np.tile([200.0, 0.0, 400.0], (300, 1))  # mG: the field never moved in the compass
    raw = h + np.array([50.0, -20.0, 10.0]) + np.random.default_rng(0).normal(0, 1.0, h.shape)
    level = np.tile(np.eye(3), (300, 1, 1))
    with pytest.raises(NotExcited) as second:
        fit_firmware(target, raw * unit, field_body=h * unit, heading_free=level, instance=1)
    assert own in str(second.value) and first not in str(second.value)
    with pytest.raises(NotExcited) as one:
        fit_firmware(target, raw * unit, field_body=h * unit, heading_free=level, instance=0)
    assert first in str(one.value)
