"""The gyroscope of a gyro-aided fit (``method=gyro``, docs/method-gyro.md): from columns of the magnetometer's own
rows (``gyro_columns``), from a second file with its own clock (``gyro_file``), or from a vehicle log's own
gyroscope (a phone export's ``Gyroscope*.csv``, an autopilot's IMU); and the lines the fit prints about it."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from ..calibration import Calibration
from ..errors import TrimagInputError
from ..fields.gyro import AngularRate, rate_in_rad_s
from ..io import Samples
from ..io.logs.base import forward_in_time
from .requests import FitRequest

#: RMS rate (rad/s) above which rates said to be in rad/s are flagged as probably deg/s (a hand turns a phone at
#: 1-5 rad/s; 20 rad/s is over 3 turns a second, sustained).
IMPLAUSIBLE_RAD_S = 20.0
#: A rate beyond this (rad/s, on any axis) is no gyroscope's reading in either unit (MEMS gyroscopes saturate at
#: 35-70 rad/s; deg/s read as rad/s stays below 4 000): the row is dropped and counted.
MAX_RATE_RAD_S = 1e4


def gyro_requested(req: FitRequest) -> bool:
    """Whether the request names a gyroscope (``gyro_columns`` or ``gyro_file``) or the gyro-aided method."""
    return req.gyro_columns is not None or req.gyro_file is not None or req.method == "gyro"


def log_has_gyro(samples: Samples) -> bool:
    """Whether a vehicle log offers a gyroscope (a phone export's is read with it; an autopilot's on request)."""
    return bool(samples.log_info and samples.log_info.get("gyro"))


def _names(spec: str, option: str) -> list[str]:
    from ..fields.attitude import parse_columns

    names = parse_columns(spec, 3, option=f"`{option}`")
    assert names is not None
    return names


def _values(table: pd.DataFrame, names: list[str], path: Any, option: str) -> np.ndarray:
    missing = [n for n in names if n not in table.columns]
    if missing:
        raise TrimagInputError(f"{path}: no column {missing[0]!r} (named by `{option}`); the columns are "
                               f"{', '.join(map(str, table.columns))}")
    return np.column_stack([pd.to_numeric(table[n], errors="coerce").to_numpy(dtype=float) for n in names])


def _unit(req: FitRequest, names: list[str], messages: list[str]) -> str:
    """The rate's unit: ``gyro_unit``, else deg/s when the column names say so (``deg``, ``dps``), else rad/s."""
    if req.gyro_unit is not None:
        return req.gyro_unit
    if any("deg" in n.lower() or "dps" in n.lower() for n in names):
        messages.append(f"gyroscope columns {', '.join(names)} in deg/s (from their names)")
        return "deg/s"
    messages.append("gyroscope rate taken as rad/s (give `gyro_unit=deg/s` if it is not)")
    return "rad/s"


#: The names of a sample rate (Hz) stored as a variable of an NPZ or MAT file beside the samples (BROAD's
#: ``sampling_rate``), lower case.
RATE_VARIABLES = ("sampling_rate", "sample_rate", "sampling_rate_hz", "rate_hz", "fs", "samplerate")


def _times(req: FitRequest, samples: Samples, messages: list[str]) -> np.ndarray:
    """The magnetometer's time stamps (s) of the kept rows: ``time_column`` (a vehicle log's ``time_s``), or the
    row number over ``rate_hz`` (else over the file's own sample rate variable, :data:`RATE_VARIABLES`)."""
    column = req.attitude.time_column or ("time_s" if "time_s" in samples.table.columns else None)
    if column is not None:
        from ..vehicle.timesync import time_values

        return time_values(samples.table, column, str(req.input.path))
    rate_hz = req.rate_hz
    if rate_hz is None and samples.variable:
        from ..io.tables import file_variables

        stored = {k: v for k, v in file_variables(req.input.path, req.input.fmt).items()
                  if k.lower() in RATE_VARIABLES and v.size == 1}
        if stored:
            name, value = next(iter(stored.items()))
            rate_hz = float(value.ravel()[0])
            if not (np.isfinite(rate_hz) and rate_hz > 0):
                raise TrimagInputError(f"{req.input.path}: its sample rate {name} = {rate_hz:g} is no rate; give "
                                       "`rate_hz=HZ`")
            messages.append(f"sample rate {rate_hz:g} Hz from the file's variable {name}")
    if rate_hz is None:
        raise TrimagInputError("the gyro-aided fit needs the samples' time: give `time_column=T` (seconds) or "
                               "`rate_hz=HZ`")
    return np.asarray(samples.table.index, dtype=np.float64) / float(rate_hz)


