"""One calibration through every command, as a user chains them (issue 39, "Done when"): fit -> evaluate -> apply
-> export -> live replay -> batch, each naming and using the same sensor and unit.

One :class:`Case` per kind of source: a lab table with two magnetometers (the second one's columns), the second
compass of a DataFlash log, a PX4 ULog whose compass's device id is in two calibration slots (``CAL_MAG1_ID``
and a stale ``CAL_MAG2_ID``: the compass is number 2, slot 1), and a MATLAB file with a gyroscope (BROAD's layout:
the magnetometer is the variable ``imu_mag``, the gyro-aided fit reads the variable ``imu_gyr``). A Tolles-Lawson
compensation (:func:`test_a_tolles_lawson_compensation_through_every_command`) goes through the same commands: those
that take it name its vector and scalar columns, the others (export, live, batch) refuse it in one line that says
which command does take it.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from trimag import Calibration
from trimag.calibration import SensorRecord
from trimag.cli import main

from _helpers import run_trimag, simulate_ellipsoid


@dataclass
class Case:
    """One calibration's chain: ``make(folder)`` writes the data and returns its path; ``fit`` are the arguments
    of ``trimag fit`` after the path (the same select the sensor for ``live --replay`` and ``batch``: ``select``);
    ``said``: what ``evaluate`` and ``apply`` say of the sensor; ``raw(path, record)``: the readings of that
    sensor (N, 3); ``export``: the target and the names its file must (and must not) hold."""

    name: str
    make: Callable[[Path], Path]
    fit: list[str]
    select: list[str]
    unit: str
    said: str
    raw: Callable[[Path, SensorRecord], np.ndarray]
    export: tuple[str, list[str], list[str]]
    record: dict[str, object] = field(default_factory=dict)


def _lab_table(folder: Path) -> Path:
    """Two magnetometers on one bench (nT): ``a_*`` and ``b_*``, each with its own soft and hard iron."""
    a = simulate_ellipsoid(n=600, noise=5.0, seed=1)
    b = simulate_ellipsoid(n=600, noise=5.0, seed=2) @ np.diag([1.1, 0.9, 1.0]) + [300.0, -200.0, 100.0]
    path = folder / "lab.csv"
    pd.DataFrame({"t": np.arange(600) * 0.01, "a_x": a[:, 0], "a_y": a[:, 1], "a_z": a[:, 2],
                  "b_x": b[:, 0], "b_y": b[:, 1], "b_z": b[:, 2]}).to_csv(path, index=False)
    return path


def _table_raw(path: Path, record: SensorRecord) -> np.ndarray:
    return pd.read_csv(path)[list(record.columns or ())].to_numpy(dtype=float)


def _log_raw(path: Path, record: SensorRecord) -> np.ndarray:
    from trimag.io.logs import read_log

    return read_log(path).choose(record).field


def _two_compass_flight(folder: Path) -> Path:
    """A simulated two-compass DataFlash flight that turns and tilts (the bundled ``ardusub_small.BIN`` sat still:
    ``fit --target`` refuses it, issue 38 item 1)."""
    from _two_compass_flight import write_two_compass_flight

    return write_two_compass_flight(folder / "two.BIN")


def _duplicate_slot_ulog(folder: Path) -> Path:
    from _px4_ulog import write_duplicate_slot_ulog

    return write_duplicate_slot_ulog(folder / "dup.ulg")


def _mat_with_gyroscope(folder: Path) -> Path:
    """A phone-like magnetometer (uT) and its gyroscope (rad/s) turning together at 100 Hz, in BROAD's layout."""
    import scipy.io

    from trimag.simulate import simulate_gyro

    sim = simulate_gyro(3000, 7, motion="cone")
    path = folder / "trial.mat"
    scipy.io.savemat(path, {"imu_gyr": sim.rate, "imu_mag": sim.raw, "sampling_rate": np.array([[100.0]])})
    return path


def _mat_raw(path: Path, record: SensorRecord) -> np.ndarray:
    import scipy.io

    assert record.variable is not None
    return np.asarray(scipy.io.loadmat(path)[record.variable], dtype=float)


