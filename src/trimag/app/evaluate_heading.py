"""``trimag evaluate --accel-columns``: the tilt-compensated true heading of a calibrated log against a reference
heading (issue 20, item 3)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from ..calibration import Calibration
from ..errors import TrimagInputError
from ..fields.reference import igrf, parse_igrf_spec
from ..io import Samples, read_samples
from ..io.tables import strict_refusal
from ._inputs import calibration_regressors
from ._sensor import input_for, sensor_line
from .requests import EvaluateRequest, as_request

__all__ = ["evaluate_heading_file"]


def evaluate_heading_file(
    request: EvaluateRequest | str | Path, *paths: str | Path, **arguments: Any
) -> dict[str, Any]:
    """Tilt-compensated true heading of a calibrated log against a reference heading (issue 20, item 3).

    ``request``: an :class:`~trimag.app.requests.EvaluateRequest` (or the calibration's and the data's paths with its
    fields as keyword arguments). The corrected field is rotated into the accelerometer frame by the calibration's
    alignment (``diagnostics.alignment``, from ``fit --accel-columns``; without one the frames are taken as the
    same), the heading computed with the accelerometer ``accel_columns``
    (:func:`trimag.vehicle.heading.tilt_compensated_heading`) plus the declination (IGRF at ``igrf_spec``, or
    ``declination`` in degrees east; 0 when neither: magnetic heading), and compared with ``heading_column``
    (degrees clockwise from true north) or the yaw of ``attitude_columns`` (yaw, pitch, roll).

    Returns
    -------
    dict
        ``heading_error_rms_deg``, ``heading_error_max_deg``, ``heading_error_mean_deg``, ``heading_error_std_deg``
        (wrapped into -180..180), ``n_used``, ``declination_deg`` and its ``declination_source``, ``alignment``
        (``"calibration"`` or ``"none"``), ``reference_heading`` and the usual ``calibration``, ``data``,
        ``units``, ``columns``, ``n_samples``, ``n_dropped``.
    """
    from ..vehicle.heading import heading_error_stats, tilt_compensated_heading

    req = as_request(EvaluateRequest, request, paths, arguments)
    src, heading_column, attitude_columns = req.input, req.heading_column, req.attitude.attitude_columns
    cal = Calibration.from_file(req.calibration)
    if src.units is not None:
        cal.check_units(src.units)
    if (heading_column is None) == (attitude_columns is None):
        raise TrimagInputError("a heading evaluation needs exactly one reference: `heading_column=H` (degrees "
                               "clockwise from true north) or `attitude_columns=yaw,pitch,roll`")
    decl, decl_source = _declination(req)
    src, sensor = input_for(cal, src)  # the calibration's sensor by default (issue 39)
    samples = read_samples(src.path, fmt=src.fmt, columns=src.columns, var=src.var, rows=src.rows, where=src.where,
                           strict=src.strict, sensor=sensor)
    sensor_read = sensor_line(cal, req.input, samples.log_info, samples.columns, samples.variable)
    reference, accel = _reference_and_accel(req, samples)
    u = None
    if cal.regressors is not None:
        values = calibration_regressors(cal, samples, src.path, time_column=req.attitude.time_column,
                                        rate_hz=req.rate_hz)
        assert values is not None
        u = np.column_stack([values[n] for n in cal.regressors["names"]])
    ok = np.isfinite(reference) & np.isfinite(accel).all(axis=1) & (np.linalg.norm(accel, axis=1) > 0)
    if u is not None:
        ok &= np.isfinite(u).all(axis=1)
    if src.strict and not ok.all():
        raise strict_refusal(f"{src.path}: ", int((~ok).sum()), "a missing or non-numeric reference heading, "
                             "accelerometer or regressor value", f"kept row {int(np.flatnonzero(~ok)[0])}")
    if not ok.any():
        raise TrimagInputError(f"{src.path}: no row has a finite reference heading and accelerometer")
    corrected = cal.apply(samples.field[ok], regressors=None if u is None else u[ok])
    alignment = cal.diagnostics.get("alignment")
    if alignment is not None:
        corrected = corrected @ np.asarray(alignment["matrix"], dtype=np.float64).T
    heading = tilt_compensated_heading(corrected, accel[ok], declination_deg=decl)
    stats = heading_error_stats(heading, reference[ok])
    return {
        "calibration": str(req.calibration), "data": str(src.path), "model": cal.model, "method": cal.method,
        "sensor": sensor_read,
        "units": cal.units, "columns": list(samples.columns), "n_samples": samples.n_rows,
        "n_used": int(ok.sum()), "n_dropped": samples.n_dropped + int((~ok).sum()),
        "accel_columns": req.accel_columns,
        "reference_heading": f"column {heading_column}" if heading_column is not None
        else f"yaw of attitude columns {attitude_columns}",
        "declination_deg": float(decl), "declination_source": decl_source,
        "alignment": "calibration" if alignment is not None else "none",
        "board_rotation": None if alignment is None else alignment["board_rotation"]["name"],
        **stats,
    }


def _declination(req: EvaluateRequest) -> tuple[float, str]:
    """The declination (degrees east) added to the magnetic heading, and its source."""
    igrf_spec, declination = req.reference.igrf_spec, req.declination
    if igrf_spec is not None and declination is not None:
        raise TrimagInputError("give only one of `igrf_spec` and `declination`")
    if igrf_spec is not None:
        return igrf(*parse_igrf_spec(igrf_spec)).declination_deg, f"igrf {igrf_spec}"
    if declination is None:
        return 0.0, "none (magnetic heading compared)"
    try:
        decl = float(declination)
    except ValueError:
        raise TrimagInputError(f"`declination` takes degrees east of north; got {declination!r}") from None
    if not -180.0 <= decl <= 180.0:
        raise TrimagInputError(f"`declination` must be within -180..180 degrees; got {decl}")
    return decl, "given"


def _reference_and_accel(req: EvaluateRequest, samples: Samples) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The reference heading (N,) (degrees; NaN where missing) and the accelerometer (N, 3) of the samples' rows;
    one line naming a missing column."""
    from ..fields.attitude import parse_columns

    path, attitude_columns = req.input.path, req.attitude.attitude_columns
    ref_col = req.heading_column if req.heading_column is not None else (attitude_columns or "").split(",")[0].strip()
    if attitude_columns is not None:
        parse_columns(attitude_columns, 3, option="`attitude_columns`")
    if ref_col not in samples.table.columns:
        raise TrimagInputError(f"{path}: no column {ref_col!r} (the reference heading); the columns are "
                               f"{', '.join(map(str, samples.table.columns))}")
    reference = pd.to_numeric(samples.table[ref_col], errors="coerce").to_numpy(dtype=float)
    if req.accel_columns is None:
        raise TrimagInputError("a heading evaluation needs the accelerometer: give `accel_columns=AX,AY,AZ`")
    names = parse_columns(req.accel_columns, 3, option="`accel_columns`")
    assert names is not None
    missing = [n for n in names if n not in samples.table.columns]
    if missing:
        raise TrimagInputError(f"{path}: no column {missing[0]!r} (named by `accel_columns`); the columns are "
                               f"{', '.join(map(str, samples.table.columns))}")
    accel = np.column_stack([pd.to_numeric(samples.table[n], errors="coerce").to_numpy(dtype=float) for n in names])
    return reference, accel
