"""ArduPilot DataFlash (``.bin``/``.log``) and MAVLink telemetry (``.tlog``) logs, read with pymavlink.

ArduPilot logs the magnetometer **after** its onboard calibration. ``AP_Compass_Backend::correct_field``
(libraries/AP_Compass/AP_Compass_Backend.cpp) turns the reading ``r`` (already rotated to the body frame by
``COMPASS_ORIENTn`` / ``AHRS_ORIENTATION``) into

    m = M (s (r + ofs)) + mot          M = [[DIA_X, ODI_X, ODI_Y], [ODI_X, DIA_Y, ODI_Z], [ODI_Y, ODI_Z, DIA_Z]]

with ``ofs`` = ``COMPASS_OFSn_*`` (milligauss), ``s`` = ``COMPASS_SCALEn`` (applied only within [1/1.5, 1.5]),
``M`` the identity when ``DIA`` is zero, and ``mot`` the motor compensation (logged as ``MOX..MOZ`` / ``MOfsX..``).
Older firmware (logs with ``MOfs*`` fields) added ``mot`` before the matrix. The reader undoes exactly that
(``r = (M^-1 (m - mot)) / s - ofs``) and says what it undid. The orientation is *not* undone: ArduPilot's offsets
and matrix act in the rotated frame, so a calibration to be written back must be fitted there.
"""

from __future__ import annotations

import datetime as _dt
import re
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...errors import TrimagInputError
from .base import Channel, MagnetometerStream, VehicleLog, mavlink_messages
from .tlog import read_tlog_messages

__all__ = ["onboard_matrix", "read_ardupilot", "undo_ardupilot"]

_SCALE_MAX = 1.5  # COMPASS_MAX_SCALE_FACTOR (AP_Compass.h)

_DF_TYPES = ["MAG", "MAG2", "MAG3", "ATT", "BAT", "CURR", "RCOU", "GPS", "PARM", "CTUN", "FMTU", "UNIT", "MULT", "MSG",
             "XKY0", "AHR2", "BARO"]
_TLOG_TYPES = ["RAW_IMU", "SCALED_IMU2", "SCALED_IMU3", "ATTITUDE", "BATTERY_STATUS", "SYS_STATUS",
               "GLOBAL_POSITION_INT", "GPS_RAW_INT", "PARAM_VALUE", "SERVO_OUTPUT_RAW", "VFR_HUD",
               "SCALED_PRESSURE", "AHRS2"]


def _suffix(instance: int) -> str:
    return "" if instance == 0 else str(instance + 1)


def onboard_matrix(params: dict[str, float], instance: int) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """``(ofs, M, s)`` of ArduPilot compass ``instance`` from its parameters (see the module docstring)."""
    n = _suffix(instance)
    ofs = np.array([params.get(f"COMPASS_OFS{n}_{a}", 0.0) for a in "XYZ"])
    dia = np.array([params.get(f"COMPASS_DIA{n}_{a}", 0.0) for a in "XYZ"])
    odi = np.array([params.get(f"COMPASS_ODI{n}_{a}", 0.0) for a in "XYZ"])
    if not dia.any():
        dia = np.ones(3)
    M = np.array([[dia[0], odi[0], odi[1]], [odi[0], dia[1], odi[2]], [odi[1], odi[2], dia[2]]])
    scale = float(params.get(f"COMPASS_SCALE{n}", 0.0))
    s = scale if 1.0 / _SCALE_MAX <= scale <= _SCALE_MAX else 1.0
    return ofs, M, s


