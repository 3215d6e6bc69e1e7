"""PX4 logs: ULog (``.ulg``, read with pyulog) and the older sdlog2 format (``.px4log``, read with pymavlink).

Calibration PX4 applies, by era (the reader says which it undid):

- sdlog2 and ULog up to v1.11: the driver logs ``m = (r - off) * scale`` per axis (``CAL_MAGn_xOFF``, gauss,
  subtracted; ``CAL_MAGn_xSCALE``), after rotating ``r`` to the board frame; undone as ``r = m / scale + off``.
  On a ULog that also holds ``vehicle_magnetometer`` the reader checks it: the prime sensor's ``sensor_mag`` equals
  ``vehicle_magnetometer`` when ``sensor_mag`` is calibrated.
- Early ULog (2016) without ``sensor_mag``: the prime magnetometer only in ``sensor_combined.magnetometer_ga``
  (gauss), the same calibrated reading, then rotated into the body frame by the sensors module; read as the
  compass ``sensor_combined`` (:func:`sensor_combined_magnetometer`), its offsets and scales undone, its rotation not.
- ULog from v1.12: ``sensor_mag`` is the raw reading; ``sensor_calibration::Magnetometer`` (PX4-Autopilot
  src/lib/sensor_calibration/Magnetometer.cpp) applies ``rotation * (S_sym * ((r + power * comp) - off))``
  afterwards, so nothing is undone.
"""

from __future__ import annotations

import datetime as _dt
import re
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...errors import TrimagInputError
from .base import Channel, MagnetometerStream, VehicleLog, mavlink_messages, require

__all__ = ["MAX_CALIBRATION_SLOTS", "RELATIVE_TIMESTAMP_INVALID", "calibration_slots", "read_px4log", "read_ulog",
           "sensor_combined_magnetometer", "undo_px4_legacy"]

_SLOW_HZ = 5.0
#: ``sensor_combined``'s ``*_timestamp_relative`` when the row holds no reading of that sensor (PX4
#: ``msg/sensor_combined.msg``: ``RELATIVE_TIMESTAMP_INVALID = 2147483647``).
RELATIVE_TIMESTAMP_INVALID = 2147483647


#: The calibration slots PX4 searches (``MAX_SENSOR_COUNT`` of ``src/lib/sensor_calibration/Utilities.cpp``).
MAX_CALIBRATION_SLOTS = 4


def calibration_slots(params: dict[str, float]) -> tuple[dict[int, int], list[str]]:
    """The calibration slot of each device id (``CAL_MAGn_ID``) as PX4 chooses it, and a line per stale duplicate.

    PX4's rule (``calibration::FindCurrentCalibrationIndex``, ``src/lib/sensor_calibration/Utilities.cpp``, used by
    ``Magnetometer::set_device_id``): the **first** slot ``n`` of ``0 .. MAX_SENSOR_COUNT - 1`` whose ``CAL_MAGn_ID``
    equals the device id; a device id of 0 has none. A later slot that holds the same id (a stale entry left by an
    earlier calibration: real v1.14 logs hold the external compass's id in ``CAL_MAG1_ID`` and ``CAL_MAG2_ID``) is
    never read by the firmware, and writing it changes nothing.

    Returns
    -------
    slot_of, notes
        ``{device_id: slot}`` (0-based) and one line per device id found in more than one slot.
    """
    slot_of: dict[int, int] = {}
    duplicates: dict[int, list[int]] = {}
    for k in range(MAX_CALIBRATION_SLOTS):
        dev = int(params.get(f"CAL_MAG{k}_ID", 0) or 0)
        if not dev:
            continue
        if dev in slot_of:
            duplicates.setdefault(dev, []).append(k)
        else:
            slot_of[dev] = k
    notes = [f"device id {dev} is in CAL_MAG{slot_of[dev]}_ID and again in "
             + ", ".join(f"CAL_MAG{k}_ID" for k in later)
             + f": PX4 uses the first slot (CAL_MAG{slot_of[dev]}_*, calibration::FindCurrentCalibrationIndex); "
             + ", ".join(f"CAL_MAG{k}_*" for k in later) + " is a stale duplicate the firmware never reads"
             for dev, later in duplicates.items()]
    return slot_of, notes