def cases() -> list[Case]:
    from _two_compass_flight import DEVICE_ID_2, SITE

    return [
        Case("lab table, second magnetometer", _lab_table, ["--columns", "b_x,b_y,b_z", "--units", "nT",
                                                            "--reference", "48000"],
             ["--columns", "b_x,b_y,b_z", "--units", "nT"], "nT",
             "sensor: columns b_x, b_y, b_z of lab.csv: the calibration's", _table_raw,
             ("json", [], []), {"kind": "table", "columns": ("b_x", "b_y", "b_z")}),
        Case("DataFlash, compass 2", _two_compass_flight, ["--sensor", "2", "--target", "ardupilot", "--igrf", SITE,
                                                                 "--motor", "none"],
             ["--sensor", "2"], "mG",
             f"sensor: compass 2 of two.BIN (MAG[1], device id {DEVICE_ID_2}), mG: the calibration's", _log_raw,
             ("ardupilot", ["COMPASS_OFS2_X"], ["COMPASS_OFS_X"]),
             {"kind": "log", "compass": 2, "slot": 1, "device_id": DEVICE_ID_2}),
        Case("PX4 ULog, a device id in two slots", _duplicate_slot_ulog, ["--sensor", "2", "--reference", "0.5"],
             ["--sensor", "2"], "G",
             "sensor: compass 2 of dup.ulg (sensor_mag[1], device id 592905), G: the calibration's", _log_raw,
             ("px4", ["CAL_MAG1_XOFF"], ["CAL_MAG2_", "CAL_MAG0_"]),
             {"kind": "log", "compass": 2, "slot": 1, "device_id": 592905, "stale_slots": (2,)}),
        Case("MATLAB file with a gyroscope", _mat_with_gyroscope, ["--units", "uT", "--gyro-columns", "imu_gyr"],
             ["--var", "imu_mag", "--units", "uT"], "uT",
             "sensor: columns col0, col1, col2 (variable imu_mag) of trial.mat: the calibration's", _mat_raw,
             ("json", ['"unit": "uT"'], []),
             {"kind": "table", "variable": "imu_mag", "columns": ("col0", "col1", "col2"), "format": "mat"}),
    ]


def _same_sensor(record: SensorRecord | None, fitted: SensorRecord) -> None:
    assert record is not None
    for name in ("kind", "unit", "compass", "name", "device_id", "slot", "columns", "variable", "source"):
        assert getattr(record, name) == getattr(fitted, name), name