def undo_ardupilot(
    logged_mG: NDArray[np.float64], params: dict[str, float], instance: int,
    motor_mG: NDArray[np.float64] | None = None, *, motor_before_matrix: bool = False,
) -> tuple[NDArray[np.float64], list[str], dict[str, float]]:
    """The raw reading (body frame, mG) behind ArduPilot's logged corrected field; and what was undone."""
    ofs, M, s = onboard_matrix(params, instance)
    mot = np.zeros_like(logged_mG) if motor_mG is None else motor_mG
    if motor_before_matrix:
        raw = np.linalg.solve(M, logged_mG.T).T / s - mot - ofs
    else:
        raw = np.linalg.solve(M, (logged_mG - mot).T).T / s - ofs
    n = _suffix(instance)
    undone = [f"offsets COMPASS_OFS{n}_X..Z = {np.round(ofs, 2).tolist()} mG (added onboard) subtracted"]
    if not np.allclose(M, np.eye(3)):
        undone.append(f"soft-iron matrix COMPASS_DIA{n}/ODI{n} (det {np.linalg.det(M):.4f}) inverted")
    if s != 1.0:
        undone.append(f"scale COMPASS_SCALE{n} = {s:.4f} divided out")
    if np.any(mot != 0):
        undone.append(f"motor compensation (logged, up to {np.abs(mot).max():.1f} mG) subtracted")
    if not undone[1:] and not ofs.any():
        undone = ["no onboard calibration was set (offsets zero, matrix identity): the logged reading is raw"]
    onboard = {f"COMPASS_OFS{n}_{a}": float(v) for a, v in zip("XYZ", ofs, strict=True)}
    onboard.update({f"M{i}{j}": float(M[i, j]) for i in range(3) for j in range(3)})
    onboard["scale"] = s
    return raw, undone, onboard


def _gps_date(week: float, ms: float) -> str:
    t = _dt.datetime(1980, 1, 6, tzinfo=_dt.UTC) + _dt.timedelta(weeks=float(week), milliseconds=float(ms))
    return t.date().isoformat()


Columns = dict[str, dict[str, NDArray[Any]]]
#: Per message type: ``"format"`` (its format characters by field) and ``"units"`` (field -> (unit, multiplier) from
#: ``FMTU``), what the physical value of an integer field depends on (:func:`_physical`).
Meta = dict[str, dict[str, Any]]


def _collect(path: Path, kind: str, gyro: bool = False, progress: Callable[[float, str], None] | None = None
             ) -> tuple[Columns, dict[str, float], Meta, list[str]]:
    """Every wanted message type as columns, the parameters (first value of each), each type's field formats
    and units, and what was skipped as damage; ``gyro``: also ``IMU``."""
    types = _TLOG_TYPES if kind == "tlog" else _DF_TYPES + (["IMU"] if gyro else [])
    if kind == "dataflash":
        with path.open("rb") as fh:
            binary = fh.read(2) == b"\xa3\x95"
        if binary:
            from .dataflash import field_units, read_dataflash

            formats: dict[str, tuple[int, str, list[str]]] = {}
            cols = read_dataflash(path, types, formats, progress)
            params: dict[str, float] = {}
            parm = cols.get("PARM")  # kept: a calibration set in flight is undone where it was in force
            if parm is not None:
                for name, value in zip(parm["Name"].tolist(), parm["Value"].tolist(), strict=True):
                    params.setdefault(str(name), float(value))
            units = field_units(cols, formats)
            found: Meta = {name: {"format": dict(zip(c, f, strict=False)), "units": units.get(name, {})}
                           for name, (_, f, c) in formats.items()}
            return cols, params, found, []
    rows: dict[str, list[dict[str, Any]]] = defaultdict(list)
    params = {}
    meta: Meta = {}
    notes: list[str] = []
    if kind == "tlog":  # pymavlink's reader can take quadratic time on a damaged tlog (tlog.py)
        read = read_tlog_messages(path, types)
        messages: Any = read.messages
        notes = read.notes()
    else:
        messages = mavlink_messages(path, types)
    for msg in messages:
        name = msg.get_type()
        if name == "PARM":
            params.setdefault(str(msg.Name), float(msg.Value))
            rows[name].append({"TimeUS": getattr(msg, "TimeUS", 0), "Name": str(msg.Name), "Value": float(msg.Value)})
        elif name == "PARAM_VALUE":
            params[str(msg.param_id).rstrip("\x00")] = float(msg.param_value)
        else:
            d = msg.to_dict()
            d["_timestamp"] = getattr(msg, "_timestamp", None)
            rows[name].append(d)
            fmt = getattr(msg, "fmt", None)  # a text DataFlash message's FMT (a telemetry message has none)
            if name not in meta and fmt is not None and hasattr(fmt, "format"):
                meta[name] = {"format": dict(zip(fmt.columns, fmt.format, strict=False)), "units": {}}
    return {name: _columns(rs) for name, rs in rows.items()}, params, meta, notes


