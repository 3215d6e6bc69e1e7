"""What a newcomer hit with an autopilot log (issue 30, item 7; docs/autopilot.md): the refusals of a log that cannot
identify a 3-D calibration list the log's compasses and what would help (``--level-turn``, ``--heading``,
``--prior``) and never quote a condition number; ``--sensor`` counts compasses from 1 as the firmware's parameter
names and ``export --instance`` do; ``trimag export LOG.bin`` says that export takes a calibration file.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from trimag.errors import TrimagInputError
from trimag.io import read_samples
from trimag.io.logs import read_log

from _helpers import TESTS_DIR, refusal_text, run_trimag

LOGS = TESTS_DIR / "data" / "logs"
PX4 = LOGS / "px4tools_01_07_59.px4log"  # two magnetometers, IMU.Mag and IMU1.Mag; barely turned
SUB = LOGS / "ardusub_small.BIN"  # two compasses, MAG[0] and MAG[1]; static


def _one_line(stderr: str) -> str:
    """The refusal: one verdict line, then its detail lines (indented; docs/cli.md, "Errors"), as one text."""
    return refusal_text(stderr, max_verdict=None)  # (some quote the log's path; test_refusal_layout measures)


@pytest.mark.parametrize("sensor", [None, "2"])
def test_a_log_that_cannot_be_fitted_names_its_compasses_and_the_modes_that_help(sensor: str | None) -> None:
    """The second magnetometer of the PX4 log gave "condition number 3.03e+15"; neither refusal listed the log's
    magnetometers or named --level-turn, --heading or --prior."""
    r = run_trimag("fit", PX4, *(["--sensor", sensor] if sensor else []))
    assert r.returncode == 3, r.stderr
    line = _one_line(r.stderr)
    assert "condition number" not in line and "e+15" not in line
    assert "1 (IMU.Mag)" in line and "2 (IMU1.Mag)" in line, line
    for flag in ("--level-turn", "--heading", "--prior"):
        assert flag in line, (flag, line)


def test_a_static_log_names_the_fixed_heading_mode() -> None:
    r = run_trimag("fit", SUB)
    assert r.returncode == 3
    line = _one_line(r.stderr)
    assert "1 (MAG[0])" in line and "2 (MAG[1])" in line
    assert "--heading" in line and "--prior" in line


def test_sensor_counts_compasses_from_one_as_the_firmware_names_them() -> None:
    """``--sensor 1`` picked MAG[1] (the second compass, COMPASS_OFS2) while ``export --instance 1`` writes
    COMPASS_OFS: the two now count the same way."""
    log = read_log(SUB)
    assert log.choose("1").name == "MAG[0]" and log.choose("2").name == "MAG[1]"
    assert log.choose("MAG[1]").name == "MAG[1]"  # the log's own names still work
    np.testing.assert_array_equal(read_samples(SUB, sensor="1").field, log.magnetometers[0].field)
    with pytest.raises(TrimagInputError, match="from 1"):
        log.choose("0")
    px4 = read_log(PX4)
    assert px4.choose("1").name == "IMU.Mag" and px4.choose("2").name == "IMU1.Mag"  # CAL_MAG0, CAL_MAG1
    r = run_trimag("fit", SUB, "--sensor", "0")
    assert r.returncode == 2 and "--sensor 1" in _one_line(r.stderr)


def test_the_log_summary_numbers_compasses_and_names_the_flag(tmp_path: Path) -> None:
    """The log's summary said "(* = used; choose another with sensor)" and listed the compasses unnumbered."""
    from trimag import Calibration

    Calibration.from_matrix_offset(np.eye(3), [0.0, 0.0, 0.0], units="G").to_file(tmp_path / "p.json")
    r = run_trimag("fit", PX4, "--sensor", "2", "--prior", tmp_path / "p.json")
    assert r.returncode == 0, r.stderr
    text = r.stdout + r.stderr
    assert "choose another with --sensor" in text, text
    assert "1: IMU.Mag" in text and "2: IMU1.Mag" in text


