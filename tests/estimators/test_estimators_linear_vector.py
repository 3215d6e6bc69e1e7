"""linear-vector: paper C's three 4-unknown least-squares problems."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pandas as pd
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

import trimag
from trimag.calibration import Calibration
from trimag.errors import IdentifiabilityError, NotFittedError, TrimagInputError
from trimag.estimators import get_estimator
from trimag.estimators import linear_vector as lv
from trimag.estimators.linear_vector import LinearVector, fit_with_background, solve_interference
from trimag.fields.attitude import ENU_TO_NED, body_field, from_euler
from trimag.models.interference12 import Interference12
from trimag.quality.diagnostics import design_condition

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


def test_joint_background_scale_gauges():
    """Issue 31, item 3: without a reference the scale is ``det K = 1`` (|H_n| = the mean corrected magnitude),
    with a number it is that magnitude; a number without ``estimate_background`` is refused."""
    truth = _truth(7)
    R = _attitudes(30, seed=8)
    H_m = truth.distort(body_field(R, H_N))
    cal = trimag.fit(H_m, model="interference12", attitude=R, units="nT", estimate_background=True)
    K = np.linalg.inv(cal.matrix)
    s = np.cbrt(np.linalg.det(truth.K))
    assert np.linalg.det(K) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(K, truth.K / s, atol=1e-9)
    np.testing.assert_allclose(cal.diagnostics["background_ned"], H_N * s, atol=1e-6)
    np.testing.assert_allclose(cal.offset, truth.c, atol=1e-6)
    assert cal.diagnostics["background_fitted"] and "det(K) = 1" in cal.diagnostics["background_scale"]
    cal = trimag.fit(H_m, model="interference12", reference=50000.0, attitude=R, units="nT",
                     estimate_background=True)
    assert np.linalg.norm(cal.diagnostics["background_ned"]) == pytest.approx(50000.0, rel=1e-12)
    with pytest.raises(TrimagInputError, match="not a magnitude"):
        trimag.fit(H_m, model="interference12", reference=50000.0, attitude=R, units="nT")


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


# --- joint background fit on the 13-row factor of [D10 | B] (variable projection, analytic Jacobian) -----------


def _noisy_vehicle(n: int, noise: float, seed: int, random_attitudes: bool = True) -> tuple[np.ndarray, Rotation]:
    truth = _truth(seed)
    R = Rotation.random(n, random_state=seed) if random_attitudes else _attitudes(n, seed=seed + 1)
    rng = np.random.default_rng(seed + 100)
    return truth.distort(body_field(R, H_N)) + rng.normal(scale=noise, size=(n, 3)), R


def _full_residual(H_m: np.ndarray, R: Rotation, h: np.ndarray) -> np.ndarray:
    """``B - A(h) X(h)`` on all N samples (N, 3), ``A(h) = [C_i^T h, 1]``."""
    A = np.column_stack([R.inv().apply(h), np.ones(len(H_m))])
    X, *_ = np.linalg.lstsq(A, H_m, rcond=None)
    return H_m - A @ X


def _reference_fit(H_m: np.ndarray, R: Rotation, magnitude: float, max_iter: int = 50):
    """The straightforward full-data fit (the implementation before the 13-row reduction): the (N, 10) linear start,
    then variable projection over all 3N residuals with a finite-difference Jacobian."""
    B = np.asarray(H_m, dtype=np.float64)
    D = np.column_stack([R.inv().as_matrix().reshape(len(B), 9), np.ones(len(B))])
    cond_lin, _, _ = design_condition(D)
    X, *_ = np.linalg.lstsq(D, B, rcond=None)
    u, sv, vt = np.linalg.svd(X[:9].T.reshape(9, 3), full_matrices=False)
    h0 = vt[0] if np.linalg.det((sv[0] * u[:, 0]).reshape(3, 3)) >= 0 else -vt[0]
    e1, e2 = lv._orthonormal_complement(h0)

    def direction(p: np.ndarray) -> np.ndarray:
        v = h0 + p[0] * e1 + p[1] * e2
        return v / np.linalg.norm(v)

    res = least_squares(lambda p: _full_residual(B, R, magnitude * direction(p)).ravel(), np.zeros(2),
                        method="lm", xtol=1e-14, ftol=1e-14, max_nfev=max_iter * 3)
    H_n = magnitude * direction(res.x)
    K, c, info = solve_interference(B, R.inv().apply(H_n))
    if np.linalg.det(K) < 0:
        H_n = -H_n
        K, c, info = solve_interference(B, R.inv().apply(H_n))
    info.update({"linear_condition_number": cond_lin, "iterations": int(res.nfev), "converged": bool(res.success),
                 "background_start": (magnitude * h0).tolist()})
    return K, c, H_n, info


def _projection(H_m: np.ndarray, R: Rotation, block: int | None = None) -> lv._ReducedProjection:
    Rf = lv._factor_background_design(H_m, R, block=block)
    X, *_ = np.linalg.lstsq(Rf[:10, :10], Rf[:10, 10:], rcond=None)
    h0 = np.linalg.svd(X[:9].T.reshape(9, 3))[2][0]
    return lv._ReducedProjection(Rf, float(np.linalg.norm(H_N)), h0)


def _rel(a, b) -> float:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


@pytest.mark.parametrize("block", [None, 97])
def test_reduced_residual_norm_equals_full_residual_norm(block):
    H_m, R = _noisy_vehicle(1000, 3.0, seed=21)
    proj = _projection(H_m, R, block=block)
    assert proj.Bs.shape == (13, 3)
    rng = np.random.default_rng(22)
    F = np.linalg.norm(H_N)
    for h in [H_N, H_N + rng.normal(scale=50.0, size=3), *(F * rng.normal(size=(6, 3)))]:
        full = np.linalg.norm(_full_residual(H_m, R, h))
        reduced = np.linalg.norm(proj.residual_matrix(h))
        assert reduced == pytest.approx(full, rel=1e-10)
    # the linear start from R: the (N, 10) least squares and its condition number
    D = np.column_stack([R.inv().as_matrix().reshape(len(H_m), 9), np.ones(len(H_m))])
    Rf = lv._factor_background_design(H_m, R, block=block)
    X_full, *_ = np.linalg.lstsq(D, H_m, rcond=None)
    np.testing.assert_allclose(np.linalg.lstsq(Rf[:10, :10], Rf[:10, 10:], rcond=None)[0], X_full, rtol=0,
                               atol=1e-10 * np.abs(X_full).max())
    assert design_condition(Rf[:10, :10])[0] == pytest.approx(design_condition(D)[0], rel=1e-10)


def test_analytic_jacobian_matches_finite_differences():
    H_m, R = _noisy_vehicle(600, 300.0, seed=23)
    proj = _projection(H_m, R)
    rng = np.random.default_rng(24)
    for p in [np.zeros(2), *(0.05 * rng.normal(size=(4, 2)))]:
        J = proj.jacobian(p)
        assert J.shape == (39, 2)
        step = 1e-6
        J_fd = np.column_stack([(proj.residual(p + step * e) - proj.residual(p - step * e)) / (2 * step)
                                for e in np.eye(2)])
        np.testing.assert_allclose(J, J_fd, rtol=0, atol=1e-6 * np.abs(J).max())
        # the same Gauss-Newton quantities as a finite-difference Jacobian of the full 3N residuals
        full = np.column_stack([(_full_residual(H_m, R, proj.background(p + step * e))
                                 - _full_residual(H_m, R, proj.background(p - step * e))).ravel() / (2 * step)
                                for e in np.eye(2)])
        np.testing.assert_allclose(J.T @ J, full.T @ full, rtol=1e-6)
        r, r_full = proj.residual(p), _full_residual(H_m, R, proj.background(p)).ravel()
        np.testing.assert_allclose(J.T @ r, full.T @ r_full, rtol=0,
                                   atol=1e-6 * np.linalg.norm(J) * np.linalg.norm(r))


@pytest.mark.parametrize(
    ("n", "noise", "seed", "random_attitudes", "block"),
    [
        (200, 3.0, 31, True, None),
        (2000, 300.0, 32, True, None),
        (5000, 30.0, 33, False, None),
        (3000, 100.0, 34, True, 211),  # many blocks
        (40, 3.0, 6, False, None),
    ],
)
def test_fit_with_background_equals_full_data_reference(small_chunks, n, noise, seed, random_attitudes, block):
    if block is not None:
        small_chunks(block * 104 * 12 // 24)  # QR panels of 13 columns and `block` rows
    H_m, R = _noisy_vehicle(n, noise, seed, random_attitudes)
    F = float(np.linalg.norm(H_N))
    K, c, H_n, info = fit_with_background(H_m, R, F)
    K0, c0, H0, info0 = _reference_fit(H_m, R, F)
    assert _rel(K, K0) < 1e-8 and _rel(c, c0) < 1e-8 and _rel(H_n, H0) < 1e-8
    assert info.keys() == info0.keys()
    assert info["iterations"] == info0["iterations"] and info["converged"] == info0["converged"]
    assert info["n_attitudes"] == info0["n_attitudes"] == n
    for key in ("linear_condition_number", "condition_number", "background_start"):
        assert _rel(info[key], info0[key]) < 1e-9, key
    # the total residual is stationary at the optimum, each axis's is not: a 1e-10 change of direction (the
    # reference's finite-difference Jacobian stops there) moves the per-axis RMS by ~F / rms times that
    rms, rms0 = np.array(info["residual_rms_axis"]), np.array(info0["residual_rms_axis"])
    assert np.sum(rms**2) == pytest.approx(np.sum(rms0**2), rel=1e-12)
    assert _rel(rms, rms0) < 1e-8
    assert _rel(list(info["param_std"].values()), list(info0["param_std"].values())) < 1e-8


@pytest.mark.parametrize("n", [8, 12])
def test_fit_with_background_fewer_samples_than_columns(n):
    """Fewer than 13 (or 10) samples: R is trapezoidal, the linear start the minimum-norm one as before."""
    H_m, R = _noisy_vehicle(n, 3.0, seed=41)
    F = float(np.linalg.norm(H_N))
    K, c, H_n, info = fit_with_background(H_m, R, F)
    K0, c0, H0, info0 = _reference_fit(H_m, R, F)
    assert _rel(K, K0) < 1e-8 and _rel(c, c0) < 1e-8 and _rel(H_n, H0) < 1e-8
    assert _rel(info["linear_condition_number"], info0["linear_condition_number"]) < 1e-9
    assert _rel(info["background_start"], info0["background_start"]) < 1e-9


def test_fit_with_background_input_checks():
    H_m, R = _noisy_vehicle(50, 3.0, seed=42)
    with pytest.raises(TrimagInputError, match="one attitude per sample"):
        fit_with_background(H_m, R[:49], 5e4)
    with pytest.raises(TrimagInputError, match=r"\(N, 3\)"):
        fit_with_background(H_m[:, :2], R, 5e4)


def test_solve_interference_in_blocks_matches_the_whole_least_squares(small_chunks):
    """Blocks of 7 rows: K, c, residuals, standard errors and singular values of the one-shot [H_b, 1] fit."""
    from trimag.estimators.linear_vector import solve_interference

    rng = np.random.default_rng(11)
    H_b = Rotation.random(300, random_state=3).inv().apply([30000.0, 2000.0, 40000.0])
    K = np.array([[1.02, 0.01, -0.02], [0.03, 0.97, 0.01], [0.0, 0.02, 1.01]])
    H_m = H_b @ K.T + [200.0, -100.0, 50.0] + rng.normal(scale=30.0, size=H_b.shape)
    small_chunks(7)
    K_fit, c_fit, info = solve_interference(H_m, H_b)
    A = np.column_stack([H_b, np.ones(len(H_b))])
    X, *_ = np.linalg.lstsq(A, H_m, rcond=None)
    np.testing.assert_allclose(K_fit, X[:3].T, rtol=1e-10)
    np.testing.assert_allclose(c_fit, X[3], rtol=1e-9)
    resid = H_m - A @ X
    np.testing.assert_allclose(info["residual_rms_axis"], np.sqrt(np.mean(resid**2, axis=0)), rtol=1e-9)
    s2 = np.sum(resid**2, axis=0) / (len(A) - 4)
    std = np.sqrt(np.outer(s2, np.diag(np.linalg.inv(A.T @ A))))
    assert info["param_std"]["k12"] == pytest.approx(std[0, 1], rel=1e-9)
    assert info["param_std"]["c3"] == pytest.approx(std[2, 3], rel=1e-9)
    d = np.linalg.norm(A, axis=0)
    np.testing.assert_allclose(info["singular_values"], np.linalg.svd(A / d, compute_uv=False), rtol=1e-10)


def _survey(n: int = 3000, noise: float = 1.0, seed: int = 5) -> tuple[np.ndarray, Rotation, np.ndarray]:
    """A survey line: the background (NED, nT) changes by a few hundred nT along the track (IGRF gradient and a
    regional anomaly), the aircraft weaves (heading changes, pitch/roll manoeuvres)."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, n)
    H = H_N + np.column_stack([250.0 * s, -120.0 * s, 300.0 * s]) + 150.0 * np.sin(2 * np.pi * 3 * s)[:, None]
    R = from_euler(rng.uniform(0, 360, n), rng.uniform(-40, 40, n), rng.uniform(-40, 40, n))
    B = _truth(3).distort(body_field(R, H)) + rng.normal(size=(n, 3)) * noise
    return B, R, H