def _variable_rate(req: FitRequest, samples: Samples, name: str) -> np.ndarray | None:
    """The gyroscope as the variable ``name`` of the magnetometer's own NPZ or MAT file (``gyro_columns=imu_gyr``):
    its rows of the kept samples, (N, 3); None when ``name`` is not a single name or the file has no variables."""
    if "," in name or not samples.variable:
        return None
    from ..io.tables import file_variables

    variables = file_variables(req.input.path, req.input.fmt)
    if name not in variables:
        raise TrimagInputError(f"{req.input.path}: no variable {name!r} (named by `gyro_columns`); its variables are "
                               f"{', '.join(sorted(variables))}")
    values = np.squeeze(variables[name])
    if values.ndim == 2 and values.shape[0] == 3 and values.shape[1] != 3:
        values = values.T
    if values.ndim != 2 or values.shape[1] != 3:
        raise TrimagInputError(f"{req.input.path}: variable {name!r} has shape {variables[name].shape}; a gyroscope "
                               "is N x 3")
    if len(values) != samples.n_total_rows:
        raise TrimagInputError(f"{req.input.path}: variable {name!r} has {len(values)} rows and the magnetometer "
                               f"{samples.variable!r} {samples.n_total_rows}: a gyroscope of the same rows is needed "
                               "(else give `gyro_file` with its own time column)")
    return np.asarray(values, dtype=np.float64)[np.asarray(samples.table.index)]


def _keep(samples: Samples, ok: np.ndarray) -> Samples:
    return dataclasses.replace(samples, field=samples.field[ok], table=samples.table[ok],
                               n_dropped=samples.n_dropped + int((~ok).sum()))


def angular_rate(
    req: FitRequest, samples: Samples, max_lag: float, estimate_lag: bool | None
) -> tuple[Samples, AngularRate, list[str]]:
    """The samples (rows without a gyroscope value or time dropped, counted; with a gyroscope of its own clock,
    those outside its span less the lag search's ``max_lag`` unless ``estimate_lag`` is False; in the same rows with
    ``estimate_lag`` True, the first and last ``max_lag`` seconds, left out for the lag search) and their
    gyroscope."""
    messages: list[str] = []
    own = req.gyro_file is not None or (req.gyro_columns is None and log_has_gyro(samples))
    if not own and req.gyro_columns is None:
        raise TrimagInputError("method gyro needs the gyroscope: `gyro_columns=GX,GY,GZ` (the same rows), "
                               "`gyro_file=FILE` (its own clock) or a log with a gyroscope")
    t = _times(req, samples, messages)
    if own:
        tg, rate, source = _own_stream(req, samples, messages)
        margin = max_lag if estimate_lag is not False else 0.0
        ok = np.isfinite(t) & (t >= tg[0] + margin) & (t <= tg[-1] - margin)
        bridged = _in_gyro_gaps(t, tg) & ok
        if not ok.any():
            raise TrimagInputError(f"none of the magnetometer's samples ({np.nanmin(t):.6g}..{np.nanmax(t):.6g} s) "
                                   f"lies inside the gyroscope's span ({tg[0]:.6g}..{tg[-1]:.6g} s): check the time "
                                   "columns")
        if (~ok).sum():
            messages.append(f"dropped {int((~ok).sum())} of {len(t)} magnetometer samples outside the gyroscope's "
                            f"span ({tg[0]:.6g}..{tg[-1]:.6g} s, less the lag search's {margin:g} s)")
        if bridged.any():  # (the integration would bridge the gap: the fit's segments end at a gap in t instead)
            messages.append(f"dropped {int(bridged.sum())} magnetometer samples inside gaps of the gyroscope's "
                            "stream (its rows dropped or missing there)")
            ok &= ~bridged
        samples = _keep(samples, ok)
        gyro = AngularRate(t[ok], tg, rate, 0.0, True, source)
    else:
        assert req.gyro_columns is not None
        stored = _variable_rate(req, samples, req.gyro_columns.strip())
        names = [req.gyro_columns.strip()] if stored is not None else _names(req.gyro_columns, "gyro_columns")
        unit = _unit(req, names, messages)
        values = stored if stored is not None else _values(samples.table, names, req.input.path, "gyro_columns")
        ok = _rate_ok(rate_in_rad_s(values, unit)) & np.isfinite(t)
        if (~ok).sum():
            if req.input.strict:
                raise TrimagInputError(f"{int((~ok).sum())} rows have a missing gyroscope value or time, or a rate "
                                       f"beyond {MAX_RATE_RAD_S:g} rad/s; drop `strict` to skip and count them")
            messages.append(f"dropped {int((~ok).sum())} rows whose gyroscope value or time is missing, or whose "
                            f"rate is beyond {MAX_RATE_RAD_S:g} rad/s")
        samples = _keep(samples, ok)
        source = (f"variable {names[0]} ({unit})" if stored is not None else f"columns {', '.join(names)} ({unit})")
        messages.append(f"gyroscope: {source}, in the magnetometer's rows")
        gyro = AngularRate.same_rows(t[ok], values[ok], unit=unit, source=source)
        if estimate_lag:  # a lag between columns of the same rows: the rows' stamps as the gyroscope's own clock
            samples, gyro = _same_rows_lag(samples, gyro, max_lag, messages)
    _plausible(gyro, messages)
    return samples, gyro, messages


