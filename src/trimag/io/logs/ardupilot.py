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
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...errors import TrimagInputError
from . import Channel, MagnetometerStream, VehicleLog, require

__all__ = ["onboard_matrix", "read_ardupilot", "undo_ardupilot"]

_SCALE_MAX = 1.5  # COMPASS_MAX_SCALE_FACTOR (AP_Compass.h)

_DF_TYPES = ["MAG", "MAG2", "MAG3", "ATT", "BAT", "CURR", "RCOU", "GPS", "PARM", "CTUN"]
_TLOG_TYPES = ["RAW_IMU", "SCALED_IMU2", "SCALED_IMU3", "ATTITUDE", "BATTERY_STATUS", "SYS_STATUS",
               "GLOBAL_POSITION_INT", "GPS_RAW_INT", "PARAM_VALUE", "SERVO_OUTPUT_RAW", "VFR_HUD",
               "SCALED_PRESSURE"]


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


def _collect(path: Path, kind: str) -> tuple[dict[str, list[dict[str, Any]]], dict[str, float]]:
    mavutil = require("pymavlink.mavutil")
    try:
        conn = mavutil.mavlink_connection(str(path), robust_parsing=True) if kind == "tlog" else \
            mavutil.mavlink_connection(str(path))
    except Exception as exc:  # pymavlink raises many kinds on a damaged file
        raise TrimagInputError(f"{path}: not a readable {kind} log ({type(exc).__name__}: {exc})") from None
    types = _TLOG_TYPES if kind == "tlog" else _DF_TYPES
    rows: dict[str, list[dict[str, Any]]] = defaultdict(list)
    params: dict[str, float] = {}
    while True:
        try:
            msg = conn.recv_match(type=types)
        except Exception as exc:
            raise TrimagInputError(f"{path}: the log is damaged ({type(exc).__name__}: {exc})") from None
        if msg is None:
            break
        name = msg.get_type()
        if name == "PARM":
            params.setdefault(str(msg.Name), float(msg.Value))
        elif name == "PARAM_VALUE":
            params[str(msg.param_id).rstrip("\x00")] = float(msg.param_value)
        else:
            d = msg.to_dict()
            d["_timestamp"] = getattr(msg, "_timestamp", None)
            rows[name].append(d)
    return rows, params


def _array(rows: list[dict[str, Any]], keys: list[str]) -> NDArray[np.float64]:
    values = [[float(r.get(k, np.nan)) for k in keys] for r in rows]
    return np.array(values, dtype=np.float64).reshape(len(rows), len(keys))


def _time_s(rows: list[dict[str, Any]], *, receipt: bool = False) -> NDArray[np.float64]:
    """Time of each message, s: the autopilot's clock, or (``receipt``, telemetry logs) the time it was received."""
    if not rows:
        return np.zeros(0)
    if receipt:
        return _array(rows, ["_timestamp"])[:, 0]
    for key, factor in (("TimeUS", 1e-6), ("time_usec", 1e-6), ("TimeMS", 1e-3), ("time_boot_ms", 1e-3)):
        if key in rows[0]:
            return _array(rows, [key])[:, 0] * factor
    return _array(rows, ["_timestamp"])[:, 0]


