"""``trimag export --to qgc`` (issue 40): PX4's parameters as QGroundControl's own parameter file, the one its
"Load from file" reads (``ParameterManager::loadFromStream``): comment lines, then ``vehicle-id component-id name
value type`` separated by tabs, ``type`` MAVLink's ``MAV_PARAM_TYPE`` (6 INT32, 9 REAL32), and ``CAL_MAGn_ID`` set
from the device id of the log's magnetometer the calibration was fitted to."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from test_export_firmware import AMPS, RAW_mG, _firmware_fit_calibration

from trimag.io.export import export_calibration
from trimag.io.export_instances import export_instances
from trimag.models.firmware import PX4Magnetometer

from _helpers import run_trimag


def _read_qgc(text: str) -> dict[str, tuple[int, int, str, int]]:
    """A QGroundControl parameter file as QGC reads it: '#' lines skipped, 5 tab-separated fields per line."""
    rows = {}
    for line in text.splitlines():
        if line.startswith("#") or not line.strip():
            continue
        vehicle, component, name, value, kind = line.split("\t")
        rows[name] = (int(vehicle), int(component), value, int(kind))
    return rows


def test_qgc_file_holds_px4s_parameters_with_types_and_the_device_id(tmp_path: Path) -> None:
    cal = _firmware_fit_calibration("px4").with_diagnostics(
        log_compass={"compass": 2, "name": "sensor_mag[1]", "format": "PX4 ULog", "device_id": 396825})
    px4 = export_calibration(cal, "px4", instance=1)
    exp = export_calibration(cal, "qgc", instance=1)
    assert "# Vehicle-Id Component-Id Name Value Type" in exp.text
    rows = _read_qgc(exp.text)
    assert rows["CAL_MAG1_ID"] == (1, 1, "396825", 6)
    assert rows["CAL_MAG1_ROT"][2:] == ("2", 6) and rows["CAL_MAG_COMP_TYP"][2:] == ("2", 6)
    assert rows["CAL_MAG1_XOFF"][3] == 9 and rows["CAL_MAG1_XOFF"][:2] == (1, 1)
    assert set(rows) == set(px4.parameters) | {"CAL_MAG1_ID"}
    values = {name: float(row[2]) for name, row in rows.items()}
    for name, value in px4.parameters.items():  # the same numbers as the param-set script, to float32 precision
        assert np.isclose(values[name], value, rtol=1e-8, atol=0), name
    compass = PX4Magnetometer.from_parameters(values, 1)
    raw_G = RAW_mG / 1000.0
    assert np.allclose(compass.correct(raw_G, AMPS), cal.apply(raw_G, regressors={"current_A": AMPS}), atol=1e-7)


def test_qgc_without_a_device_id_is_written_without_it_and_says_so() -> None:
    exp = export_calibration(_firmware_fit_calibration("px4"), "qgc", instance=0)
    assert "CAL_MAG0_ID" not in _read_qgc(exp.text)
    assert any("CAL_MAG0_ID not written" in note for note in exp.notes)


def test_qgc_for_several_magnetometers_in_one_file() -> None:
    a = _firmware_fit_calibration("px4").with_diagnostics(log_compass={"compass": 1, "device_id": 11})
    b = _firmware_fit_calibration("px4").with_diagnostics(log_compass={"compass": 2, "device_id": 22})
    rows = _read_qgc(export_instances([(b, 2), (a, 1)], "qgc").text)
    assert rows["CAL_MAG0_ID"][2] == "11" and rows["CAL_MAG1_ID"][2] == "22"


def test_cli_export_to_qgc(tmp_path: Path) -> None:
    cal = tmp_path / "cal.json"
    _firmware_fit_calibration("px4").with_diagnostics(
        log_compass={"compass": 1, "name": "sensor_mag[0]", "format": "PX4 ULog", "device_id": 396809}).to_file(cal)
    out = tmp_path / "mag.params"
    r = run_trimag("export", cal, "--to", "qgc", "-o", out)
    assert r.returncode == 0, r.stderr
    assert _read_qgc(out.read_text())["CAL_MAG0_ID"][2] == "396809"
