"""A simulated PX4 flight written as a ULog (pyulog's writer), built on pyulog's sample_log_small.ulg (BSD-3-Clause,
tests/data/logs): PX4 v1.13's raw ``sensor_mag`` of one external magnetometer (``CAL_MAG0_ID`` its device id) with
hard and soft iron and a current term, ``vehicle_attitude``, ``battery_status`` and a GPS fix, 10 Hz."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from trimag.fields.attitude import body_field
from trimag.fields.reference import igrf
from trimag.models.firmware import PX4Magnetometer
from trimag.simulate import current_profile

from _helpers import TESTS_DIR

SAMPLE = TESTS_DIR / "data" / "logs" / "pyulog_sample_log_small.ulg"
DEVICE_ID = 396809
LAT, LON, ALT_M, UTC_S = 47.397742, 8.545594, 488.0, 1_688_601_600  # 2023-07-06, Zurich
TRUTH = PX4Magnetometer(orientation=0, offsets=[0.12, -0.08, 0.04], diagonal=[1.05, 0.98, 1.02],
                        offdiagonal=[0.02, -0.01, 0.03], motor=[-0.3, 0.5, 1.1], motor_type="current")


def _resized(data: dict[str, np.ndarray], n: int, **values: Any) -> dict[str, np.ndarray]:
    """``data``'s fields for ``n`` rows: ``values`` where given, else the first row repeated (dtypes kept)."""
    return {k: (np.asarray(values[k]) if k in values else np.repeat(v[:1], n)).astype(v.dtype)
            for k, v in data.items()}


def write_px4_flight(path: Path, n: int = 1200, seed: int = 5) -> Path:
    from pyulog import ULog

    ulog = ULog(str(SAMPLE))
    rng = np.random.default_rng(seed)
    yaw = np.cumsum(rng.normal(0, 3, n)) % 360
    pitch = np.clip(np.cumsum(rng.normal(0, 2, n)), -35, 35)
    roll = np.clip(np.cumsum(rng.normal(0, 2, n)), -35, 35)
    true = Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll]), degrees=True)
    logged = Rotation.from_rotvec(np.radians(rng.normal(0, [0.5, 0.5, 1.0], (n, 3)))) * true
    amps = current_profile(n, seed + 1, max_current=30.0)
    ned_G = np.asarray(igrf(LAT, LON, ALT_M / 1000.0, "2023-07-06").ned_nT) * 1e-5
    raw = TRUTH.uncorrect(body_field(true, ned_G), amps) + rng.normal(0, 0.002, (n, 3))
    t0 = int(ulog.data_list[0].data["timestamp"][0])
    t_us = t0 + np.arange(n, dtype=np.uint64) * 100_000
    q = logged.as_quat()  # x, y, z, w -> PX4's w, x, y, z
    kept = []
    for d in ulog.data_list:
        if d.name == "sensor_mag" and d.multi_id == 0:
            d.data = _resized(d.data, n, timestamp=t_us, timestamp_sample=t_us, device_id=np.full(n, DEVICE_ID),
                              x=raw[:, 0], y=raw[:, 1], z=raw[:, 2], is_external=np.ones(n))
        elif d.name == "vehicle_attitude":
            d.data = _resized(d.data, n, timestamp=t_us, **{f"q[{i}]": q[:, (i + 3) % 4] for i in range(4)})
        elif d.name == "battery_status" and d.multi_id == 0:
            d.data = _resized(d.data, n, timestamp=t_us, current_a=amps, current_filtered_a=amps)
        elif d.name == "vehicle_gps_position":
            m = n // 10
            d.data = _resized(d.data, m, timestamp=t_us[::10][:m], time_utc_usec=np.full(m, UTC_S * 1_000_000),
                              lat=np.full(m, round(LAT * 1e7)), lon=np.full(m, round(LON * 1e7)),
                              alt=np.full(m, round(ALT_M * 1000)))
        elif d.name in ("sensor_mag", "vehicle_magnetometer", "battery_status", "actuator_controls_0"):
            continue
        kept.append(d)
    ulog._data_list = kept
    ulog._msg_info_dict["ver_sw_branch"] = "v1.13.3"
    ulog._msg_info_dict.pop("ver_sw_release", None)
    params = ulog._initial_parameters
    params.update({"CAL_MAG0_ID": DEVICE_ID, "CAL_MAG0_ROT": 0, "CAL_MAG_PRIME": DEVICE_ID, "CAL_MAG1_ID": 0,
                   "CAL_MAG0_XOFF": 0.0, "CAL_MAG0_YOFF": 0.0, "CAL_MAG0_ZOFF": 0.0, "CAL_MAG0_XSCALE": 1.0,
                   "CAL_MAG0_YSCALE": 1.0, "CAL_MAG0_ZSCALE": 1.0})
    ulog.write_ulog(str(path))
    return path
