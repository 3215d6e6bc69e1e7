"""``trimag evaluate`` of an attitude-based calibration (``interference12``): vector errors against the background
field rotated into the body frame at every sample."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from ..calibration import Calibration
from ..errors import TrimagInputError
from ..io import Samples, read_samples
from ..validation import ROUNDOFF_FRACTION
from ._inputs import (
    attitudes_of,
    background_field,
    calibration_regressors,
    drop_rows_without_attitude,
    drop_rows_without_background,
)
from ._sensor import input_for, sensor_line
from ._timesync import attach_attitude_file
from .evaluate import worse_than_raw_warning
from .requests import AttitudeSpec, EvaluateRequest, as_request

__all__ = ["evaluate_vector_file"]


def evaluate_vector_file(request: EvaluateRequest | str | Path, *paths: str | Path, **arguments: Any) -> dict[str, Any]:
    """Vector errors of an attitude-based calibration (``interference12``) on a log with attitudes.

    ``request``: an :class:`~trimag.app.requests.EvaluateRequest` (or the calibration's and the data's paths with its
    fields as keyword arguments). The background field (N, E, D) -- one vector, or one per row from
    ``background_columns`` -- is rotated into the body frame at every sample (docs/conventions-attitude.md) and
    compared with the raw and the corrected vector: per-axis RMS, vector RMS, and the angle between the corrected
    field and the background in degrees (RMS and maximum). With ``attitude_file`` the attitudes come from that
    file (its own ``attitude_time_column``), interpolated (slerp) to the data's ``time_column`` after the lag the
    calibration stores (``diagnostics.time_sync.lag_s``, 0 when none); samples outside its span are dropped.
    """
    from ..fields import attitude as _attitude

    req = as_request(EvaluateRequest, request, paths, arguments)
    src, given = req.input, req.reference
    if given.background_run is not None:
        raise TrimagInputError("`background_run` is for fitting; evaluate against `background_ned=N,E,D`, "
                               "`igrf_spec=LAT,LON,ALT_M,DATE` or `background_columns=N,E,D`")
    cal = Calibration.from_file(req.calibration)
    gradient = cal.diagnostics.get("background_gradient")
    if gradient is not None and req.position_columns is None and not given.given:
        req = dataclasses.replace(req, position_columns=gradient.get("position_columns"))  # the fitted columns
    if src.units is not None:
        cal.check_units(src.units)
    src, sensor = input_for(cal, src)  # the calibration's sensor by default (issue 39)
    samples = read_samples(src.path, fmt=src.fmt, columns=src.columns, var=src.var, rows=src.rows, where=src.where,
                           strict=src.strict, sensor=sensor)
    sensor_read = sensor_line(cal, req.input, samples.log_info, samples.columns, samples.variable)
    samples, att, lag = _attitudes(req, samples, cal)
    samples, _ = drop_rows_without_attitude(samples, att.attitude_columns, att.quaternion_columns, strict=src.strict)
    samples, _ = drop_rows_without_background(samples, given.background_columns, given.igrf_columns,
                                              strict=src.strict)
    if req.position_columns is not None:
        samples, _ = drop_rows_without_attitude(samples, req.position_columns, None, strict=src.strict,
                                                what="position")
    rot = attitudes_of(samples, att)
    background, source = _background(given, cal, samples, req.position_columns)
    expected = _attitude.body_field(rot, background)
    u = calibration_regressors(cal, samples, src.path, time_column=req.attitude.time_column, rate_hz=req.rate_hz)
    raw, corrected = samples.field, cal.apply(samples.field, regressors=u)
    before, after = _vector_errors(raw, expected), _vector_errors(corrected, expected)
    attitude_file = req.attitude.attitude_file
    field = float(np.mean(np.linalg.norm(np.atleast_2d(expected), axis=1)))
    worse = bool(after["rms_vector"] > before["rms_vector"] and after["rms_vector"] > ROUNDOFF_FRACTION * field)
    return {
        "calibration": str(req.calibration), "data": str(src.path), "model": cal.model, "method": cal.method,
        "sensor": sensor_read,
        "units": cal.units, "columns": list(samples.columns), "n_samples": samples.n_rows,
        "n_used": len(raw), "n_dropped": samples.n_dropped,  # the attitude and background drops included
        "background": {"ned": (background.mean(axis=0) if background.ndim == 2 else background).tolist(),
                       "source": source, "per_sample": background.ndim == 2},
        **({"attitude_file": str(attitude_file), "lag_s": lag} if attitude_file is not None else {}),
        "before": before, "after": after,
        "rms_before": before["rms_vector"], "rms_after": after["rms_vector"],
        "angular_error_rms_deg": after["angular_error_rms_deg"],
        "worse_than_raw": worse,
        "warnings": [worse_than_raw_warning("RMS vector error", after["rms_vector"], before["rms_vector"], cal.units)]
        if worse else [],
    }


#: A background given to ``evaluate`` agrees with the one a calibration fitted when their directions are within this
#: angle (degrees) and their magnitudes within this fraction of each other.
AGREE_DEG, AGREE_FRACTION = 0.5, 0.01


def _background(
    given: Any, cal: Calibration, samples: Samples, position_columns: str | None = None
) -> tuple[NDArray[np.float64], str]:
    """The background the evaluation measures against, and its source: the given one, or, when none is given, the
    one stored in the calibration (``diagnostics.background_ned``: fitted, or given at fit time). A background
    given for a calibration that fitted its own (``estimate_background``) must agree with it: the fitted one is in
    the attitude source's frame (e.g. a motion-capture system's), so another vector is refused, never used."""
    stored = cal.diagnostics.get("background_ned")
    fitted = bool(cal.diagnostics.get("background_fitted"))
    if not given.given:
        if stored is None or cal.diagnostics.get("background_per_sample"):
            raise TrimagInputError(
                "the calibration stores no single background field: give `background_ned=N,E,D`, "
                "`igrf_spec=LAT,LON,ALT_M,DATE` or `background_columns=N,E,D`")
        vec = np.asarray(stored, dtype=np.float64)
        how = "fitted" if fitted else "given at fit time"
        if cal.diagnostics.get("background_gradient") is not None:
            return _with_gradient(cal, samples, position_columns, how)
        return vec, f"stored in the calibration ({how}), NED {np.round(vec, 6).tolist()}"
    background, source = background_field(given, cal.units, samples)
    if fitted and stored is not None:
        vec = np.asarray(stored, dtype=np.float64)
        mean = background.mean(axis=0) if background.ndim == 2 else background
        angle = float(np.degrees(np.arccos(np.clip(mean @ vec / (np.linalg.norm(mean) * np.linalg.norm(vec)), -1, 1))))
        ratio = float(np.linalg.norm(mean) / np.linalg.norm(vec))
        if background.ndim == 2 or angle > AGREE_DEG or abs(ratio - 1.0) > AGREE_FRACTION:
            raise TrimagInputError(
                f"the calibration fitted its own background, NED {np.round(vec, 3).tolist()} {cal.units} in the "
                f"attitude source's frame; the given one ({source}) differs by {angle:.3g} deg and "
                f"{100 * (ratio - 1):+.3g} % in magnitude: drop the background option to evaluate against the fitted "
                "one")
        source += f"; agrees with the fitted background stored in the calibration ({angle:.2g} deg)"
    return background, source


def _with_gradient(
    cal: Calibration, samples: Samples, position_columns: str | None, how: str
) -> tuple[NDArray[np.float64], str]:
    """The background a calibration with a fitted gradient predicts at each sample's position."""
    from ..vehicle.gradient import background_at

    if position_columns is None:
        raise TrimagInputError("the calibration fitted the background's gradient across the room: give the positions "
                               "(`position_columns=X,Y,Z`), or `background_ned=N,E,D` for one background")
    names = [c.strip() for c in position_columns.split(",") if c.strip()]
    missing = [n for n in names if n not in samples.table.columns]
    if missing or len(names) != 3:
        raise TrimagInputError(f"no position column {(missing or names)[0]!r} (`position_columns`) in the data or "
                               "the attitude file")
    P = np.column_stack([pd.to_numeric(samples.table[n], errors="coerce").to_numpy(dtype=float) for n in names])
    grad = cal.diagnostics["background_gradient"]
    low, high = np.asarray(grad["position_range_m"])
    outside = (P < low) | (P > high)
    note = (f"; {int(outside.any(axis=1).sum())} samples outside the fitted positions' span (extrapolated)"
            if outside.any() else "")
    return background_at(cal, P), (f"stored in the calibration ({how}) with its gradient, at the positions "
                                   f"{', '.join(names)}{note}")


