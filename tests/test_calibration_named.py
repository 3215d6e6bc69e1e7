"""A calibration file trimag cannot use is named in the message (issue 41, item 17): ``apply``, ``evaluate`` and
``fit --prior`` of a JSON file that is not a trimag calibration (before: "not a trimag calibration file (no
"format" ...)" with no file named, although the command reads a calibration and a log, or two calibrations)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from trimag.calibration import Calibration
from trimag.errors import CalibrationFormatError

from _helpers import run_trimag, write_sphere_csv


def test_from_file_names_the_file(tmp_path: Path) -> None:
    path = tmp_path / "settings.json"
    path.write_text(json.dumps({"model": "ellipsoid"}))
    with pytest.raises(CalibrationFormatError, match=rf"^{path}: not a trimag calibration file"):
        Calibration.from_file(path)


@pytest.mark.parametrize("command", ["apply", "evaluate", "prior"])
def test_each_command_names_the_calibration_it_could_not_use(tmp_path: Path, command: str) -> None:
    log = write_sphere_csv(tmp_path / "log.csv", n=200, seed=10)
    other = tmp_path / "settings.json"
    other.write_text(json.dumps({"model": "ellipsoid", "offset": [0, 0, 0]}))
    args = {"apply": ["apply", other, log, "-o", tmp_path / "out.csv"], "evaluate": ["evaluate", other, log],
            "prior": ["fit", log, "--prior", other, "-q"]}[command]
    r = run_trimag(*args)
    assert r.returncode == 2
    assert f"error: {other}: not a trimag calibration file" in r.stderr, r.stderr
