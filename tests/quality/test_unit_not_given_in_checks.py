"""A fit without ``--units`` has no unit: the drift check's warning and the level turn's lines say "(unit not given)"
after a number, never "0.0034 unknown" as if "unknown" were a unit (issue 41 item 17, the rest of edges4's item 5)."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from trimag.quality.honesty import _drift_warning

from _helpers import run_trimag, simulate_boat


def test_the_drift_warning_of_a_unitless_fit_names_no_unknown_unit() -> None:
    names = ["w11", "w12", "w13", "w22", "w23", "w33", "hard_iron_x", "hard_iron_y", "hard_iron_z"]
    drift = {"z": dict.fromkeys(names, 0.5) | {"hard_iron_x": 3.7}, "change": dict.fromkeys(names, 0.001),
             "moved": ["hard_iron_x"], "offset_change": [0.0034, 0.0025, 0.0022], "rms_z": 2.7, "p_value": 1e-11,
             "inflation": 7.8}
    text = _drift_warning(drift, "unknown")
    assert "unknown" not in text and "(unit not given)" in text, text
    assert "nT" in _drift_warning(drift, "nT")


def test_a_level_turn_without_a_unit_names_no_unknown_unit(tmp_path: Path) -> None:
    boat = simulate_boat(seed=2)
    log = tmp_path / "boat.csv"
    table = np.column_stack([boat["raw"], boat["ypr"]])
    np.savetxt(log, table, delimiter=",", header="x,y,z,yaw,pitch,roll", comments="")
    F = float(np.linalg.norm(boat["field_ned"]))
    r = run_trimag("fit", log, "--level-turn", "--attitude-columns", "yaw,pitch,roll", "--reference", f"{F:.3f}")
    assert r.returncode == 0, r.stderr
    assert not re.search(r"\d unknown", r.stdout) and "unit not given" in r.stdout, r.stdout
