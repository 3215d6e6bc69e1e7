"""The halves check of ``trimag fit LOG --target ardupilot`` (issue 30 follow-up): the chosen level refitted on each
half of the log and judged on the other half through ArduPilot's formula, against the log's own calibration.

Simulated ArduCopter flights written as binary DataFlash logs (MAG corrected by the calibration in force, truncated
to int16, ATT, BAT, GPS, PARM; 2 mGauss of noise, 0.5/1 deg attitude errors), whose compass's hard iron changes
halfway (a tool or a battery beside the compass while the vehicle is handled): the level choice's five contiguous
folds all lie within the log, so before the check these were written with exit 0 and nothing said.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from trimag.fields.attitude import body_field
from trimag.fields.reference import igrf
from trimag.models.firmware import ArduPilotCompass
from trimag.simulate import current_profile

from _helpers import TESTS_DIR, refusal, refusal_text, run_trimag

pytest.importorskip("pymavlink")

LAT, LON, ALT, WEEK, MS = 52.8, -4.12, 30.0, 2269, 388_800_000  # 2023-07-06
NED_mG = np.asarray(igrf(LAT, LON, ALT, "2023-07-06").ned_nT) / 100.0
TRUTH = ArduPilotCompass(orientation=0, offsets=[120.0, -80.0, 40.0], scale=1.0, diagonal=[1.02, 0.97, 1.01],
                         offdiagonal=[0.02, -0.01, 0.03])


def _write_log(path: Path, onboard: ArduPilotCompass, shift_first_mG: tuple[float, float, float] = (0.0, 0.0, 0.0),
               shift_second_mG: tuple[float, float, float] = (0.0, 0.0, 0.0), n: int = 2000, seed: int = 1) -> Path:
    """A flight whose raw readings carry ``shift_first_mG`` in the first half and ``shift_second_mG`` in the second
    (added hard iron, sensor frame), logged through the calibration ``onboard`` in force."""
    sys.path.insert(0, str(TESTS_DIR / "io"))
    from _dataflash import write_dataflash

    rng = np.random.default_rng(seed)
    yaw = np.cumsum(rng.normal(0, 3, n)) % 360
    pitch = np.clip(np.cumsum(rng.normal(0, 2, n)), -35, 35)
    roll = np.clip(np.cumsum(rng.normal(0, 2, n)), -35, 35)
    true = Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll]), degrees=True)
    logged = Rotation.from_rotvec(np.radians(rng.normal(0, [0.5, 0.5, 1.0], (n, 3)))) * true
    amps = current_profile(n, seed + 1, max_current=30.0)
    raw = TRUTH.uncorrect(body_field(true, NED_mG)) + rng.normal(0, 2.0, (n, 3))
    raw[: n // 2] += shift_first_mG
    raw[n // 2:] += shift_second_mG
    t_us = 10_000_000 + np.arange(n) * 100_000  # 10 Hz
    mag = np.trunc(onboard.correct(raw))
    ofs = np.round(onboard.offsets).astype(int)
    rows = [(int(t), 0, *map(int, m), *map(int, ofs), 0, 0, 0, 1, int(t)) for t, m in zip(t_us, mag, strict=True)]
    ypr = logged.as_euler("ZYX", degrees=True)
    params = {**onboard.parameters(0), "COMPASS_EXTERNAL": 1.0, "COMPASS_MOTCT": 0.0, "COMPASS_USE": 1.0}
    return write_dataflash(path, {
        "MSG": ("QZ", "TimeUS,Message", [(1000, "ArduCopter V4.3.6 (simulated)")]),
        "PARM": ("QNf", "TimeUS,Name,Value", [(1000, k, v) for k, v in params.items()]),
        "MAG": ("QBhhhhhhhhhBI", "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S", rows),
        "ATT": ("QccccCCCCB", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw,AEKF",
                [(int(t), 0.0, r, 0.0, p, 0.0, y % 360.0, 0.0, 0.0, 3)
                 for t, (y, p, r) in zip(t_us, ypr, strict=True)]),
        "BAT": ("QBfffffcfB", "TimeUS,Instance,Volt,VoltR,Curr,CurrTot,EnrgTot,Temp,Res,RemPct",
                [(int(t), 0, 16.0, 16.0, float(a), 0.0, 0.0, 25.0, 0.0, 80) for t, a in zip(t_us, amps, strict=True)]),
        "GPS": ("QBBIHBcLLeffffB", "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,Yaw,U",
                [(int(t), 0, 3, MS, WEEK, 12, 0.8, LAT, LON, ALT, 0.0, 0.0, 0.0, 0.0, 1) for t in t_us[::10]]),
    })


#: the calibration in force is right (the true one, its offsets rounded as ArduPilot logs them)
RIGHT = ArduPilotCompass(orientation=0, offsets=np.round(TRUTH.offsets), scale=1.0, diagonal=TRUTH.diagonal,
                         offdiagonal=TRUTH.offdiagonal)


def test_a_hard_iron_only_in_the_first_half_is_refused_keep_the_logs_calibration(tmp_path: Path):
    """The vehicle was handled with iron beside the compass for the first half; the log's calibration is right for
    the second. Before the check: exit 0, silent (the whole-log fit improves the whole log's RMS, and its folds are all
    within the log). After: exit 3, naming both halves' numbers and what to do."""
    log = _write_log(tmp_path / "handled.bin", RIGHT, shift_first_mG=(60.0, -40.0, 50.0))
    cal = tmp_path / "cal.json"
    r = run_trimag("fit", log, "--target", "ardupilot", "-o", cal)
    assert r.returncode == 3, (r.returncode, r.stdout, r.stderr)
    said = refusal_text(r.stderr)  # the verdict and its detail lines
    assert "keep the log's calibration" in refusal(r.stderr)[0]
    assert "keep the log's calibration" in said and "other half" in said
    assert "changed between the halves" in said
    assert not cal.exists()


