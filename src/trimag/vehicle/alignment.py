"""Sensor-to-accelerometer alignment from the invariance of the angle between field and gravity (issue 20, item 2).

A vehicle at rest (or moving slowly) sees gravity and the Earth's field at a fixed angle whatever its attitude:
with ``m_i`` the unit corrected field in the magnetometer's (corrected) frame and ``d_i = -a_i / |a_i|`` the unit
down direction from the accelerometer's specific force ``a_i`` (level and at rest ``a = (0, 0, -g)``; body frame
forward-right-down, docs/conventions-attitude.md), the rotation ``R`` (corrected magnetometer frame ->
accelerometer frame) and the dip (inclination) ``I`` satisfy

    (R m_i) . d_i = sin I        for every sample i.

``R`` and ``I`` are estimated jointly by Gauss-Newton with a multiplicative update ``R <- exp([delta]x) R``
(Levenberg damping when a step does not descend), from the best of the 24 axis-aligned rotations as starts. The
residual's Jacobian is ``(R m_i) x d_i`` for ``delta`` (a small rotation vector in the accelerometer frame) and
``-cos I`` for the dip. ``(R m_i) x d_i`` is the magnetic east direction in the body frame (times ``cos I``): a
rotation about the vertical is seen only when the vertical moves in the body frame, i.e. when the vehicle is tilted
in pitch and roll; data recorded level (turning about the vertical only), or pitched about one horizontal axis
only, leave a rotation unobserved. That is detected from the Jacobian's singular values and refused
(:class:`~trimag.errors.IdentifiabilityError`, exit 3).

Uncertainty: ``sigma^2 (J^T J)^-1`` with ``sigma^2`` from the residuals times their integrated autocorrelation time
(:func:`trimag.quality.honesty.correlation_time`); with an ellipsoid-model calibration whose covariance is known, the
calibration's uncertainty is propagated too (``G C_cal G'``, ``G = -(J^T J)^-1 J^T dr/dtheta_cal``).

The rotation of the sensor's own axes, ``R Q`` with ``W = Q P`` the polar decomposition of the calibration matrix
(the frame a symmetric soft-iron correction, as ArduPilot and PX4 apply, leaves), is also expressed as the nearest
standard autopilot board rotation (ArduPilot's ``COMPASS_ORIENT`` / ``AHRS_ORIENTATION`` list,
``libraries/AP_Math/rotations.h``; ``v_body = R_board v_sensor`` with ``R_board = Rz(yaw) Ry(pitch) Rx(roll)``) and
the remaining rotation.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from .._core.solve import gauss_newton_then_lm
from ..calibration import Calibration
from ..errors import IdentifiabilityError, TrimagInputError
from ..quality.honesty import correlation_time

__all__ = [
    "BOARD_ROTATIONS",
    "MIN_COS_DIP",
    "MIN_TILT_SPREAD_DEG",
    "RANK_TOLERANCE",
    "RESIDUAL_WARNING_DEG",
    "alignment_heading_sigma",
    "board_rotation_matrix",
    "check_tilt_variation",
    "fit_alignment",
    "nearest_board_rotation",
    "polar_rotation",
]

#: ArduPilot's board rotations (``enum Rotation`` of ``libraries/AP_Math/rotations.h``; MAVLink's
#: ``MAV_SENSOR_ORIENTATION``): name -> (number, roll, pitch, yaw) in degrees, ``R = Rz(yaw) Ry(pitch) Rx(roll)``.
#: Number 38 (roll 90, pitch 68, yaw 293) and 41 (pitch 7), board-specific odd angles, are left out.
BOARD_ROTATIONS: dict[str, tuple[int, float, float, float]] = {
    "ROTATION_NONE": (0, 0, 0, 0),
    "ROTATION_YAW_45": (1, 0, 0, 45),
    "ROTATION_YAW_90": (2, 0, 0, 90),
    "ROTATION_YAW_135": (3, 0, 0, 135),
    "ROTATION_YAW_180": (4, 0, 0, 180),
    "ROTATION_YAW_225": (5, 0, 0, 225),
    "ROTATION_YAW_270": (6, 0, 0, 270),
    "ROTATION_YAW_315": (7, 0, 0, 315),
    "ROTATION_ROLL_180": (8, 180, 0, 0),
    "ROTATION_ROLL_180_YAW_45": (9, 180, 0, 45),
    "ROTATION_ROLL_180_YAW_90": (10, 180, 0, 90),
    "ROTATION_ROLL_180_YAW_135": (11, 180, 0, 135),
    "ROTATION_PITCH_180": (12, 0, 180, 0),
    "ROTATION_ROLL_180_YAW_225": (13, 180, 0, 225),
    "ROTATION_ROLL_180_YAW_270": (14, 180, 0, 270),
    "ROTATION_ROLL_180_YAW_315": (15, 180, 0, 315),
    "ROTATION_ROLL_90": (16, 90, 0, 0),
    "ROTATION_ROLL_90_YAW_45": (17, 90, 0, 45),
    "ROTATION_ROLL_90_YAW_90": (18, 90, 0, 90),
    "ROTATION_ROLL_90_YAW_135": (19, 90, 0, 135),
    "ROTATION_ROLL_270": (20, 270, 0, 0),
    "ROTATION_ROLL_270_YAW_45": (21, 270, 0, 45),
    "ROTATION_ROLL_270_YAW_90": (22, 270, 0, 90),
    "ROTATION_ROLL_270_YAW_135": (23, 270, 0, 135),
    "ROTATION_PITCH_90": (24, 0, 90, 0),
    "ROTATION_PITCH_270": (25, 0, 270, 0),
    "ROTATION_PITCH_180_YAW_90": (26, 0, 180, 90),
    "ROTATION_PITCH_180_YAW_270": (27, 0, 180, 270),
    "ROTATION_ROLL_90_PITCH_90": (28, 90, 90, 0),
    "ROTATION_ROLL_180_PITCH_90": (29, 180, 90, 0),
    "ROTATION_ROLL_270_PITCH_90": (30, 270, 90, 0),
    "ROTATION_ROLL_90_PITCH_180": (31, 90, 180, 0),
    "ROTATION_ROLL_270_PITCH_180": (32, 270, 180, 0),
    "ROTATION_ROLL_90_PITCH_270": (33, 90, 270, 0),
    "ROTATION_ROLL_180_PITCH_270": (34, 180, 270, 0),
    "ROTATION_ROLL_270_PITCH_270": (35, 270, 270, 0),
    "ROTATION_ROLL_90_PITCH_180_YAW_90": (36, 90, 180, 90),
    "ROTATION_ROLL_90_YAW_270": (37, 90, 0, 270),
    "ROTATION_PITCH_315": (39, 0, 315, 0),
    "ROTATION_ROLL_90_PITCH_315": (40, 90, 315, 0),
    "ROTATION_ROLL_45": (42, 45, 0, 0),
    "ROTATION_ROLL_315": (43, 315, 0, 0),
}

#: Smallest ratio of the weakest to the strongest singular value of the rotation part of the Jacobian: below it a
#: rotation component counts as unobserved (about 3 degrees of tilt spread).
RANK_TOLERANCE = 0.05
#: Least cosine of the fitted dip: a field (nearly) along gravity is a fit that maps the field onto gravity, what
#: data turned about magnetic east only allow (or a site at a magnetic pole, where heading is undefined anyway).
MIN_COS_DIP = 0.05
#: Least RMS angle (degrees) of the gravity directions about their mean before any fit is tried.
MIN_TILT_SPREAD_DEG = 3.0
#: RMS (degrees) of the field-gravity angle's residual above which the fit warns that the invariance holds poorly
#: (sensor noise gives a few tenths of a degree at most).
RESIDUAL_WARNING_DEG = 1.0
#: Samples whose ``|a|`` differs from the median by more than this fraction are dropped (the vehicle accelerated).
MAX_ACCEL_DEVIATION = 0.05

_RECORD = ("record more attitudes with the vehicle tilted in pitch and roll (nose up and down, on each side, "
           "30 degrees or more) while it is at rest or moving slowly")
_UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
_CAL_NAMES = ("w11", "w12", "w13", "w22", "w23", "w33", "hard_iron_x", "hard_iron_y", "hard_iron_z")


def board_rotation_matrix(name: str) -> NDArray[np.float64]:
    """The 3x3 matrix of a board rotation of :data:`BOARD_ROTATIONS` (``v_body = R v_sensor``).

    Examples
    --------
    >>> board_rotation_matrix("ROTATION_YAW_90").round(12) @ [1.0, 0.0, 0.0]     # sensor x is body y (right)
    array([0., 1., 0.])
    """
    if name not in BOARD_ROTATIONS:
        raise TrimagInputError(f"unknown board rotation {name!r}; known: {', '.join(BOARD_ROTATIONS)}")
    _, roll, pitch, yaw = BOARD_ROTATIONS[name]
    return np.asarray(Rotation.from_euler("ZYX", [yaw, pitch, roll], degrees=True).as_matrix(), dtype=np.float64)


def nearest_board_rotation(matrix: ArrayLike) -> dict[str, Any]:
    """The board rotation of :data:`BOARD_ROTATIONS` nearest to a rotation (sensor -> body), and what remains.

    Parameters
    ----------
    matrix : array_like, shape (3, 3)
        A rotation matrix, sensor frame -> body frame.

    Returns
    -------
    dict
        ``name``, ``number`` (the ``COMPASS_ORIENT`` value), ``remaining_angle_deg`` (angle of
        ``R R_board^T``), ``remaining_rotvec_deg`` (its rotation vector in the body frame, degrees;
        ``R = exp(remaining) R_board``).
    """
    R = np.asarray(matrix, dtype=np.float64)
    best: tuple[float, str, NDArray[np.float64]] | None = None
    for name in BOARD_ROTATIONS:
        rest = Rotation.from_matrix(R @ board_rotation_matrix(name).T).as_rotvec()
        angle = float(np.degrees(np.linalg.norm(rest)))
        if best is None or angle < best[0] - 1e-9:
            best = (angle, name, rest)
    assert best is not None
    angle, name, rest = best
    return {"name": name, "number": BOARD_ROTATIONS[name][0], "remaining_angle_deg": angle,
            "remaining_rotvec_deg": np.degrees(rest).tolist()}


def polar_rotation(matrix: ArrayLike) -> NDArray[np.float64]:
    """The rotation ``Q`` of the polar decomposition ``W = Q P`` (``P`` symmetric positive definite), shape (3, 3).

    ``W (x - b) = Q P (x - b)``: ``P`` is the symmetric soft-iron correction that autopilots apply in the sensor's
    own axes (docs/autopilot.md), ``Q`` the rotation from the sensor's axes to the calibration's corrected frame
    (the gauge of the fit: upper-triangular ``W`` for the ellipsoid estimators).
    """
    U, _, Vt = np.linalg.svd(np.asarray(matrix, dtype=np.float64))
    Q = U @ Vt
    if np.linalg.det(Q) < 0:  # a reflecting W (never a fitted one): keep a proper rotation
        U[:, -1] = -U[:, -1]
        Q = U @ Vt
    return np.asarray(Q, dtype=np.float64)


def _unit_down(accel: NDArray[np.float64]) -> NDArray[np.float64]:
    return -accel / np.linalg.norm(accel, axis=1, keepdims=True)


def check_tilt_variation(accel: ArrayLike) -> float:
    """RMS angle (degrees) of the gravity directions about their mean; refuses less than
    :data:`MIN_TILT_SPREAD_DEG` (the rotation about the vertical cannot be identified).

    Parameters
    ----------
    accel : array_like, shape (N, 3)
        Specific force, any unit (m/s^2, g).

    Raises
    ------
    IdentifiabilityError
        The vehicle stayed (nearly) level, or at one tilt.
    """
    d = _unit_down(np.asarray(accel, dtype=np.float64))
    mean = d.mean(axis=0)
    mean /= np.linalg.norm(mean)
    angle = np.degrees(np.arccos(np.clip(d @ mean, -1.0, 1.0)))
    spread = float(np.sqrt(np.mean(angle**2)))
    if not spread >= MIN_TILT_SPREAD_DEG:
        raise IdentifiabilityError(
            f"the accelerometer's gravity direction stayed within {spread:.2g} deg RMS (at most {angle.max():.2g} "
            f"deg) of its mean over {len(d)} samples: the rotation between magnetometer and accelerometer about the "
            f"vertical cannot be identified from the field-gravity angle; {_RECORD}"
        )
    return spread


def _check_inputs(field: ArrayLike, accel: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    y = np.asarray(field, dtype=np.float64)
    a = np.asarray(accel, dtype=np.float64)
    if y.ndim != 2 or y.shape[1] != 3 or a.shape != y.shape:
        raise TrimagInputError(f"`accel_columns`: the accelerometer must have one (ax, ay, az) row per field sample; "
                               f"got shapes {a.shape} and {y.shape}")
    if not (np.isfinite(y).all() and np.isfinite(a).all()):
        raise TrimagInputError("`accel_columns`: the accelerometer or the field has NaN or inf values")
    if np.any(np.linalg.norm(a, axis=1) == 0) or np.any(np.linalg.norm(y, axis=1) == 0):
        raise TrimagInputError("`accel_columns`: a sample has a zero accelerometer or field vector")
    return y, a


def _left_jacobian(phi: NDArray[np.float64]) -> NDArray[np.float64]:
    """SO(3)'s left Jacobian: ``exp(phi + dphi) = exp(J_l(phi) dphi) exp(phi)`` to first order."""
    theta = float(np.linalg.norm(phi))
    Phi = np.array([[0.0, -phi[2], phi[1]], [phi[2], 0.0, -phi[0]], [-phi[1], phi[0], 0.0]])
    if theta < 1e-8:
        return np.eye(3) + 0.5 * Phi
    return np.eye(3) + (1.0 - np.cos(theta)) / theta**2 * Phi + (theta - np.sin(theta)) / theta**3 * (Phi @ Phi)