def _physical(meta: Meta, name: str, field: str, values: NDArray[Any]) -> tuple[NDArray[np.float64], str]:
    """A field's values in its physical unit and a note of the scaling applied: the log's ``FMTU`` multiplier, or,
    in a log without ``FMTU``, ArduPilot's documented integer encodings (``CURR.Volt``/``Curr`` centivolts and
    centiamps, ``Log_Write_Current`` of ArduPilot 3.x; ArduCopter 3.x ``CTUN.ThrOut`` throttle x 1000; a
    ``%`` throttle is divided by 100)."""
    v = np.asarray(values, dtype=np.float64)
    info = meta.get(name, {})
    fmt = info.get("format", {}).get(field, "f")
    unit, mult = info.get("units", {}).get(field, ("", None))
    if mult is not None and not (mult == 1.0 and unit == "" and field == "ThrOut"):
        if unit == "%":
            return v * mult / 100.0, f"{name}.{field} (% / 100)"
        return (v * mult, f"{name}.{field} (x {mult:g}, FMTU)") if mult != 1.0 else (v, f"{name}.{field}")
    integer = fmt in "bBhHiIqQ"
    if integer and name == "CURR" and field in ("Volt", "Curr", "Volt2"):
        return v * 0.01, f"{name}.{field} (x 0.01: centi-units of ArduPilot 3.x, no FMTU)"
    if integer and field == "ThrOut":
        cols = info.get("format", {})
        if "ThrIn" in cols:  # ArduCopter 3.x: motors throttle 0..1000
            return v * 0.001, f"{name}.{field} (x 0.001: ArduCopter 3.x throttle 0..1000, no FMTU)"
        return v * 0.01, f"{name}.{field} (% / 100: ArduPlane throttle, no FMTU)"
    return v, f"{name}.{field}"


def _columns(rows: list[dict[str, Any]]) -> dict[str, NDArray[Any]]:
    """Messages (dicts) -> one array per numeric field."""
    out: dict[str, NDArray[Any]] = {}
    for key in rows[0]:
        values = [r.get(key) for r in rows]
        if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
            out[key] = np.asarray(values, dtype=np.float64)
    return out


def _array(cols: dict[str, NDArray[Any]], keys: list[str]) -> NDArray[np.float64]:
    return np.column_stack([np.asarray(cols[k], dtype=np.float64) for k in keys])


def _n(cols: dict[str, NDArray[Any]] | None) -> int:
    return 0 if not cols else len(next(iter(cols.values())))


def _take(cols: dict[str, NDArray[Any]], mask: NDArray[np.bool_]) -> dict[str, NDArray[Any]]:
    return {k: v[mask] for k, v in cols.items()}


def _time_s(cols: dict[str, NDArray[Any]], *, receipt: bool = False) -> NDArray[np.float64]:
    """Time of each message, s: the autopilot's clock, or (``receipt``, telemetry logs) the time it was received."""
    if receipt:
        return np.asarray(cols["_timestamp"], dtype=np.float64)
    for key, factor in (("TimeUS", 1e-6), ("time_usec", 1e-6), ("TimeMS", 1e-3), ("time_boot_ms", 1e-3)):
        if key in cols:
            return np.asarray(cols[key], dtype=np.float64) * factor
    return np.asarray(cols["_timestamp"], dtype=np.float64)


