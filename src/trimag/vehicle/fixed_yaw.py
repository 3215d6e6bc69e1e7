"""Fixed-heading calibration: the offsets of a vehicle at a known heading from the field's vector (issue 30, item
5b; docs/autopilot.md, "Large vehicles").

ArduPilot's ``MAG_CAL_YAW`` (``Compass::mag_cal_fixed_yaw``, libraries/AP_Compass/AP_Compass_Calibration.cpp) sets
a compass's offsets so that, at the vehicle's given yaw and its current roll and pitch, the reading equals the WMM
field rotated into the body frame:

    f_NED = from_euler(0, -I, D) [F, 0, 0]        the field: magnitude F, inclination I, declination D
    h = R(roll, pitch, yaw)^T f_NED                 body frame; yaw = the vehicle's TRUE heading
    OFS = h - M^-1 m - OFS_old ,  DIA = 1, ODI = 0  (one sample, the matrix reset to the identity)

trimag does the same in its own convention, ``c = W (x - b)``, with the matrix ``W`` held (the identity, as the
firmware resets it, or an earlier calibration's with ``prior``) and every sample used (one heading, or a heading
per sample from a column: a GPS course, a survey):

    b = mean_i (x_i - W^-1 R_i^T f_NED)

Its covariance is the data's (the residuals' covariance over ``N / tau``, ``tau`` their autocorrelation time) plus
the reference's own uncertainty propagated, ``J C_ref J^T`` with ``J = d b / d theta`` (finite differences) for
``theta`` = the field's relative magnitude, inclination, declination, and the heading, pitch and roll given:

| source | default 1-sigma | option |
|---|---|---|
| field magnitude (IGRF against the local field) | 0.5 % | ``scale_sigma`` |
| inclination | 0.2 deg | ``inclination_sigma_deg`` |
| declination | 0.3 deg | ``declination_sigma_deg`` |
| the heading given | 1 deg | ``heading_sigma_deg`` |
| roll and pitch (the autopilot's, or level) | 0.5 deg | ``attitude_sigma_deg`` |

At 500 mG and 65 deg inclination one degree of heading error is 3.7 mG of horizontal offset: the heading's accuracy
usually dominates.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from ..calibration import Calibration, make_uncertainty
from ..errors import IdentifiabilityError, TrimagInputError
from ..quality.honesty import correlation_time

__all__ = ["DEFAULTS", "field_ned", "fit_fixed_heading"]

#: Default standard deviations of the reference (relative, or degrees): ``option KEY=VALUE`` changes them.
DEFAULTS = {"scale_sigma": 0.005, "inclination_sigma_deg": 0.2, "declination_sigma_deg": 0.3,
            "heading_sigma_deg": 1.0, "attitude_sigma_deg": 0.5}
#: Residuals above this fraction of the field (RMS) say that the held matrix does not fit the data.
MISFIT_FRACTION = 0.02
#: Residuals above this fraction of the field (RMS) contradict the headings given: the vehicle turned (or the
#: heading or the field is wrong), and offsets taken from them would make the heading worse (issue 41, item 5: a log
#: that turned, with `--heading`, missed the field by 70 % and its offsets raised the deviation 45.9 -> 67.5 deg).
CONTRADICTION_FRACTION = 0.2


def field_ned(magnitude: float, inclination_deg: float, declination_deg: float) -> NDArray[np.float64]:
    """The field vector (north, east, down) of a magnitude, inclination and declination: ArduPilot's
    ``from_euler(0, -I, D) [F, 0, 0]``."""
    inc, dec = np.radians(inclination_deg), np.radians(declination_deg)
    return magnitude * np.array([np.cos(inc) * np.cos(dec), np.cos(inc) * np.sin(dec), np.sin(inc)])


def _expected(theta: NDArray[np.float64], F: float, ypr_deg: NDArray[np.float64], W_inv: NDArray[np.float64]
              ) -> NDArray[np.float64]:
    """``mean_i W^-1 R_i^T f`` (3,) for ``theta`` = (scale, inclination, declination, d_yaw, d_pitch, d_roll)."""
    f = field_ned(F * theta[0], theta[1], theta[2])
    R = Rotation.from_euler("ZYX", ypr_deg + theta[3:6], degrees=True)
    return np.asarray(np.mean(R.inv().apply(f), axis=0) @ W_inv.T, dtype=np.float64)


def fit_fixed_heading(
    B: ArrayLike,
    field: tuple[float, float, float],
    yaw_deg: ArrayLike,
    *,
    pitch_deg: ArrayLike = 0.0,
    roll_deg: ArrayLike = 0.0,
    matrix: ArrayLike | None = None,
    units: str = "unknown",
    sigmas: dict[str, float] | None = None,
    model: str = "ellipsoid",
) -> Calibration:
    """The offsets of a vehicle at a known (true) heading from the field's vector (module docstring).

    Parameters
    ----------
    B : array_like, shape (N, 3)
        Raw samples (body frame: forward, right, down), ``units``.
    field : (magnitude, inclination_deg, declination_deg)
        The field at the site (IGRF), magnitude in ``units``.
    yaw_deg : float or array_like, shape (N,)
        The vehicle's true heading (degrees clockwise from true north) at each sample.
    pitch_deg, roll_deg : float or array_like, shape (N,)
        Its pitch and roll (degrees; Z-Y-X Euler angles, body -> NED); level by default.
    matrix : array_like, shape (3, 3), optional
        The correction matrix held (an earlier calibration's); the identity by default, as the firmware's.
    units : str
    sigmas : dict, optional
        The reference's standard deviations (:data:`DEFAULTS`' keys).
    model : str
        The model recorded (an earlier calibration's).

    Returns
    -------
    Calibration
        ``matrix`` held, the new ``offset``; method ``fixed-heading``; ``uncertainty`` of ``hard_iron_x..z`` with
        the data's and the reference's parts (``diagnostics["fixed_heading"]``).
    """
    X = np.asarray(B, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or len(X) < 1 or not np.isfinite(X).all():
        raise TrimagInputError(f"`B` must have shape (N, 3) with finite values; got {X.shape}")
    n = len(X)
    ypr = np.asarray(np.column_stack([np.broadcast_to(np.asarray(v, dtype=np.float64), (n,))
                                      for v in (yaw_deg, pitch_deg, roll_deg)]), dtype=np.float64)
    if not np.isfinite(ypr).all():
        raise TrimagInputError("the heading, pitch and roll must be finite numbers (degrees)")
    F, incl, decl = (float(v) for v in field)
    if not (np.isfinite(F) and F > 0 and np.isfinite(incl) and np.isfinite(decl)):
        raise TrimagInputError(f"a fixed-heading calibration needs the field's magnitude, inclination and "
                               f"declination: give `igrf_spec=LAT,LON,ALT_M,DATE`; got {field}")
    s = {**DEFAULTS, **(sigmas or {})}
    for key, value in s.items():
        if not (np.isfinite(value) and value >= 0):
            raise TrimagInputError(f"`option {key}` must be a number >= 0; got {value}")
    W = np.eye(3) if matrix is None else np.asarray(matrix, dtype=np.float64)
    W_inv = np.asarray(np.linalg.inv(W), dtype=np.float64)
    R = Rotation.from_euler("ZYX", ypr, degrees=True)
    expected = R.inv().apply(field_ned(F, incl, decl)) @ W_inv.T  # W^-1 R_i^T f, (N, 3)
    e = X - expected
    b = e.mean(axis=0)
    resid = e - b
    rms_resid = float(np.sqrt(np.mean(np.sum(resid**2, axis=1))))
    if rms_resid > CONTRADICTION_FRACTION * F:
        one = bool(np.ptp(np.mod(ypr[:, 0] - ypr[0, 0] + 180.0, 360.0)) < 1.0)
        raise IdentifiabilityError(
            f"the {n} samples differ from the field expected at the {'heading' if one else 'headings'} given by "
            f"{rms_resid:.4g} {units} RMS ({100 * rms_resid / F:.0f} % of the field; above "
            f"{100 * CONTRADICTION_FRACTION:.0f} % the data contradict "
            f"{'a fixed heading' if one else 'the headings given'}): the vehicle turned, or the heading or the "
            "field is wrong, and offsets from them would make the heading worse. For a vehicle that turned, fit "
            "with `level_turn` (or a full calibration); give each sample's heading with `heading_column`"
        )
    tau = max(max(correlation_time(resid[:, k]) for k in range(3)), 1.0) if n >= 20 else 1.0
    cov_data = (np.cov(resid.T) if n > 1 else np.zeros((3, 3))) * tau / n
    theta0 = np.array([1.0, incl, decl, 0.0, 0.0, 0.0])
    steps = np.array([1e-4, 1e-3, 1e-3, 1e-3, 1e-3, 1e-3])
    J = np.column_stack([(_expected(theta0 + h * np.eye(6)[k], F, ypr, W_inv)
                          - _expected(theta0 - h * np.eye(6)[k], F, ypr, W_inv)) / (2 * h)
                         for k, h in enumerate(steps.tolist())])
    ref_sd = np.array([s["scale_sigma"], s["inclination_sigma_deg"], s["declination_sigma_deg"],
                       s["heading_sigma_deg"], s["attitude_sigma_deg"], s["attitude_sigma_deg"]])
    contributions = J * ref_sd  # b = mean(x) - expected: the sign does not matter for the covariance
    cov_ref = contributions @ contributions.T
    cov = cov_data + cov_ref
    return _assemble(X, b, W, cov, cov_data, contributions, resid, tau, F, (incl, decl), ypr, units, s, model)


def _assemble(X: NDArray[np.float64], b: NDArray[np.float64], W: NDArray[np.float64], cov: NDArray[np.float64],
              cov_data: NDArray[np.float64], contributions: NDArray[np.float64], resid: NDArray[np.float64],
              tau: float, F: float, angles: tuple[float, float], ypr: NDArray[np.float64], units: str,
              sigmas: dict[str, float], model: str) -> Calibration:
    """The Calibration of a fixed-heading fit."""
    from ..models import get_model

    names = ["hard_iron_x", "hard_iron_y", "hard_iron_z"]
    sources = ("field magnitude", "inclination", "declination", "heading", "pitch", "roll")
    rms_resid = float(np.sqrt(np.mean(np.sum(resid**2, axis=1))))
    mag_before, mag_after = np.linalg.norm(X, axis=1), np.linalg.norm((X - b) @ W.T, axis=1)
    spread = float(np.ptp(np.mod(ypr[:, 0] - ypr[0, 0] + 180.0, 360.0)))
    diagnostics = {"fixed_heading": {
        "headings": "one" if spread < 1.0 else f"{spread:.0f} deg of headings",
        "heading_deg": float(ypr[0, 0]) if spread < 1.0 else None,
        "field_ned": field_ned(F, *angles).tolist(), "inclination_deg": angles[0], "declination_deg": angles[1],
        "matrix_held": "identity (as ArduPilot's MAG_CAL_YAW: DIA = 1, ODI = 0)" if np.allclose(W, np.eye(3))
                       else "the prior calibration's",
        "rms_vector_residual": rms_resid, "misfit": rms_resid > MISFIT_FRACTION * F,
        "offset_sigma_data": np.sqrt(np.diag(cov_data)).tolist(),
        "offset_sigma_by_source": {src: np.abs(contributions[:, k]).tolist() for k, src in enumerate(sources)},
        "reference_sigmas": dict(sigmas),
        "equations": "b = mean_i (x_i - W^-1 R_i^T f_NED), f_NED = from_euler(0, -I, D) [F, 0, 0] "
                     "(Compass::mag_cal_fixed_yaw)",
    }}
    uncertainty = make_uncertainty(
        names, covariance=cov, noise_std=float(np.sqrt(np.mean(resid**2))), gauge="the matrix held",
        basis="the residuals' covariance over N / tau plus the reference's uncertainty (magnitude, inclination, "
              "declination, heading, pitch, roll) propagated by finite differences (trimag.vehicle.fixed_yaw)",
        inflation={"total": tau, "correlated_residuals": tau},
    )
    err_before, err_after = mag_before - F, mag_after - F
    stats = {
        "n_samples": len(X), "n_used": len(X), "iterations": 0, "converged": True,
        "rms_before": float(np.sqrt(np.mean(err_before**2))), "rms_after": float(np.sqrt(np.mean(err_after**2))),
        "max_abs_before": float(np.max(np.abs(err_before))), "max_abs_after": float(np.max(np.abs(err_after))),
        "mean_norm_before": float(np.mean(mag_before)), "std_norm_before": float(np.std(mag_before)),
        "mean_norm_after": float(np.mean(mag_after)), "std_norm_after": float(np.std(mag_after)),
        "rms_vector_after": rms_resid,
    }
    try:
        params = get_model(model).from_matrix_offset(W, b).as_dict()
    except Exception:  # a model whose parameters do not hold this matrix: the ellipsoid's
        model, params = "ellipsoid", get_model("ellipsoid").from_matrix_offset(W, b).as_dict()
    return Calibration.from_matrix_offset(
        W, b, units=units, model=model, method="fixed-heading", params=params,
        reference={"value": F, "source": "given", "unit": units}, stats=stats, uncertainty=uncertainty,
        diagnostics=diagnostics,
    )


def heading_misfit_message(cal: Calibration) -> str | None:
    """A warning when the held matrix does not fit the data (soft iron, or a wrong heading), else None."""
    d = cal.diagnostics.get("fixed_heading") or {}
    if not d.get("misfit"):
        return None
    return (f"the samples differ from the field expected at the given headings by {d['rms_vector_residual']:.4g} "
            f"{cal.units} RMS (vector): the matrix held ({d['matrix_held']}) does not fit them (soft iron, a wrong "
            "heading or attitude): turn the vehicle and fit with `level_turn`, or give an earlier calibration with "
            "`prior`")


__all__ += ["heading_misfit_message"]
