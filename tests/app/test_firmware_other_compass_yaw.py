"""A compass the EKF did not use, fitted to the EKF's yaw: that yaw is another compass's heading (issue 38, held-out
real logs).

On two held-out ArduCopter 3.4.6 logs (docs/autopilot.md, "Held-out real logs") compass 2 (``COMPASS_USE2 0``) of a
vehicle that never turned was fitted to the vector with the EKF's yaw, which is compass 1's heading: the offsets were
"identified" and beat the log's calibration on the unfitted half at the same heading, but they are only as good as
compass 1's heading, and the fit said only that the yaw "did not use this compass". The fit must say whose heading
it takes.
"""

from __future__ import annotations

import sys
from pathlib import Path

from _helpers import TESTS_DIR, run_trimag


def _flight(path: Path, use2: float, yaw_source: float | None = None) -> Path:
    sys.path.insert(0, str(TESTS_DIR / "app"))
    from test_firmware_fit import _write_log

    from trimag.models.firmware import ArduPilotCompass

    params = {**ArduPilotCompass(orientation=0).parameters(1), "COMPASS_EXTERN2": 1.0, "COMPASS_USE2": use2}
    if yaw_source is not None:
        params["EK3_SRC1_YAW"] = yaw_source
    return _write_log(path, n=600, seed=3, tilt=20.0, second=True, parameters=params)


def test_a_compass_the_ekf_did_not_use_is_told_its_yaw_is_another_compass_s_heading(tmp_path: Path) -> None:
    log = _flight(tmp_path / "two.BIN", use2=0.0)
    r = run_trimag("fit", log, "--sensor", "2", "--target", "ardupilot", "-o", tmp_path / "cal.json", timeout=600)
    assert r.returncode == 0, r.stderr
    text = r.stdout + r.stderr
    assert "another compass's heading" in text and "COMPASS_USE2 = 0" in text


def test_a_gps_yaw_is_not_called_another_compass_s_heading(tmp_path: Path) -> None:
    log = _flight(tmp_path / "two.BIN", use2=1.0, yaw_source=2.0)
    r = run_trimag("fit", log, "--sensor", "2", "--target", "ardupilot", "-o", tmp_path / "cal.json", timeout=600)
    assert r.returncode == 0, r.stderr
    text = r.stdout + r.stderr
    assert "did not use this compass" in text and "another compass's heading" not in text
