"""A PX4 ULog built for the tests: pyulog's real sample log (``tests/data/logs/pyulog_sample_log_small.ulg``, BSD-3,
see tests/data/logs/README.md) with its external compass's readings replaced by a simulated tumble and its
parameters edited, written back with pyulog's own writer (``ULog.write_ulog``).

:func:`write_duplicate_slot_ulog` gives the case of issue 39, item 3: as in real PX4 v1.14 logs, the external
compass's device id is in ``CAL_MAG1_ID`` and again, stale, in ``CAL_MAG2_ID`` (with other offsets); PX4 uses the
first matching slot (``calibration::FindCurrentCalibrationIndex``), so the compass is number 2 (slot 1).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from _helpers import TESTS_DIR

SAMPLE = TESTS_DIR / "data" / "logs" / "pyulog_sample_log_small.ulg"
#: the external compass of the sample log (``sensor_mag`` multi 1, ``CAL_MAG1_ID``)
DEVICE_ID = 592905
#: the simulated sensor: raw = A @ true + HARD_IRON_G (gauss), the field's magnitude FIELD_G
HARD_IRON_G = np.array([0.12, -0.07, 0.21])
SOFT_IRON = np.array([[1.06, 0.02, 0.0], [0.02, 0.95, 0.01], [0.0, 0.01, 1.01]])
FIELD_G = 0.5


def write_duplicate_slot_ulog(path: Path, n: int = 600, seed: int = 0, noise_G: float = 0.001) -> Path:
    """Write the ULog of the module docstring to ``path`` (PX4 v1.14: ``sensor_mag`` is the raw reading)."""
    import pyulog

    ulog = pyulog.ULog(str(SAMPLE))
    ulog.msg_info_dict["ver_sw_branch"] = "v1.14.0"
    params = ulog.initial_parameters
    for k in range(4):  # the parameters v1.14 has and this v1.11 log lacks: the off-diagonal scales
        for a in "XYZ":
            params.setdefault(f"CAL_MAG{k}_{a}ODIAG", 0.0)
    params["CAL_MAG2_ID"] = DEVICE_ID  # the stale duplicate
    for a, v in zip("XYZ", (0.4, 0.3, -0.2), strict=True):
        params[f"CAL_MAG2_{a}OFF"] = v
    params["CAL_MAG2_ROT"] = 6
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    true = FIELD_G * d / np.linalg.norm(d, axis=1, keepdims=True)
    raw = true @ SOFT_IRON.T + HARD_IRON_G + rng.normal(scale=noise_G, size=(n, 3))
    att = next(x for x in ulog.data_list if x.name == "vehicle_attitude").data["timestamp"]
    for data in ulog.data_list:
        if data.name == "sensor_mag" and data.multi_id == 1:
            old = data.data
            t = np.linspace(float(att[0]), float(att[-1]), n).astype(old["timestamp"].dtype)
            new = {k: np.resize(v, n) for k, v in old.items()}
            new["timestamp"] = t
            new["timestamp_sample"] = t.astype(old["timestamp_sample"].dtype)
            for k, a in enumerate("xyz"):
                new[a] = raw[:, k].astype(old[a].dtype)
            data.data = new
    ulog.write_ulog(str(path))
    return path