def _cal(params: dict[str, float], slot: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    off = np.array([float(params.get(f"CAL_MAG{slot}_{a}OFF", 0.0)) for a in "XYZ"])
    scale = np.array([float(params.get(f"CAL_MAG{slot}_{a}SCALE", 1.0)) for a in "XYZ"])
    return off, np.where(scale == 0, 1.0, scale)


def undo_px4_legacy(logged_G: NDArray[np.float64], params: dict[str, float], slot: int
                    ) -> tuple[NDArray[np.float64], list[str], dict[str, float]]:
    """Raw reading (gauss, board frame) behind a driver-calibrated PX4 reading ``m = (r - off) * scale``."""
    off, scale = _cal(params, slot)
    raw = logged_G / scale + off
    undone = [f"CAL_MAG{slot}_xSCALE = {np.round(scale, 5).tolist()} divided out, "
              f"CAL_MAG{slot}_xOFF = {np.round(off, 5).tolist()} G added back (PX4 subtracts it)"]
    onboard = {f"CAL_MAG{slot}_{a}OFF": float(v) for a, v in zip("XYZ", off, strict=True)}
    onboard.update({f"CAL_MAG{slot}_{a}SCALE": float(v) for a, v in zip("XYZ", scale, strict=True)})
    return raw, undone, onboard


def _slow_warning(stream: MagnetometerStream) -> str | None:
    if 0 < stream.rate_hz < _SLOW_HZ:
        return (f"warning: {stream.name} is logged at only {stream.rate_hz:.2g} Hz (PX4's default logging profile): "
                "too few samples to calibrate from a short flight; add 'Estimator replay (EKF2)' (+2) or 'Sensor "
                "comparison' (+64) to SDLOG_PROFILE to log the magnetometer faster")
    return None


def _ulog_version_minor(ulog: Any) -> int | None:
    branch = str(ulog.msg_info_dict.get("ver_sw_branch", ""))
    m = re.search(r"v1\.(\d+)", branch)
    if m:
        return int(m.group(1))
    release = ulog.msg_info_dict.get("ver_sw_release")
    if isinstance(release, int) and release > 0:
        return (release >> 16) & 0xFF
    return None


def _ekf_mag_device_ids(data: dict[tuple[str, int], dict[str, NDArray[Any]]]) -> tuple[int, ...] | None:
    """The magnetometers any EKF instance fused over the log (``estimator_status.mag_device_id`` of every instance,
    PX4 v1.12+; 0, no magnetometer, left out), or None where no ``estimator_status`` records it."""
    ids: set[int] = set()
    seen = False
    for (name, _), d in data.items():
        if name == "estimator_status" and "mag_device_id" in d:
            seen = True
            ids.update(int(x) for x in np.unique(d["mag_device_id"]) if int(x) != 0)
    return tuple(sorted(ids)) if seen else None


def read_ulog(path: Path) -> VehicleLog:
    """Read a PX4 ULog file."""
    pyulog = require("pyulog")
    try:
        ulog = pyulog.ULog(str(path))
    except Exception as exc:
        raise TrimagInputError(f"{path}: not a readable ULog file ({type(exc).__name__}: {exc})") from None
    params = {k: float(v) for k, v in ulog.initial_parameters.items()}
    data = {(d.name, d.multi_id): d.data for d in ulog.data_list}
    mags = _ulog_magnetometers(data, params, _ulog_version_minor(ulog))
    log = VehicleLog(str(path), "PX4 ULog", mags, parameters=params)
    stale = calibration_slots(params)[1]
    _ulog_channels(log, data)
    log.gps = _ulog_gps(data.get(("vehicle_gps_position", 0)) or data.get(("sensor_gps", 0)))
    log.ekf_mag_device_ids = _ekf_mag_device_ids(data)
    imu = data.get(("sensor_combined", 0))
    if imu is not None and "gyro_rad[0]" in imu:
        log.gyro = Channel(imu["timestamp"].astype(np.float64) * 1e-6,
                           np.column_stack([imu[f"gyro_rad[{i}]"] for i in range(3)]).astype(np.float64), "rad/s",
                           "sensor_combined.gyro_rad")
    log.messages = [w for w in (_slow_warning(m) for m in mags) if w] + stale
    if not mags and imu is not None:
        prime = int(params.get("CAL_MAG_PRIME", 0))
        stream, note = sensor_combined_magnetometer(imu, params, calibration_slots(params)[0].get(prime, 0))
        log.messages += [note] if note else []
        if stream is not None:
            log.magnetometers.append(stream)
    if not log.magnetometers:
        raise TrimagInputError(f"{path}: the log has no magnetometer readings (no sensor_mag, vehicle_magnetometer "
                               "or sensor_combined.magnetometer_ga values); log the magnetometer (PX4's default "
                               "logging profile logs sensor_mag and vehicle_magnetometer)")
    return log


def sensor_combined_magnetometer(imu: Any, params: dict[str, float], slot: int
                                 ) -> tuple[MagnetometerStream | None, str]:
    """The magnetometer of an early ULog's ``sensor_combined`` (``magnetometer_ga[0..2]``, gauss), one row per reading.

    ``sensor_combined`` is published at the IMU's rate and repeats the last magnetometer value between readings: a
    row is kept where the value changed (the first one too), at the magnetometer's own time
    (``timestamp + magnetometer_timestamp_relative`` where the message has it). Rows without a reading (relative time
    stamp :data:`RELATIVE_TIMESTAMP_INVALID`, all-zero or non-finite values) and repeats are dropped and counted.
    The values are the firmware's output: calibrated by ``CAL_MAGn_xOFF``/``xSCALE`` (undone, as
    :func:`undo_px4_legacy`) and rotated into the body frame (PX4 before v1.12 ``sensors.cpp``: ``SENS_BOARD_ROT``
    and its ``SENS_BOARD_x_OFF`` trims for an internal compass, ``CAL_MAGn_ROT`` for an external one; not undone).

    Parameters
    ----------
    imu : mapping of str to ndarray
        The ``sensor_combined`` fields (pyulog's ``data``), each shape (N,).
    params : dict
        The log's parameters.
    slot : int
        The calibration slot of the prime magnetometer (``CAL_MAGn_ID == CAL_MAG_PRIME``).

    Returns
    -------
    stream, message
        The compass ``sensor_combined`` (None without magnetometer values) and what was kept and dropped.
    """
    if "magnetometer_ga[0]" not in imu:
        return None, ""
    logged = np.column_stack([imu[f"magnetometer_ga[{i}]"] for i in range(3)]).astype(np.float64)
    t_us = imu["timestamp"].astype(np.int64)
    rel = imu.get("magnetometer_timestamp_relative")
    valid = np.isfinite(logged).all(axis=1) & np.any(logged != 0, axis=1)
    if rel is not None:
        valid &= rel != RELATIVE_TIMESTAMP_INVALID
        t_us = t_us + np.where(valid, rel, 0).astype(np.int64)
    idx = np.flatnonzero(valid)
    n_rows, n_without = len(logged), len(logged) - len(idx)
    if not len(idx):
        return None, f"sensor_combined.magnetometer_ga: none of its {n_rows} rows holds a reading (all zero or invalid)"
    new = np.r_[True, np.any(np.diff(logged[idx], axis=0) != 0, axis=1)]
    keep = idx[new]
    repeats = idx[~new]
    republished = int(np.count_nonzero(t_us[repeats] != t_us[idx[np.flatnonzero(~new) - 1]])) if rel is not None else 0
    times = "the magnetometer's own (timestamp + magnetometer_timestamp_relative)" if rel is not None else \
        "the rows' (the message has no time stamp of the magnetometer's)"
    span_s = float(imu["timestamp"][-1]) * 1e-6 - float(imu["timestamp"][0]) * 1e-6
    rate = (n_rows - 1) / span_s if span_s > 0 else 0.0
    message = (f"sensor_combined.magnetometer_ga: {n_rows} sensor_combined rows (published at the IMU's rate, "
               f"{rate:.3g} Hz), {len(keep)} kept (a new reading: the value changed); {len(repeats)} repeat the "
               "reading before them and were dropped"
               + (f" ({republished} of them under a new magnetometer time stamp: an unchanged reading published "
                  "again)" if republished else "")
               + (f"; {n_without} without a reading dropped" if n_without else "")
               + f"; times: {times}")
    raw, undone, onboard = undo_px4_legacy(logged[keep], params, slot)
    undone.append(_rotation_note(params, slot, _cal(params, slot)[0]))
    prime = int(params.get("CAL_MAG_PRIME", 0))
    stream = MagnetometerStream("sensor_combined", slot, t_us[keep].astype(np.float64) * 1e-6, raw, logged[keep], "G",
                                undone, prime or None, onboard)
    return stream, message


def _rotation_note(params: dict[str, float], slot: int, offset_G: NDArray[np.float64]) -> str:
    """What the firmware's rotation of ``sensor_combined`` means for the readings (one line).

    PX4 2016 ``sensors.cpp`` (``mag_poll``): ``magnetometer_ga = R (r - off) * scale``, the driver's calibrated report
    rotated by ``_mag_rotation``: ``SENS_BOARD_ROT`` with its trims ``Dcm(Euler(SENS_BOARD_X/Y/Z_OFF))`` for an
    internal compass, ``CAL_MAGn_ROT`` for an external one. Adding the offsets back in the rotated frame (as
    :func:`undo_px4_legacy`) keeps the log's own calibration exact on the logged readings; against the exact undo
    ``R (R^T m / scale + off)`` it is off by ``|(R - I) off|`` (for unit scales), which is said.
    """
    from ...models.firmware import PX4_ROTATIONS, euler_matrix, rotation_matrix

    rot = int(params.get(f"CAL_MAG{slot}_ROT", -1))
    if rot >= 0:
        in_force = f"CAL_MAG{slot}_ROT = {rot}"
        R = rotation_matrix("px4", rot) if rot in PX4_ROTATIONS else None
    else:
        board = int(params.get("SENS_BOARD_ROT", 0))
        trims = [float(params.get(f"SENS_BOARD_{a}_OFF", 0.0)) for a in "XYZ"]
        in_force = (f"SENS_BOARD_ROT = {board} with its trims SENS_BOARD_X/Y/Z_OFF = {np.round(trims, 3).tolist()} "
                    "deg: an internal compass")
        R = euler_matrix(*trims) @ rotation_matrix("px4", board) if board in PX4_ROTATIONS else None
    size = (f" (so the offsets added back are in the rotated frame: {np.linalg.norm((R - np.eye(3)) @ offset_G):.2g} G "
            "from the exact undo)") if R is not None else ""
    return ("sensor_combined.magnetometer_ga is the firmware's calibrated, rotated output (PX4 before v1.12, as an old "
            f"log's sensor_mag): the rotation in force ({in_force}), applied after the offsets and scales, was not "
            f"undone{size}")


_Topics = dict[tuple[str, int], Any]


def _ulog_calibrated_in_log(data: _Topics, vm: Any, prime: int, slot_of: dict[int, int], minor: int | None) -> bool:
    """Whether ``sensor_mag`` holds calibrated values: compared with ``vehicle_magnetometer`` of the prime sensor
    when both are there, else from the log's version (v1.11 and older logged calibrated values)."""
    calibrated_in_log: bool | None = None
    if vm is not None and prime in slot_of:
        for (name, _), d in data.items():
            if name == "sensor_mag" and int(d["device_id"][0]) == prime:
                idx = np.clip(np.searchsorted(vm["timestamp"], d["timestamp"]), 0, len(vm["timestamp"]) - 1)
                vmx = np.column_stack([vm[f"magnetometer_ga[{i}]"][idx] for i in range(3)])
                smx = np.column_stack([d[a] for a in "xyz"])
                calibrated_in_log = bool(np.abs(vmx - smx).max() < 1e-6)
    if calibrated_in_log is None:
        calibrated_in_log = minor is not None and minor <= 11
    return calibrated_in_log


def _ulog_magnetometers(data: _Topics, params: dict[str, float], minor: int | None) -> list[MagnetometerStream]:
    """Every ``sensor_mag`` instance, then the prime ``vehicle_magnetometer``, with the on-board calibration
    undone where the log holds calibrated values."""
    slot_of = calibration_slots(params)[0]
    vm = data.get(("vehicle_magnetometer", 0))
    prime = int(params.get("CAL_MAG_PRIME", 0))
    calibrated_in_log = _ulog_calibrated_in_log(data, vm, prime, slot_of, minor)
    mags: list[MagnetometerStream] = []
    for (name, multi), d in sorted(data.items(), key=lambda kv: kv[0][1]):
        if name != "sensor_mag":
            continue
        dev = int(d["device_id"][0])
        slot = slot_of.get(dev, multi)
        logged = np.column_stack([d[a] for a in "xyz"]).astype(np.float64)
        t = d["timestamp"].astype(np.float64) * 1e-6
        if calibrated_in_log:
            raw, undone, onboard = undo_px4_legacy(logged, params, slot)
        else:
            raw, undone, onboard = logged, ["sensor_mag is the raw reading (PX4 v1.12+): nothing undone"], {}
        mags.append(MagnetometerStream(f"sensor_mag[{multi}]", slot, t, raw, logged, "G", undone, dev, onboard))
    if vm is not None and prime in slot_of:
        logged = np.column_stack([vm[f"magnetometer_ga[{i}]"] for i in range(3)]).astype(np.float64)
        slot = slot_of[prime]
        raw, undone, onboard = undo_px4_legacy(logged, params, slot)
        if not calibrated_in_log:
            undone.append("warning: this log's vehicle_magnetometer may also hold CAL_MAGn_ROT and power "
                          "compensation, which were not undone")
        mags.append(MagnetometerStream("vehicle_magnetometer", slot, vm["timestamp"].astype(np.float64) * 1e-6, raw,
                                       logged, "G", undone, prime, onboard))
    return mags


def _ulog_channels(log: VehicleLog, data: _Topics) -> None:
    """The attitude (yaw, pitch, roll from ``vehicle_attitude.q``), battery current, throttle and magnetometer
    temperatures, into ``log``."""
    att = data.get(("vehicle_attitude", 0))
    if att is not None:
        from scipy.spatial.transform import Rotation

        q = np.column_stack([att[f"q[{i}]"] for i in range(4)])
        ok = np.linalg.norm(q, axis=1) > 0.5
        ypr = Rotation.from_quat(q[ok][:, [1, 2, 3, 0]]).as_euler("ZYX", degrees=True)
        log.attitude = Channel(att["timestamp"][ok] * 1e-6, ypr, "deg", "vehicle_attitude.q")
    for topic, key, sign, what in (("vehicle_global_position", "alt", 1.0, "m above sea level"),
                                   ("vehicle_local_position", "z", -1.0, "m above the origin"),
                                   ("vehicle_air_data", "baro_alt_meter", 1.0, "m, barometric")):
        pos = data.get((topic, 0))
        if pos is not None and key in pos:
            log.altitude = Channel(pos["timestamp"] * 1e-6, sign * pos[key].astype(np.float64), "m",
                                   f"{topic}.{key} ({what})")
            break
    bat = data.get(("battery_status", 0))
    if bat is not None:
        log.channels["current_A"] = Channel(bat["timestamp"] * 1e-6, bat["current_a"].astype(np.float64), "A",
                                            "battery_status.current_a")
    act = data.get(("actuator_controls_0", 0))
    if act is not None and "control[3]" in act:
        log.channels["throttle"] = Channel(act["timestamp"] * 1e-6, act["control[3]"].astype(np.float64), "",
                                           "actuator_controls_0.control[3]")
    for (name, multi), d in data.items():
        if name == "sensor_mag" and "temperature" in d and np.isfinite(d["temperature"]).any():
            log.channels[f"temperature_C_mag{multi}"] = Channel(d["timestamp"] * 1e-6,
                                                                 d["temperature"].astype(np.float64), "degC",
                                                                 f"sensor_mag[{multi}].temperature")


def _ulog_gps(gps: Any) -> dict[str, Any] | None:
    """The middle 3-D fix of ``vehicle_gps_position`` / ``sensor_gps`` (latitude, longitude, altitude, UTC date), or
    None; the fields as PX4 names them before v1.14 (``lat``, ``lon``: 1e-7 deg, ``alt``: mm) and from it
    (``latitude_deg``, ``longitude_deg``, ``altitude_msl_m``)."""
    if gps is None or not len(gps["timestamp"]):
        return None
    fix = gps.get("fix_type", np.full(len(gps["timestamp"]), 3))
    good = np.flatnonzero(fix >= 3)
    if not len(good):
        return None
    k = good[len(good) // 2]
    utc = int(gps["time_utc_usec"][k]) if "time_utc_usec" in gps else 0
    date = _dt.datetime.fromtimestamp(utc / 1e6, _dt.UTC).date().isoformat() if utc else None
    if "latitude_deg" in gps:  # PX4 v1.14+ (sensor_gps): degrees and metres as floats
        return {"lat_deg": float(gps["latitude_deg"][k]), "lon_deg": float(gps["longitude_deg"][k]),
                "alt_m": float(gps["altitude_msl_m"][k]), "date": date}
    if "lat" not in gps:
        return None
    scale = 1e-7 if np.issubdtype(gps["lat"].dtype, np.integer) else 1.0
    return {"lat_deg": float(gps["lat"][k]) * scale, "lon_deg": float(gps["lon"][k]) * scale,
            "alt_m": float(gps["alt"][k]) * (1e-3 if scale == 1e-7 else 1.0), "date": date}


def read_px4log(path: Path) -> VehicleLog:
    """Read a PX4 sdlog2 ``.px4log`` file (``IMU``, ``IMU1``, ``IMU2``: ``MagX..Z`` in gauss, calibrated)."""
    rows: dict[str, list[dict[str, Any]]] = {}
    params: dict[str, float] = {}
    now_s = float("nan")
    for msg in mavlink_messages(path, ["TIME", "IMU", "IMU1", "IMU2", "ATT", "BATT", "GPS", "PARM", "OUT0", "GPOS"]):
        name = msg.get_type()
        if name == "PARM":
            params.setdefault(str(msg.Name), float(msg.Value))
            continue
        if name == "TIME":  # sdlog2 writes the time (us since boot) before each group of messages
            now_s = float(msg.StartTime) * 1e-6
            continue
        d = msg.to_dict()
        d["_t"] = now_s
        rows.setdefault(name, []).append(d)

    def arr(rs: list[dict[str, Any]], keys: list[str]) -> NDArray[np.float64]:
        return np.array([[float(r[k]) for k in keys] for r in rs], dtype=np.float64)

    mags = []
    for slot, name in enumerate(("IMU", "IMU1", "IMU2")):
        rs = rows.get(name, [])
        if not rs or "MagX" not in rs[0]:
            continue
        logged = arr(rs, ["MagX", "MagY", "MagZ"])
        raw, undone, onboard = undo_px4_legacy(logged, params, slot)
        dev = params.get(f"CAL_MAG{slot}_ID")  # sdlog2: the IMU's magnetometer n calibrated by slot n
        mags.append(MagnetometerStream(f"{name}.Mag", slot, arr(rs, ["_t"])[:, 0], raw, logged, "G", undone,
                                       int(dev) if dev else None, onboard))
    if not mags:
        raise TrimagInputError(f"{path}: the log has no IMU magnetometer fields (IMU.MagX..)")
    log = VehicleLog(str(path), "PX4 sdlog2", mags, parameters=params)
    for slot, name in enumerate(("IMU", "IMU1", "IMU2")):
        rs = rows.get(name, [])
        if rs and "tM" in rs[0]:
            log.channels[f"temperature_C_mag{slot}"] = Channel(arr(rs, ["_t"])[:, 0], arr(rs, ["tM"])[:, 0], "degC",
                                                               f"{name}.tM")
    imu = rows.get("IMU", [])
    if imu and "GyroX" in imu[0]:
        log.gyro = Channel(arr(imu, ["_t"])[:, 0], arr(imu, ["GyroX", "GyroY", "GyroZ"]), "rad/s", "IMU.GyroX..Z")
    if rows.get("ATT"):
        att = rows["ATT"]
        log.attitude = Channel(arr(att, ["_t"])[:, 0], np.degrees(arr(att, ["Yaw", "Pitch", "Roll"])), "deg", "ATT")
    if rows.get("GPOS") and "Alt" in rows["GPOS"][0]:
        log.altitude = Channel(arr(rows["GPOS"], ["_t"])[:, 0], arr(rows["GPOS"], ["Alt"])[:, 0], "m",
                               "GPOS.Alt (m, the position estimate)")
    if rows.get("BATT"):
        b = rows["BATT"]
        log.channels["current_A"] = Channel(arr(b, ["_t"])[:, 0], arr(b, ["C"])[:, 0], "A", "BATT.C")
    gps = [r for r in rows.get("GPS", []) if r.get("Fix", 0) >= 3]
    if gps:
        g = gps[len(gps) // 2]
        log.gps = {"lat_deg": float(g["Lat"]), "lon_deg": float(g["Lon"]), "alt_m": float(g["Alt"]),
                   "date": _dt.datetime.fromtimestamp(float(g["GPSTime"]) / 1e6, _dt.UTC).date().isoformat()}
    return log
