"""Sensor-to-accelerometer alignment and heading (issue 20, items 2 and 3; docs/vehicle.md).

Simulated vehicles with known truth (:func:`trimag.simulate.simulate_vehicle`): a magnetometer with soft and hard
iron mounted at a known rotation to the accelerometer (a 90-degree yaw mounting plus 2 degrees, or 2 degrees
only), 20 nT noise per axis on a 49 000 nT field (inclination 67.1 deg, declination 3.0 deg), 0.005 m/s^2
accelerometer noise, at rest in random attitudes (yaw 0-360, pitch within 75, roll within 180 degrees).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

import trimag
from trimag import Calibration
from trimag.errors import IdentifiabilityError
from trimag.simulate import VehicleSimulation, simulate_vehicle
from trimag.vehicle.alignment import (
    BOARD_ROTATIONS,
    board_rotation_matrix,
    check_tilt_variation,
    fit_alignment,
    nearest_board_rotation,
)
from trimag.vehicle.heading import heading_difference, heading_error_stats, tilt_compensated_heading

from _helpers import TESTS_DIR, run_trimag

SMALL = Rotation.from_rotvec(np.radians(2.0) * np.array([1.0, -1.0, 2.0]) / np.sqrt(6.0))


def _expected_rotation(sim: VehicleSimulation, cal: Calibration) -> np.ndarray:
    """The true alignment of the calibration's corrected frame: ``R W_true W_fit^-1`` (the fit's gauge)."""
    M = sim.alignment @ sim.matrix @ np.linalg.inv(np.asarray(cal.matrix))
    U, _, Vt = np.linalg.svd(M)
    return np.asarray(U @ Vt)


def _heading(cal: Calibration, sim: VehicleSimulation, aligned: bool = True) -> np.ndarray:
    y = cal.apply(sim.raw)
    if aligned:
        y = y @ np.asarray(cal.diagnostics["alignment"]["matrix"]).T
    return tilt_compensated_heading(y, sim.accel, declination_deg=sim.declination_deg)


def _csv(sim: VehicleSimulation, path: Path) -> Path:
    pd.DataFrame({
        "mx": sim.raw[:, 0], "my": sim.raw[:, 1], "mz": sim.raw[:, 2],
        "ax": sim.accel[:, 0], "ay": sim.accel[:, 1], "az": sim.accel[:, 2],
        "heading": sim.attitude_deg[:, 0], "yaw": sim.attitude_deg[:, 0], "pitch": sim.attitude_deg[:, 1],
        "roll": sim.attitude_deg[:, 2],
    }).to_csv(path, index=False)
    return path


@pytest.fixture(scope="module")
def fitted() -> tuple[VehicleSimulation, Calibration]:
    sim = simulate_vehicle(2000, 1)
    cal = trimag.fit(sim.raw)
    return sim, cal.with_diagnostics(alignment=fit_alignment(cal, sim.raw, sim.accel))


# ------------------------------------------------------------------ conventions
def test_tilt_compensated_heading_is_the_yaw_at_any_tilt():
    rng = np.random.default_rng(0)
    yaw, pitch, roll = rng.uniform(0, 360, 500), rng.uniform(-80, 80, 500), rng.uniform(-180, 180, 500)
    att = Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll]), degrees=True)
    H = np.array([19_000.0, 1_000.0, 45_150.0])
    h = att.inv().apply(H)
    a = att.inv().apply([0.0, 0.0, -9.80665])
    decl = np.degrees(np.arctan2(H[1], H[0]))
    psi = tilt_compensated_heading(h, a, declination_deg=decl)
    assert np.abs(heading_difference(psi, yaw)).max() < 1e-9
    # hand-checked: level, heading east, the field's north on the left
    assert tilt_compensated_heading([[0.0, -20.0, 40.0]], [[0.0, 0.0, -9.81]])[0] == pytest.approx(90.0)


def test_heading_difference_wraps():
    assert heading_difference([359.0, 1.0, 180.0], [1.0, 359.0, 0.0]).tolist() == [-2.0, 2.0, -180.0]
    stats = heading_error_stats([359.0, 1.0], [1.0, 359.0])
    assert stats["heading_error_rms_deg"] == pytest.approx(2.0)
    assert stats["heading_error_max_deg"] == pytest.approx(2.0)


def test_board_rotations_match_ardupilot():
    # ArduPilot's Vector3::rotate: YAW_90 (x, y) -> (-y, x); ROLL_180 (y, z) -> (-y, -z); PITCH_90 x' = z, z' = -x
    v = np.array([1.0, 2.0, 3.0])
    np.testing.assert_allclose(board_rotation_matrix("ROTATION_YAW_90") @ v, [-2.0, 1.0, 3.0], atol=1e-12)
    np.testing.assert_allclose(board_rotation_matrix("ROTATION_ROLL_180") @ v, [1.0, -2.0, -3.0], atol=1e-12)
    np.testing.assert_allclose(board_rotation_matrix("ROTATION_PITCH_90") @ v, [3.0, 2.0, -1.0], atol=1e-12)
    h = np.sqrt(0.5)  # ROLL_180_YAW_45: x' = h (x + y), y' = h (x - y), z' = -z
    np.testing.assert_allclose(board_rotation_matrix("ROTATION_ROLL_180_YAW_45") @ v, [3 * h, -h, -3.0], atol=1e-12)
    for name, (number, *_) in BOARD_ROTATIONS.items():
        near = nearest_board_rotation(board_rotation_matrix(name))
        assert near["remaining_angle_deg"] < 1e-6
        assert BOARD_ROTATIONS[near["name"]][0] <= number  # duplicates (26 = 14, 27 = 10) give the first number


# ------------------------------------------------------------------ estimation with known truth
def test_misalignment_and_dip_recovered_within_their_uncertainty(fitted):
    sim, cal = fitted
    al = cal.diagnostics["alignment"]
    error = Rotation.from_matrix(np.asarray(al["matrix"]) @ _expected_rotation(sim, cal).T).as_rotvec()
    std = np.radians(al["rotation_std_deg"])
    assert np.all(np.abs(error) < 3 * std), (np.degrees(error), al["rotation_std_deg"])
    assert abs(al["dip_deg"] - sim.dip_deg) < 3 * al["dip_std_deg"]
    assert al["calibration_uncertainty_propagated"]
    assert 0 < al["rotation_std_deg"][0] < 0.01  # degrees: 2000 samples at 20 nT / 49 000 nT


def test_reported_sigmas_hold_over_repeated_logs():
    z, z_dip = [], []
    for seed in range(10, 22):
        sim = simulate_vehicle(800, seed)
        cal = trimag.fit(sim.raw)
        al = fit_alignment(cal, sim.raw, sim.accel)
        error = Rotation.from_matrix(np.asarray(al["matrix"]) @ _expected_rotation(sim, cal).T).as_rotvec()
        z.append(np.degrees(error) / np.asarray(al["rotation_std_deg"]))
        z_dip.append((al["dip_deg"] - sim.dip_deg) / al["dip_std_deg"])
    assert 0.6 < float(np.std(z)) < 1.5
    assert 0.6 < float(np.std(z_dip)) < 1.6


def test_nearest_board_rotation_of_a_yaw_90_mounting_plus_2_degrees(fitted):
    sim, cal = fitted
    board = cal.diagnostics["alignment"]["board_rotation"]
    # the sensor's own axes (symmetric soft iron, as simulated): the true mounting
    sensor = np.asarray(cal.diagnostics["alignment"]["sensor_matrix"])
    assert np.degrees(np.linalg.norm(Rotation.from_matrix(sensor @ sim.alignment.T).as_rotvec())) < 0.02
    assert board["name"] == "ROTATION_YAW_90" and board["number"] == 2
    assert board["remaining_angle_deg"] == pytest.approx(2.0, abs=0.01)
    np.testing.assert_allclose(board["remaining_rotvec_deg"], np.degrees(SMALL.as_rotvec()), atol=0.01)


def test_held_out_heading_at_the_noise_floor_and_worse_without_alignment(fitted):
    _, cal = fitted
    held = simulate_vehicle(2000, 2)
    rms = heading_error_stats(_heading(cal, held), held.attitude_deg[:, 0])["heading_error_rms_deg"]
    assert rms < 0.3
    # a 2-degree mounting error only: without the alignment term heading shows it, several times the floor
    sim2, held2 = simulate_vehicle(2000, 3, alignment=SMALL), simulate_vehicle(2000, 4, alignment=SMALL)
    cal2 = trimag.fit(sim2.raw)
    cal2 = cal2.with_diagnostics(alignment=fit_alignment(cal2, sim2.raw, sim2.accel))
    with_term = heading_error_stats(_heading(cal2, held2), held2.attitude_deg[:, 0])["heading_error_rms_deg"]
    without = heading_error_stats(_heading(cal2, held2, aligned=False),
                                  held2.attitude_deg[:, 0])["heading_error_rms_deg"]
    assert with_term < 0.3
    assert without > 4 * with_term and without > 1.0


def test_accelerating_samples_are_dropped(fitted):
    sim, cal = fitted
    accel = sim.accel.copy()
    accel[:50] *= 1.3  # the vehicle accelerated: |a| is 30 % off g
    al = fit_alignment(cal, sim.raw, accel)
    assert al["n_dropped_accelerating"] == 50 and al["n_used"] == len(sim.raw) - 50


# ------------------------------------------------------------------ refusals
def test_level_log_is_refused_before_any_fit():
    level = simulate_vehicle(400, 5, max_pitch_deg=0.5, max_roll_deg=0.5)
    with pytest.raises(IdentifiabilityError, match="tilted in pitch and roll"):
        check_tilt_variation(level.accel)


@pytest.mark.parametrize("axis", ["pitch", "roll"])
def test_turns_about_one_horizontal_axis_are_refused(fitted, axis):
    sim, _ = fitted
    # heading magnetic north, pitched (or rolled) -60..60 deg: the vehicle turns about magnetic east (north) only.
    # Pitch: the field keeps its place relative to gravity, and a rotation mapping one onto the other fits (dip 90);
    # roll: magnetic east stays in the body's y-z plane, the Jacobian's rows (R m) x d have rank 2.
    n = 400
    tilt = np.linspace(-60, 60, n)
    angles = [np.full(n, sim.declination_deg), tilt, np.zeros(n)] if axis == "pitch" else \
        [np.full(n, sim.declination_deg), np.zeros(n), tilt]
    att = Rotation.from_euler("ZYX", np.column_stack(angles), degrees=True)
    h_mag = att.inv().apply(sim.field_ned) @ sim.alignment
    rng = np.random.default_rng(6)
    raw = np.linalg.solve(sim.matrix, h_mag.T).T + sim.offset + rng.normal(0, 20.0, (n, 3))
    accel = att.inv().apply([0.0, 0.0, -9.80665]) + rng.normal(0, 0.005, (n, 3))
    truth = Calibration.from_matrix_offset(sim.matrix, sim.offset, units="nT")
    match = "field stays at one place relative to gravity" if axis == "pitch" else "singular value ratio"
    with pytest.raises(IdentifiabilityError, match=f"{match}.* tilted in pitch and roll"):
        fit_alignment(truth, raw, accel)


# ------------------------------------------------------------------ files and the command line
def test_calibration_file_round_trip_and_files_without_alignment_unchanged(fitted, tmp_path):
    _, cal = fitted
    back = Calibration.from_file(cal.to_file(tmp_path / "cal.json"))
    assert back.diagnostics["alignment"]["board_rotation"]["name"] == "ROTATION_YAW_90"
    np.testing.assert_allclose(back.diagnostics["alignment"]["matrix"], cal.diagnostics["alignment"]["matrix"])
    assert back.format_version == "1.0.0"
    for path in sorted((TESTS_DIR / "data" / "calibrations").glob("*.json")):
        text = path.read_text(encoding="utf-8")
        if json.loads(text)["format"] != "trimag-calibration":
            continue
        old = Calibration.from_json(text)
        assert "alignment" not in old.diagnostics
        assert Calibration.from_json(old.to_json()).as_dict() == old.as_dict()


def test_cli_fit_and_evaluate_heading(tmp_path):
    fit_csv = _csv(simulate_vehicle(2000, 1), tmp_path / "fit.csv")
    held = simulate_vehicle(2000, 2)
    held_csv = _csv(held, tmp_path / "held.csv")
    cal_path = tmp_path / "cal.json"
    r = run_trimag("fit", fit_csv, "--units", "nT", "--accel-columns", "ax,ay,az", "-o", cal_path, "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    al = out["alignment"]
    for key in ("matrix", "rotation_std_deg", "dip_deg", "dip_std_deg", "board_rotation", "covariance"):
        assert key in al
    assert al["board_rotation"]["name"] == "ROTATION_YAW_90"
    assert json.loads(cal_path.read_text())["diagnostics"]["alignment"]["accel_columns"] == "ax,ay,az"
    decl = f"{held.declination_deg:.6f}"
    r = run_trimag("evaluate", cal_path, held_csv, "--accel-columns", "ax,ay,az", "--heading-column", "heading",
                   "--declination", decl, "--json")
    assert r.returncode == 0, r.stderr
    ev = json.loads(r.stdout)
    assert ev["heading_error_rms_deg"] < 0.3 and ev["heading_error_max_deg"] < 1.5
    assert ev["alignment"] == "calibration" and ev["n_used"] == 2000
    r = run_trimag("evaluate", cal_path, held_csv, "--accel-columns", "ax,ay,az", "--attitude-columns",
                   "yaw,pitch,roll", "--declination", decl)
    assert r.returncode == 0, r.stderr
    assert "heading error rms" in r.stdout
    # the same calibration without the alignment: the 90-degree mounting shows in heading
    r = run_trimag("fit", fit_csv, "--units", "nT", "-o", tmp_path / "plain.json", "-q")
    assert r.returncode == 0, r.stderr
    r = run_trimag("evaluate", tmp_path / "plain.json", held_csv, "--accel-columns", "ax,ay,az", "--heading-column",
                   "heading", "--declination", decl, "--json")
    assert r.returncode == 0 and "no alignment" in r.stderr
    assert json.loads(r.stdout)["heading_error_rms_deg"] > 30.0


def test_cli_refusals(tmp_path):
    level_csv = _csv(simulate_vehicle(400, 5, max_pitch_deg=0.5, max_roll_deg=0.5), tmp_path / "level.csv")
    r = run_trimag("fit", level_csv, "--units", "nT", "--accel-columns", "ax,ay,az", "-o", tmp_path / "c.json")
    assert r.returncode == 3
    assert len(r.stderr.strip().splitlines()) == 1 and "tilted in pitch and roll" in r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "c.json").exists()
    fit_csv = _csv(simulate_vehicle(300, 1), tmp_path / "fit.csv")
    r = run_trimag("fit", fit_csv, "--units", "nT", "--accel-columns", "ax,ay,nope")
    assert r.returncode == 2 and "no column 'nope'" in r.stderr and "--accel-columns" in r.stderr
    r = run_trimag("fit", fit_csv, "--units", "nT", "--accel-columns", "ax,ay")
    assert r.returncode == 2 and "--accel-columns" in r.stderr
    assert run_trimag("fit", fit_csv, "--units", "nT", "-o", tmp_path / "c.json", "-q").returncode == 0
    r = run_trimag("evaluate", tmp_path / "c.json", fit_csv, "--accel-columns", "ax,ay,az")
    assert r.returncode == 2 and "--heading-column" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    r = run_trimag("evaluate", tmp_path / "c.json", fit_csv, "--heading-column", "heading")
    assert r.returncode == 2 and "--accel-columns" in r.stderr
    r = run_trimag("evaluate", tmp_path / "c.json", fit_csv, "--accel-columns", "ax,ay,az", "--heading-column",
                   "heading", "--declination", "east")
    assert r.returncode == 2 and "--declination" in r.stderr


def test_policy_measures_the_inclination_error_from_the_fitted_dip(fitted):
    from trimag.vehicle.policy import check_policy

    sim, cal = fitted
    verdict = check_policy(cal, {"max_inclination_error_deg": 0.5}, inclination_deg=sim.dip_deg + 1.0)
    assert not verdict["accepted"]
    assert verdict["failed"][0]["measured"] == pytest.approx(1.0, abs=0.01)
    plain = dataclasses.replace(cal, diagnostics={})
    assert check_policy(plain, {"max_inclination_error_deg": 0.5}, inclination_deg=60.0)["not_evaluated"] == [
        "max_inclination_error_deg"]


def test_cli_dip_against_igrf_and_an_accelerometer_of_the_wrong_sign(tmp_path):
    sim = simulate_vehicle(600, 7)
    csv = _csv(sim, tmp_path / "fit.csv")
    r = run_trimag("fit", csv, "--units", "nT", "--accel-columns", "ax,ay,az", "--igrf", "52.5,13.3,40,2025-06-01")
    assert r.returncode == 0, r.stderr
    assert "against IGRF's" in r.stdout and "opposite sign" not in r.stderr
    flipped = pd.read_csv(csv)
    flipped[["ax", "ay", "az"]] *= -1.0  # gravity (+g down) instead of specific force
    flipped.to_csv(tmp_path / "flipped.csv", index=False)
    r = run_trimag("fit", tmp_path / "flipped.csv", "--units", "nT", "--accel-columns", "ax,ay,az", "--igrf",
                   "52.5,13.3,40,2025-06-01", "-q")
    assert r.returncode == 0 and "opposite sign of IGRF's" in r.stderr


def test_heading_sigma_of_the_alignment_holds():
    """The heading error of a level vehicle that the alignment's error alone causes, over repeated fits, against
    the predicted ``heading_sigma_deg`` (held-out noise-free level samples, fitted against true alignment)."""
    held = simulate_vehicle(720, 99, mag_noise_nT=0.0, accel_noise=0.0, max_pitch_deg=0.0, max_roll_deg=0.0)
    errors, predicted = [], []
    for seed in range(200, 212):
        sim = simulate_vehicle(800, seed)
        cal = trimag.fit(sim.raw)
        al = fit_alignment(cal, sim.raw, sim.accel)
        y = cal.apply(held.raw)
        fitted = tilt_compensated_heading(y @ np.asarray(al["matrix"]).T, held.accel)
        true = tilt_compensated_heading(y @ _expected_rotation(sim, cal).T, held.accel)
        errors.append(heading_difference(fitted, true))
        predicted.append(al["heading_sigma_deg"]["rms_deg"])
    ratio = float(np.sqrt(np.mean(np.square(errors)))) / float(np.mean(predicted))
    assert 0.5 < ratio < 1.5, ratio


def test_cli_tolles_lawson_refuses_accel_columns(tmp_path):
    csv = _csv(simulate_vehicle(100, 1), tmp_path / "log.csv")
    r = run_trimag("fit", csv, "--model", "tolles-lawson", "--columns", "mx,my,mz", "--scalar-column", "heading",
                   "--rate", "10", "--accel-columns", "ax,ay,az")
    assert r.returncode == 2 and "--accel-columns" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_a_poorly_holding_invariance_is_warned(fitted):
    sim, cal = fitted
    assert cal.diagnostics["alignment"]["warning"] is None
    rng = np.random.default_rng(8)
    wobble = Rotation.from_rotvec(rng.normal(0.0, np.radians(2.0), (len(sim.accel), 3)))  # 3.5 deg of tilt error
    al = fit_alignment(cal, sim.raw, wobble.apply(sim.accel))
    assert al["rms_residual_deg"] > 1.0 and "holds poorly" in al["warning"]


def test_ardupilot_export_names_the_board_rotation(fitted):
    from trimag.io.export import export_calibration

    _, cal = fitted
    exp = export_calibration(dataclasses.replace(cal, units="nT"), "ardupilot")
    assert any("ROTATION_YAW_90 (COMPASS_ORIENT = 2)" in note for note in exp.notes)
    assert "COMPASS_ORIENT" not in exp.text
