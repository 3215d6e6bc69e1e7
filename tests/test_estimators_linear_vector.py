"""linear-vector: paper C's three 4-unknown least-squares problems."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

import trimag
from trimag.attitude import ENU_TO_NED, body_field, from_euler
from trimag.calibration import Calibration
from trimag.errors import IdentifiabilityError, NotFittedError, TrimagInputError
from trimag.estimators import get_estimator
from trimag.estimators.linear_vector import LinearVector, fit_with_background
from trimag.models.interference12 import Interference12

from _helpers import run_trimag

H_N = np.array([27000.0, 1500.0, 42000.0])  # nT, NED (a mid-latitude field)


def _truth(seed: int = 0) -> Interference12:
    rng = np.random.default_rng(seed)
    return Interference12.from_K_c(np.eye(3) + 0.08 * rng.normal(size=(3, 3)), rng.normal(size=3) * 1500)


def _attitudes(n: int, seed: int = 1) -> Rotation:
    rng = np.random.default_rng(seed)
    return from_euler(rng.uniform(0, 360, n), rng.uniform(-60, 60, n), rng.uniform(-60, 60, n))


def test_registry_and_contract():
    assert get_estimator("linear-vector") is LinearVector
    est = LinearVector()
    assert LinearVector.reference_kind == "vector" and LinearVector.requires_reference
    assert not hasattr(est, "calibration_")
    with pytest.raises(NotFittedError):
        est.transform(np.zeros((4, 3)))


def test_noise_free_recovers_12_coefficients_to_1e9():
    truth = _truth()
    R = _attitudes(10)
    H_m = truth.distort(body_field(R, H_N))
    before = H_m.copy()
    est = LinearVector().fit(H_m, H_N, units="nT", attitude=R)
    assert est.fit(H_m, H_N, units="nT", attitude=R) is est
    np.testing.assert_array_equal(H_m, before)
    got = Interference12.from_dict(est.calibration_.params)
    np.testing.assert_allclose(got.as_vector(), truth.as_vector(), rtol=0, atol=1e-9)
    assert est.calibration_.stats["rms_after"] < 1e-6  # nT, on a 50000 nT field (~1e-11 relative)
    assert est.calibration_.stats["vector_rms_after"] < 1e-6
    assert est.calibration_.diagnostics["n_attitudes"] == 10
    assert 1 <= est.cond_ < 100
    # JSON round trip keeps the correction exactly
    cal2 = Calibration.from_json(est.calibration_.to_json())
    np.testing.assert_array_equal(cal2.matrix, est.calibration_.matrix)


def test_four_well_spread_attitudes_suffice():
    truth = _truth(3)
    R = from_euler([0, 90, 180, 270], [0, 45, -30, 20], [0, -40, 30, 60])
    cal = trimag.fit(truth.distort(body_field(R, H_N)), model="interference12", reference=H_N,
                     attitude=R, units="nT")
    np.testing.assert_allclose(np.array(list(cal.params.values())), truth.as_vector(), atol=1e-7)


def test_three_attitudes_exit_3_with_message():
    truth = _truth()
    R = _attitudes(3)
    with pytest.raises(IdentifiabilityError, match="at least 4"):
        trimag.fit(truth.distort(body_field(R, H_N)), model="interference12", reference=H_N, attitude=R)
    # many samples, still only 3 attitudes
    R9 = Rotation.concatenate([R, R, R])
    with pytest.raises(IdentifiabilityError, match="only 3 distinct attitude"):
        trimag.fit(truth.distort(body_field(R9, H_N)), model="interference12", reference=H_N, attitude=R9)


def test_coplanar_heading_only_turn_is_refused():
    R = from_euler(np.arange(0, 360, 30), 0, 0)
    with pytest.raises(IdentifiabilityError, match="coplanar"):
        trimag.fit(_truth().distort(body_field(R, H_N)), model="interference12", reference=H_N, attitude=R)
    assert IdentifiabilityError.exit_code == 3


def test_noise_gives_small_errors_and_std():
    rng = np.random.default_rng(5)
    truth = _truth(4)
    R = _attitudes(40, seed=6)
    H_m = truth.distort(body_field(R, H_N)) + rng.normal(scale=3.0, size=(40, 3))
    cal = trimag.fit(H_m, model="interference12", reference=H_N, attitude=R, units="nT")
    assert cal.stats["rms_after"] < 10.0 < cal.stats["rms_before"]
    std = cal.uncertainty["param_std"]
    err = np.array(list(cal.params.values())) - truth.as_vector()
    # errors within 5 standard errors for every coefficient
    assert np.all(np.abs(err) < 5 * np.array([std[k] for k in truth.param_names()]))


def test_bad_input_messages():
    truth = _truth()
    R = _attitudes(6)
    H_m = truth.distort(body_field(R, H_N))
    with pytest.raises(TrimagInputError, match="attitude"):
        trimag.fit(H_m, model="interference12", reference=H_N)
    with pytest.raises(TrimagInputError, match="one attitude per sample"):
        trimag.fit(H_m, model="interference12", reference=H_N, attitude=R[:5])
    with pytest.raises(TrimagInputError, match="background"):
        trimag.fit(H_m, model="interference12", attitude=R)
    with pytest.raises(TrimagInputError, match="3 finite numbers"):
        trimag.fit(H_m, model="interference12", reference=[1.0, 2.0], attitude=R)
    bad = H_m.copy()
    bad[2, 0] = np.nan
    with pytest.raises(TrimagInputError, match="NaN"):
        trimag.fit(bad, model="interference12", reference=H_N, attitude=R)


def test_joint_background_estimate_noise_free():
    truth = _truth(7)
    R = _attitudes(30, seed=8)
    H_m = truth.distort(body_field(R, H_N))
    K, c, H_n, _info = fit_with_background(H_m, R, float(np.linalg.norm(H_N)))
    np.testing.assert_allclose(H_n, H_N, atol=1e-6)
    np.testing.assert_allclose(K, truth.K, atol=1e-10)
    np.testing.assert_allclose(c, truth.c, atol=1e-6)
    # through the estimator option, starting from a wrong direction with the right magnitude
    wrong = np.linalg.norm(H_N) * np.array([0.0, 1.0, 0.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cal = trimag.fit(H_m, model="interference12", reference=wrong, attitude=R, units="nT",
                         estimate_background=True)
    np.testing.assert_allclose(cal.diagnostics["background_ned"], H_N, atol=1e-6)


def test_joint_background_needs_rotations_about_several_axes():
    R = from_euler(np.arange(0, 360, 20), 0, 0)
    H_m = _truth().distort(body_field(R, H_N))
    with pytest.raises(IdentifiabilityError):
        fit_with_background(H_m, R, float(np.linalg.norm(H_N)))


@pytest.mark.slow
def test_cli_fit_interference12_end_to_end(tmp_path):
    """The installed ``trimag fit`` with Euler or ENU-quaternion columns; 3 attitudes -> exit 3."""
    truth = _truth(11)
    yaw, pitch, roll = np.array([[0, 0, 0], [60, 30, -20], [130, -40, 25], [200, 15, 50], [290, -25, -45],
                                 [330, 45, 10]], dtype=float).T
    R = from_euler(yaw, pitch, roll)
    H_m = truth.distort(body_field(R, H_N))
    # the same attitudes as quaternions of body -> ENU, scalar last
    q_enu = (Rotation.from_matrix(ENU_TO_NED.T) * R).as_quat(scalar_first=False)
    df = pd.DataFrame({"x": H_m[:, 0], "y": H_m[:, 1], "z": H_m[:, 2], "yaw": yaw, "pitch": pitch, "roll": roll,
                       "qx": q_enu[:, 0], "qy": q_enu[:, 1], "qz": q_enu[:, 2], "qw": q_enu[:, 3]})
    df.to_csv(tmp_path / "vehicle.csv", index=False)
    bg = ",".join(str(v) for v in H_N)
    common = ["fit", tmp_path / "vehicle.csv", "--model", "interference12", "--units", "nT",
              "--background-ned", bg, "--json"]
    for extra in (["--attitude-columns", "yaw,pitch,roll"],
                  ["--quaternion-columns", "qx,qy,qz,qw", "--quaternion-order", "xyzw", "--quaternion-frame", "enu"]):
        proc = run_trimag(*common, *extra, "-o", tmp_path / "cal.json")
        assert proc.returncode == 0, proc.stderr
        out = json.loads(proc.stdout)
        assert out["method"] == "linear-vector"
        got = np.array([out["params"][k] for k in truth.param_names()])
        np.testing.assert_allclose(got, truth.as_vector(), atol=1e-6)
    df.iloc[:3].to_csv(tmp_path / "three.csv", index=False)
    proc = run_trimag("fit", tmp_path / "three.csv", "--model", "interference12", "--units", "nT",
                      "--background-ned", bg, "--attitude-columns", "yaw,pitch,roll")
    assert proc.returncode == 3
    assert "at least 4" in proc.stderr and "Traceback" not in proc.stderr
