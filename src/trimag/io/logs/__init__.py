"""Readers of vehicle logs: one :class:`VehicleLog` per file (docs/autopilot.md), with the onboard calibration
undone and the streams aligned to one magnetometer.

Formats: ArduPilot DataFlash (``.bin``, ``.log``) and MAVLink telemetry (``.tlog``), PX4 ULog (``.ulg``) and sdlog2
(``.px4log``), ROS 1/2 bags and MCAP (``.bag``, ROS 2 folders, ``.mcap``), phone sensor-logger exports
(``Magnetometer.csv``, ``MagnetometerUncalibrated.csv``). They need the optional extra ``trimag[logs]`` (pymavlink,
pyulog, rosbags); a missing one is named in a one-line error.

Every reader returns the magnetometers it found (each with its time stamps, the field in a stated unit and, where
the autopilot logs its readings after its own calibration, that calibration undone and described), the vehicle's
attitude, battery current, throttle, temperature and GPS fix where the log has them, and the parameters.
:meth:`VehicleLog.table` aligns everything to one magnetometer's time stamps (linear interpolation, attitude by
slerp) and counts what it dropped.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ...errors import TrimagError, TrimagInputError
from .base import Channel, MagnetometerStream, VehicleLog

__all__ = [
    "LOG_FORMATS",
    "Channel",
    "MagnetometerStream",
    "VehicleLog",
    "log_format",
    "read_log",
]

#: extension -> log format
LOG_FORMATS: dict[str, str] = {
    ".bin": "dataflash",
    ".log": "dataflash",
    ".tlog": "tlog",
    ".ulg": "ulog",
    ".px4log": "px4log",
}


def log_format(path: str | Path, fmt: str | None = None) -> str | None:
    """The log format of ``path`` (from ``fmt``, the extension or the name), or None for other files."""
    if fmt in {*LOG_FORMATS.values(), "rosbag", "phone"}:
        return fmt
    if fmt is not None:
        return None
    p = Path(path)
    if p.is_dir():
        return "rosbag" if (p / "metadata.yaml").exists() else None
    from .phone import PHONE_NAME

    if PHONE_NAME.match(p.name) and _sensor_logger_header(p):
        return "phone"
    suffix = p.suffix.lower()
    if suffix in (".bag", ".mcap"):
        return "rosbag"
    kind = LOG_FORMATS.get(suffix)
    if kind == "dataflash" and suffix == ".log":
        # a text DataFlash log starts with FMT lines; any other .log is left to the table readers
        try:
            with open(path, "rb") as fh:
                head = fh.read(256)
        except OSError:
            return None
        if not (head.startswith(b"FMT") or head[:2] == b"\xa3\x95"):
            return None
    return kind


def _sensor_logger_header(path: Path) -> bool:
    """Whether a file named like a phone's sensor-logger export has its header (``x``, ``y``, ``z`` among the
    comma-separated names of its first line): a plain table of the same name is read as a table (issue 32)."""
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            names = {n.strip().strip('"').lower() for n in fh.readline().split(",")}
    except OSError:
        return True  # the reader says what is wrong with the path
    return {"x", "y", "z"} <= names


def _check_dataflash_head(path: Path) -> None:
    """Refuse a file that is not a DataFlash log before pymavlink reads it byte by byte (it prints a "bad header"
    line for each byte it skips): a binary log (``.bin``; pymavlink reads any ``.bin`` as binary) starts with a
    message header ``0xA3 0x95``, a text log (``.log``) with ``FMT`` (``AP_Logger`` writes the ``FMT`` messages
    first)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(3)
    except OSError as exc:
        raise TrimagInputError(f"{path}: cannot read the log ({exc.strerror or exc})") from None
    binary = head[:2] == b"\xa3\x95"
    if not binary and (path.suffix.lower() == ".bin" or not head.startswith(b"FMT")):
        raise TrimagInputError(
            f"{path}: not an ArduPilot DataFlash log (a binary log starts with the message header 0xA3 0x95, a "
            "text .log with FMT lines); if it is a table of x, y, z values, give `--format` (csv, npy, mat, ...)"
        )


#: What a reader raises on a damaged log whose structure it trusted (an FMT without a field the firmware always
#: writes, a parameter's type name, a singular logged matrix, a number out of range): said as damage, exit 2.
_DAMAGE = (KeyError, IndexError, ValueError, TypeError, AttributeError, ArithmeticError, EOFError, UnicodeError,
           np.linalg.LinAlgError, struct.error)


def read_log(path: str | Path, fmt: str | None = None, *, gyro: bool = False,
             progress: Callable[[float, str], None] | None = None) -> VehicleLog:
    """Read an autopilot log (format from ``fmt`` or the extension). ``gyro``: also read a DataFlash log's ``IMU``
    messages (the gyroscope, ``VehicleLog.gyro``; the other formats always give theirs, at no extra cost).

    ``progress``, when given, is called as ``progress(fraction, what)`` while the log is read (a page showing a
    large log's reading): a binary DataFlash log reports every few MB of its scan (fraction of its bytes, 0..1);
    every format reports 0.0 at the start and 1.0 when read."""
    if progress is not None:
        progress(0.0, f"reading {Path(path).name}")
    log = _read_log(path, fmt, gyro=gyro, progress=progress)
    if progress is not None:
        progress(1.0, f"read {Path(path).name}: {len(log.magnetometers)} magnetometer(s)")
    return log


def _read_log(path: str | Path, fmt: str | None, *, gyro: bool,
              progress: Callable[[float, str], None] | None) -> VehicleLog:
    """:func:`read_log` without its progress ends. A log whose damage breaks what its reader expects of the format
    (fuzzed copies, issue 41 item 4) raises :class:`TrimagInputError` naming what was wrong, never a reader's own
    exception."""
    p = Path(path)
    kind = log_format(p, fmt)
    if not p.exists():
        raise TrimagInputError(f"{p}: no such file")
    if p.is_dir() and kind != "rosbag":
        raise TrimagInputError(f"{p}: is a folder; give a log file")
    try:
        return _read(p, kind, gyro, progress)
    except TrimagError:
        raise
    except _DAMAGE as exc:
        what = f"a message lacks its field {exc.args[0]!r}" if isinstance(exc, KeyError) and exc.args else \
            f"{type(exc).__name__}: {str(exc)[:120]}"
        raise TrimagInputError(f"{p}: the log is damaged or not as its firmware writes it ({what}); read a copy "
                               "taken straight from the vehicle, or another log") from None


def _read(p: Path, kind: str | None, gyro: bool, progress: Callable[[float, str], None] | None) -> VehicleLog:
    """The log ``p`` read by the reader of its format ``kind``."""
    if kind == "rosbag":
        from .ros import read_ros

        return read_ros(p)
    if kind == "phone":
        from .phone import read_phone

        return read_phone(p)
    if kind in ("dataflash", "tlog"):
        from .ardupilot import read_ardupilot

        if kind == "dataflash":
            _check_dataflash_head(p)
        return read_ardupilot(p, kind, gyro=gyro, progress=progress)
    if kind == "ulog":
        from .px4 import read_ulog

        return read_ulog(p)
    if kind == "px4log":
        from .px4 import read_px4log

        return read_px4log(p)
    raise TrimagInputError(f"{p}: not a vehicle log (.bin, .log, .tlog, .ulg, .px4log, .bag, .mcap, ROS 2 folder)")
