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
    from ..vehicle.timesync import interpolate_attitude, read_attitude_stream, time_values
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
        ok = np.isfinite(t)
        result, described = _search_lag(req, samples.field[ok], t[ok], stream, unit, estimator,
                                        float(options.get("max_lag", 1.0)))
        lag = float(result["lag_s"])
        sync.update(result, lag_estimated=True, lag_background=described)
        messages.append(
            f"lag between the streams (attitude clock - magnetometer clock): {lag:+.5f} +- {result['lag_std_s']:.2g} "
            f"s against the {described}; vector RMS of the interference12 fit {result['rms_at_lag']:.4g} {unit} at "
            f"that lag against {result['rms_at_zero']:.4g} at zero lag"
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
    table = _positions_from_file(req, table, t[inside] + lag, messages)
    samples = dataclasses.replace(samples, field=samples.field[inside], table=table,
                                  n_dropped=samples.n_dropped + n_out)
    req = dataclasses.replace(req, attitude=AttitudeSpec(quaternion_columns=",".join(names),
                                                         time_column=att.time_column))  # the eddy terms' time
    return samples, req, sync, messages



#: With ``estimate_background`` the lag search and the background fit alternate at most this many times.
MAX_LAG_ROUNDS = 3


def _search_lag(
    req: FitRequest | EvaluateRequest, B: Any, t: Any, stream: Any, unit: str, estimator: Any, max_lag: float
) -> tuple[dict[str, Any], str]:
    """The lag (:func:`trimag.vehicle.timesync.estimate_lag`) against the given background, or, with
    ``estimate_background``, against the background fitted at lag 0, then refitted at the lag found and searched
    again until the lag moves by less than the sigma of the lag the background was fitted at (at most
    :data:`MAX_LAG_ROUNDS` searches): a background
    fitted at a wrong lag is itself a little off, and the search against it a little biased. Returns the search's
    result (with ``lag_rounds``) and the background's description."""
    from ..vehicle.timesync import estimate_lag

    lag, std, result, described = 0.0, 0.0, None, ""
    for rounds in range(1, MAX_LAG_ROUNDS + 1):
        background, described, fitted = _lag_background(req, B, t, stream, unit, estimator, lag)
        new = estimate_lag(B, t, stream, background, max_lag=max_lag)
        moved = abs(float(new["lag_s"]) - lag)
        lag, result = float(new["lag_s"]), {**new, "lag_rounds": rounds}
        if not fitted or moved < std:  # within the sigma of the lag the background was fitted at
            break
        std = float(new["lag_std_s"])
    assert result is not None
    return result, described


def _lag_background(
    req: FitRequest | EvaluateRequest, B: Any, t: Any, stream: Any, unit: str, estimator: Any, lag: float
) -> tuple[Any, str, bool]:
    """The background (N, E, D) the lag is searched against, its description and whether it was fitted: the given
    one, or, with ``estimate_background``, the one fitted jointly at ``lag`` (:func:`trimag.estimators
    .linear_vector.fit_with_background`; a given vector or magnitude only sets its scale, as in the fit itself)."""
    from ..vehicle.timesync import interpolate_attitude

    given = req.reference
    fitted = estimator is not None and truthy(getattr(estimator, "estimate_background", False))
    if estimator is None or estimator.reference_kind != "vector" or given.background_run is not None or (
            not fitted and given.background_ned is None and given.igrf_spec is None):
        raise TrimagInputError("`option estimate_lag=true` maximises the quality of the vector fit: it needs "
                               "`model=interference12` with `background_ned=N,E,D`, `igrf_spec=...` or "
                               "`option estimate_background=true`")
    if not fitted:
        background, source = background_field(ReferenceSpec(background_ned=given.background_ned,
                                                            igrf_spec=given.igrf_spec), unit)
        return background, f"background {np.round(background, 6).tolist()} ({source})", False
    from ..estimators.linear_vector import fit_with_background

    rot, inside = interpolate_attitude(stream, t, lag)
    if rot is None or inside.sum() < 20:
        raise TrimagInputError(f"fewer than 20 magnetometer samples lie inside the attitude stream's span at lag "
                               f"{lag:+.4g} s: the background cannot be fitted for the lag search; check the time "
                               "columns")
    _, _, background, _ = fit_with_background(B[inside], rot, 1.0)
    return background, (f"fitted background direction {np.round(background, 6).tolist()} (fitted at lag "
                        f"{lag:+.5g} s)"), True


def _positions_from_file(req: FitRequest | EvaluateRequest, table: Any, t: Any, messages: list[str]) -> Any:
    """The positions (``position_columns``) from the attitude file when the magnetometer's table lacks them: each
    interpolated linearly to the (lag-shifted) time stamps ``t``; NaN where the file has none."""
    import pandas as pd

    spec = getattr(req, "position_columns", None)
    if spec is None:
        return table
    names = [c.strip() for c in spec.split(",") if c.strip()]
    if all(n in table.columns for n in names):
        return table
    from ..io.tables import read_table
    from ..vehicle.timesync import time_values

    att = req.attitude
    source = read_table(att.attitude_file)  # type: ignore[arg-type]
    missing = [n for n in names if n not in source.columns]
    if missing:
        raise TrimagInputError(f"no column {missing[0]!r} (named by `position_columns`) in the data or in "
                               f"{att.attitude_file}")
    ta = time_values(source, att.attitude_time_column or att.time_column, str(att.attitude_file))  # type: ignore[arg-type]
    values = {n: np.asarray(pd.to_numeric(source[n], errors="coerce"), dtype=np.float64) for n in names}
    out = {}
    for n, v in values.items():
        ok = np.isfinite(ta) & np.isfinite(v)
        order = np.argsort(ta[ok], kind="stable")
        tt, vv = ta[ok][order], v[ok][order]
        col = np.interp(t, tt, vv) if len(tt) >= 2 else np.full(len(t), np.nan)
        if len(tt):
            col[(t < tt[0]) | (t > tt[-1])] = np.nan
        out[n] = col
    messages.append(f"positions {', '.join(names)} from {att.attitude_file}, interpolated to the magnetometer's time "
                    "stamps")
    return table.assign(**out)