def _dataflash(path: Path, rows: Columns, params: dict[str, float], meta: Meta) -> VehicleLog:
    log = VehicleLog(str(path), "ArduPilot DataFlash", _dataflash_magnetometers(rows, params), parameters=params)
    _dataflash_channels(log, rows, meta)
    log.gps = _dataflash_gps(rows.get("GPS"))
    log.vehicle = _vehicle(rows.get("MSG"))
    log.yaw_sources = _yaw_sources(rows, meta)
    gps = rows.get("GPS")
    if _n(gps) and gps is not None and {"GCrs", "Spd", "Status"} <= set(gps):
        course = gps_course(_array(gps, ["GCrs"])[:, 0], _array(gps, ["Spd"])[:, 0],
                            np.asarray(gps["Status"]) >= 3)
        if np.isfinite(course).any():
            log.channels["gps_course_deg"] = Channel(_time_s(gps), course, "deg", "GPS.GCrs")
    return log


_VEHICLES = re.compile(r"\b(ArduCopter|ArduPlane|ArduSub|ArduRover|Rover|Blimp|AntennaTracker|APM:\w+)\s*V?[\d.]*")


def _vehicle(msg: Any) -> str | None:
    """The firmware and version of the log's first ``MSG`` that names one (``"ArduCopter V4.3.6"``)."""
    if not _n(msg) or msg is None or "Message" not in msg:
        return None
    for text in msg["Message"][:50]:
        m = _VEHICLES.search(str(text))
        if m:
            return m.group(0).strip()
    return None


def _yaw_sources(rows: Columns, meta: Meta) -> dict[str, Channel]:
    """Yaw estimates that do not use the compass: the EKF-GSF yaw (``XKY0.YC`` and its sigma ``YCS``, EKF3 core 0;
    degrees, radians where the log's FMTU says so) and a GPS heading (``GPS.Yaw`` of a moving-baseline GPS, where it
    is non-zero)."""
    out: dict[str, Channel] = {}
    gsf = rows.get("XKY0")
    if _n(gsf) and gsf is not None and "YC" in gsf:
        core = _take(gsf, np.asarray(gsf["C"]).astype(int) == 0) if "C" in gsf else gsf
        if _n(core):
            rad = str(meta.get("XKY0", {}).get("units", {}).get("YC", ("deg", None))[0]).startswith("rad")
            to_deg = np.degrees if rad else np.asarray
            spread = to_deg(np.asarray(core.get("YCS", np.zeros(_n(core))), dtype=np.float64))
            values = np.column_stack([to_deg(np.asarray(core["YC"], dtype=np.float64)), spread])
            out["XKY0.YC"] = Channel(_time_s(core), values, "deg", "XKY0.YC (EKF-GSF yaw; column 2: its sigma YCS)")
    gps = rows.get("GPS")
    if _n(gps) and gps is not None and "Yaw" in gps and np.any(np.asarray(gps["Yaw"]) != 0):
        out["GPS.Yaw"] = Channel(_time_s(gps), np.asarray(gps["Yaw"], dtype=np.float64), "deg", "GPS.Yaw")
    return out


#: Below this ground speed (m/s) a GPS course says nothing of the heading.
MIN_COURSE_SPEED_MPS = 1.0


def gps_course(course_deg: NDArray[np.float64], speed_mps: NDArray[np.float64], fixed: NDArray[np.bool_]
               ) -> NDArray[np.float64]:
    """The GPS course over ground (degrees), empty (NaN) without a 3-D fix or below :data:`MIN_COURSE_SPEED_MPS`,
    unwrapped over the valid samples (so that the channel's linear interpolation never crosses 360 -> 0 the long
    way; a heading column is read modulo 360). A course is the heading only when the vehicle moves straight ahead:
    leeway, a current or a side slip make them differ (docs/autopilot.md, "Fixed heading")."""
    out = np.full(len(course_deg), np.nan)
    ok = fixed & (speed_mps >= MIN_COURSE_SPEED_MPS) & np.isfinite(course_deg)
    if ok.any():
        out[ok] = np.degrees(np.unwrap(np.radians(course_deg[ok])))
    return out


