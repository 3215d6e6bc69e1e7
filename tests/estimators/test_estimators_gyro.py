"""The gyro-aided fit (issue 31, items 1-2; docs/method-gyro.md): simulated logs with known truth
(:func:`trimag.simulate.simulate_gyro`: 100 Hz, a phone-like sensor in uT, 0.3 uT noise per axis, a gyroscope with a
bias of (0.01, -0.02, 0.015) rad/s and 0.002 rad/s of noise, the magnetometer turned 2 degrees from the gyroscope)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import trimag
from trimag.errors import IdentifiabilityError, IdentifiabilityWarning, TrimagInputError
from trimag.estimators import get_estimator
from trimag.estimators import gyro as gyro_module
from trimag.estimators.gyro import GyroAided
from trimag.fields.gyro import AngularRate
from trimag.quality.crlb import UPPER
from trimag.simulate import simulate_gyro

SOFT = ("w11", "w12", "w13", "w22", "w23", "w33")
HARD = ("hard_iron_x", "hard_iron_y", "hard_iron_z")
BIAS = ("gyro_bias_x", "gyro_bias_y", "gyro_bias_z")
ROT = ("gyro_alignment_x", "gyro_alignment_y", "gyro_alignment_z")


def _fit(sim, F: float | None = None, **options):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        est = GyroAided(**options).fit(sim.raw, F, units="uT", attitude=sim.angular_rate())
    return est.calibration_, [str(w.message) for w in caught if issubclass(w.category, IdentifiabilityWarning)]


def _z_scores(sim, cal) -> dict[str, float]:
    std = cal.uncertainty["param_std"]
    err = dict(zip(SOFT, cal.matrix[UPPER] - sim.matrix[UPPER], strict=True))
    err.update(zip(HARD, cal.offset - sim.offset, strict=True))
    err.update(zip(BIAS, np.asarray(cal.diagnostics["gyro"]["bias_rad_s"]) - sim.gyro_bias, strict=True))
    R = np.asarray(cal.diagnostics["gyro_alignment"]["matrix"])
    err.update(zip(ROT, Rotation.from_matrix(R @ sim.alignment.T).as_rotvec(), strict=True))
    return {k: v / std[k] for k, v in err.items()}


def test_registered_for_the_ellipsoid():
    assert get_estimator("gyro") is GyroAided and GyroAided.models == ("ellipsoid",)
    assert GyroAided.reference_kind == "gyro"


@pytest.mark.parametrize("motion", ["tumble", "cone"])
def test_recovered_within_the_sigmas_over_20_logs(motion):
    """Done-when of issue 31: soft iron, hard iron, the gyroscope's bias (and the rotation to its frame) within
    their sigmas over 20 logs (60 s each): the z-scores' standard deviation <= 1.2 per group (soft iron: 120
    values, the others 60), their mean within 0.35, no single parameter's above 1.5 (20 values each)."""
    z = {k: [] for k in (*SOFT, *HARD, *BIAS, *ROT)}
    F = float(np.linalg.norm(simulate_gyro(10, 0).field_nav))
    for seed in range(20):
        sim = simulate_gyro(6000, seed, motion=motion)
        cal, caught = _fit(sim, F)
        assert not caught, caught
        for k, v in _z_scores(sim, cal).items():
            z[k].append(v)
    for group in (SOFT, HARD, BIAS, ROT):
        pooled = np.concatenate([z[k] for k in group])
        assert pooled.std(ddof=1) <= 1.2 and abs(pooled.mean()) <= 0.35, (group, pooled.std(ddof=1), pooled.mean())
        for k in group:
            assert np.std(z[k], ddof=1) <= 1.5, (k, np.std(z[k], ddof=1))


