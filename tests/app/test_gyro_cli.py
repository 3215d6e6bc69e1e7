"""The gyro-aided fit from files (issue 31, item 1): the gyroscope in the magnetometer's rows, in a file of its own
(with its own clock: the lag is fitted), or beside a phone's magnetometer export (read automatically); and what is
refused. Simulated truth: :func:`trimag.simulate.simulate_gyro`."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from trimag import Calibration
from trimag.io.logs import read_log
from trimag.simulate import simulate_gyro

from _helpers import refusal, run_trimag


def _one_line(proc) -> None:
    """One verdict line, then its indented detail lines, if any (docs/cli.md, "Errors")."""
    refusal(proc.stderr, max_verdict=None)


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("gyro")
    cone = simulate_gyro(6000, 7, motion="cone")
    pd.DataFrame({"t": cone.time_s, "mx": cone.raw[:, 0], "my": cone.raw[:, 1], "mz": cone.raw[:, 2],
                  "gx": cone.rate[:, 0], "gy": cone.rate[:, 1], "gz": cone.rate[:, 2]}).to_csv(d / "cone.csv",
                                                                                               index=False)
    two = simulate_gyro(6000, 8, gyro_rate_hz=200.0, lag_s=0.05)
    pd.DataFrame({"t": two.time_s, "mx": two.raw[:, 0], "my": two.raw[:, 1], "mz": two.raw[:, 2]}).to_csv(
        d / "mag.csv", index=False)
    rate = np.degrees(two.rate)
    pd.DataFrame({"tg": two.gyro_time_s, "gx_dps": rate[:, 0], "gy_dps": rate[:, 1], "gz_dps": rate[:, 2]}).to_csv(
        d / "gyro.csv", index=False)
    # a Sensor Logger export: uT, columns time (ns), seconds_elapsed, z, y, x; the gyroscope on its own stamps
    phone = simulate_gyro(3000, 9, gyro_rate_hz=97.0, lag_s=0.004, offset=(20.0, -15.0, 30.0))
    (d / "phone").mkdir()
    for name, t, v in (("MagnetometerUncalibrated.csv", phone.time_s, phone.raw),
                       ("GyroscopeUncalibrated.csv", phone.gyro_time_s, phone.rate)):
        pd.DataFrame({"time": (1.7e18 + t * 1e9).astype(np.int64), "seconds_elapsed": t, "z": v[:, 2], "y": v[:, 1],
                      "x": v[:, 0]}).to_csv(d / "phone" / name, index=False)
    return {"dir": d, "cone": d / "cone.csv", "mag": d / "mag.csv", "gyro": d / "gyro.csv",
            "phone": d / "phone" / "MagnetometerUncalibrated.csv", "truth_cone": cone, "truth_two": two,
            "truth_phone": phone}


def test_gyro_columns_in_the_same_rows(files):
    out = files["dir"] / "cone.json"
    proc = run_trimag("fit", files["cone"], "--columns", "mx,my,mz", "--units", "uT", "--gyro-columns", "gx,gy,gz",
                      "--time-column", "t", "--reference", "49.2", "-o", out, "--json")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary["method"] == "gyro"
    cal = Calibration.from_file(out)
    sim = files["truth_cone"]
    std = cal.uncertainty["param_std"]
    for k, axis in enumerate("xyz"):
        assert abs(cal.offset[k] - sim.offset[k]) < 4 * std[f"hard_iron_{axis}"]
        assert abs(cal.diagnostics["gyro"]["bias_rad_s"][k] - sim.gyro_bias[k]) < 4 * std[f"gyro_bias_{axis}"]
    board = cal.diagnostics["gyro_alignment"]["board_rotation"]
    U, _, Vt = np.linalg.svd(sim.matrix)  # the truth: the mounting times the rotation of W's polar decomposition
    truth = np.degrees(Rotation.from_matrix(sim.alignment @ U @ Vt).magnitude())
    assert board["name"] == "ROTATION_NONE" and board["remaining_angle_deg"] == pytest.approx(truth, abs=0.15)
    assert cal.diagnostics["identifiability"]["identified_by_gyro"]
    # the printed lines
    proc = run_trimag("fit", files["cone"], "--columns", "mx,my,mz", "--units", "uT", "--gyro-columns", "gx,gy,gz",
                      "--time-column", "t")
    assert proc.returncode == 0, proc.stderr
    assert "gyroscope bias" in proc.stdout and "nearest board rotation ROTATION_NONE" in proc.stdout
    assert "identified with the gyroscope where the magnitude alone leaves them unidentified" in proc.stdout


def test_gyro_file_with_its_own_clock(files):
    """deg/s from the column names, the lag between the clocks (50 ms) fitted within its sigma."""
    out = files["dir"] / "two.json"
    proc = run_trimag("fit", files["mag"], "--columns", "mx,my,mz", "--units", "uT", "--gyro-file", files["gyro"],
                      "--gyro-columns", "gx_dps,gy_dps,gz_dps", "--gyro-time-column", "tg", "--time-column", "t",
                      "-o", out)
    assert proc.returncode == 0, proc.stderr
    assert "in deg/s (from their names)" in proc.stdout
    cal = Calibration.from_file(out)
    g = cal.diagnostics["gyro"]
    assert g["lag_estimated"] and abs(g["lag_s"] - 0.05) < 3 * cal.uncertainty["param_std"]["lag_s"]
    np.testing.assert_allclose(g["bias_rad_s"], files["truth_two"].gyro_bias, atol=1e-3)


def test_phone_export_takes_its_gyroscope(files):
    """A Sensor Logger export: the gyroscope file beside the magnetometer's is read and used without a flag."""
    log = read_log(files["phone"])
    assert log.gyro is not None and log.gyro.source == "GyroscopeUncalibrated.csv"
    out = files["dir"] / "phone.json"
    proc = run_trimag("fit", files["phone"], "-o", out)
    assert proc.returncode == 0, proc.stderr
    assert "gyro-aided fit" in proc.stdout
    cal = Calibration.from_file(out)
    assert cal.method == "gyro"
    np.testing.assert_allclose(cal.offset, files["truth_phone"].offset, atol=0.1)
    assert abs(cal.diagnostics["gyro"]["lag_s"] - 0.004) < 3 * cal.uncertainty["param_std"]["lag_s"]
    proc = run_trimag("fit", files["phone"], "--option", "estimate_lag=false", "--json")  # the fit's own option
    assert proc.returncode == 0, proc.stderr
    assert not json.loads(proc.stdout)["diagnostics"]["gyro"]["lag_estimated"]
    proc = run_trimag("fit", files["phone"], "--method", "ml", "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["method"] == "ml"


def test_refusals(files, tmp_path):
    proc = run_trimag("fit", files["cone"], "--columns", "mx,my,mz", "--gyro-columns", "gx,gy,gz", "--time-column",
                      "t", "--method", "ml")
    assert proc.returncode == 2 and "gyro" in proc.stderr
    _one_line(proc)
    proc = run_trimag("fit", files["cone"], "--columns", "mx,my,mz", "--method", "gyro")
    assert proc.returncode == 2 and "--gyro-columns" in proc.stderr
    _one_line(proc)
    proc = run_trimag("fit", files["cone"], "--columns", "mx,my,mz", "--gyro-columns", "gx,gy,gz")
    assert proc.returncode == 2 and "--time-column" in proc.stderr
    _one_line(proc)
    proc = run_trimag("fit", files["cone"], "--columns", "mx,my,mz", "--gyro-columns", "gx,gy,wz", "--time-column",
                      "t")
    assert proc.returncode == 2 and "'wz'" in proc.stderr
    _one_line(proc)
    # a sensor that does not turn: exit 3
    still = tmp_path / "still.csv"
    rng = np.random.default_rng(0)
    pd.DataFrame({"t": np.arange(500) * 0.01, "mx": 20 + rng.normal(0, 0.3, 500), "my": rng.normal(0, 0.3, 500),
                  "mz": 45 + rng.normal(0, 0.3, 500), "gx": rng.normal(0, 0.002, 500), "gy": rng.normal(0, 0.002, 500),
                  "gz": rng.normal(0, 0.002, 500)}).to_csv(still, index=False)
    proc = run_trimag("fit", still, "--columns", "mx,my,mz", "--gyro-columns", "gx,gy,gz", "--time-column", "t")
    assert proc.returncode == 3, proc.stderr
    _one_line(proc)


_MISMATCHES = {  # case: (simulation speed, what is done to the rate, to the time, extra flags, what is said)
    "deg/s read as rad/s, a slow turn": (0.15, np.degrees, 1.0, [], ("do not match the magnetometer", "deg/s")),
    "deg/s read as rad/s": (1.0, np.degrees, 1.0, [], ("do not match the magnetometer", "deg/s")),
    "rad/s read as deg/s": (1.0, lambda w: w, 1.0, ["--gyro-unit", "deg/s"], ("do not match the magnetometer",
                                                                                "deg/s")),
    "one axis reversed": (1.0, lambda w: w * np.array([1.0, 1.0, -1.0]), 1.0, [], ("do not match the magnetometer",
                                                                                   "right-handed")),
    "time in ms": (1.0, lambda w: w, 1000.0, [], ("in seconds",)),
}


@pytest.mark.parametrize("case", list(_MISMATCHES))
def test_a_gyroscope_that_does_not_match_the_magnetometer_is_refused(tmp_path, case):
    """A slow turn logged in deg/s read as rad/s (8.6 'rad/s' RMS: under the 20 rad/s of the deg/s warning) was
    fitted with exit 0: F 71.6 uT for a true 49.3, |B| RMS 5.9 uT where the noise is 0.3, and 'identified with the
    gyroscope'; rad/s read as deg/s ended in an internal error (exit 1: a mirror-image rotation); a fast turn in
    deg/s read as rad/s, a gyroscope axis with the wrong sign, and a time column in ms, were refused as 'the sensor
    barely turns'. Each is refused (exit 3, one line) saying what disagrees and what to check; nothing is
    written."""
    speed, rate, time_scale, flags, said = _MISMATCHES[case]
    sim = simulate_gyro(3000, 1, speed=speed)
    w = rate(sim.rate)
    path, out = tmp_path / "log.csv", tmp_path / "cal.json"
    pd.DataFrame({"t": sim.time_s * time_scale, "mx": sim.raw[:, 0], "my": sim.raw[:, 1], "mz": sim.raw[:, 2],
                  "gx": w[:, 0], "gy": w[:, 1], "gz": w[:, 2]}).to_csv(path, index=False)
    proc = run_trimag("fit", path, "--units", "uT", "--gyro-columns", "gx,gy,gz", "--time-column", "t", *flags,
                      "-o", out)
    assert proc.returncode == 3, (proc.returncode, proc.stdout[-600:], proc.stderr)
    _one_line(proc)
    assert all(words in proc.stderr for words in said), proc.stderr
    assert not out.exists()
    # the same rows with the rate as logged: fitted
    right = tmp_path / "right.csv"
    pd.DataFrame({"t": sim.time_s, "mx": sim.raw[:, 0], "my": sim.raw[:, 1], "mz": sim.raw[:, 2], "gx": sim.rate[:, 0],
                  "gy": sim.rate[:, 1], "gz": sim.rate[:, 2]}).to_csv(right, index=False)
    assert run_trimag("fit", right, "--units", "uT", "--gyro-columns", "gx,gy,gz", "--time-column", "t",
                      "-o", out).returncode == 0


def test_a_lag_between_columns_of_the_same_rows_is_fitted(tmp_path):
    """Finding (review 2): the lag search between a gyroscope and a magnetometer logged in the same rows, documented
    as `--option estimate_lag=true` (docs/method-gyro.md, BROAD's "gyro, lag fitted" column), could not be had from
    the command line: with `--gyro-columns` alone it said "method 'ml' has no option 'estimate_lag'" (the implied
    gyro method was chosen after the options were checked), and with `--method gyro` "the magnetometer's samples do
    not lie inside the gyroscope's span for lags within +-0.5 s: check the two files' time columns" (one file). Now
    the first and last `max_lag` seconds of the magnetometer are left out (counted) and the lag is fitted."""
    sim = simulate_gyro(6000, 11, motion="cone")
    shift = 3  # the magnetometer 3 rows (30 ms at 100 Hz) behind the gyroscope in the same rows
    rate = sim.rate[shift:]
    log = tmp_path / "lagged.csv"
    pd.DataFrame({"t": sim.time_s[:-shift], "mx": sim.raw[:-shift, 0], "my": sim.raw[:-shift, 1],
                  "mz": sim.raw[:-shift, 2], "gx": rate[:, 0], "gy": rate[:, 1], "gz": rate[:, 2]}).to_csv(log,
                                                                                                          index=False)
    dt = float(np.median(np.diff(sim.time_s)))
    base = ("fit", log, "--columns", "mx,my,mz", "--units", "uT", "--gyro-columns", "gx,gy,gz", "--time-column", "t",
            "--reference", "49.2")
    held = run_trimag(*base, "--json")
    assert held.returncode == 0, held.stderr
    for extra in ((), ("--method", "gyro")):
        out = tmp_path / f"lag{len(extra)}.json"
        proc = run_trimag(*base, *extra, "--option", "estimate_lag=true", "--option", "max_lag=0.2", "-o", out)
        assert proc.returncode == 0, proc.stderr
        assert "left out" in proc.stdout and "lag search" in proc.stdout, proc.stdout  # the rows are counted
        cal = Calibration.from_file(out)
        g, sigma = cal.diagnostics["gyro"], cal.uncertainty["param_std"]["lag_s"]
        assert g["lag_estimated"] and abs(abs(g["lag_s"]) - shift * dt) < 4 * sigma + 1e-3, (g["lag_s"], sigma)
        assert g["vector_rms"] < 0.9 * json.loads(held.stdout)["diagnostics"]["gyro"]["vector_rms"]  # 0.52 vs 0.63
        assert cal.stats["n_used"] < 6000 - shift - 2 * 0.2 / dt + 2


def test_a_gyro_file_whose_stamps_go_back_is_said_and_its_rows_dropped(files, tmp_path):
    """Issue 41 item 6: 100 gyroscope rows stamped 5 s early were sorted into another moment, silently (the fit
    refused, or with a smaller jump gave a bias 5 sigma off). They are dropped and counted, the magnetometer samples
    in the gap they leave too, and the bias stays within 3 sigma of the truth."""
    table = pd.read_csv(files["gyro"])
    t = table["tg"].to_numpy().copy()
    t[3000:3100] -= 5.0
    table["tg"] = t
    back = tmp_path / "gyro_back.csv"
    table.to_csv(back, index=False)
    out = tmp_path / "back.json"
    proc = run_trimag("fit", files["mag"], "--columns", "mx,my,mz", "--units", "uT", "--gyro-file", back,
                      "--gyro-columns", "gx_dps,gy_dps,gz_dps", "--gyro-time-column", "tg", "--time-column", "t",
                      "-o", out)
    assert proc.returncode == 0, proc.stderr
    cal = Calibration.from_file(out)
    std = cal.uncertainty["param_std"]
    for k, axis in enumerate("xyz"):
        assert abs(cal.diagnostics["gyro"]["bias_rad_s"][k] - files["truth_two"].gyro_bias[k]) < 3 * std[
            f"gyro_bias_{axis}"]
    assert "100 whose time stamp is missing, repeats or goes back" in proc.stderr
    assert "magnetometer samples inside gaps of the gyroscope's stream" in proc.stdout


@pytest.mark.parametrize("where", ["columns", "file"])
def test_a_gyro_rate_of_1e300_is_dropped_and_counted(files, tmp_path, where):
    """Issue 41 item 4: one gyroscope row of 1e300 ended in `LinAlgError: Eigenvalues did not converge` (exit 1)."""
    if where == "columns":
        table = pd.read_csv(files["cone"])
        table.loc[100, "gx"] = 1e300
        path = tmp_path / "cone.csv"
        table.to_csv(path, index=False)
        args = [path, "--gyro-columns", "gx,gy,gz", "--reference", "49.2"]
    else:
        table = pd.read_csv(files["gyro"])
        table.loc[200, "gx_dps"] = 1e300
        path = tmp_path / "gyro.csv"
        table.to_csv(path, index=False)
        args = [files["mag"], "--gyro-file", path, "--gyro-columns", "gx_dps,gy_dps,gz_dps", "--gyro-time-column",
                "tg"]
    proc = run_trimag("fit", *args, "--columns", "mx,my,mz", "--units", "uT", "--time-column", "t")
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr and "RuntimeWarning" not in proc.stderr
    assert "beyond 10000 rad/s" in proc.stdout + proc.stderr or "within 10000 rad/s" in proc.stderr