def _same_rows_lag(samples: Samples, gyro: AngularRate, max_lag: float, messages: list[str]
                   ) -> tuple[Samples, AngularRate]:
    """The samples less their first and last ``max_lag`` seconds (counted), and the gyroscope of the same rows taken
    as a stream of its own on those stamps, so that the lag search can slide it by up to ``max_lag`` either way."""
    t = gyro.time_s
    inside = (t >= t[0] + max_lag) & (t <= t[-1] - max_lag)
    if inside.sum() < 3:
        raise TrimagInputError(f"the log ({t[-1] - t[0]:.3g} s) is too short for a lag search of +-{max_lag:g} s: "
                               "give a smaller `option max_lag`")
    messages.append(f"left out the first and last {max_lag:g} s ({int((~inside).sum())} of {len(t)} samples) for "
                    "the lag search between the magnetometer and the gyroscope of the same rows")
    return _keep(samples, inside), AngularRate(t[inside], t, gyro.rate, 0.0, True, gyro.source)


def _own_stream(req: FitRequest, samples: Samples, messages: list[str]) -> tuple[np.ndarray, np.ndarray, str]:
    """A gyroscope with its own time stamps: ``gyro_file`` (its time column, ``gyro_columns``) or the log's."""
    if req.gyro_file is None:
        from ..io.logs import read_log

        log = read_log(Path(req.input.path), req.input.fmt, gyro=True)  # (read as a log already: fmt is one or None)
        if log.gyro is None:
            raise TrimagInputError(f"{req.input.path}: the log has no gyroscope (IMU messages); give `gyro_file`")
        tg, rate, source = log.gyro.time_s, log.gyro.values, f"{log.gyro.source} (rad/s, the log's own)"
    elif _is_variable_file(req):
        tg, rate, source = _variable_stream(req, messages)
    else:
        from ..io.tables import read_table
        from ..vehicle.timesync import time_values

        table = read_table(Path(req.gyro_file))
        column = req.gyro_time_column or req.attitude.time_column
        if column is None:
            raise TrimagInputError("`gyro_file` needs its time column: `gyro_time_column=NAME` (or `time_column`)")
        names = _names(req.gyro_columns or "x,y,z", "gyro_columns")
        unit = _unit(req, names, messages)
        tg = time_values(table, column, f"{req.gyro_file} (`gyro_file`)")
        rate = rate_in_rad_s(_values(table, names, req.gyro_file, "gyro_columns"), unit)
        source = f"{req.gyro_file}: {', '.join(names)} ({unit}), time {column}"
    ok = _rate_ok(rate)
    tg, rate = tg[ok], rate[ok]
    keep = forward_in_time(tg, strictly=True)  # not sorted: a row stamped out of order is another moment's rate
    if keep.sum() < 3:
        raise TrimagInputError("the gyroscope has fewer than 3 samples with a finite time and rate")
    dropped = [f"{n} {what}" for n, what in ((int((~ok).sum()), "without a finite rate within "
                                              f"{MAX_RATE_RAD_S:g} rad/s"),
                                             (int((~keep).sum()), "whose time stamp is missing, repeats or goes back "
                                              "(earlier than a row before it)")) if n]
    tg, rate = tg[keep], rate[keep]
    messages.append(f"gyroscope: {source}, {len(tg)} samples over {tg[0]:.6g}..{tg[-1]:.6g} s")
    if dropped:
        messages.append(f"warning: gyroscope rows dropped: {'; '.join(dropped)}")
    return tg, rate, source


