"""A log of one firmware fitted for another's parameters is the user's mistake, said in one line (exit 2).

An ArduPilot log fitted with ``--target px4`` used to exit 0 with ``CAL_MAG0_*`` parameters, judged against the
ArduPilot calibration it undid, with only a note ("the log is not px4's: nothing of its calibration is held"): the
vehicle that wrote the log loads ArduPilot's parameters, so the file written could not be loaded by it.
"""

from __future__ import annotations

import sys
from pathlib import Path

TESTS_DIR = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(TESTS_DIR))

from _px4_ulog import write_duplicate_slot_ulog  # noqa: E402
from _two_compass_flight import write_two_compass_flight  # noqa: E402

from _helpers import refusal, run_trimag  # noqa: E402


def test_an_ardupilot_log_fitted_for_px4_is_refused_naming_the_log_s_own_target(tmp_path: Path) -> None:
    log = write_two_compass_flight(tmp_path / "flight.BIN", n=600)
    out = tmp_path / "cal.json"
    r = run_trimag("fit", str(log), "--target", "px4", "-o", str(out))
    assert r.returncode == 2, r.stderr
    verdict = refusal(r.stderr)[0]
    assert "ArduPilot" in verdict and "--target ardupilot" in verdict, verdict
    assert not out.exists()


def test_a_px4_log_fitted_for_ardupilot_is_refused_naming_the_log_s_own_target(tmp_path: Path) -> None:
    log = write_duplicate_slot_ulog(tmp_path / "flight.ulg")
    out = tmp_path / "cal.json"
    r = run_trimag("fit", str(log), "--target", "ardupilot", "-o", str(out))
    assert r.returncode == 2, r.stderr
    verdict = refusal(r.stderr)[0]
    assert "PX4" in verdict and "--target px4" in verdict, verdict
    assert not out.exists()