def _attitudes(req: EvaluateRequest, samples: Samples, cal: Calibration) -> tuple[Samples, AttitudeSpec, float | None]:
    """The samples and where their attitudes are: the request's columns, or, with ``attitude_file``, quaternion
    columns interpolated from that file after the calibration's lag (returned; None without a file)."""
    if req.attitude.attitude_file is None:
        return samples, req.attitude, None
    lag = float((cal.diagnostics.get("time_sync") or {}).get("lag_s", 0.0))
    samples, attached, _, _ = attach_attitude_file(req, samples, cal.units, {"lag_s": lag}, None)
    return samples, AttitudeSpec(quaternion_columns=attached.attitude.quaternion_columns), lag


def _vector_errors(B: NDArray[np.float64], expected: NDArray[np.float64]) -> dict[str, Any]:
    """Errors of the vectors ``B`` (N, 3) against ``expected`` (N, 3): per-axis and vector RMS, angle RMS and max
    (degrees)."""
    e = B - expected
    cos = np.einsum("ij,ij->i", B, expected) / (np.linalg.norm(B, axis=1) * np.linalg.norm(expected, axis=1))
    angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return {"rms_axis": np.sqrt(np.mean(e**2, axis=0)).tolist(),
            "rms_vector": float(np.sqrt(np.mean(np.sum(e**2, axis=1)))),
            "angular_error_rms_deg": float(np.sqrt(np.mean(angle**2))),
            "angular_error_max_deg": float(angle.max())}
