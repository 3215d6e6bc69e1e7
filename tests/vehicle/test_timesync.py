"""Two streams, one clock (issue 20, item 6; docs/vehicle.md): attitudes from a second file with their own time
stamps, slerp to the magnetometer's, and the constant lag between the streams.

Simulated vehicle with known truth (paper C's model ``H_m = K H_b + c``, background (18 000, 1 200, 46 000) nT, 20 nT
noise per axis): the attitude turns smoothly (up to ~2 rad/s); the magnetometer logs at 50 Hz from -0.5 s to 61 s,
the attitude stream at 120 Hz from 0 to 60 s, its clock ``LAG`` = 0.12 s ahead (the attitude stamped ``t + LAG``
is the one at the magnetometer's ``t``).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from trimag import Calibration
from trimag.errors import IdentifiabilityError, TrimagInputError
from trimag.simulate import body_field
from trimag.vehicle.timesync import AttitudeStream, estimate_lag, interpolate_attitude, read_attitude_stream

from _helpers import run_trimag

H_N = np.array([18_000.0, 1_200.0, 46_000.0])
K = np.array([[1.02, 0.01, -0.02], [0.015, 0.98, 0.01], [-0.01, 0.02, 1.01]])
C = np.array([250.0, -120.0, 80.0])
NOISE = 20.0
LAG = 0.12


def _attitude(t: np.ndarray) -> Rotation:
    rv = np.column_stack([1.2 * np.sin(0.7 * t) + 0.5 * np.sin(1.9 * t + 1), 0.8 * np.sin(0.5 * t + 2)
                          + 0.3 * np.sin(2.3 * t), 1.5 * np.sin(0.3 * t) + 0.6 * np.cos(1.1 * t)])
    return Rotation.from_rotvec(rv)


def _streams(seed: int = 0) -> tuple[np.ndarray, np.ndarray, AttitudeStream]:
    ta = np.arange(0.0, 60.0, 1 / 120.0)
    stream = AttitudeStream(ta, _attitude(ta - LAG))
    rng = np.random.default_rng(seed)
    tm = np.arange(-0.5, 61.0, 1 / 50.0) + 0.003
    B = body_field(_attitude(tm), H_N) @ K.T + C + rng.normal(0, NOISE, (len(tm), 3))
    return B, tm, stream


def _vector_rms(B: np.ndarray, R: Rotation) -> float:
    H_b = body_field(R, H_N)
    A = np.column_stack([H_b, np.ones(len(H_b))])
    X, *_ = np.linalg.lstsq(A, B, rcond=None)
    return float(np.sqrt(np.mean(np.sum((B - A @ X) ** 2, axis=1))))


def test_lag_recovered_within_its_uncertainty() -> None:
    B, tm, stream = _streams()
    r = estimate_lag(B, tm, stream, H_N)
    assert abs(r["lag_s"] - LAG) < 3 * r["lag_std_s"], r
    assert r["lag_std_s"] < 1e-3
    # the fit with the lag is at the noise floor (20 sqrt(3) = 34.6 nT), without it far worse
    R_lag, inside = interpolate_attitude(stream, tm, r["lag_s"])
    rms_lag = _vector_rms(B[inside], R_lag)
    R_0, inside0 = interpolate_attitude(stream, tm, 0.0)
    rms_0 = _vector_rms(B[inside0], R_0)
    assert rms_lag < 1.05 * NOISE * np.sqrt(3)
    assert rms_0 > 10 * rms_lag


def test_samples_outside_the_span_are_flagged() -> None:
    _, tm, stream = _streams()
    _, inside = interpolate_attitude(stream, tm, 0.0)
    expected = int(np.sum((tm < 0.0) | (tm > stream.times[-1])))
    assert int((~inside).sum()) == expected > 0
    _, inside = interpolate_attitude(stream, tm + 1000.0)
    assert not inside.any()


def test_slerp_matches_the_stream_at_its_own_stamps() -> None:
    _, _, stream = _streams()
    R, inside = interpolate_attitude(stream, stream.times[10:20])
    assert inside.all()
    assert np.allclose((R * stream.rotation[10:20].inv()).magnitude(), 0.0, atol=1e-9)


def test_no_motion_no_lag() -> None:
    ta = np.arange(0.0, 10.0, 0.01)
    stream = AttitudeStream(ta, Rotation.from_rotvec(np.tile([0.1, 0.2, 0.3], (len(ta), 1))))
    tm = np.arange(1.0, 9.0, 0.02)
    B = np.tile(body_field(stream.rotation[:1], H_N), (len(tm), 1)) + np.random.default_rng(1).normal(0, 20,
                                                                                                      (len(tm), 3))
    with pytest.raises(IdentifiabilityError):
        estimate_lag(B, tm, stream, H_N)
    with pytest.raises(TrimagInputError, match="max_lag"):
        estimate_lag(B, tm, stream, H_N, max_lag=-1.0)


# ------------------------------------------------------------------ files and the command line
@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("timesync")
    B, tm, stream = _streams()
    q = stream.rotation.as_quat(scalar_first=True)
    pd.DataFrame({"t_att": stream.times, "qw": q[:, 0], "qx": q[:, 1], "qy": q[:, 2], "qz": q[:, 3]}).to_csv(
        d / "att.csv", index=False)
    euler = stream.rotation.as_euler("ZYX", degrees=True)
    pd.DataFrame({"time": stream.times, "yaw": euler[:, 0], "pitch": euler[:, 1], "roll": euler[:, 2]}).to_csv(
        d / "att_euler.csv", index=False)
    pd.DataFrame({"time": tm, "x": B[:, 0], "y": B[:, 1], "z": B[:, 2]}).to_csv(d / "mag.csv", index=False)
    return {"dir": d, "att": d / "att.csv", "att_euler": d / "att_euler.csv", "mag": d / "mag.csv"}


def test_read_attitude_stream(files) -> None:
    s = read_attitude_stream(files["att"], time_column="t_att", quaternion_columns="qw,qx,qy,qz")
    e = read_attitude_stream(files["att_euler"], time_column="time", attitude_columns="yaw,pitch,roll")
    assert len(s.times) == len(e.times) == 7200
    assert np.allclose((s.rotation * e.rotation.inv()).magnitude(), 0.0, atol=1e-9)
    with pytest.raises(TrimagInputError, match="no time column 'when'"):
        read_attitude_stream(files["att"], time_column="when", quaternion_columns="qw,qx,qy,qz")


def _fit(files, *extra: str):
    return run_trimag("fit", files["mag"], "--units", "nT", "--model", "interference12", "--background-ned",
                      "18000,1200,46000", "--attitude-file", files["att"], "--quaternion-columns", "qw,qx,qy,qz",
                      "--time-column", "time", "--attitude-time-column", "t_att", *extra)


def test_cli_estimate_lag(files) -> None:
    out = files["dir"] / "cal.json"
    proc = _fit(files, "--option", "estimate_lag=true", "-o", out, "--json")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    sync = summary["time_sync"]
    assert sync["lag_estimated"] and abs(sync["lag_s"] - LAG) < 3 * sync["lag_std_s"]
    _, tm, stream = _streams()
    outside = int(np.sum((tm + sync["lag_s"] < 0.0) | (tm + sync["lag_s"] > stream.times[-1])))
    assert sync["n_outside"] == outside > 0
    assert f"dropped {outside} of {len(tm)} magnetometer samples outside" in proc.stderr
    cal = Calibration.from_file(out)
    assert cal.diagnostics["time_sync"]["lag_s"] == pytest.approx(sync["lag_s"])
    assert cal.stats["vector_rms_after"] < 1.05 * NOISE * np.sqrt(3)
    np.testing.assert_allclose(cal.offset, C, atol=5 * 0.7)
    # without the lag the same files fit far worse
    proc = _fit(files, "--json")
    assert proc.returncode == 0, proc.stderr
    plain = json.loads(proc.stdout)
    assert plain["time_sync"]["lag_s"] == 0.0 and not plain["time_sync"]["lag_estimated"]
    assert plain["time_sync"]["n_outside"] == int(np.sum((tm < 0.0) | (tm > stream.times[-1])))
    assert summary["rms_after"] < 1.05 * NOISE  # |B| - F at the noise floor with the lag
    assert plain["rms_after"] > 5 * summary["rms_after"]


def test_cli_refusals(files) -> None:
    proc = run_trimag("fit", files["mag"], "--units", "nT", "--model", "interference12", "--background-ned",
                      "18000,1200,46000", "--attitude-file", files["att"], "--quaternion-columns", "qw,qx,qy,qz")
    assert proc.returncode == 2 and "--time-column" in proc.stderr
    proc = _fit(files, "--option", "estimate_lag=true", "--option", "max_lag=0.05")
    assert proc.returncode == 3 and "edge of the search" in proc.stderr
    proc = run_trimag("fit", files["mag"], "--units", "nT", "--reference", "49411", "--option", "estimate_lag=true")
    assert proc.returncode == 2 and "--attitude-file" in proc.stderr
    for p in (proc,):
        assert "Traceback" not in p.stderr and len(p.stderr.strip().splitlines()) == 1


def test_cli_evaluate_applies_the_stored_lag(files) -> None:
    out = files["dir"] / "cal_eval.json"
    assert _fit(files, "--option", "estimate_lag=true", "-o", out, "-q").returncode == 0
    args = ["evaluate", out, files["mag"], "--background-ned", "18000,1200,46000", "--attitude-file", files["att"],
            "--quaternion-columns", "qw,qx,qy,qz", "--time-column", "time", "--attitude-time-column", "t_att",
            "--json"]
    proc = run_trimag(*args)
    assert proc.returncode == 0, proc.stderr
    v = json.loads(proc.stdout)
    assert v["lag_s"] == pytest.approx(Calibration.from_file(out).diagnostics["time_sync"]["lag_s"])
    assert v["rms_after"] < 1.05 * NOISE * np.sqrt(3)
    assert v["angular_error_rms_deg"] < 0.05
    _, tm, stream = _streams()
    assert v["n_dropped"] == int(np.sum((tm + v["lag_s"] < 0.0) | (tm + v["lag_s"] > stream.times[-1])))


def test_estimate_lag_takes_the_attitudes_of_the_datas_own_rows(tmp_path: Path):
    """`--option estimate_lag` needed `--attitude-file` even when the attitudes are in the data's rows (issue 42,
    item 6): the rows' own attitude columns are the stream, on the same time column. Here the attitude columns lag
    the magnetometer by 0.3 s (a filter's delay): the lag is found, and the fit's RMS drops."""
    rng = np.random.default_rng(3)
    t = np.arange(1200) * 0.05
    ypr = np.column_stack([np.degrees(0.9 * t), 35.0 * np.sin(t / 2.1), 40.0 * np.cos(t / 3.3)])
    rot = Rotation.from_euler("ZYX", ypr, degrees=True)
    B = rot.inv().apply([18000.0, 1200.0, 46000.0]) + np.array([300.0, -200.0, 100.0])
    B += rng.normal(0, 5.0, (len(t), 3))
    late = np.vstack([np.interp(t - 0.3, t, np.unwrap(np.radians(c))) for c in ypr.T]).T  # attitudes 0.3 s late
    log = tmp_path / "rows.csv"
    np.savetxt(log, np.column_stack([t, B, np.degrees(late)]), delimiter=",", comments="", fmt="%.6f",
               header="t,x,y,z,yaw,pitch,roll")
    r = run_trimag("fit", log, "--model", "interference12", "--units", "nT", "--columns", "x,y,z",
                   "--attitude-columns", "yaw,pitch,roll", "--background-ned", "18000,1200,46000",
                   "--time-column", "t", "--option", "estimate_lag=true", "--json")
    assert r.returncode == 0, r.stderr
    sync = json.loads(r.stdout)["time_sync"]
    assert abs(sync["lag_s"] - 0.3) < 0.02 and sync["rms_at_lag"] < 0.5 * sync["rms_at_zero"], sync