def test_a_90_degree_cone_identifies_what_the_magnitude_alone_cannot():
    """Done-when of issue 31: the field's body-frame direction within a 90-degree cone. ``ml`` warns that the
    calibration is poorly identified (its worst combination >100x a full sphere's sigma); the gyro-aided fit of the
    same samples does not warn, names what it identifies that the magnitude alone does not, and is right."""
    sim = simulate_gyro(6000, 3, motion="cone")
    F = float(np.linalg.norm(sim.field_nav))
    with pytest.warns(IdentifiabilityWarning, match="poorly identified"):
        ml = trimag.fit(sim.raw, reference=F, units="uT")
    ml_ident = ml.diagnostics["identifiability"]
    assert ml_ident["std_inflation_vs_full_sphere"] > 100
    cal, caught = _fit(sim, F)
    assert not caught
    ident = cal.diagnostics["identifiability"]
    assert ident["std_inflation_vs_full_sphere"] < 30 and not ident["unidentified"]
    assert set(ident["magnitude_only"]["unidentified"]) >= {"hard_iron_x", "hard_iron_y", "hard_iron_z"}
    assert set(ident["identified_by_gyro"]) == set(ident["magnitude_only"]["unidentified"])
    z = _z_scores(sim, cal)
    assert max(abs(v) for v in z.values()) < 3.5, z
    # the magnitude-only fit is much less certain, and further off
    assert all(ident["magnitude_only"]["std_ratio_to_gyro"][k] > 3 for k in HARD)


def test_noise_free_exact_and_the_unknown_magnitude():
    sim = simulate_gyro(3000, 5, mag_noise=0.0, gyro_noise=0.0)
    cal, _ = _fit(sim, None)
    s = np.cbrt(np.linalg.det(sim.matrix))
    np.testing.assert_allclose(cal.matrix, sim.matrix / s, atol=1e-7)
    np.testing.assert_allclose(cal.offset, sim.offset, atol=1e-5)
    assert cal.reference["fitted_radius"] == pytest.approx(np.linalg.norm(sim.field_nav) / s, rel=1e-7)
    np.testing.assert_allclose(cal.diagnostics["gyro"]["bias_rad_s"], sim.gyro_bias, atol=1e-7)
    np.testing.assert_allclose(cal.diagnostics["gyro_alignment"]["matrix"], sim.alignment, atol=1e-7)
    assert "F" in cal.uncertainty["covariance_order"]


def test_alignment_to_the_gyroscope_frame():
    """Item 2: a magnetometer mounted at 90 degrees of yaw (plus 2 degrees) from the gyroscope: the rotation of its
    own axes to the gyroscope's (symmetric soft iron, so the truth is the mounting) within its sigma."""
    mount = Rotation.from_rotvec(np.radians(2.0) * np.array([1.0, -1.0, 2.0]) / np.sqrt(6)) * Rotation.from_euler(
        "Z", 90, degrees=True)
    W = np.array([[1.04, 0.02, -0.01], [0.02, 0.97, 0.03], [-0.01, 0.03, 1.01]])  # symmetric
    sim = simulate_gyro(6000, 2, matrix=W, alignment=mount)
    cal, _ = _fit(sim, float(np.linalg.norm(sim.field_nav)), form="symmetric")
    align = cal.diagnostics["gyro_alignment"]
    np.testing.assert_allclose(cal.matrix, W, atol=5e-4)
    miss = Rotation.from_matrix(np.asarray(align["sensor_matrix"]) @ mount.as_matrix().T).as_rotvec()
    assert np.all(np.abs(np.degrees(miss)) < 4 * np.asarray(align["rotation_std_deg"]) + 1e-3), (miss, align)
    assert align["sensor_euler_zyx_deg"][0] == pytest.approx(mount.as_euler("ZYX", degrees=True)[0], abs=0.05)


