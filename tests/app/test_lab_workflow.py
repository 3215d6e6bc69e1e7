"""The lab user's two commands (issue 31, item 3): a magnetometer file and a motion-capture file with their own
clocks, no trusted field reference in the room.

``trimag fit mag.csv --model interference12 --attitude-file att.csv ... --option estimate_background=true
--option estimate_lag=true -o cal.json`` then ``trimag evaluate cal.json held_out.csv --attitude-file ...``: no
background flag is needed, the fitted background is stored and is what ``evaluate`` uses, and the lag is searched
against the fitted background (not against an invented one).

Simulated truth: paper C's model ``H_m = K H_b + c`` in an arbitrary motion-capture frame (background
(12 000, -30 000, 38 000) nT in that frame, |H| = 49 889 nT), 20 nT noise per axis, the attitude stream at 120 Hz
with its clock ``LAG`` = 0.12 s ahead of the magnetometer's (50 Hz).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from trimag import Calibration
from trimag.simulate import body_field

from _helpers import run_trimag

H_ROOM = np.array([12_000.0, -30_000.0, 38_000.0])
K = np.array([[1.02, 0.01, -0.02], [0.015, 0.98, 0.01], [-0.01, 0.02, 1.01]])
C = np.array([250.0, -120.0, 80.0])
NOISE = 20.0
LAG = 0.12
INVENTED = "0,0,50000"  # what a user had to type before: a background that is not the room's


def _attitude(t: np.ndarray, phase: float) -> Rotation:
    rv = np.column_stack([1.2 * np.sin(0.7 * t + phase) + 0.5 * np.sin(1.9 * t + 1), 0.8 * np.sin(0.5 * t + 2)
                          + 0.3 * np.sin(2.3 * t + phase), 1.5 * np.sin(0.3 * t) + 0.6 * np.cos(1.1 * t + phase)])
    return Rotation.from_rotvec(rv)


def _write(d: Path, name: str, seed: int, phase: float) -> dict[str, Path]:
    ta = np.arange(0.0, 60.0, 1 / 120.0)
    q = _attitude(ta - LAG, phase).as_quat(scalar_first=True)
    rng = np.random.default_rng(seed)
    tm = np.arange(-0.5, 61.0, 1 / 50.0) + 0.003
    B = body_field(_attitude(tm, phase), H_ROOM) @ K.T + C + rng.normal(0, NOISE, (len(tm), 3))
    pd.DataFrame({"t_att": ta, "qw": q[:, 0], "qx": q[:, 1], "qy": q[:, 2], "qz": q[:, 3]}).to_csv(
        d / f"{name}_att.csv", index=False)
    pd.DataFrame({"time": tm, "x": B[:, 0], "y": B[:, 1], "z": B[:, 2]}).to_csv(d / f"{name}_mag.csv", index=False)
    return {"mag": d / f"{name}_mag.csv", "att": d / f"{name}_att.csv"}


@pytest.fixture(scope="module")
def lab(tmp_path_factory) -> dict[str, object]:
    d = tmp_path_factory.mktemp("lab")
    return {"dir": d, "fit": _write(d, "fit", 0, 0.0), "held": _write(d, "held", 1, 0.9)}


def _sync(files: dict[str, Path]) -> list[str]:
    return ["--attitude-file", str(files["att"]), "--quaternion-columns", "qw,qx,qy,qz", "--time-column", "time",
            "--attitude-time-column", "t_att"]


def _fit(lab: dict, out: Path, *extra: str):
    return run_trimag("fit", lab["fit"]["mag"], "--units", "nT", "--model", "interference12", *_sync(lab["fit"]),
                      "--option", "estimate_background=true", "--option", "max_lag=0.3", *extra, "-o", out, "--json")


@pytest.fixture(scope="module")
def fitted(lab) -> Path:
    """The lab user's first command: no background flag, the lag estimated."""
    out = lab["dir"] / "no_flag.json"
    proc = _fit(lab, out, "--option", "estimate_lag=true")
    assert proc.returncode == 0, proc.stderr
    return out


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def test_fit_estimates_the_background_without_a_background_flag(fitted) -> None:
    """Finding: ``estimate_background=true`` was refused unless a background flag was also given (exit 2)."""
    cal = Calibration.from_file(fitted)
    H_n = np.asarray(cal.diagnostics["background_ned"])
    assert _angle_deg(H_n, H_ROOM) < 0.05
    # the scale gauge without a reference: det(K) = 1, so |H_n| is the mean corrected magnitude of the fit
    assert np.linalg.det(np.linalg.inv(cal.matrix)) == pytest.approx(1.0, abs=1e-9)
    assert np.linalg.norm(H_n) == pytest.approx(np.linalg.norm(H_ROOM) * np.cbrt(np.linalg.det(K)), rel=1e-3)
    assert cal.diagnostics["background_fitted"] is True
    # the lag is recovered within its sigma
    sync = cal.diagnostics["time_sync"]
    assert sync["lag_estimated"] and abs(sync["lag_s"] - LAG) < 3 * sync["lag_std_s"] and sync["lag_std_s"] < 2e-3
    assert "fitted background" in sync["lag_background"]
    assert cal.stats["vector_rms_after"] < 1.05 * NOISE * np.sqrt(3)


