"""The vehicle logs' gyroscopes (issue 31, item 1): every reader gives its gyroscope (rad/s, own time stamps) for
the gyro-aided fit; a DataFlash log's IMU messages are read only on request (they are many)."""

from __future__ import annotations

import numpy as np
import pytest

from trimag.io.logs import read_log

from _helpers import TESTS_DIR

LOGS = TESTS_DIR / "data" / "logs"


@pytest.mark.parametrize(("name", "source", "gyro"), [
    ("pyulog_sample_log_small.ulg", "sensor_combined.gyro_rad", False),
    ("px4tools_01_07_59.px4log", "IMU.GyroX..Z", False),
    ("ardusub_small.BIN", "IMU.GyrX..Z (instance 0)", True),
])
def test_log_gyroscopes(name, source, gyro):
    pytest.importorskip("pymavlink" if not name.endswith(".ulg") else "pyulog")
    log = read_log(LOGS / name, gyro=gyro)
    assert log.gyro is not None and log.gyro.source == source
    t, w = log.gyro.time_s, log.gyro.values
    assert w.shape == (len(t), 3) and np.isfinite(w).all()
    assert np.sqrt(np.mean(w**2)) < 20.0  # rad/s, not deg/s
    assert any("gyroscope:" in line for line in log.summary_lines())


def test_dataflash_imu_only_on_request():
    pytest.importorskip("pymavlink")
    assert read_log(LOGS / "ardusub_small.BIN").gyro is None
