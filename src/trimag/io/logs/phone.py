"""Phone sensor-logger exports: ``Magnetometer.csv`` / ``MagnetometerUncalibrated.csv`` (uT).

The Sensor Logger app writes one CSV per sensor with columns ``time`` (ns since the epoch), ``seconds_elapsed``
and ``z, y, x`` in uT. ``Magnetometer.csv`` is the phone's own calibrated field; ``MagnetometerUncalibrated.csv``
the raw one, which is what a calibration should be fitted to: the reader says which it read. An
``Accelerometer.csv`` in the same folder is aligned as channels; a ``GyroscopeUncalibrated.csv`` (or
``Gyroscope.csv``, rad/s) is the log's gyroscope, for the gyro-aided fit (docs/method-gyro.md).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd

from ...errors import TrimagInputError
from .base import Channel, MagnetometerStream, VehicleLog

__all__ = ["PHONE_NAME", "read_phone"]

PHONE_NAME = re.compile(r"^Magnetometer(Uncalibrated)?\.csv$", re.I)


def _read(path: Path) -> pd.DataFrame:
    try:
        return pd.read_csv(path)
    except (pd.errors.ParserError, UnicodeDecodeError, ValueError) as exc:
        raise TrimagInputError(f"{path}: not a sensor-logger CSV ({exc})") from None


def _time(df: pd.DataFrame) -> np.ndarray:
    if "seconds_elapsed" in df.columns:
        return df["seconds_elapsed"].to_numpy(dtype=np.float64)
    return df["time"].to_numpy(dtype=np.float64) * 1e-9


def read_phone(path: Path) -> VehicleLog:
    """Read a sensor-logger magnetometer export (and the accelerometer beside it, when there is one)."""
    df = _read(path)
    missing = [c for c in ("x", "y", "z") if c not in df.columns]
    if missing or ("seconds_elapsed" not in df.columns and "time" not in df.columns):
        raise TrimagInputError(f"{path}: expected sensor-logger columns time/seconds_elapsed, x, y, z")
    field = df[["x", "y", "z"]].to_numpy(dtype=np.float64)
    raw = bool(re.search("uncalibrated", path.name, re.I))
    note = ("the phone's uncalibrated (raw) field" if raw else
            "warning: Magnetometer.csv is the phone's own calibrated field; fit MagnetometerUncalibrated.csv if "
            "the export has it")
    stream = MagnetometerStream(path.stem, 0, _time(df), field, field.copy(), "uT", [note])
    log = VehicleLog(str(path), "phone sensor logger", [stream])
    acc_path = path.with_name("Accelerometer.csv")
    if acc_path.exists():
        acc = _read(acc_path)
        if all(c in acc.columns for c in ("x", "y", "z")):
            for axis in "xyz":
                log.channels[f"accel_{axis}"] = Channel(_time(acc), acc[axis].to_numpy(dtype=np.float64), "m/s2",
                                                        f"Accelerometer.csv {axis}")
    log.gyro = _gyroscope(path, raw)
    return log


def _gyroscope(path: Path, raw: bool) -> Channel | None:
    """The gyroscope export beside the magnetometer's (``GyroscopeUncalibrated.csv`` for a raw magnetometer,
    else ``Gyroscope.csv``; the other when only it is there): rad/s, its own time stamps."""
    names = ("GyroscopeUncalibrated.csv", "Gyroscope.csv") if raw else ("Gyroscope.csv", "GyroscopeUncalibrated.csv")
    for name in names:
        gyro_path = path.with_name(name)
        if gyro_path.exists():
            df = _read(gyro_path)
            if all(c in df.columns for c in ("x", "y", "z")):
                return Channel(_time(df), df[["x", "y", "z"]].to_numpy(dtype=np.float64), "rad/s", name)
    return None