@pytest.mark.parametrize("case", cases(), ids=lambda c: c.name)
def test_every_command_names_and_uses_the_calibrations_sensor(case: Case, tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    if case.name.startswith("PX4"):
        pytest.importorskip("pyulog")
    if case.name.startswith(("DataFlash", "PX4")):
        pytest.importorskip("pymavlink")
    data = case.make(tmp_path)
    cal_path = tmp_path / "cal.json"
    # fit: the record
    r = run_trimag("fit", data, *case.fit, "-o", cal_path, timeout=600)
    assert r.returncode == 0, r.stderr
    cal = Calibration.from_file(cal_path)
    if "--gyro-columns" in case.fit:
        assert cal.method == "gyro"
    fitted = cal.sensor
    assert fitted is not None and cal.units == case.unit and fitted.unit == case.unit
    for name, value in case.record.items():
        assert getattr(fitted, name) == value, name
    # evaluate: the same sensor, said, in the same unit
    e = run_trimag("evaluate", cal_path, data, timeout=600)
    assert e.returncode == 0, e.stderr
    assert case.said in e.stdout and f"[{case.unit}]" in e.stdout
    # apply: the same sensor's readings corrected
    out = tmp_path / "applied.csv"
    a = run_trimag("apply", cal_path, data, "-o", out, timeout=600)
    assert a.returncode == 0, a.stderr
    assert case.said in a.stdout and f"({case.unit})" in a.stdout
    applied = pd.read_csv(out)
    raw = case.raw(data, fitted)
    x, y, z = fitted.columns or ("mag_x", "mag_y", "mag_z")
    np.testing.assert_allclose(applied[[x, y, z]].to_numpy(dtype=float), raw, rtol=1e-9)
    np.testing.assert_allclose(applied[[f"{x}_cal", f"{y}_cal", f"{z}_cal"]].to_numpy(dtype=float), cal.apply(raw),
                               rtol=1e-9, atol=1e-9)
    # export: the sensor's own slot
    target, present, absent = case.export
    exported = tmp_path / f"exported.{target}"
    x_ = run_trimag("export", cal_path, "--to", target, "-o", exported, timeout=600)
    assert x_.returncode == 0, x_.stderr
    text = exported.read_text()
    assert all(name in text for name in present) and not any(name in text for name in absent), text
    # live replay: the same sensor recorded in what it saves
    live_out = tmp_path / "live.json"
    code = main(["live", "--replay", str(data), *case.select, "--rate", "1e6", "--exit-at-end", "--no-browser",
                 "--port", "0", "-o", str(live_out)])
    said, _ = capsys.readouterr()
    assert f"sensor: {fitted.describe()}" in said
    if live_out.exists():  # (a log that does not identify the live fit's model saves the samples only)
        assert code == 0
        _same_sensor(Calibration.from_file(live_out).sensor, fitted)
    # batch: the same sensor, in its calibration and its summary row
    folder = tmp_path / "batch"
    b = run_trimag("batch", data, *case.fit, "--out", folder, timeout=600)
    assert b.returncode == 0, b.stderr
    batch_cal = Calibration.from_file(folder / f"{Path(data).stem}.json")
    _same_sensor(batch_cal.sensor, fitted)
    assert batch_cal.method == cal.method
    summary = pd.read_csv(folder / "summary.csv")
    assert summary["sensor"].tolist() == [fitted.describe()]
    assert json.loads(cal_path.read_text())["sensor"]["unit"] == case.unit


def _box(folder: Path) -> Path:
    """A simulated calibration box (60 s legs) of an aircraft's vector and scalar magnetometers, in nT."""
    from trimag.simulate import simulate_aircraft

    sim = simulate_aircraft(60.0, seed=0, terms="p,i5,e8")
    path = folder / "box.csv"
    np.savetxt(path, np.column_stack([sim.time_s, sim.vector_nT, sim.scalar_nT]), delimiter=",",
               header="time,fx,fy,fz,mag", comments="", fmt="%.6f")
    return path


def _one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def test_a_tolles_lawson_compensation_through_every_command(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    """fit -> evaluate -> apply name the vector and scalar columns, the source and the unit; export, live and batch
    (which do not take a compensation) refuse it in one line that points to the commands that do."""
    from trimag.aircraft.compensation import ScalarCompensation

    data = _box(tmp_path)
    fit = ["--model", "tolles-lawson", "--columns", "fx,fy,fz", "--scalar-column", "mag", "--time-column", "time",
           "--option", "terms=p,i5,e8"]
    comp_path = tmp_path / "tl.json"
    assert main(["fit", str(data), *fit, "-q", "-o", str(comp_path)]) == 0
    comp = ScalarCompensation.from_file(comp_path)
    assert comp.sensors["vector_columns"] == ["fx", "fy", "fz"] and comp.sensors["scalar_column"] == "mag"
    assert Path(comp.sensors["source"]).name == "box.csv" and comp.sensors["units"] == "nT"
    capsys.readouterr()
    said = "sensor: vector fx, fy, fz and scalar mag of box.csv, nT: the compensation's"
    assert main(["evaluate", str(comp_path), str(data)]) == 0
    assert said in capsys.readouterr().out
    out = tmp_path / "compensated.csv"
    assert main(["apply", str(comp_path), str(data), "-o", str(out)]) == 0
    assert said in capsys.readouterr().out
    applied, raw = pd.read_csv(out), pd.read_csv(data)
    np.testing.assert_allclose(applied[["fx", "fy", "fz", "mag"]].to_numpy(), raw[["fx", "fy", "fz", "mag"]].to_numpy())
    assert np.isfinite(applied["mag_compensated"]).all()
    assert applied["mag_compensated"].std() < raw["mag"].std()
    # another file's columns are said as the ones read, with the compensation's own beside them
    renamed = tmp_path / "other.csv"
    raw.rename(columns={"fx": "bx", "fy": "by", "fz": "bz"}).to_csv(renamed, index=False)
    assert main(["evaluate", str(comp_path), str(renamed), "--columns", "bx,by,bz"]) == 0
    assert ("sensor: vector bx, by, bz and scalar mag of other.csv, nT (the compensation was fitted to vector fx, fy, "
            "fz and scalar mag of box.csv)") in capsys.readouterr().out
    # the commands that do not take a compensation: one line each, pointing to those that do; nothing written
    exported = tmp_path / "x.param"
    assert main(["export", str(comp_path), "--to", "ardupilot", "-o", str(exported)]) == 2
    line = _one_line(capsys.readouterr().err)
    assert "Tolles-Lawson" in line and "trimag apply" in line and not exported.exists()
    live_out = tmp_path / "live.json"
    assert main(["live", "--replay", str(data), "--model", "tolles-lawson", "--columns", "fx,fy,fz",
                 "--scalar-column", "mag", "--rate", "1e6", "--exit-at-end", "--no-browser", "--port", "0", "-o",
                 str(live_out)]) == 2
    line = _one_line(capsys.readouterr().err)
    assert "Tolles-Lawson" in line and "trimag fit" in line and "--model tolles-lawson" in line, line
    assert not live_out.exists()
    folder = tmp_path / "batch"
    assert main(["batch", str(data), *fit, "--out", str(folder)]) == 2
    line = _one_line(capsys.readouterr().err)
    assert "Tolles-Lawson" in line and "trimag fit" in line and "--model tolles-lawson" in line, line
    assert not folder.exists()