def _calibration_segments(parm: dict[str, NDArray[Any]] | None, params: dict[str, float], instance: int,
                          t_s: NDArray[np.float64]) -> tuple[list[tuple[dict[str, float], NDArray[np.intp]]], str]:
    """The compass's onboard calibration in force at each sample: ``[(parameters, sample indices)]`` in time order,
    one entry unless a ``PARM`` message changed ``COMPASS_OFSn``/``DIAn``/``ODIn``/``SCALEn`` while the compass was
    logged (a calibration set in flight); and a sentence saying so ("" when it did not change)."""
    every = np.arange(len(t_s))
    if not _n(parm) or parm is None or "TimeUS" not in parm:
        return [(params, every)], ""
    n = _suffix(instance)
    names = {f"COMPASS_{kind}{n}_{a}" for kind in ("OFS", "DIA", "ODI") for a in "XYZ"} | {f"COMPASS_SCALE{n}"}
    which = np.array([str(name) in names for name in parm["Name"].tolist()], dtype=bool)
    if not which.any():
        return [(params, every)], ""
    p_time = np.asarray(parm["TimeUS"], dtype=np.float64)[which] * 1e-6
    p_name = [str(v) for v in np.asarray(parm["Name"])[which].tolist()]
    p_value = np.asarray(parm["Value"], dtype=np.float64)[which]
    order = np.argsort(p_time, kind="stable")
    t_first = float(t_s.min()) if len(t_s) else 0.0
    current = dict(params)
    for k in order[p_time[order] <= t_first]:  # the values in force when the compass's first sample was logged
        current[p_name[k]] = float(p_value[k])
    sets, starts = [dict(current)], [-np.inf]
    for k in order[p_time[order] > t_first]:
        if current.get(p_name[k]) != float(p_value[k]):
            current[p_name[k]] = float(p_value[k])
            if p_time[k] == starts[-1]:
                sets[-1] = dict(current)
            else:
                sets.append(dict(current))
                starts.append(float(p_time[k]))
    segment = np.searchsorted(np.asarray(starts), t_s, side="right") - 1
    used = [k for k in range(len(sets)) if np.any(segment == k)]
    out = [(sets[k], np.flatnonzero(segment == k)) for k in used]
    if len(out) < 2:
        return [(out[0][0] if out else params, every)], ""
    first, last = onboard_matrix(out[0][0], instance), onboard_matrix(out[-1][0], instance)
    what = (f"offsets COMPASS_OFS{n}_X..Z {np.round(first[0], 1).tolist()} -> {np.round(last[0], 1).tolist()} mG"
            if not np.allclose(first[0], last[0]) else f"soft iron / scale (COMPASS_DIA{n}, ODI{n}, SCALE{n})")
    when = ", ".join(f"{starts[k]:.1f} s" for k in used[1:])
    return out, (f"the onboard calibration was changed during the log ({what}; at {when}, a calibration set in "
                 f"flight): each sample's was undone with the parameters in force when it was logged, and the "
                 f"log's calibration compared below is the last one; to fit one period only, cut the log there")