def test_per_sample_background_reaches_the_noise_floor_the_mean_does_not():
    """A (N, 3) NED background (IGRF along a line, a reference vector magnetometer) is used row by row."""
    B, R, H = _survey(noise=1.0)
    per_sample = trimag.fit(B, model="interference12", reference=H, attitude=R, units="nT")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mean = trimag.fit(B, model="interference12", reference=H.mean(axis=0), attitude=R, units="nT")
    floor = np.sqrt(3.0) * 1.0  # vector RMS of white noise of 1 nT per axis
    assert per_sample.stats["vector_rms_after"] < 1.05 * floor
    assert mean.stats["vector_rms_after"] > 20 * floor
    truth = _truth(3).as_vector()
    assert np.max(np.abs(Interference12.from_dict(per_sample.params).as_vector() - truth)[9:]) < 1.0  # c, nT
    assert per_sample.reference["per_sample"] and per_sample.diagnostics["background_per_sample"]
    assert len(json.dumps(per_sample.as_dict())) < 20_000  # the background is summarised, not stored per row
    with pytest.raises(TrimagInputError, match=r"one row per sample .* 3000 .* got 10 rows"):
        trimag.fit(B, model="interference12", reference=H[:10], attitude=R, units="nT")


def test_cli_background_columns_fit_and_evaluate(tmp_path):
    B, R, H = _survey(n=1500, noise=1.0, seed=8)
    ypr = R.as_euler("ZYX", degrees=True)
    df = pd.DataFrame({"x": B[:, 0], "y": B[:, 1], "z": B[:, 2], "yaw": ypr[:, 0], "pitch": ypr[:, 1],
                       "roll": ypr[:, 2], "bn": H[:, 0], "be": H[:, 1], "bd": H[:, 2]})
    df.loc[17, "bd"] = np.nan  # a row without a background: dropped and counted
    log = tmp_path / "survey.csv"
    df.to_csv(log, index=False)
    cal = tmp_path / "cal.json"
    common = ("--columns", "x,y,z", "--attitude-columns", "yaw,pitch,roll", "--units", "nT")
    r = run_trimag("fit", log, *common, "--model", "interference12", "--background-columns", "bn,be,bd", "-o", cal,
                   "--json")
    assert r.returncode == 0, r.stderr
    assert "dropped 1 rows whose background is missing" in r.stderr + r.stdout
    assert json.loads(r.stdout)["rms_after"] < 1.1
    assert json.loads(cal.read_text())["stats"]["vector_rms_after"] < 1.1 * np.sqrt(3.0)
    e = run_trimag("evaluate", cal, log, *common, "--background-columns", "bn,be,bd", "--json")
    assert e.returncode == 0, e.stderr
    ev = json.loads(e.stdout)
    assert ev["rms_after"] < 1.1 * np.sqrt(3.0) and ev["n_used"] == 1499 and ev["background"]["per_sample"]
    both = run_trimag("fit", log, *common, "--model", "interference12", "--background-columns", "bn,be,bd",
                      "--background-ned", "1,2,3")
    assert both.returncode == 2 and "--background-columns" in both.stderr and "Traceback" not in both.stderr