def _residuals(
    m: NDArray[np.float64], d: NDArray[np.float64], R: NDArray[np.float64], inc: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(R m_i) . d_i - sin I`` (N,) and its Jacobian (N, 4) for a small rotation ``exp(w) R`` and the dip."""
    v = m @ R.T
    r = np.einsum("ij,ij->i", v, d) - np.sin(inc)
    return r, np.column_stack([np.cross(v, d), np.full(len(v), -np.cos(inc))])


def _solve(
    m: NDArray[np.float64], d: NDArray[np.float64], R0: NDArray[np.float64], max_iter: int = 50
) -> tuple[NDArray[np.float64], float, NDArray[np.float64], NDArray[np.float64], int]:
    """Least squares on ``(R m_i) . d_i - sin I`` from ``R0``: ``(R, I, residuals, Jacobian, evaluations)``.

    The rotation is ``R = exp(phi) R0`` (``phi`` a rotation vector, so the parameters ``(phi, I)`` are a vector
    space and the core's one Gauss-Newton / Levenberg-Marquardt driver, :func:`trimag._core.solve.gauss_newton_then_lm`,
    runs on them); the Jacobian in ``phi`` is the small-rotation one times SO(3)'s left Jacobian.
    """
    inc0 = float(np.arcsin(np.clip(np.mean(np.einsum("ij,ij->i", m @ R0.T, d)), -1.0, 1.0)))

    def rotation(p: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.asarray(Rotation.from_rotvec(p[:3]).as_matrix() @ R0, dtype=np.float64)

    def fun(p: NDArray[np.float64]) -> NDArray[np.float64]:
        return _residuals(m, d, rotation(p), float(p[3]))[0]

    def jac(p: NDArray[np.float64]) -> NDArray[np.float64]:
        J = _residuals(m, d, rotation(p), float(p[3]))[1]
        return np.column_stack([J[:, :3] @ _left_jacobian(p[:3]), J[:, 3]])

    res = gauss_newton_then_lm(fun, jac, np.array([0.0, 0.0, 0.0, inc0]), max_steps=max_iter,
                               lm_options={"xtol": 1e-15, "ftol": 1e-15, "gtol": 1e-15, "max_nfev": 20 * max_iter})
    R, inc = rotation(res.x), float(res.x[3])
    if np.cos(inc) < 0:  # the same sin(I) with the dip within -90..90
        inc = float(np.arcsin(np.clip(np.sin(inc), -1.0, 1.0)))
    r, J = _residuals(m, d, R, inc)
    return R, inc, r, J, int(res.nfev)


def _starts(m: NDArray[np.float64], d: NDArray[np.float64], k: int = 3) -> list[NDArray[np.float64]]:
    """The ``k`` axis-aligned rotations (of 24) whose field-gravity dot products vary least: the starts."""
    cube = Rotation.create_group("O").as_matrix()
    spread = [float(np.var(np.einsum("ij,ij->i", m @ Q.T, d))) for Q in cube]
    return [np.asarray(cube[i], dtype=np.float64) for i in np.argsort(spread)[:k]]


def _calibration_jacobian(
    cal: Calibration, raw: NDArray[np.float64], d: NDArray[np.float64], R: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """``dr/dtheta_cal`` (N, 9) for the ellipsoid gauge (``w11 .. w33``, hard iron) and its covariance, when the
    calibration carries it; else None."""
    unc = cal.uncertainty or {}
    order = list(unc.get("covariance_order") or [])
    if unc.get("covariance") is None or not all(n in order for n in _CAL_NAMES):
        return None
    idx = [order.index(n) for n in _CAL_NAMES]
    C = np.asarray(unc["covariance"], dtype=np.float64)[np.ix_(idx, idx)]
    W, b = np.asarray(cal.matrix), np.asarray(cal.offset)
    x = raw - b
    y = x @ W.T
    ny = np.linalg.norm(y, axis=1, keepdims=True)
    mhat = y / ny
    w = d @ R  # R^T d per sample: dr/dm = R^T d
    g = (w - np.einsum("ij,ij->i", w, mhat)[:, None] * mhat) / ny  # dr/dy = (I - m m^T) R^T d / |y|
    G = np.empty((len(raw), 9))
    for k, (i, j) in enumerate(_UPPER):  # y_i = sum_j W_ij x_j
        G[:, k] = g[:, i] * x[:, j]
    G[:, 6:] = -g @ W  # dy/db = -W
    return G, C


def alignment_heading_sigma(rotation_covariance: ArrayLike, dip_deg: float) -> dict[str, float]:
    """1-sigma heading error (degrees) of a level vehicle that the alignment's uncertainty alone causes.

    A small rotation ``delta`` (accelerometer frame) of the aligned field moves the tilt-compensated heading by
    ``g . delta``; ``g`` is taken by central differences of :func:`trimag.vehicle.heading.tilt_compensated_heading` at
    every 5 degrees of heading, level, at the dip ``dip_deg``, and ``sigma^2 = g C g'``.

    Parameters
    ----------
    rotation_covariance : array_like, shape (3, 3)
        Covariance of the rotation vector, rad^2.
    dip_deg : float

    Returns
    -------
    dict
        ``rms_deg`` (over headings) and ``max_deg``.
    """
    from .heading import heading_difference, tilt_compensated_heading

    C = np.asarray(rotation_covariance, dtype=np.float64)
    psi = np.radians(np.arange(0.0, 360.0, 5.0))
    inc = np.radians(dip_deg)
    h = np.column_stack([np.cos(inc) * np.cos(psi), -np.cos(inc) * np.sin(psi), np.full(len(psi), np.sin(inc))])
    a = np.tile([0.0, 0.0, -1.0], (len(psi), 1))
    eps = 1e-6
    g = np.empty((len(psi), 3))
    for k in range(3):
        step = np.zeros(3)
        step[k] = eps
        plus = tilt_compensated_heading(h @ Rotation.from_rotvec(step).as_matrix().T, a)
        minus = tilt_compensated_heading(h @ Rotation.from_rotvec(-step).as_matrix().T, a)
        g[:, k] = np.radians(heading_difference(plus, minus)) / (2 * eps)
    sigma = np.degrees(np.sqrt(np.clip(np.einsum("ni,ij,nj->n", g, C, g), 0.0, None)))
    return {"rms_deg": float(np.sqrt(np.mean(sigma**2))), "max_deg": float(sigma.max())}


def fit_alignment(
    cal: Calibration,
    B: ArrayLike,
    accel: ArrayLike,
    *,
    max_accel_deviation: float = MAX_ACCEL_DEVIATION,
    regressors: Any = None,
) -> dict[str, Any]:
    """Rotation (corrected magnetometer frame -> accelerometer frame) and dip angle from field-gravity invariance.

    Parameters
    ----------
    cal : Calibration
        The magnetometer calibration (fitted on the same or other samples); its corrected frame is the one
        aligned.
    B : array_like, shape (N, 3)
        Raw magnetometer samples, the calibration's unit.
    accel : array_like, shape (N, 3)
        Accelerometer specific force at the same instants (any unit; at rest and level ``(0, 0, -g)``), body frame.
    max_accel_deviation : float
        Samples whose ``|a|`` differs from the median ``|a|`` by more than this fraction are dropped (the vehicle
        was accelerating: gravity is not the down direction there).
    regressors : optional
        The calibration's regressor values (as for :meth:`Calibration.apply`).

    Returns
    -------
    dict
        ``matrix`` (3x3, corrected magnetometer -> accelerometer), ``rotvec_deg`` (its rotation vector),
        ``euler_zyx_deg`` (yaw, pitch, roll of it), ``sensor_matrix`` and ``sensor_euler_zyx_deg`` (the rotation
        of the sensor's own axes, ``R Q``, :func:`polar_rotation`), ``rotation_std_deg`` (3, 1-sigma of a small
        rotation about the accelerometer's x, y, z axes), ``dip_deg``, ``dip_std_deg``, ``covariance`` (4x4,
        radians^2, order ``covariance_order``), ``board_rotation`` (:func:`nearest_board_rotation` of
        ``sensor_matrix``), ``rms_residual`` (of the dot products) and ``rms_residual_deg``, ``correlation_time``,
        ``calibration_uncertainty_propagated``, ``n_used``, ``n_dropped_accelerating``, ``weakest_rotation_axis``,
        ``singular_value_ratio``, ``heading_sigma_deg`` (:func:`alignment_heading_sigma`: ``rms_deg``,
        ``max_deg``) and ``warning`` (a line when the residual exceeds :data:`RESIDUAL_WARNING_DEG`, else None).

    Raises
    ------
    IdentifiabilityError
        Too little tilt variation (a rotation component is unobserved), or fewer than 10 samples.
    """
    raw, a, u, n_drop = _at_rest(B, accel, regressors, max_accel_deviation)
    check_tilt_variation(a)
    y = cal.apply(raw, regressors=u)
    m = y / np.linalg.norm(y, axis=1, keepdims=True)
    d = _unit_down(a)
    R, inc, r, J, iterations = min((_solve(m, d, R0) for R0 in _starts(m, d)), key=lambda out: float(out[2] @ out[2]))
    ratio, weak = _check_identified(J, inc)
    n = len(r)
    tau = correlation_time(r)
    cov, propagated = _covariance(J, r, tau, cal, raw, d, R, calibration_known=u is None)
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    rot = Rotation.from_matrix(R)
    sensor = R @ polar_rotation(np.asarray(cal.matrix, dtype=np.float64))
    rms_deg = float(np.degrees(np.sqrt(np.mean(r**2))) / max(np.cos(inc), 1e-12))
    return {
        "warning": _residual_warning(rms_deg),
        "heading_sigma_deg": alignment_heading_sigma(cov[:3, :3], float(np.degrees(inc))),
        "matrix": R.tolist(),
        "rotvec_deg": np.degrees(rot.as_rotvec()).tolist(),
        "euler_zyx_deg": rot.as_euler("ZYX", degrees=True).tolist(),
        "rotation_std_deg": np.degrees(std[:3]).tolist(),
        "dip_deg": float(np.degrees(inc)),
        "dip_std_deg": float(np.degrees(std[3])),
        "covariance": cov.tolist(),
        "covariance_order": ["rotation_x", "rotation_y", "rotation_z", "dip"],
        "sensor_matrix": sensor.tolist(),
        "sensor_euler_zyx_deg": Rotation.from_matrix(sensor).as_euler("ZYX", degrees=True).tolist(),
        "board_rotation": nearest_board_rotation(sensor),
        "rms_residual": float(np.sqrt(np.mean(r**2))),
        "rms_residual_deg": rms_deg,
        "correlation_time": tau,
        "calibration_uncertainty_propagated": propagated,
        "n_used": n,
        "n_dropped_accelerating": n_drop,
        "singular_value_ratio": ratio,
        "weakest_rotation_axis": weak.tolist(),
        "iterations": iterations,
    }


def _at_rest(
    B: ArrayLike, accel: ArrayLike, regressors: Any, max_accel_deviation: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], Any, int]:
    """The samples where ``|a|`` is within ``max_accel_deviation`` of its median (gravity is the down direction
    there): ``(B, accel, regressors, number dropped)``; fewer than 10 raise."""
    raw, a = _check_inputs(B, accel)
    norm_a = np.linalg.norm(a, axis=1)
    keep = np.abs(norm_a / np.median(norm_a) - 1.0) <= max_accel_deviation
    u = None
    if regressors is not None:
        u = np.asarray(regressors, dtype=np.float64)[keep] if not isinstance(regressors, dict) else {
            k: np.asarray(v, dtype=np.float64)[keep] for k, v in regressors.items()}
    raw, a = raw[keep], a[keep]
    if len(raw) < 10:
        raise IdentifiabilityError(f"only {len(raw)} samples at rest (|a| within {100 * max_accel_deviation:g}% of "
                                   f"the median): too few to align the magnetometer; {_RECORD}")
    return raw, a, u, int((~keep).sum())


def _check_identified(J: NDArray[np.float64], inc: float) -> tuple[float, NDArray[np.float64]]:
    """Refuse a rotation component the samples do not observe, or a field that stays at one angle to gravity;
    return the singular value ratio of the rotation's Jacobian columns and its weakest axis."""
    n = len(J)
    # the rotation's three columns share one unit (radians): no column scaling, which would blow a component
    # that only noise carries up to the size of the others
    _, s, vt = np.linalg.svd(J[:, :3], full_matrices=False)
    ratio = float(s[-1] / s[0]) if s[0] > 0 else 0.0
    weak = vt[-1]
    if not ratio >= RANK_TOLERANCE:
        raise IdentifiabilityError(
            f"the field-gravity angle of these {n} samples cannot identify the rotation between magnetometer and "
            f"accelerometer about the axis {np.round(weak, 2).tolist()} (accelerometer frame; singular value ratio "
            f"{ratio:.2g} < {RANK_TOLERANCE}): the vehicle turned about too few axes; {_RECORD}"
        )
    if not np.cos(inc) >= MIN_COS_DIP:
        raise IdentifiabilityError(
            f"the fitted field-gravity angle is {90.0 - abs(np.degrees(inc)):.2g} deg (dip "
            f"{np.degrees(inc):.4g} deg): in these {n} samples the field stays at one place relative to gravity, "
            f"as when the vehicle turns about magnetic east only, and the rotation between magnetometer and "
            f"accelerometer cannot be identified; {_RECORD}"
        )
    return ratio, weak


def _covariance(
    J: NDArray[np.float64], r: NDArray[np.float64], tau: float, cal: Calibration, raw: NDArray[np.float64],
    d: NDArray[np.float64], R: NDArray[np.float64], *, calibration_known: bool,
) -> tuple[NDArray[np.float64], bool]:
    """Covariance (4x4, radians^2) of the rotation and dip: the residuals' ``sigma^2 (J^T J)^-1`` inflated by the
    correlation time ``tau``, plus the calibration's own uncertainty propagated when it is known (no regressor
    terms); returns ``(covariance, propagated)``."""
    n = len(r)
    sigma2 = float(r @ r) / max(n - 4, 1) * tau
    JtJ_inv = np.linalg.inv(J.T @ J)
    cov = np.asarray(sigma2 * JtJ_inv, dtype=np.float64)
    cal_part = _calibration_jacobian(cal, raw, d, R) if calibration_known else None
    if cal_part is None:
        return cov, False
    G_r, C_cal = cal_part
    G = -JtJ_inv @ (J.T @ G_r)
    return np.asarray(cov + G @ C_cal @ G.T, dtype=np.float64), True


def _residual_warning(rms_deg: float) -> str | None:
    """A line when the field-gravity angle varies by more than :data:`RESIDUAL_WARNING_DEG` RMS, else None."""
    if not rms_deg > RESIDUAL_WARNING_DEG:
        return None
    return (f"the field-gravity angle varies by {rms_deg:.3g} deg RMS over the samples: the invariance holds "
            "poorly (the vehicle moving, a field that changes over the place, as indoors, or a calibration that "
            "does not fit), and the alignment can be off by more than its sigmas; record at rest, outdoors, "
            "away from iron")