def _dataflash_magnetometers(rows: Columns, params: dict[str, float]) -> list[MagnetometerStream]:
    """Every compass of ``MAG``/``MAG2``/``MAG3`` (or ``MAG`` by instance ``I``), onboard calibration undone."""
    mags: list[MagnetometerStream] = []
    streams: list[tuple[int, str, dict[str, NDArray[Any]]]] = []
    for name in ("MAG", "MAG2", "MAG3"):
        cols = rows.get(name)
        if not _n(cols):
            continue
        assert cols is not None
        if "I" in cols:
            inst_col = np.asarray(cols["I"]).astype(int)
            streams += [(int(i), f"MAG[{int(i)}]", _take(cols, inst_col == i)) for i in np.unique(inst_col)]
        else:
            streams.append((0 if name == "MAG" else int(name[-1]) - 1, name, cols))
    for inst, label, rs in streams:
        logged = _array(rs, ["MagX", "MagY", "MagZ"])
        mot_keys = ["MOX", "MOY", "MOZ"] if "MOX" in rs else ["MOfsX", "MOfsY", "MOfsZ"]
        mot = np.nan_to_num(_array(rs, mot_keys)) if mot_keys[0] in rs else None
        t_s = _time_s(rs)
        segments, changed = _calibration_segments(rows.get("PARM"), params, inst, t_s)
        raw = np.empty_like(logged)
        undone: list[str] = []
        onboard: dict[str, float] = {}
        for seg_params, rows_in in segments:
            raw[rows_in], undone, onboard = undo_ardupilot(
                logged[rows_in], seg_params, inst, None if mot is None else mot[rows_in],
                motor_before_matrix=mot_keys[0] == "MOfsX")
        if changed:
            params.update(segments[-1][0])  # the log's own calibration: the one in force at its end
            undone.insert(0, changed)
        if "OfsX" in rs and params:
            ofs_logged = _array(rs, ["OfsX", "OfsY", "OfsZ"])
            ofs_param = np.empty_like(ofs_logged)
            for seg_params, rows_in in segments:
                ofs_param[rows_in] = onboard_matrix(seg_params, inst)[0]
            gap = np.abs(ofs_logged - ofs_param).max(axis=1)
            if gap.max() > 1.0:
                n = _suffix(inst)
                undone.append(f"warning: the offsets logged with each sample (OfsX..Z) differ from the parameters "
                              f"COMPASS_OFS{n}_X..Z in {int(np.count_nonzero(gap > 1.0))} of {len(gap)} samples "
                              f"(by up to {gap.max():.0f} mG; first at {t_s[int(np.argmax(gap > 1.0))]:.1f} s): the "
                              "parameters were used; if the compass was recalibrated in flight without a PARM "
                              "message, fit only the samples before or after the change")
        if not params:
            undone = ["warning: the log has no PARM messages: the onboard calibration cannot be undone; the "
                      "logged (corrected) reading is used"]
            raw = logged
        dev = params.get(f"COMPASS_DEV_ID{_suffix(inst)}")
        mags.append(MagnetometerStream(label, inst, t_s, raw, logged, "mG", undone,
                                       int(dev) if dev else None, onboard))
    return mags