def _is_variable_file(req: FitRequest) -> bool:
    """Whether ``gyro_file`` is an NPZ or MAT file and ``gyro_columns`` one name (a variable of it)."""
    from ..io.tables import guess_format

    spec = (req.gyro_columns or "").strip()
    return bool(spec) and "," not in spec and guess_format(Path(str(req.gyro_file))) in ("mat", "npz")


def _variable_stream(req: FitRequest, messages: list[str]) -> tuple[np.ndarray, np.ndarray, str]:
    """The gyroscope as a variable of another NPZ or MAT file (``gyro_file=other.mat gyro_columns=imu_gyr``) on
    its own clock: the variable ``gyro_time_column`` names (s), else the row number over that file's own sample
    rate variable (:data:`RATE_VARIABLES`), from 0 s; (time s (M,), rate rad/s (M, 3), where it came from)."""
    from ..io.tables import file_variables

    path = Path(str(req.gyro_file))
    name = str(req.gyro_columns).strip()
    if not path.is_file():
        raise TrimagInputError(f"{path}: no such file (named by `gyro_file`)")
    variables = file_variables(path)
    listed = ", ".join(sorted(variables)) or "none"
    if name not in variables:
        raise TrimagInputError(f"{path}: no variable {name!r} (named by `gyro_columns`); its variables are {listed}")
    values = np.squeeze(variables[name])
    if values.ndim == 2 and values.shape[0] == 3 and values.shape[1] != 3:
        values = values.T
    if values.ndim != 2 or values.shape[1] != 3:
        raise TrimagInputError(f"{path}: variable {name!r} has shape {variables[name].shape}; a gyroscope is N x 3")
    unit = _unit(req, [name], messages)
    if req.gyro_time_column is not None:
        column = req.gyro_time_column
        if column not in variables:
            raise TrimagInputError(f"{path}: no variable {column!r} (named by `gyro_time_column`); its variables "
                                   f"are {listed}")
        tg = np.asarray(np.ravel(variables[column]), dtype=np.float64)
        if len(tg) != len(values):
            raise TrimagInputError(f"{path}: time variable {column!r} has {len(tg)} values and {name!r} "
                                   f"{len(values)} rows: give the gyroscope's own time stamps (s)")
        clock = f"time {column}"
    else:
        stored = {k: v for k, v in variables.items() if k.lower() in RATE_VARIABLES and v.size == 1}
        if not stored:
            raise TrimagInputError(f"{path}: the gyroscope {name!r} has no clock: name its time stamps (s) with "
                                   f"`gyro_time_column=VARIABLE`, or store its sample rate as a variable "
                                   f"sampling_rate (its variables are {listed})")
        rate_name, value = next(iter(stored.items()))
        rate_hz = float(value.ravel()[0])
        if not (np.isfinite(rate_hz) and rate_hz > 0):
            raise TrimagInputError(f"{path}: its sample rate {rate_name} = {rate_hz:g} is no rate; name its time "
                                   "stamps with `gyro_time_column=VARIABLE`")
        tg = np.arange(len(values), dtype=np.float64) / rate_hz
        clock = f"{rate_hz:g} Hz from its {rate_name}, from 0 s"
    return tg, rate_in_rad_s(np.asarray(values, dtype=np.float64), unit), f"{path}: variable {name} ({unit}), {clock}"