def test_a_known_magnitude_sets_the_scale(lab) -> None:
    """``--reference F`` (a magnitude) sets |H_n| of the fitted background."""
    out = lab["dir"] / "with_F.json"
    proc = _fit(lab, out, "--reference", "49889", "--option", "estimate_lag=true")
    assert proc.returncode == 0, proc.stderr
    H_n = np.asarray(Calibration.from_file(out).diagnostics["background_ned"])
    assert np.linalg.norm(H_n) == pytest.approx(49889.0, rel=1e-9)
    assert _angle_deg(H_n, H_ROOM) < 0.05


def test_lag_is_searched_against_the_fitted_background(lab) -> None:
    """Finding: with an invented background (needed before) the lag search ran against it and found no lag."""
    out = lab["dir"] / "invented.json"
    proc = _fit(lab, out, "--background-ned", INVENTED, "--option", "estimate_lag=true")
    assert proc.returncode == 0, proc.stderr
    sync = Calibration.from_file(out).diagnostics["time_sync"]
    assert abs(sync["lag_s"] - LAG) < 3 * sync["lag_std_s"], sync
    assert "fitted background" in sync["lag_background"]
    # searched against the room's background, the vector fit at the lag is at the noise floor (20 sqrt(3) nT)
    assert sync["rms_at_lag"] < 1.05 * NOISE * np.sqrt(3)


def _evaluate(lab: dict, cal: Path, *extra: str):
    return run_trimag("evaluate", cal, lab["held"]["mag"], *_sync(lab["held"]), *extra, "--json")


def test_evaluate_uses_the_stored_background(lab, fitted) -> None:
    """Finding: evaluate measured against whatever background was passed (138 deg "error" with an invented one)."""
    cal = fitted
    proc = _evaluate(lab, cal)
    assert proc.returncode == 0, proc.stderr
    v = json.loads(proc.stdout)
    assert v["angular_error_rms_deg"] < 0.06  # the noise: 20 nT / 49 889 nT = 0.023 deg per axis
    assert "stored in the calibration" in v["background"]["source"]
    H_n = np.asarray(Calibration.from_file(cal).diagnostics["background_ned"])
    # an invented background is refused, naming the stored one
    proc = _evaluate(lab, cal, "--background-ned", INVENTED)
    assert proc.returncode == 2, proc.stderr
    assert "fitted" in proc.stderr and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    # the same background typed back is accepted
    proc = _evaluate(lab, cal, "--background-ned", ",".join(f"{v:.3f}" for v in H_n))
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["angular_error_rms_deg"] < 0.06