def _dataflash(path: Path, rows: dict[str, list[dict[str, Any]]], params: dict[str, float]) -> VehicleLog:
    mags: list[MagnetometerStream] = []
    streams: list[tuple[int, str, list[dict[str, Any]]]] = []
    for name in ("MAG", "MAG2", "MAG3"):
        if not rows.get(name):
            continue
        if "I" in rows[name][0]:
            by_inst: dict[int, list[dict[str, Any]]] = defaultdict(list)
            for r in rows[name]:
                by_inst[int(r["I"])].append(r)
            streams += [(i, f"MAG[{i}]", rs) for i, rs in sorted(by_inst.items())]
        else:
            inst = 0 if name == "MAG" else int(name[-1]) - 1
            streams.append((inst, name, rows[name]))
    for inst, label, rs in streams:
        logged = _array(rs, ["MagX", "MagY", "MagZ"])
        mot_keys = ["MOX", "MOY", "MOZ"] if "MOX" in rs[0] else ["MOfsX", "MOfsY", "MOfsZ"]
        mot = np.nan_to_num(_array(rs, mot_keys)) if mot_keys[0] in rs[0] else None
        raw, undone, onboard = undo_ardupilot(logged, params, inst, mot, motor_before_matrix=mot_keys[0] == "MOfsX")
        ofs_logged = _array(rs, ["OfsX", "OfsY", "OfsZ"]) if "OfsX" in rs[0] else None
        if ofs_logged is not None and params:
            ofs_param = onboard_matrix(params, inst)[0]
            if np.abs(ofs_logged - ofs_param).max() > 1.0:
                undone.append("warning: the logged offsets OfsX..Z change during the log or differ from "
                              "COMPASS_OFS*: the parameters at the start of the log were used")
        if not params:
            undone = ["warning: the log has no PARM messages: the onboard calibration cannot be undone; the "
                      "logged (corrected) reading is used"]
            raw = logged
        dev = params.get(f"COMPASS_DEV_ID{_suffix(inst)}")
        mags.append(MagnetometerStream(label, inst, _time_s(rs), raw, logged, "mG", undone,
                                       int(dev) if dev else None, onboard))
    log = VehicleLog(str(path), "ArduPilot DataFlash", mags, parameters=params)
    if rows.get("ATT"):
        log.attitude = Channel(_time_s(rows["ATT"]), _array(rows["ATT"], ["Yaw", "Pitch", "Roll"]), "deg", "ATT")
    bat = rows.get("BAT") or rows.get("CURR") or []
    if bat:
        key = "Inst" if "Inst" in bat[0] else ("Instance" if "Instance" in bat[0] else None)
        first = [r for r in bat if key is None or int(r[key]) == 0]
        log.channels["current_A"] = Channel(_time_s(first), _array(first, ["Curr"])[:, 0], "A", "BAT.Curr")
        if "Volt" in first[0]:
            log.channels["voltage_V"] = Channel(_time_s(first), _array(first, ["Volt"])[:, 0], "V", "BAT.Volt")
    if rows.get("CTUN") and "ThO" in rows["CTUN"][0]:
        log.channels["throttle"] = Channel(_time_s(rows["CTUN"]), _array(rows["CTUN"], ["ThO"])[:, 0], "", "CTUN.ThO")
    if rows.get("RCOU"):
        rc = rows["RCOU"]
        for k in range(1, 15):
            key = f"C{k}"
            if key in rc[0]:
                v = _array(rc, [key])[:, 0]
                if np.ptp(v) > 0:
                    log.channels[f"rcou_{key}"] = Channel(_time_s(rc), v, "us", f"RCOU.{key}")
    gps = [r for r in rows.get("GPS", []) if int(r.get("Status", 0)) >= 3]
    if gps:
        g = gps[len(gps) // 2]
        log.gps = {"lat_deg": float(g["Lat"]), "lon_deg": float(g["Lng"]), "alt_m": float(g["Alt"]),
                   "date": _gps_date(g["GWk"], g["GMS"]) if "GWk" in g else None}
    return log


def _tlog(path: Path, rows: dict[str, list[dict[str, Any]]], params: dict[str, float]) -> VehicleLog:
    mags: list[MagnetometerStream] = []
    for inst, name in enumerate(("RAW_IMU", "SCALED_IMU2", "SCALED_IMU3")):
        rs = [r for r in rows.get(name, []) if any(r.get(k) for k in ("xmag", "ymag", "zmag"))]
        if not rs:
            continue
        logged = _array(rs, ["xmag", "ymag", "zmag"])
        raw, undone, onboard = undo_ardupilot(logged, params, inst) if params else (logged, [
            "warning: no PARAM_VALUE messages: the onboard calibration cannot be undone"], {})
        dev = params.get(f"COMPASS_DEV_ID{_suffix(inst)}")
        mags.append(MagnetometerStream(name, inst, _time_s(rs, receipt=True), raw, logged, "mG", undone,
                                       int(dev) if dev else None, onboard))
    log = VehicleLog(str(path), "MAVLink telemetry", mags, parameters=params)
    if rows.get("ATTITUDE"):
        att = np.degrees(_array(rows["ATTITUDE"], ["yaw", "pitch", "roll"]))
        log.attitude = Channel(_time_s(rows["ATTITUDE"], receipt=True), att, "deg", "ATTITUDE")
    bat = rows.get("BATTERY_STATUS") or []
    if bat:
        amps = _array(bat, ["current_battery"])[:, 0] / 100.0  # cA
        log.channels["current_A"] = Channel(_time_s(bat, receipt=True), amps, "A", "BATTERY_STATUS.current_battery")
    elif rows.get("SYS_STATUS"):
        ss = rows["SYS_STATUS"]
        amps = _array(ss, ["current_battery"])[:, 0] / 100.0
        log.channels["current_A"] = Channel(_time_s(ss, receipt=True), amps, "A", "SYS_STATUS.current_battery")
    if rows.get("VFR_HUD"):
        hud = rows["VFR_HUD"]
        log.channels["throttle"] = Channel(_time_s(hud, receipt=True), _array(hud, ["throttle"])[:, 0], "%",
                                           "VFR_HUD.throttle")
    pos = [r for r in rows.get("GLOBAL_POSITION_INT", []) if r.get("lat")]
    if pos:
        g = pos[len(pos) // 2]
        ts = g.get("_timestamp")
        log.gps = {"lat_deg": g["lat"] * 1e-7, "lon_deg": g["lon"] * 1e-7, "alt_m": g["alt"] * 1e-3,
                   "date": _dt.datetime.fromtimestamp(ts, _dt.UTC).date().isoformat() if ts else None}
    return log


def read_ardupilot(path: Path, kind: str = "dataflash") -> VehicleLog:
    """Read an ArduPilot DataFlash (``kind="dataflash"``) or telemetry (``"tlog"``) log."""
    rows, params = _collect(path, kind)
    log = _dataflash(path, rows, params) if kind == "dataflash" else _tlog(path, rows, params)
    if not log.magnetometers:
        raise TrimagInputError(
            f"{path}: the log has no magnetometer messages ({'MAG' if kind == 'dataflash' else 'RAW_IMU/SCALED_IMU'}); "
            "enable compass logging (LOG_BITMASK: IMU/compass) and record again"
        )
    return log
