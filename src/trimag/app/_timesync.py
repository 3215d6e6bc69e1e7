"""Attitudes from a second file (its own clock) attached to the samples: ``fit`` and ``evaluate`` with
``attitude_file`` (:mod:`trimag.vehicle.timesync`)."""

from __future__ import annotations

import dataclasses
from typing import Any, TypeVar

import numpy as np

from ..errors import TrimagInputError
from ..io import Samples
from ._inputs import background_field, truthy
from .requests import EvaluateRequest, FitRequest, ReferenceSpec

_Q = TypeVar("_Q", FitRequest, EvaluateRequest)


def attach_attitude_file(
    req: _Q, samples: Samples, unit: str, options: dict[str, Any], estimator: Any
) -> tuple[Samples, _Q, dict[str, Any], list[str]]:
    """Attitudes from ``attitude_file`` interpolated (slerp) to the samples' time stamps, after the lag when
    ``estimate_lag`` (:mod:`trimag.vehicle.timesync`): the samples outside the stream's span dropped, the attitudes
    put in the table as quaternion columns and the request pointed at them."""
    from ..vehicle.timesync import estimate_lag, interpolate_attitude, read_attitude_stream, time_values
    from .requests import AttitudeSpec

    att = req.attitude
    if att.time_column is None:
        raise TrimagInputError("`attitude_file` needs the time stamps of the magnetometer's samples: give "
                               "`time_column=NAME` (and `attitude_time_column=NAME` if the attitude file's differs)")
    if att.attitude_columns is None and att.quaternion_columns is None:
        raise TrimagInputError("name the attitude file's columns: `attitude_columns=YAW,PITCH,ROLL` or "
                               "`quaternion_columns=W,X,Y,Z`")
    stream = read_attitude_stream(
        att.attitude_file, time_column=att.attitude_time_column or att.time_column,  # type: ignore[arg-type]
        attitude_columns=att.attitude_columns, quaternion_columns=att.quaternion_columns,
        scalar_first=att.quaternion_order == "wxyz", frame=att.quaternion_frame,
    )
    t = time_values(samples.table, att.time_column, str(req.input.path))
    t0, t1 = stream.span
    sync: dict[str, Any] = {
        "attitude_file": str(att.attitude_file), "time_column": att.time_column,
        "attitude_time_column": att.attitude_time_column or att.time_column, "n_attitudes": len(stream.times),
        "attitude_span_s": [t0, t1], "attitude_interval_s": stream.median_interval,
        "n_attitude_rows_dropped": stream.n_dropped, "interpolation": "slerp",
        "lag_convention": "lag = attitude clock - magnetometer clock: the sample stamped t takes the attitude at "
                          "t + lag", "lag_s": 0.0, "lag_estimated": False,
    }
    messages = [f"attitudes from {att.attitude_file}: {len(stream.times)} rows over {t0:.6g}..{t1:.6g} s "
                f"(every {stream.median_interval:.4g} s), interpolated (slerp) to the magnetometer's time stamps"]
    lag = float(options.get("lag_s", 0.0))  # a known lag (evaluate: the calibration's)
    if truthy(options.get("estimate_lag", False)):
        if estimator.reference_kind != "vector" or req.reference.background_run is not None:
            raise TrimagInputError("`option estimate_lag=true` maximises the quality of the vector fit: it needs "
                                   "`model=interference12` with `background_ned=N,E,D` or `igrf_spec=...`")
        given = req.reference
        background, _ = background_field(ReferenceSpec(background_ned=given.background_ned, igrf_spec=given.igrf_spec),
                                         unit)
        ok = np.isfinite(t)
        result = estimate_lag(samples.field[ok], t[ok], stream, background,
                              max_lag=float(options.get("max_lag", 1.0)))
        lag = float(result["lag_s"])
        sync.update(result, lag_estimated=True)
        messages.append(
            f"lag between the streams (attitude clock - magnetometer clock): {lag:+.5f} +- {result['lag_std_s']:.2g} "
            f"s; vector RMS of the interference12 fit {result['rms_at_lag']:.4g} {unit} at that lag against "
            f"{result['rms_at_zero']:.4g} at zero lag"
        )
    rot, inside = interpolate_attitude(stream, t, lag)
    n_out = int((~inside).sum())
    sync["n_outside"] = n_out
    if rot is None:
        raise TrimagInputError(
            f"none of the {len(t)} magnetometer samples (time {np.nanmin(t):.6g}..{np.nanmax(t):.6g} s) lies inside "
            f"the attitude stream's span {t0:.6g}..{t1:.6g} s: check the time columns and their units"
        )
    if n_out:
        messages.append(f"dropped {n_out} of {len(t)} magnetometer samples outside the attitude stream's span "
                        f"({t0:.6g}..{t1:.6g} s{f', lag {lag:+.4g} s' if lag else ''}) or without a time stamp")
    table = samples.table[inside]  # the index keeps the original row numbers
    names = ("_attitude_qw", "_attitude_qx", "_attitude_qy", "_attitude_qz")
    q = rot.as_quat(scalar_first=True)
    table = table.assign(**{name: q[:, k] for k, name in enumerate(names)})
    samples = dataclasses.replace(samples, field=samples.field[inside], table=table,
                                  n_dropped=samples.n_dropped + n_out)
    req = dataclasses.replace(req, attitude=AttitudeSpec(quaternion_columns=",".join(names),
                                                         time_column=att.time_column))  # the eddy terms' time
    return samples, req, sync, messages