def test_export_of_a_log_says_it_needs_a_calibration_file(tmp_path: Path) -> None:
    """``trimag export LOG.bin`` said "the file is not UTF-8 text (byte b'\\xa3' ...)"."""
    out = tmp_path / "compass.param"
    for log in (SUB, PX4):
        r = run_trimag("export", log, "--to", "ardupilot", "-o", out)
        assert r.returncode == 2
        line = _one_line(r.stderr)
        assert "calibration" in line and "trimag fit" in line and "UTF-8" not in line, line
        assert not out.exists()
    data = tmp_path / "d.csv"
    data.write_text("x,y,z\n1,2,3\n")
    r = run_trimag("export", data, "--to", "json", "-o", out)
    assert r.returncode == 2 and "trimag fit" in _one_line(r.stderr) and not out.exists()


def test_a_fitted_log_records_the_compass_number(tmp_path: Path) -> None:
    """The calibration of a log says which compass it is (the number --sensor and export --instance take)."""
    from trimag.app import fit_file

    prior = tmp_path / "p.json"
    from trimag import Calibration

    Calibration.from_matrix_offset(np.diag([1.10669, 1.0409, 1.05836]), [0.09462, -0.06406, 0.00244],
                                   units="G").to_file(prior)
    result = fit_file(PX4, prior=str(prior), sensor="1")
    assert result.summary["log"]["compass"] == 1 and result.summary["log"]["name"] == "IMU.Mag"
    r = run_trimag("fit", PX4, "--prior", prior, "--sensor", "1", "--json")
    assert json.loads(r.stdout)["log"]["compass"] == 1


def test_a_flight_that_cannot_identify_a_3d_fit_names_the_firmware_fit() -> None:
    """Review after the firmware merge: the real PX4 flight (attitude and GPS logged, mostly yawed) is refused by the
    default fit naming --level-turn, --heading and --prior, but not ``--target px4``, which fits the parameters the
    firmware loads from exactly such a flight (docs/autopilot.md: offsets + current for its compass 2). The refusal
    names it, with the firmware of the log's format; and the fit it names gives parameters."""
    r = run_trimag("fit", PX4)
    assert r.returncode == 3, r.stderr
    line = _one_line(r.stderr)
    assert "--target px4" in line and "--target ardupilot" not in line, line
    static = _one_line(run_trimag("fit", SUB).stderr)  # no GPS fix: the firmware fit needs --igrf
    assert "--target ardupilot" in static and "--igrf" in static, static


def test_compasses_that_share_a_number_are_listed_with_the_name_that_chooses_them() -> None:
    """A ULog's vehicle_magnetometer is the prime compass's calibrated output: it has that compass's number, so the
    list read '1 (sensor_mag[0]), 2 (sensor_mag[1]), 2 (vehicle_magnetometer)' and `--sensor 2` picks sensor_mag[1]
    while the default had picked vehicle_magnetometer ('compass 2'). A repeated number is said with its name."""
    from trimag.io.logs.base import MagnetometerStream, VehicleLog

    def stream(name: str, instance: int) -> MagnetometerStream:
        t = np.arange(3.0)
        return MagnetometerStream(name, instance, t, np.ones((3, 3)), np.ones((3, 3)), "G")

    log = VehicleLog(path=Path("x.ulg"), format="ulog",
                     magnetometers=[stream("sensor_mag[0]", 0), stream("sensor_mag[1]", 1),
                                    stream("vehicle_magnetometer", 1)])
    listed = log.compass_list()
    assert "1 (sensor_mag[0])" in listed and "2 (sensor_mag[1])" in listed, listed
    assert "2 (vehicle_magnetometer)" not in listed and "vehicle_magnetometer" in listed, listed
    assert "--sensor vehicle_magnetometer" in listed or "sensor=vehicle_magnetometer" in listed, listed
