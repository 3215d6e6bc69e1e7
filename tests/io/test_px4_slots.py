"""PX4's calibration slot of a magnetometer is the first ``CAL_MAGn_ID`` that holds its device id (issue 39, item
3; ``calibration::FindCurrentCalibrationIndex`` in PX4's ``src/lib/sensor_calibration/Utilities.cpp``): a stale
duplicate in a later slot is named, never used."""

from __future__ import annotations

from pathlib import Path

import pytest

pytest.importorskip("pyulog")

from _px4_ulog import DEVICE_ID, write_duplicate_slot_ulog
from trimag.io.logs import read_log
from trimag.io.logs.px4 import calibration_slots


def test_the_first_matching_slot_is_the_device_s_and_a_later_one_is_called_stale() -> None:
    params = {"CAL_MAG0_ID": 11.0, "CAL_MAG1_ID": 22.0, "CAL_MAG2_ID": 22.0, "CAL_MAG3_ID": 0.0}
    slot_of, notes = calibration_slots(params)
    assert slot_of == {11: 0, 22: 1}
    assert len(notes) == 1 and "CAL_MAG1_ID and again in CAL_MAG2_ID" in notes[0] and "stale" in notes[0]
    # PX4 searches four slots (MAX_SENSOR_COUNT): an id only in a fifth is not calibrated there
    assert calibration_slots({"CAL_MAG4_ID": 33.0})[0] == {}


def test_a_ulog_with_a_device_id_in_two_slots_numbers_the_compass_by_the_first(tmp_path: Path) -> None:
    log = read_log(write_duplicate_slot_ulog(tmp_path / "dup.ulg"))
    mag = log.choose("2")
    assert (mag.name, mag.device_id, mag.instance) == ("sensor_mag[1]", DEVICE_ID, 1)
    numbers = {m.name: m.number for m in log.magnetometers}
    assert numbers["sensor_mag[1]"] == 2 and numbers["vehicle_magnetometer"] == 2
    # the prime compass's calibrated output is undone with the slot PX4 applied (CAL_MAG1), not the stale CAL_MAG2
    vm = log.choose("vehicle_magnetometer")
    assert any("CAL_MAG1_xOFF" in line for line in vm.undone) and not any("CAL_MAG2" in line for line in vm.undone)
    assert any("stale duplicate" in m and "CAL_MAG2_ID" in m for m in log.summary_lines("2"))
