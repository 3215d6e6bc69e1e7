"""ROS 1 bags, ROS 2 bags (folders with ``metadata.yaml``) and MCAP files, read with rosbags.

``sensor_msgs/MagneticField`` is in tesla (REP-145): converted to uT. ``sensor_msgs/Imu`` gives the attitude
(its orientation, REP-103: body forward-left-up in an east-north-up world) converted to trimag's convention
(yaw, pitch, roll Z-Y-X, body forward-right-down -> NED: docs/conventions-attitude.md) and the accelerometer.
Time stamps are the messages' ``header.stamp``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ...errors import TrimagInputError
from .base import Channel, MagnetometerStream, VehicleLog, require

__all__ = ["read_ros"]

_NED_FROM_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
_FLU_FROM_FRD = np.diag([1.0, -1.0, -1.0])


def read_ros(path: Path) -> VehicleLog:
    """Read the magnetometer and IMU topics of a ROS bag or MCAP file."""
    require("rosbags")
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore
    from scipy.spatial.transform import Rotation

    mags: dict[str, dict[str, list[Any]]] = {}
    imus: dict[str, dict[str, list[Any]]] = {}
    try:
        with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
            wanted = [c for c in reader.connections
                      if c.msgtype in ("sensor_msgs/msg/MagneticField", "sensor_msgs/msg/Imu")]
            for conn, _, raw in reader.messages(connections=wanted):
                msg: Any = reader.deserialize(raw, conn.msgtype)
                t = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
                if conn.msgtype.endswith("MagneticField"):
                    m = mags.setdefault(conn.topic, {"t": [], "v": []})
                    f = msg.magnetic_field
                    m["t"].append(t)
                    m["v"].append((f.x, f.y, f.z))
                else:
                    d = imus.setdefault(conn.topic, {"t": [], "q": [], "a": [], "w": []})
                    q, a, w = msg.orientation, msg.linear_acceleration, msg.angular_velocity
                    d["t"].append(t)
                    d["q"].append((q.x, q.y, q.z, q.w))
                    d["a"].append((a.x, a.y, a.z))
                    d["w"].append((w.x, w.y, w.z))
    except Exception as exc:  # rosbags raises its own error types for damaged or unknown files
        if isinstance(exc, TrimagInputError):
            raise
        raise TrimagInputError(f"{path}: not a readable ROS bag or MCAP file ({type(exc).__name__}: {exc})") from None
    streams = []
    for k, (topic, m) in enumerate(sorted(mags.items())):
        field_uT = np.asarray(m["v"], dtype=np.float64) * 1e6
        streams.append(MagnetometerStream(topic, k, np.asarray(m["t"]), field_uT, field_uT.copy(), "uT",
                                          ["sensor_msgs/MagneticField is in tesla: converted to uT (nothing else "
                                           "undone; a ROS driver publishes what its sensor measures)"]))
    if not streams:
        raise TrimagInputError(f"{path}: no sensor_msgs/MagneticField topic in this bag")
    log = VehicleLog(str(path), "ROS bag", streams)
    if imus:
        topic, d = sorted(imus.items())[0]
        q = np.asarray(d["q"], dtype=np.float64)
        ok = np.linalg.norm(q, axis=1) > 0.5  # an IMU without orientation publishes zeros
        if ok.any():
            R_enu_flu = Rotation.from_quat(q[ok]).as_matrix()
            R_ned_frd = _NED_FROM_ENU @ R_enu_flu @ _FLU_FROM_FRD
            ypr = Rotation.from_matrix(R_ned_frd).as_euler("ZYX", degrees=True)
            log.attitude = Channel(np.asarray(d["t"])[ok], ypr, "deg", f"{topic} orientation")
        log.gyro = Channel(np.asarray(d["t"]), np.asarray(d["w"], dtype=np.float64), "rad/s",
                           f"{topic} angular_velocity")
        acc = np.asarray(d["a"], dtype=np.float64)
        for k, axis in enumerate("xyz"):
            log.channels[f"accel_{axis}_mps2"] = Channel(np.asarray(d["t"]), acc[:, k], "m/s2",
                                                         f"{topic} linear_acceleration.{axis} (FLU)")
    return log
