"""A table's motor channel (issue 39, item 7): `fit F.csv --target ardupilot --motor current` finds the usual names of
a current column (current, curr, current_a, battery_current, ...) and of a throttle (throttle, thr, ...), takes
`--motor current=COLUMN`, and lists the table's columns when none is found (it looked for `current_A` only and said
"this log has none that varies")."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from trimag.cli import main
from trimag.fields.attitude import body_field
from trimag.fields.reference import igrf
from trimag.models.firmware import ArduPilotCompass
from trimag.simulate import current_profile

SITE = "52.8,-4.12,30,2023-07-06"
TRUTH = ArduPilotCompass(orientation=0, offsets=[120.0, -80.0, 40.0], scale=1.05, diagonal=[1.02, 0.97, 1.01],
                         offdiagonal=[0.02, -0.01, 0.03], motor=[2.0, -1.5, 3.0], motor_type="current")


@pytest.fixture(scope="module")
def flight() -> np.ndarray:
    """A tumbling flight (tests/app/test_firmware_fit.py's): raw mG, the logged attitude, the current (A)."""
    rng = np.random.default_rng(1)
    n = 2500
    yaw = np.cumsum(rng.normal(0, 3, n)) % 360
    pitch = np.clip(np.cumsum(rng.normal(0, 2, n)), -35.0, 35.0)
    roll = np.clip(np.cumsum(rng.normal(0, 2, n)), -35.0, 35.0)
    true = Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll]), degrees=True)
    logged = Rotation.from_rotvec(np.radians(rng.normal(0, [0.5, 0.5, 1.0], (n, 3)))) * true
    amps = current_profile(n, 2, max_current=30.0)
    ned_mG = np.asarray(igrf(52.8, -4.12, 30.0, "2023-07-06").ned_nT) / 100.0
    raw = TRUTH.uncorrect(body_field(true, ned_mG), amps) + rng.normal(0, 2.0, (n, 3))
    return np.column_stack([raw, logged.as_euler("ZYX", degrees=True), amps])


def _table(path: Path, flight: np.ndarray, current_name: str) -> Path:
    np.savetxt(path, flight, delimiter=",", header=f"x,y,z,yaw,pitch,roll,{current_name}", comments="", fmt="%.5f")
    return path


def _fit(path: Path, motor: str, capsys: pytest.CaptureFixture[str]) -> tuple[int, dict | None, str]:
    code = main(["fit", str(path), "--units", "mG", "--target", "ardupilot", "--motor", motor, "--igrf", SITE,
                 "--attitude-columns", "yaw,pitch,roll", "--json"])
    captured = capsys.readouterr()
    return code, (json.loads(captured.out) if code == 0 else None), captured.err


@pytest.mark.parametrize("name", ["current", "Curr", "battery_current", "Current (A)"])
def test_the_usual_names_of_a_current_column_are_found(name: str, flight: np.ndarray, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    code, summary, err = _fit(_table(tmp_path / "log.csv", flight, name), "current", capsys)
    assert code == 0, err
    params = summary["params"]  # type: ignore[index]
    assert params["COMPASS_MOTCT"] == 2
    assert np.allclose([params[f"COMPASS_MOT_{a}"] for a in "XYZ"], TRUTH.motor, atol=0.1)
    assert f"column {name}" in err


def test_a_current_column_is_named_with_motor_current_equals(flight: np.ndarray, tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    path = _table(tmp_path / "log.csv", flight, "bus_amps")
    code, summary, err = _fit(path, "current=bus_amps", capsys)
    assert code == 0, err
    assert summary["params"]["COMPASS_MOTCT"] == 2  # type: ignore[index]
    assert summary["regressors"]["names"] == ["bus_amps"]  # type: ignore[index]


def test_no_current_column_lists_the_tables_columns(flight: np.ndarray, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    path = _table(tmp_path / "log.csv", flight, "bus_amps")
    for motor in ("current", "current=amps"):
        code, _, err = _fit(path, motor, capsys)
        assert code == 2
        lines = err.strip().splitlines()
        assert len(lines) == 1 and "bus_amps" in lines[0] and "--motor current" in lines[0], err
    code, _, err = _fit(path, "voltage=bus_amps", capsys)
    assert code == 2 and "--motor" in err and "current" in err and "throttle" in err
