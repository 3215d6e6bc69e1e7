"""Which sensor a calibration belongs to, from fit to every later command (issue 39; docs/calibration-file.md).

``fit`` (and ``batch``, ``live``) records the sensor it read in the calibration (:func:`sensor_record`: a
:class:`~trimag.calibration.SensorRecord`). ``evaluate``, ``apply``, ``live --replay`` and ``batch --prior`` read
the same sensor by default (:func:`input_for`): of a log, the compass with the recorded device id (a log without it
is refused, exit 2, unless ``sensor`` names a compass); of a table, the recorded columns (and variable) when the
file has them. :func:`sensor_line` says which sensor was read, and whose calibration it is.
"""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path
from typing import Any

from ..calibration import Calibration, SensorRecord
from ..errors import UnitMismatchError
from ..io import Samples
from ..io.logs import log_format
from .requests import InputSpec

__all__ = ["input_for", "offset_parameters", "sensor_line", "sensor_record"]


def _firmware(fmt: str) -> str | None:
    if fmt.startswith(("ArduPilot", "MAVLink")):
        return "ardupilot"
    if fmt.startswith("PX4"):
        return "px4"
    return None


def offset_parameters(firmware: str | None, slot: int | None) -> tuple[str, ...] | None:
    """The offset parameters of a firmware's calibration slot (0-based): ArduPilot ``COMPASS_OFS2_X..Z`` for slot
    1, PX4 ``CAL_MAG1_XOFF..`` (None for another source)."""
    if firmware is None or slot is None:
        return None
    if firmware == "ardupilot":
        n = "" if slot == 0 else str(slot + 1)
        return tuple(f"COMPASS_OFS{n}_{a}" for a in "XYZ")
    return tuple(f"CAL_MAG{slot}_{a}OFF" for a in "XYZ")