def test_lag_between_two_clocks():
    """A gyroscope with its own clock (200 Hz, stamps 37 ms ahead): the lag is fitted, within its sigma."""
    sim = simulate_gyro(6000, 3, gyro_rate_hz=200.0, lag_s=0.037)
    cal, _ = _fit(sim, None)
    g = cal.diagnostics["gyro"]
    assert g["lag_estimated"] and g["own_clock"]
    std = cal.uncertainty["param_std"]["lag_s"]
    assert abs(g["lag_s"] - 0.037) < 3 * std and std < 1e-3
    assert g["vector_rms"] < 1.05 * 0.3 * np.sqrt(3)
    # the same data with the lag held at 0 fit far worse
    cal0, _ = _fit(sim, None, estimate_lag=False)
    assert cal0.diagnostics["gyro"]["vector_rms"] > 1.5 * g["vector_rms"]


def test_jacobian_against_finite_differences():
    """The analytic Jacobian (bias and lag included) against central differences of the residual."""
    sim = simulate_gyro(400, 4, gyro_rate_hz=150.0, lag_s=0.02, mag_noise=0.0, gyro_noise=0.0)
    est = GyroAided(segment_s=1.0, estimate_lag=True)
    problem, _ = est._problem(sim.raw, sim.angular_rate())
    p = gyro_module._linear_start(problem, 0.02)
    p[12:15] = [0.01, -0.02, 0.015]
    st, _ = gyro_module._evaluate(problem, p)
    E = gyro_module._tangent(st.h)
    J, L = gyro_module._jacobians(problem, st, slice(0, len(problem.u)), E)
    for k in range(problem.p):
        e = np.zeros_like(p)
        e[k] = 1e-6
        num = (gyro_module._evaluate(problem, p + e)[0].r - gyro_module._evaluate(problem, p - e)[0].r) / 2e-6
        np.testing.assert_allclose(J[:, :, k], num, atol=2e-5 * max(1.0, np.abs(num).max()), err_msg=f"column {k}")
    s = 1  # a segment's direction, along its first tangent vector
    rows = problem.seg == s
    h = p[problem.p:].reshape(-1, 3)
    for sign in (1, -1):
        q = p.copy()
        q[problem.p:] = (h + sign * 1e-6 * (np.arange(len(h)) == s)[:, None] * E[:, :, 0]).ravel()
        if sign == 1:
            plus = gyro_module._evaluate(problem, q)[0].r
        else:
            minus = gyro_module._evaluate(problem, q)[0].r
    np.testing.assert_allclose(L[rows, :, 0], ((plus - minus) / 2e-6)[rows], atol=1e-5)


def test_refusals():
    sim = simulate_gyro(2000, 1)
    F = float(np.linalg.norm(sim.field_nav))
    with pytest.raises(TrimagInputError, match="angular rate"):
        GyroAided().fit(sim.raw, F)
    with pytest.raises(TrimagInputError, match="one time stamp per sample"):
        GyroAided().fit(sim.raw[:-5], F, attitude=sim.angular_rate())
    with pytest.raises(TrimagInputError, match="one field magnitude"):
        GyroAided().fit(sim.raw, np.linspace(40, 50, len(sim.raw)), attitude=sim.angular_rate())
    # the magnetometer's x and y swapped (a mirror image of the gyroscope's axes): the kinematics and the magnitude
    # do not see the field's sign, so it fits as a 180-degree rotation about (1, -1, 0) with the field reversed
    # (ArduPilot's ROTATION_ROLL_180_YAW_270): documented in docs/method-gyro.md
    swapped = GyroAided().fit(sim.raw[:, [1, 0, 2]], F, attitude=sim.angular_rate()).calibration_
    sensor = np.asarray(swapped.diagnostics["gyro_alignment"]["sensor_matrix"])
    np.testing.assert_allclose(sensor, -np.eye(3)[[1, 0, 2]], atol=0.05)
    # a sensor that does not turn: refused (exit 3)
    still = AngularRate.same_rows(sim.time_s, np.zeros((len(sim.raw), 3)))
    raw = np.tile(sim.raw[:1], (len(sim.raw), 1)) + np.random.default_rng(0).normal(0, 0.3, sim.raw.shape)
    with pytest.raises(IdentifiabilityError):
        GyroAided().fit(raw, F, attitude=still)