def _in_gyro_gaps(t: np.ndarray, tg: np.ndarray) -> np.ndarray:
    """The magnetometer samples (time stamps ``t``) that fall inside a gap of the gyroscope's stamps ``tg`` longer
    than the gyro fit's gap rule (:data:`trimag.estimators.gyro.GAP_INTERVALS` median intervals)."""
    from ..estimators.gyro import GAP_INTERVALS

    dt = np.diff(tg)
    gaps = np.flatnonzero(dt > GAP_INTERVALS * float(np.median(dt))) if len(dt) else np.zeros(0, dtype=int)
    inside = np.zeros(len(t), dtype=bool)
    if len(gaps):
        k = np.searchsorted(tg, t, side="right") - 1  # the gyroscope row before each sample
        with np.errstate(invalid="ignore"):
            inside = np.isin(k, gaps) & (t > tg[np.clip(k, 0, len(tg) - 1)])
    return inside


def _rate_ok(rate: np.ndarray) -> np.ndarray:
    """The rows (N,) of a rate (N, 3) that are finite and within :data:`MAX_RATE_RAD_S` on every axis."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(rate).all(axis=1) & (np.abs(rate) <= MAX_RATE_RAD_S).all(axis=1)


def _plausible(gyro: AngularRate, messages: list[str]) -> None:
    rms = float(np.sqrt(np.mean(np.sum(gyro.rate**2, axis=1))))
    if rms > IMPLAUSIBLE_RAD_S:
        messages.append(f"warning: the gyroscope's rate is {rms:.3g} rad/s RMS, more than {IMPLAUSIBLE_RAD_S:g}: the "
                        "numbers look like deg/s (give `gyro_unit=deg/s`)")


def gyro_lines(cal: Calibration) -> tuple[Calibration, list[str]]:
    """After a gyro-aided fit: the nearest board rotation of the magnetometer's axes to the gyroscope's (into
    ``diagnostics["gyro_alignment"]``) and the lines about the bias, the lag, the alignment and what the gyroscope
    identified."""
    from ..vehicle.alignment import nearest_board_rotation

    g, align = cal.diagnostics["gyro"], dict(cal.diagnostics["gyro_alignment"])
    std = cal.uncertainty["param_std"] if cal.uncertainty else {}
    board = nearest_board_rotation(align["sensor_matrix"])
    align["board_rotation"] = board
    cal = cal.with_diagnostics(gyro_alignment=align)
    bias_std = [std.get(f"gyro_bias_{a}") for a in "xyz"]
    lines = [f"gyroscope bias {np.round(g['bias_rad_s'], 5).tolist()} rad/s"
             + (f" +- {np.round(np.asarray(bias_std, dtype=float), 5).tolist()}" if None not in bias_std else "")
             + f"; {g['n_segments']} segments of {g['segment_s']:g} s; vector RMS {g['vector_rms']:.4g} {cal.units}"]
    if g["lag_estimated"]:
        lines.append(f"lag between the streams (gyroscope clock - magnetometer clock): {g['lag_s']:+.5f} +- "
                     f"{std.get('lag_s', float('nan')):.2g} s")
    ypr, rot_std = align["euler_zyx_deg"], align["rotation_std_deg"]
    s_ypr = align["sensor_euler_zyx_deg"]
    lines.append(f"alignment, corrected magnetometer -> gyroscope: yaw {ypr[0]:.3f}, pitch {ypr[1]:.3f}, roll "
                 f"{ypr[2]:.3f} deg (Z-Y-X); 1 sigma about x, y, z {', '.join(f'{v:.2g}' for v in rot_std)} deg")
    lines.append(f"magnetometer axes -> gyroscope: yaw {s_ypr[0]:.3f}, pitch {s_ypr[1]:.3f}, roll {s_ypr[2]:.3f} deg; "
                 f"nearest board rotation {board['name']} (COMPASS_ORIENT = {board['number']}), remaining rotation "
                 f"{board['remaining_angle_deg']:.3g} deg")
    ident = cal.diagnostics["identifiability"]
    if ident["identified_by_gyro"]:
        lines.append(f"identified with the gyroscope where the magnitude alone leaves them unidentified: "
                     f"{', '.join(ident['identified_by_gyro'])}")
    if ident["poorly_determined"]:
        lines.append(f"poorly determined even with the gyroscope (>10x a full sphere's sigma): "
                     f"{', '.join(ident['poorly_determined'])}")
    return cal, lines