def _dataflash_channels(log: VehicleLog, rows: Columns, meta: Meta) -> None:
    """The attitude (``ATT``), battery current and voltage, throttle and the servo outputs that move, into ``log``,
    each in its physical unit (:func:`_physical`)."""
    att = rows.get("ATT")
    if _n(att):
        assert att is not None
        log.attitude = Channel(_time_s(att), _array(att, ["Yaw", "Pitch", "Roll"]), "deg", "ATT")
    dcm = rows.get("AHR2")  # the DCM's attitude (AP_AHRS_DCM; its yaw fuses the primary compass)
    if _n(dcm) and dcm is not None and {"Yaw", "Pitch", "Roll"} <= set(dcm):
        log.attitudes["AHR2"] = Channel(_time_s(dcm), _array(dcm, ["Yaw", "Pitch", "Roll"]), "deg", "AHR2 (DCM)")
    baro = rows.get("BARO")
    if _n(baro) and baro is not None and "Alt" in baro:
        first = _take(baro, np.asarray(baro["I"]).astype(int) == 0) if "I" in baro else baro
        if _n(first):
            log.altitude = Channel(_time_s(first), _array(first, ["Alt"])[:, 0], "m",
                                   "BARO.Alt (m above the barometer's ground reading)")
    gps = rows.get("GPS")
    if log.altitude is None and _n(gps) and gps is not None and {"Alt", "Status"} <= set(gps):
        fixed = _take(gps, np.asarray(gps["Status"]) >= 3)
        if _n(fixed):
            log.altitude = Channel(_time_s(fixed), _array(fixed, ["Alt"])[:, 0], "m", "GPS.Alt (m above sea level)")
    bat_name = "BAT" if _n(rows.get("BAT")) else "CURR"
    bat = rows.get(bat_name)
    if _n(bat):
        assert bat is not None
        key = "Inst" if "Inst" in bat else ("Instance" if "Instance" in bat else None)
        first = bat if key is None else _take(bat, np.asarray(bat[key]).astype(int) == 0)
        if _n(first) and "Curr" in first:
            amps, source = _physical(meta, bat_name, "Curr", first["Curr"])
            log.channels["current_A"] = Channel(_time_s(first), amps, "A", source)
            if "Volt" in first:
                volts, source = _physical(meta, bat_name, "Volt", first["Volt"])
                log.channels["voltage_V"] = Channel(_time_s(first), volts, "V", source)
    ctun = rows.get("CTUN")
    throttle_key = next((k for k in ("ThO", "ThrOut") if ctun is not None and k in ctun), None)
    if _n(ctun) and ctun is not None and throttle_key is not None:
        thr, source = _physical(meta, "CTUN", throttle_key, ctun[throttle_key])
        log.channels["throttle"] = Channel(_time_s(ctun), thr, "", source)
    rc = rows.get("RCOU")
    if _n(rc) and rc is not None:
        for k in range(1, 15):
            key = f"C{k}"
            if key in rc:
                v = _array(rc, [key])[:, 0]
                if np.ptp(v) > 0:
                    log.channels[f"rcou_{key}"] = Channel(_time_s(rc), v, "us", f"RCOU.{key}")


