"""An early PX4 ULog whose only magnetometer is ``sensor_combined.magnetometer_ga`` (issue 30: "every real log gives
parameters or a refusal naming what to record"). pyulog's ``test/sample.ulg`` (PX4 2016, AUAV-X2.1) has no
``sensor_mag`` and no ``vehicle_magnetometer``; the reader said "the log has no sensor_mag or vehicle_magnetometer
messages". ``tests/data/logs/pyulog_sample_head.ulg`` is its first 379937 bytes (header, definitions and 5.9 s of
data, cut at a message boundary; README beside it)."""

from __future__ import annotations

import numpy as np
import pytest

from trimag.io.logs import read_log
from trimag.io.logs.px4 import RELATIVE_TIMESTAMP_INVALID, sensor_combined_magnetometer

from _helpers import TESTS_DIR

HEAD = TESTS_DIR / "data" / "logs" / "pyulog_sample_head.ulg"


def _sensor_combined() -> dict[str, np.ndarray]:
    pyulog = pytest.importorskip("pyulog")
    ulog = pyulog.ULog(str(HEAD))
    assert not ulog.file_corruption
    names = {d.name for d in ulog.data_list}
    assert not names & {"sensor_mag", "vehicle_magnetometer"}, names
    return dict(ulog.get_dataset("sensor_combined").data)


def test_the_truncated_copy_is_a_readable_ulog_whose_sensor_combined_magnetometer_changes() -> None:
    assert HEAD.stat().st_size < 400_000
    sc = _sensor_combined()
    m = np.column_stack([sc[f"magnetometer_ga[{i}]"] for i in range(3)])
    changed = np.any(np.diff(m, axis=0) != 0, axis=1)
    assert len(m) > 1000 and changed.sum() > 400  # IMU-rate rows, a new magnetometer value every few of them
    assert 0.3 < np.median(np.linalg.norm(m, axis=1)) < 0.7  # gauss


def test_sensor_combined_is_read_as_a_compass_one_row_per_new_reading() -> None:
    """Before: TrimagInputError "the log has no sensor_mag or vehicle_magnetometer messages"."""
    sc = _sensor_combined()
    log = read_log(HEAD)
    assert [m.name for m in log.magnetometers] == ["sensor_combined"]
    mag = log.choose()
    assert mag.unit == "G" and mag.number == 1 and mag.device_id == int(log.parameters["CAL_MAG0_ID"])
    # the rows kept: the first and each whose value differs from the row before (counted independently here)
    m = np.column_stack([sc[f"magnetometer_ga[{i}]"] for i in range(3)]).astype(np.float64)
    new = np.r_[True, np.any(np.diff(m, axis=0) != 0, axis=1)]
    np.testing.assert_array_equal(mag.logged, m[new])
    # time: the magnetometer's own time stamp, not the IMU row's
    own_us = sc["timestamp"].astype(np.int64) + sc["magnetometer_timestamp_relative"].astype(np.int64)
    np.testing.assert_allclose(mag.time_s, own_us[new] * 1e-6, rtol=0, atol=1e-9)
    assert np.all(np.diff(mag.time_s) > 0) and 80 < mag.rate_hz < 110
    # nothing lost silently: the dropped repeats are counted in the log's messages
    dropped = int((~new).sum())
    text = "\n".join(log.summary_lines())
    assert "1 (sensor_combined)" in log.compass_list()
    assert f"{len(m)} sensor_combined rows" in text and f"{dropped} repeat" in text, text
    # the firmware's calibrated output: CAL_MAG0 offsets and scales undone, the rotation said not to be
    off = np.array([log.parameters[f"CAL_MAG0_{a}OFF"] for a in "XYZ"])
    np.testing.assert_allclose(mag.field - off, mag.logged, atol=1e-7)  # scales are 1 in this log
    assert any("CAL_MAG0_xOFF" in u for u in mag.undone)
    assert any("rotated" in u and "v1.12" in u for u in mag.undone), mag.undone
    # the rotation (SENS_BOARD_ROT 0 with its trims) is not undone, and how far that leaves the offsets is said
    from scipy.spatial.transform import Rotation

    trims = [log.parameters[f"SENS_BOARD_{a}_OFF"] for a in "ZYX"]
    R = Rotation.from_euler("ZYX", trims, degrees=True).as_matrix()
    assert any(f"{np.linalg.norm((R - np.eye(3)) @ off):.2g} G from the exact undo" in u for u in mag.undone)
    assert not any("sensor_mag is the raw reading" in line for line in log.summary_lines())


def _rows(mag: list[list[float]], rel: list[int] | None) -> dict[str, np.ndarray]:
    t = 1_000_000 + 4000 * np.arange(len(mag), dtype=np.uint64)
    rows = {"timestamp": t, **{f"magnetometer_ga[{i}]": np.array([r[i] for r in mag], np.float32) for i in range(3)}}
    if rel is not None:
        rows["magnetometer_timestamp_relative"] = np.array(rel, dtype=np.int32)
    return rows


def test_rows_without_a_reading_are_dropped_and_counted() -> None:
    """``magnetometer_timestamp_relative = INT32_MAX`` (PX4's RELATIVE_TIMESTAMP_INVALID) and an all-zero value
    mean no magnetometer reading yet: dropped and counted with the repeats."""
    a, b, c = [0.1, 0.2, 0.4], [0.1, 0.2, 0.41], [0.11, 0.2, 0.41]
    rows = _rows([[0, 0, 0], a, a, b, b, b, c], [RELATIVE_TIMESTAMP_INVALID, -100, -4100, -50, -4050, -8050, -10])
    stream, message = sensor_combined_magnetometer(rows, {"CAL_MAG0_XOFF": 0.01}, slot=0)
    assert stream is not None
    np.testing.assert_allclose(stream.logged, np.array([a, b, c], np.float32))
    np.testing.assert_allclose(stream.time_s, (1_000_000 + 4000 * np.array([1, 3, 6]) + np.array([-100, -50, -10]))
                               * 1e-6)
    np.testing.assert_allclose(stream.field[:, 0] - 0.01, stream.logged[:, 0], atol=1e-7)
    assert "7 sensor_combined rows" in message and "3 kept" in message and "1 without a reading" in message
    assert "3 repeat" in message, message


def test_without_its_own_time_stamp_the_row_time_is_used_and_repeats_dropped() -> None:
    a, b = [0.1, 0.2, 0.4], [0.1, 0.21, 0.4]
    stream, message = sensor_combined_magnetometer(_rows([a, a, b, b], None), {}, slot=0)
    assert stream is not None
    np.testing.assert_allclose(stream.time_s, (1_000_000 + 4000 * np.array([0, 2])) * 1e-6)
    assert "2 repeat" in message and "2 kept" in message


def test_a_sensor_combined_without_magnetometer_values_gives_no_compass() -> None:
    rows = {"timestamp": np.arange(3, dtype=np.uint64), "gyro_rad[0]": np.zeros(3)}
    assert sensor_combined_magnetometer(rows, {}, slot=0) == (None, "")
    zero = _rows([[0, 0, 0]] * 3, None)
    assert sensor_combined_magnetometer(zero, {}, slot=0)[0] is None