def _sha256(path: Path) -> str | None:
    if not path.is_file():
        return None
    digest = hashlib.sha256()
    with path.open("rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _message(name: str) -> str:
    """The log's message or topic of a stream's name: ``MAG[1]`` -> ``MAG``, ``IMU1.Mag`` -> ``IMU1``."""
    return name.split("[")[0].split(".")[0].split(" ")[0]


def sensor_record(samples: Samples, src: InputSpec, unit: str) -> SensorRecord:
    """The record of the sensor ``samples`` were read from (``src``: how they were read), in ``unit``."""
    path = Path(src.path)
    common: dict[str, Any] = {"unit": unit, "source": path.name, "source_sha256": _sha256(path),
              "columns": tuple(str(c) for c in samples.columns)}
    info = samples.log_info
    if info is not None:
        fmt = str(info.get("format") or "")
        firmware = _firmware(fmt)
        slot = info.get("instance")
        device = info.get("device_id")
        stale: tuple[int, ...] = ()
        if firmware == "px4" and device:
            stale = tuple(k for k in range(4) if k != slot
                          and int((info.get("parameters") or {}).get(f"CAL_MAG{k}_ID", 0) or 0) == int(device))
        absent: tuple[str, ...] = ()
        if firmware is not None and slot is not None:
            from ..models.firmware import absent_parameters

            absent = absent_parameters(firmware, info.get("parameters") or {}, int(slot))
        name = str(info.get("sensor") or "")
        return SensorRecord("log", format=fmt, compass=info.get("compass"), name=name, message=_message(name),
                            device_id=int(device) if device else None, firmware=firmware,
                            slot=None if slot is None else int(slot),
                            offset_parameters=offset_parameters(firmware, None if slot is None else int(slot)),
                            stale_slots=stale, absent_parameters=absent, **common)
    kind = log_format(path, src.fmt)
    table_fmt = src.fmt or (path.suffix.lower().lstrip(".") or None)
    return SensorRecord("log" if kind else "table", format=table_fmt, variable=src.var or samples.variable or None,
                        **common)


def input_for(cal: Calibration, src: InputSpec) -> tuple[InputSpec, Any]:
    """The input to read for ``cal``: ``(src with the recorded columns and variable of a table when none are
    given, the magnetometer to read of a log)``. The magnetometer is ``src.sensor`` when given, else the
    calibration's sensor record when it is a log's (:meth:`trimag.io.logs.VehicleLog.choose`: the same device),
    else None (the log's default)."""
    record = cal.sensor
    if src.sensor is not None or record is None:
        return src, src.sensor
    if log_format(src.path, src.fmt) is not None:
        return src, record if record.kind == "log" else None
    if record.kind == "table" and src.columns is None and record.columns and _has_columns(src, record):
        src = dataclasses.replace(src, columns=",".join(record.columns), var=src.var or record.variable)
    return src, None


def _has_columns(src: InputSpec, record: SensorRecord) -> bool:
    """Whether the table ``src`` has the record's columns (its header, read without the rows)."""
    from ..errors import TrimagError
    from ..io import open_chunks

    try:
        open_chunks(src.path, fmt=src.fmt, columns=",".join(record.columns or ()), var=src.var or record.variable)
    except TrimagError:
        return False
    return True


def sensor_line(cal: Calibration, src: InputSpec, log_info: dict[str, Any] | None,
                columns: Any = None, variable: str | None = None) -> str:
    """What was read for ``cal``, in one line (``sensor: ...``; ``variable``: the variable of an NPZ or MAT file
    read); a log's unit that is not the calibration's is refused (:class:`~trimag.errors.UnitMismatchError`,
    exit 2), a log's known unit against a calibration without one is a second line, a warning."""
    line = _sensor_line(cal, src, log_info, columns, variable)
    unit = str((log_info or {}).get("unit") or "unknown")
    if cal.units == "unknown" and unit != "unknown" and src.units is None:
        line += (f"\nwarning: the calibration's unit is not known (it was fitted without --units); this log's is "
                 f"{unit}: its numbers hold here only if it was fitted to {unit} data")
    return line


def _sensor_line(cal: Calibration, src: InputSpec, log_info: dict[str, Any] | None,
                 columns: Any = None, variable: str | None = None) -> str:
    record = cal.sensor
    if log_info is not None:
        unit = str(log_info.get("unit") or "unknown")
        if "unknown" not in (unit, cal.units) and unit != cal.units and src.units is None:
            raise UnitMismatchError(f"{src.path}: the log records {log_info.get('sensor')} in {unit}; this calibration "
                                    f"is for data in {cal.units}: fit this log, or convert the calibration")
        dev = log_info.get("device_id")
        read = (f"compass {log_info.get('compass')} of {Path(src.path).name} ({log_info.get('sensor')}"
                + (f", device id {dev}" if dev else "") + f"), {unit}")
        if record is None:
            return f"sensor: {read} (the calibration does not record its sensor: choose another with --sensor N)"
        if src.sensor is None and record.kind == "log":
            same = record.compass == log_info.get("compass") and record.source == Path(src.path).name
            return f"sensor: {read}: the calibration's" + ("" if same else f" (fitted as {record.describe()})")
        if record.kind == "log" and record.device_id and dev and int(dev) != record.device_id:
            return (f"warning: sensor: {read}, as --sensor asks; the calibration is another compass's "
                    f"({record.describe()})")
        return f"sensor: {read}" + (f"; the calibration's: {record.describe()}" if record.kind == "log" else
                                    f" (the calibration was fitted to {record.describe()})")
    cols = ", ".join(str(c) for c in (columns or ()))
    var = f" (variable {variable})" if variable else ""
    read = f"columns {cols}{var} of {Path(src.path).name}" if cols else f"{Path(src.path).name}{var}"
    if record is None:
        return f"sensor: {read}"
    same = (record.kind == "table" and tuple(record.columns or ()) == tuple(str(c) for c in (columns or ()))
            and (record.variable or None) == (variable or None))
    return f"sensor: {read}" + (": the calibration's" if same else f" (the calibration was fitted to "
                                                                     f"{record.describe()})")
