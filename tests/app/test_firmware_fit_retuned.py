"""A DataFlash log whose compass calibration was changed in flight (issue 41, item 17): ``PARM`` sets
``COMPASS_OFS_X..Z`` half way through, and the firmware corrects the samples after it with the new offsets. Each
sample's onboard calibration is undone with the parameters in force when it was logged, the log's calibration
compared is the one in force at its end, and ``fit`` says so in words (before: the first values undid every
sample, the second half came out 100 mG off and the fit left 63 mG instead of 5; the message said the offsets
"change during the log or differ from COMPASS_OFS*")."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from trimag.io.logs import read_log
from trimag.models.firmware import ArduPilotCompass

from _helpers import run_trimag

pytest.importorskip("pymavlink")

#: the calibration set in flight at sample 1250 of 2500 (t = 135 s)
RETUNED = ArduPilotCompass(orientation=0, offsets=[110.0, -70.0, 35.0])


def _logs(tmp_path: Path, n: int = 2500) -> tuple[Path, Path]:
    from test_firmware_fit import _write_log

    return (_write_log(tmp_path / "plain.bin", n=n), _write_log(tmp_path / "retuned.bin", n=n,
                                                                   retuned=(n // 2, RETUNED)))


def test_each_sample_is_undone_with_the_calibration_in_force_when_it_was_logged(tmp_path: Path) -> None:
    plain, retuned = _logs(tmp_path, n=400)
    a, b = read_log(plain).magnetometers[0], read_log(retuned).magnetometers[0]
    assert np.abs(a.field - b.field).max() <= 1.5  # the same raw readings (int16 truncation apart)
    assert b.onboard["COMPASS_OFS_X"] == 110.0  # the log's own calibration: the last one
    said = " ".join(b.undone)
    assert "changed during the log" in said and "[10.0, 5.0, -3.0] -> [110.0, -70.0, 35.0]" in said
    assert "at 30.0 s" in said and "differ" not in said


def test_fit_of_a_log_recalibrated_in_flight_says_so_and_fits_as_if_it_had_not_been(tmp_path: Path) -> None:
    plain, retuned = _logs(tmp_path)
    r = run_trimag("fit", retuned, "--target", "ardupilot", "-o", tmp_path / "cal.json")
    assert r.returncode == 0, r.stderr
    assert "the onboard calibration was changed during the log" in r.stdout
    assert "the log's calibration compared below is the last one" in r.stdout
    got = {k: float(v) for k, v in re.findall(r"(COMPASS_OFS_[XYZ]) = (\S+) \+-", r.stdout)}
    r = run_trimag("fit", plain, "--target", "ardupilot", "-o", tmp_path / "plain.json")
    want = {k: float(v) for k, v in re.findall(r"(COMPASS_OFS_[XYZ]) = (\S+) \+-", r.stdout)}
    assert set(got) == set(want) == {"COMPASS_OFS_X", "COMPASS_OFS_Y", "COMPASS_OFS_Z"}
    for name, value in want.items():
        assert abs(got[name] - value) < 2.0, (name, got, want)  # before: 90 mG apart on Y