def _dataflash_gps(gps: Any) -> dict[str, Any] | None:
    """The middle 3-D fix of ``GPS`` (latitude, longitude, altitude, date), or None."""
    if not (_n(gps) and gps is not None and "Status" in gps):
        return None
    good = np.flatnonzero(np.asarray(gps["Status"]) >= 3)
    if not len(good):
        return None
    k = int(good[len(good) // 2])
    # GPS time: GWk / GMS (ArduPilot 3.4 on), Week / TimeMS (earlier logs, e.g. ArduCopter 3.3); week 0: not known
    week, ms = ("GWk", "GMS") if "GWk" in gps else ("Week", "TimeMS")
    known = week in gps and ms in gps and float(gps[week][k]) > 0
    return {"lat_deg": float(gps["Lat"][k]), "lon_deg": float(gps["Lng"][k]), "alt_m": float(gps["Alt"][k]),
            "date": _gps_date(gps[week][k], gps[ms][k]) if known else None}


def _tlog(path: Path, rows: Columns, params: dict[str, float]) -> VehicleLog:
    mags: list[MagnetometerStream] = []
    for inst, name in enumerate(("RAW_IMU", "SCALED_IMU2", "SCALED_IMU3")):
        cols = rows.get(name)
        if not _n(cols) or cols is None or "xmag" not in cols:
            continue
        logged_all = _array(cols, ["xmag", "ymag", "zmag"])
        keep = np.any(logged_all != 0, axis=1)
        if not keep.any():
            continue
        rs = _take(cols, keep)
        logged = logged_all[keep]
        raw, undone, onboard = undo_ardupilot(logged, params, inst) if params else (logged, [
            "warning: no PARAM_VALUE messages: the onboard calibration cannot be undone"], {})
        dev = params.get(f"COMPASS_DEV_ID{_suffix(inst)}")
        mags.append(MagnetometerStream(name, inst, _time_s(rs, receipt=True), raw, logged, "mG", undone,
                                       int(dev) if dev else None, onboard))
    log = VehicleLog(str(path), "MAVLink telemetry", mags, parameters=params)
    att = rows.get("ATTITUDE")
    if _n(att) and att is not None:
        log.attitude = Channel(_time_s(att, receipt=True), np.degrees(_array(att, ["yaw", "pitch", "roll"])), "deg",
                               "ATTITUDE")
    for name in ("BATTERY_STATUS", "SYS_STATUS"):
        bat = rows.get(name)
        if _n(bat) and bat is not None and "current_battery" in bat:
            amps = _array(bat, ["current_battery"])[:, 0] / 100.0  # cA
            log.channels["current_A"] = Channel(_time_s(bat, receipt=True), amps, "A", f"{name}.current_battery")
            break
    hud = rows.get("VFR_HUD")
    if _n(hud) and hud is not None:
        log.channels["throttle"] = Channel(_time_s(hud, receipt=True), _array(hud, ["throttle"])[:, 0], "%",
                                           "VFR_HUD.throttle")
    dcm = rows.get("AHRS2")  # ArduPilot's DCM (the secondary attitude), radians
    if _n(dcm) and dcm is not None:
        log.attitudes["AHR2"] = Channel(_time_s(dcm, receipt=True), np.degrees(_array(dcm, ["yaw", "pitch", "roll"])),
                                        "deg", "AHRS2 (DCM)")
    pos = rows.get("GLOBAL_POSITION_INT")
    if _n(pos) and pos is not None and "relative_alt" in pos:
        log.altitude = Channel(_time_s(pos, receipt=True), _array(pos, ["relative_alt"])[:, 0] * 1e-3, "m",
                               "GLOBAL_POSITION_INT.relative_alt (m above home)")
    if _n(pos) and pos is not None:
        good = np.flatnonzero(np.asarray(pos["lat"]) != 0)
        if len(good):
            k = int(good[len(good) // 2])
            ts = float(pos["_timestamp"][k]) if "_timestamp" in pos else None
            log.gps = {"lat_deg": float(pos["lat"][k]) * 1e-7, "lon_deg": float(pos["lon"][k]) * 1e-7,
                       "alt_m": float(pos["alt"][k]) * 1e-3,
                       "date": _dt.datetime.fromtimestamp(ts, _dt.UTC).date().isoformat() if ts else None}
    return log


def read_ardupilot(path: Path, kind: str = "dataflash", *, gyro: bool = False,
                   progress: Callable[[float, str], None] | None = None) -> VehicleLog:
    """Read an ArduPilot DataFlash (``kind="dataflash"``) or telemetry (``"tlog"``) log; ``gyro``: also the first
    IMU's gyroscope (``IMU.GyrX..Z``, rad/s; DataFlash only: the messages are many, so read only when asked);
    ``progress``: :func:`trimag.io.logs.read_log`'s."""
    rows, params, meta, notes = _collect(path, kind, gyro, progress)
    log = _dataflash(path, rows, params, meta) if kind == "dataflash" else _tlog(path, rows, params)
    log.messages += notes
    imu = rows.get("IMU")
    if gyro and _n(imu) and imu is not None and "GyrX" in imu:
        if "I" in imu:
            imu = _take(imu, np.asarray(imu["I"]).astype(int) == 0)
        log.gyro = Channel(_time_s(imu), _array(imu, ["GyrX", "GyrY", "GyrZ"]), "rad/s", "IMU.GyrX..Z (instance 0)")
    if not log.magnetometers:
        raise TrimagInputError(
            f"{path}: the log has no magnetometer messages ({'MAG' if kind == 'dataflash' else 'RAW_IMU/SCALED_IMU'}); "
            "enable compass logging (LOG_BITMASK: IMU/compass) and record again"
        )
    return log
