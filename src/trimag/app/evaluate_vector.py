"""``trimag evaluate`` of an attitude-based calibration (``interference12``): vector errors against the background
field rotated into the body frame at every sample."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..errors import TrimagInputError
from ..io import Samples, read_samples
from ._inputs import (
    attitudes_of,
    background_field,
    calibration_regressors,
    drop_rows_without_attitude,
    drop_rows_without_background,
)
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
    if src.units is not None:
        cal.check_units(src.units)
    samples = read_samples(src.path, fmt=src.fmt, columns=src.columns, var=src.var, rows=src.rows, where=src.where,
                           strict=src.strict, sensor=src.sensor)
    samples, att, lag = _attitudes(req, samples, cal)
    samples, _ = drop_rows_without_attitude(samples, att.attitude_columns, att.quaternion_columns, strict=src.strict)
    samples, _ = drop_rows_without_background(samples, given.background_columns, given.igrf_columns,
                                              strict=src.strict)
    rot = attitudes_of(samples, att)
    background, source = background_field(given, cal.units, samples)
    expected = _attitude.body_field(rot, background)
    u = calibration_regressors(cal, samples, src.path, time_column=req.attitude.time_column, rate_hz=req.rate_hz)
    raw, corrected = samples.field, cal.apply(samples.field, regressors=u)
    before, after = _vector_errors(raw, expected), _vector_errors(corrected, expected)
    attitude_file = req.attitude.attitude_file
    return {
        "calibration": str(req.calibration), "data": str(src.path), "model": cal.model, "method": cal.method,
        "units": cal.units, "columns": list(samples.columns), "n_samples": samples.n_rows,
        "n_used": len(raw), "n_dropped": samples.n_dropped,  # the attitude and background drops included
        "background": {"ned": (background.mean(axis=0) if background.ndim == 2 else background).tolist(),
                       "source": source, "per_sample": background.ndim == 2},
        **({"attitude_file": str(attitude_file), "lag_s": lag} if attitude_file is not None else {}),
        "before": before, "after": after,
        "rms_before": before["rms_vector"], "rms_after": after["rms_vector"],
        "angular_error_rms_deg": after["angular_error_rms_deg"],
        "worse_than_raw": bool(after["rms_vector"] > before["rms_vector"]),
        "warnings": [worse_than_raw_warning("RMS vector error", after["rms_vector"], before["rms_vector"], cal.units)]
        if after["rms_vector"] > before["rms_vector"] else [],
    }


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