def test_a_hard_iron_change_that_both_halves_still_improve_on_is_a_warning_recorded_in_the_calibration(
        tmp_path: Path):
    """The log's calibration is far off (no offsets), and the hard iron moves by (30, -20, 25) mG halfway: each half's
    fit still beats the log's on the other half, so the calibration is written, with a warning naming the parameters
    that moved and both halves' numbers in diagnostics.firmware.halves. Before: silent."""
    log = _write_log(tmp_path / "moved.bin", ArduPilotCompass(orientation=0), shift_second_mG=(30.0, -20.0, 25.0))
    cal = tmp_path / "cal.json"
    r = run_trimag("fit", log, "--target", "ardupilot", "-o", cal, "--json")
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert any("halves" in w and "changed between the halves" in w for w in summary["warnings"]), summary["warnings"]
    halves = json.loads(cal.read_text())["diagnostics"]["firmware"]["halves"]
    assert halves["flagged"] and not halves["worse_than_log"] and halves["moved"]
    assert any(name.startswith("COMPASS_OFS") for name in halves["moved"])
    for half in ("first", "second"):
        assert halves[half]["rms_other_half_fit"] < halves[half]["rms_log"]


def test_a_steady_flight_is_not_flagged(tmp_path: Path):
    """The same flight without a change: the halves agree within their sigmas and both beat the log's calibration;
    nothing is said (no false alarm), and both halves' numbers are recorded."""
    log = _write_log(tmp_path / "steady.bin", ArduPilotCompass(orientation=0))
    cal = tmp_path / "cal.json"
    r = run_trimag("fit", log, "--target", "ardupilot", "-o", cal, "--json")
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert not any("halves" in w for w in summary["warnings"]), summary["warnings"]
    halves = json.loads(cal.read_text())["diagnostics"]["firmware"]["halves"]
    assert not halves["flagged"] and not halves["moved"] and not halves["worse_than_log"]
    for half in ("first", "second"):  # each half predicts the other near the whole log's fit; the log's is far off
        assert halves[half]["rms_other_half_fit"] < 1.3 * halves[half]["rms_whole_fit"]
        assert halves[half]["rms_log"] > 10 * halves[half]["rms_whole_fit"]


def test_a_policy_rejects_what_the_halves_check_only_warns_of(tmp_path: Path):
    """``max_halves_ratio``: each half's fit on the other half over the log's calibration there; the warned log (each
    half still beats the log's, by about 3x) is rejected at 0.2 (exit 4, written and marked so), accepted at 1."""
    log = _write_log(tmp_path / "moved.bin", ArduPilotCompass(orientation=0), shift_second_mG=(30.0, -20.0, 25.0))
    strict, loose = tmp_path / "strict.toml", tmp_path / "loose.toml"
    strict.write_text("[limits]\nmax_halves_ratio = 0.2\n")
    loose.write_text("[limits]\nmax_halves_ratio = 1.0\n")
    r = run_trimag("fit", log, "--target", "ardupilot", "--policy", strict, "-o", tmp_path / "cal.json")
    assert r.returncode == 4 and "max_halves_ratio" in r.stdout + r.stderr, (r.stdout, r.stderr)
    r = run_trimag("fit", log, "--target", "ardupilot", "--policy", loose, "-o", tmp_path / "cal.json")
    assert r.returncode == 0, r.stderr
