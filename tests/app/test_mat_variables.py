"""A MATLAB file's variables as sources (issue 39, item 8): a fit of a ``.mat`` names the variable it took
(``imu_mag``) as well as its columns, and the gyroscope stored beside it (``imu_gyr``, as in the BROAD data set) is
reached from the command line: ``--gyro-columns imu_gyr`` names a variable of the same file, in the same rows."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import scipy.io

from trimag import Calibration
from trimag.cli import main
from trimag.simulate import simulate_gyro


@pytest.fixture(scope="module")
def mat_file(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, object]:
    """BROAD's layout: imu_mag (N x 3, uT), imu_gyr (N x 3, rad/s), imu_acc, sampling_rate."""
    sim = simulate_gyro(3000, 7, motion="cone")
    path = tmp_path_factory.mktemp("mat") / "trial.mat"
    scipy.io.savemat(path, {"imu_mag": sim.raw, "imu_gyr": sim.rate, "imu_acc": np.tile([0.0, 0.0, 9.81], (3000, 1)),
                            "sampling_rate": np.array([[100.0]])})
    return path, sim


def test_a_mat_fit_names_the_variable_it_took(mat_file: tuple[Path, object],
                                               capsys: pytest.CaptureFixture[str]) -> None:
    path, _ = mat_file
    assert main(["fit", str(path), "--units", "uT"]) == 0
    out = capsys.readouterr().out
    line = next(ln for ln in out.splitlines() if "col0" in ln)
    assert "imu_mag" in line, out
    assert main(["fit", str(path), "--units", "uT", "--json", "-q"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["variable"] == "imu_mag" and summary["columns"] == ["col0", "col1", "col2"]


def test_the_gyroscope_of_a_mat_file_is_a_variable_of_it(mat_file: tuple[Path, object], tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    path, sim = mat_file
    out = tmp_path / "cal.json"
    assert main(["fit", str(path), "--var", "imu_mag", "--units", "uT", "--gyro-columns", "imu_gyr", "--rate", "100",
                 "-o", str(out)]) == 0, capsys.readouterr().err
    printed = capsys.readouterr().out
    assert "imu_gyr" in printed
    cal = Calibration.from_file(out)
    assert cal.method == "gyro"
    std = cal.uncertainty["param_std"]
    for k, axis in enumerate("xyz"):
        assert abs(cal.offset[k] - sim.offset[k]) < 4 * std[f"hard_iron_{axis}"]  # type: ignore[attr-defined]


def test_the_rate_is_the_files_own_sampling_rate(mat_file: tuple[Path, object],
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """Without --rate, the file's ``sampling_rate`` variable gives the samples' time (and the fit says so)."""
    path, _ = mat_file
    assert main(["fit", str(path), "--units", "uT", "--gyro-columns", "imu_gyr", "--json"]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["method"] == "gyro"
    assert "sampling_rate" in captured.err


def test_a_variable_of_other_rows_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    sim = simulate_gyro(1000, 3, motion="cone")
    path = tmp_path / "short.mat"
    scipy.io.savemat(path, {"imu_mag": sim.raw, "imu_gyr": sim.rate[:900]})
    assert main(["fit", str(path), "--var", "imu_mag", "--units", "uT", "--gyro-columns", "imu_gyr", "--rate",
                 "100"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "imu_gyr" in err and "900" in err and "1000" in err
    assert main(["fit", str(path), "--var", "imu_mag", "--units", "uT", "--gyro-columns", "imu_gyz", "--rate",
                 "100"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "imu_gyr" in err  # the file's variables listed


def test_the_gyroscope_may_be_a_variable_of_another_mat_file(mat_file: tuple[Path, object], tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    """``--gyro-file other.mat --gyro-columns imu_gyr``: the variable of that file, on its own clock (its own
    ``sampling_rate``, or the variable that ``--gyro-time-column`` names); the lag between the two is fitted."""
    path, sim = mat_file
    other = tmp_path / "gyro.mat"
    scipy.io.savemat(other, {"imu_gyr": sim.rate, "sampling_rate": np.array([[100.0]])})  # type: ignore[attr-defined]
    out = tmp_path / "cal.json"
    assert main(["fit", str(path), "--units", "uT", "--gyro-file", str(other), "--gyro-columns", "imu_gyr",
                 "-o", str(out)]) == 0, capsys.readouterr().err
    printed = capsys.readouterr().out
    line = next(ln for ln in printed.splitlines() if ln.startswith("gyroscope:"))
    assert "gyro.mat" in line and "imu_gyr" in line, printed
    cal = Calibration.from_file(out)
    assert cal.method == "gyro"
    std = cal.uncertainty["param_std"]
    for k, axis in enumerate("xyz"):
        assert abs(cal.offset[k] - sim.offset[k]) < 4 * std[f"hard_iron_{axis}"]  # type: ignore[attr-defined]
    # its time stamps as a variable of its own
    stamped = tmp_path / "stamped.mat"
    scipy.io.savemat(stamped, {"imu_gyr": sim.rate, "t_gyr": sim.gyro_time_s})  # type: ignore[attr-defined]
    assert main(["fit", str(path), "--units", "uT", "--gyro-file", str(stamped), "--gyro-columns", "imu_gyr",
                 "--gyro-time-column", "t_gyr", "-o", str(tmp_path / "cal2.json")]) == 0, capsys.readouterr().err
    capsys.readouterr()
    # no clock: one line saying what to give; nothing written
    bare = tmp_path / "bare.mat"
    scipy.io.savemat(bare, {"imu_gyr": sim.rate})  # type: ignore[attr-defined]
    out3 = tmp_path / "cal3.json"
    assert main(["fit", str(path), "--units", "uT", "--gyro-file", str(bare), "--gyro-columns", "imu_gyr",
                 "-o", str(out3)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "--gyro-time-column" in err and "bare.mat" in err, err
    assert not out3.exists()
    # a variable the other file does not have: its variables listed
    assert main(["fit", str(path), "--units", "uT", "--gyro-file", str(other), "--gyro-columns", "imu_gyz"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "imu_gyr" in err and "gyro.mat" in err, err
    assert main(["fit", str(path), "--units", "uT", "--gyro-file", str(tmp_path / "none.mat"), "--gyro-columns",
                 "imu_gyr"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "none.mat: no such file" in err, err


def test_the_export_of_a_gyro_fit_does_not_call_it_magnitude_only(mat_file: tuple[Path, object], tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """`trimag export` of the .mat's gyro-aided calibration said "a magnitude-only calibration does not determine
    [the orientation]": the gyro fit did find it (its nearest board rotation is printed by fit); the note says that
    it is not exported and where it is."""
    path, _ = mat_file
    cal = tmp_path / "cal.json"
    assert main(["fit", str(path), "--units", "uT", "--gyro-columns", "imu_gyr", "-q", "-o", str(cal)]) == 0
    capsys.readouterr()
    assert main(["export", str(cal), "--to", "ardupilot", "-o", str(tmp_path / "gyro.param")]) == 0
    said = capsys.readouterr()
    text = said.out + said.err
    assert "magnitude-only" not in text and "gyro_alignment" in text, text
