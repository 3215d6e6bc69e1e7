"""``trimag fit LOG --target ardupilot`` end to end (issue 30, items 1-4): a simulated ArduCopter flight written as a
binary DataFlash log (MAG corrected by the calibration in force and truncated to int16 as the firmware logs it, ATT,
BAT, GPS, PARM), fitted, exported, and the exported parameters put through ArduPilot's formula on a second flight
with its own current profile.

The compass is mounted yawed 270 deg (COMPASS_ORIENT 6) but the log's parameters say 0, with offsets, a symmetric
soft-iron matrix and a current term to find; 2 mGauss of sensor noise; the logged attitude has 0.5 deg (roll, pitch)
and 1 deg (yaw) errors.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from trimag.fields.attitude import body_field
from trimag.fields.reference import igrf
from trimag.models.firmware import ArduPilotCompass
from trimag.simulate import current_profile

from _helpers import TESTS_DIR, refusal_text, run_trimag

pytest.importorskip("pymavlink")

LAT, LON, ALT, WEEK, MS = 52.8, -4.12, 30.0, 2269, 388_800_000  # 2023-07-06
NED_mG = np.asarray(igrf(LAT, LON, ALT, "2023-07-06").ned_nT) / 100.0
TRUTH = ArduPilotCompass(orientation=6, offsets=[120.0, -80.0, 40.0], scale=1.05, diagonal=[1.02, 0.97, 1.01],
                         offdiagonal=[0.02, -0.01, 0.03], motor=[2.0, -1.5, 3.0], motor_type="current")
ONBOARD = ArduPilotCompass(orientation=0, offsets=[10.0, 5.0, -3.0])  # what the log's parameters say


def _flight(n: int, seed: int, tilt: float = 35.0) -> tuple[Rotation, Rotation, np.ndarray, np.ndarray]:
    """True and logged attitudes, current (A) and raw readings (the sensor's own frame, mG)."""
    rng = np.random.default_rng(seed)
    yaw = np.cumsum(rng.normal(0, 3, n)) % 360
    pitch = np.clip(np.cumsum(rng.normal(0, 2, n)), -tilt, tilt)
    roll = np.clip(np.cumsum(rng.normal(0, 2, n)), -tilt, tilt)
    true = Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll]), degrees=True)
    logged = Rotation.from_rotvec(np.radians(rng.normal(0, [0.5, 0.5, 1.0], (n, 3)))) * true
    amps = current_profile(n, seed + 1, max_current=30.0)
    raw = TRUTH.uncorrect(body_field(true, NED_mG), amps) + rng.normal(0, 2.0, (n, 3))
    return true, logged, amps, raw


#: a second compass (instance 1, COMPASS_OFS2): its own mounting, hard and soft iron and current term
SECOND = ArduPilotCompass(orientation=0, offsets=[-60.0, 90.0, -25.0], scale=0.98, diagonal=[1.01, 1.0, 0.99],
                          offdiagonal=[-0.01, 0.0, 0.01], motor=[-1.0, 0.5, 1.5], motor_type="current")


def _write_log(path: Path, n: int = 2500, seed: int = 1, tilt: float = 35.0, gsf: bool = False,
               second: bool = False, late_battery: int = 0, drop: tuple[str, ...] = (), early_mag: int = 0,
               parameters: dict[str, float] | None = None, dcm: bool = False,
               retuned: tuple[int, ArduPilotCompass] | None = None, gps_yaw: bool = False) -> Path:
    import sys

    sys.path.insert(0, str(TESTS_DIR / "io"))
    from _dataflash import write_dataflash

    true, logged, amps, raw = _flight(n, seed, tilt)
    t_us = 10_000_000 + np.arange(n) * 100_000  # 10 Hz
    mag = np.trunc(ONBOARD.correct(raw))  # the firmware logs its corrected field as int16
    ofs = np.tile(ONBOARD.offsets, (n, 1))
    later: list[tuple[int, str, float]] = []
    if retuned is not None:  # from sample k on the firmware corrects with another calibration (set in flight)
        k, compass = retuned
        mag[k:] = np.trunc(compass.correct(raw[k:]))
        ofs[k:] = compass.offsets
        later = [(int(t_us[k]) - 1000, name, v) for name, v in compass.parameters(0).items()
                 if name.startswith("COMPASS_OFS")]
    rows = [(int(t), 0, *map(int, m), *map(int, o), 0, 0, 0, 1, int(t))
            for t, m, o in zip(t_us, mag, ofs, strict=True)]
    for k in range(n // 2, n // 2 + early_mag):  # MAG rows stamped 50 s early (a clock that jumped back)
        rows[k] = (rows[k][0] - 50_000_000, *rows[k][1:])
    if second:  # compass 2 sees the same flight through its own errors; the log holds no calibration for it
        raw2 = SECOND.uncorrect(body_field(true, NED_mG), amps) + np.random.default_rng(seed + 7).normal(0, 2.0, (n, 3))
        rows += [(int(t) + 500, 1, *map(int, m), 0, 0, 0, 0, 0, 0, 1, int(t)) for t, m in
                 zip(t_us, np.trunc(raw2), strict=True)]
        rows.sort(key=lambda row: row[0])
    ypr = logged.as_euler("ZYX", degrees=True)
    params = {**ONBOARD.parameters(0), "COMPASS_EXTERNAL": 1.0, "COMPASS_DIA_X": 1.0, "COMPASS_DIA_Y": 1.0,
              "COMPASS_DIA_Z": 1.0, "COMPASS_MOTCT": 0.0, "COMPASS_USE": 1.0}
    params = {k: v for k, v in params.items() if not k.startswith(drop)}  # an older firmware's parameter list
    params.update(parameters or {})  # more of the vehicle's parameters (device ids, compass 2's neutral ones)
    extra = {}
    if gsf:  # EKF3's GSF yaw: the true yaw with 2 deg of noise, sigma 1 deg (logged at 10 Hz here)
        yaw = (true.as_euler("ZYX", degrees=True)[:, 0] + np.random.default_rng(seed + 5).normal(0, 2.0, n)) % 360
        extra["XKY0"] = ("QBffffffffffff", "TimeUS,C,YC,YCS,Y0,Y1,Y2,Y3,Y4,W0,W1,W2,W3,W4",
                         [(int(t), 0, float(y), 1.0, *([0.0] * 10)) for t, y in zip(t_us, yaw, strict=True)])
    if dcm:  # ArduPilot's DCM (AHR2: the logged attitude with 1 deg of its own noise) and the barometer (BARO)
        noisy = ypr + np.random.default_rng(seed + 9).normal(0, 1.0, (n, 3))
        extra["AHR2"] = ("QccCfLLffff", "TimeUS,Roll,Pitch,Yaw,Alt,Lat,Lng,Q1,Q2,Q3,Q4",
                         [(int(t), r, p, y % 360.0, 20.0, LAT, LON, 1.0, 0.0, 0.0, 0.0)
                          for t, (y, p, r) in zip(t_us, noisy, strict=True)])
        extra["BARO"] = ("QBff", "TimeUS,I,Alt,Press", [(int(t), 0, 20.0 + 10.0 * np.sin(k / 100.0), 101000.0)
                                                         for k, t in enumerate(t_us)])
    gps_deg, every = np.zeros(n), 10  # the GPS at 1 Hz, no heading
    if gps_yaw:  # a moving-baseline GPS heading (GPS.Yaw) at 10 Hz: the true yaw with 1.5 deg of noise
        gps_deg = (true.as_euler("ZYX", degrees=True)[:, 0] + np.random.default_rng(seed + 11).normal(0, 1.5, n)) % 360
        every = 1
    return write_dataflash(path, {
        **extra,
        "MSG": ("QZ", "TimeUS,Message", [(1000, "ArduCopter V4.3.6 (simulated)")]),
        "PARM": ("QNf", "TimeUS,Name,Value", [(1000, k, v) for k, v in params.items()] + later),
        "MAG": ("QBhhhhhhhhhBI", "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S",
                rows),
        "ATT": ("QccccCCCCB", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw,AEKF",
                [(int(t), 0.0, r, 0.0, p, 0.0, y % 360.0, 0.0, 0.0, 3)
                 for t, (y, p, r) in zip(t_us, ypr, strict=True)]),
        "BAT": ("QBfffffcfB", "TimeUS,Instance,Volt,VoltR,Curr,CurrTot,EnrgTot,Temp,Res,RemPct",
                [(int(t), 0, 16.0, 16.0, float(a), 0.0, 0.0, 25.0, 0.0, 80)
                 for t, a in zip(t_us, amps, strict=True)][late_battery:]),
        "GPS": ("QBBIHBcLLeffffB", "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,Yaw,U",
                [(int(t), 0, 3, MS, WEEK, 12, 0.8, LAT, LON, ALT, 0.0, 0.0, 0.0, float(y), 1)
                 for t, y in zip(t_us[::every], gps_deg[::every], strict=True)]),
    })


def test_a_simulated_flight_log_gives_parameters_at_the_noise_floor_and_the_true_orientation(tmp_path: Path):
    log = _write_log(tmp_path / "flight.bin")
    cal, param = tmp_path / "cal.json", tmp_path / "compass.param"
    r = run_trimag("fit", log, "--target", "ardupilot", "-o", cal)
    assert r.returncode == 0, r.stderr
    assert "levels (heading-free residual" in r.stdout and "<--" in r.stdout  # ATT's yaw used the compass
    assert "fits the field" in r.stdout and "chosen" in r.stdout  # the orientation the log did not have
    assert "its yaw is the EKF's, which fused this compass" in r.stdout  # the circularity is stated
    r = run_trimag("export", cal, "--to", "ardupilot", "-o", param)
    assert r.returncode == 0, r.stderr
    values = dict(line.split(",") for line in param.read_text().splitlines() if not line.startswith("#"))
    params = {k: float(v) for k, v in values.items()}
    assert params["COMPASS_ORIENT"] == 6 and params["COMPASS_MOTCT"] == 2
    exported = ArduPilotCompass.from_parameters({**params, "COMPASS_EXTERNAL": 1.0}, 0)
    _, logged, amps, raw = _flight(2500, seed=30)  # a second flight, its own current profile
    h = body_field(logged, NED_mG)
    floor = np.sqrt(np.mean(np.sum((TRUTH.correct(raw, amps) - h) ** 2, axis=1)))
    got = np.sqrt(np.mean(np.sum((exported.correct(raw, amps) - h) ** 2, axis=1)))
    assert got <= 1.3 * floor, (got, floor)


def test_level_and_motor_flags_and_a_log_without_a_gps_fix(tmp_path: Path):
    log = _write_log(tmp_path / "flight.bin", n=800, seed=2)
    r = run_trimag("fit", log, "--level", "offsets", "--motor", "none", "--json")  # --target from the log
    assert r.returncode == 0, r.stderr
    import json

    summary = json.loads(r.stdout)
    assert summary["firmware"]["level"] == "offsets" and summary["firmware"]["motor_type"] is None
    assert "COMPASS_DIA_X" in summary["firmware"]["held"]
    r = run_trimag("fit", TESTS_DIR / "data" / "calibrations" / "ortho-gain.out.csv", "--level", "offsets")
    assert r.returncode == 2 and "--target" in r.stderr


def test_a_flight_that_mostly_yawed_gives_offsets_and_the_current_term_instead_of_a_planar_refusal(tmp_path: Path):
    log = _write_log(tmp_path / "level.bin", n=1500, seed=3, tilt=4.0, gsf=True)
    r = run_trimag("fit", log)  # the magnitude-only default cannot identify a 3-D calibration from it
    assert r.returncode == 3
    cal = tmp_path / "cal.json"
    r = run_trimag("fit", log, "--target", "ardupilot", "--json", "-o", cal)
    assert r.returncode == 0, r.stderr
    import json

    summary = json.loads(r.stdout)
    fw = summary["firmware"]
    assert fw["motor_type"] == "current" and fw["orientation"] == 6
    assert fw["rms_after"] < 0.2 * fw["rms_before"]  # the matrix held at the log's (identity): offsets absorb the rest
    # and says what it held: keys are parameter names, the reason is the value (issue 39, item 4)
    assert "COMPASS_DIA_X" in fw["held"] or any("not identified" in h["why"] for h in fw["held"].values())
    assert "EKF-GSF" in r.stderr and "independent of the compass" in r.stderr  # the yaw source is named
    assert run_trimag("export", cal, "--to", "ardupilot", "-o", tmp_path / "c.param").returncode == 0


def _param_file(path: Path) -> dict[str, float]:
    return {k: float(v) for k, v in (line.split(",") for line in path.read_text().splitlines()
                                     if line and not line.startswith("#"))}


def test_all_compasses_with_target_write_one_file_with_each_orientation_and_motor_term(tmp_path: Path):
    """``--sensor all --target ardupilot --export-to``: every compass fitted in the firmware's space, one file with
    both compasses' orientation, offsets, matrix and current terms and one COMPASS_MOTCT; each compass's exported
    parameters reach the noise floor on a second flight. Before: exit 2, "this calibration has regressor terms"
    (the compasses' comparison applied the calibrations without their current)."""
    log = _write_log(tmp_path / "two.bin", n=2500, seed=1, second=True)
    param = tmp_path / "all.param"
    r = run_trimag("fit", log, "--sensor", "all", "--target", "ardupilot", "--export-to", "ardupilot",
                   "--export-out", param, "-o", tmp_path / "cal.json")
    assert r.returncode == 0, r.stderr
    p = _param_file(param)
    assert p["COMPASS_ORIENT"] == 6 and p["COMPASS_ORIENT2"] == 0 and p["COMPASS_MOTCT"] == 2
    assert {"COMPASS_MOT_X", "COMPASS_MOT2_Z", "COMPASS_OFS2_X", "COMPASS_DIA2_X"} <= set(p)
    _, logged, amps, raw = _flight(2500, seed=30)
    h = body_field(logged, NED_mG)
    raw2 = SECOND.uncorrect(h, amps) + np.random.default_rng(37).normal(0, 2.0, raw.shape)
    for instance, truth, readings in ((0, TRUTH, raw), (1, SECOND, raw2)):
        exported = ArduPilotCompass.from_parameters({**p, "COMPASS_EXTERNAL": 1.0, "COMPASS_EXTERN2": 1.0}, instance)
        floor = np.sqrt(np.mean(np.sum((truth.correct(readings, amps) - h) ** 2, axis=1)))
        got = np.sqrt(np.mean(np.sum((exported.correct(readings, amps) - h) ** 2, axis=1)))
        assert got <= 1.3 * floor, (instance, got, floor)
    assert (tmp_path / "cal-1.json").exists() and (tmp_path / "cal-2.json").exists()


def test_target_with_a_large_vehicle_mode_is_refused_naming_why(tmp_path: Path):
    log = _write_log(tmp_path / "flight.bin", n=300, seed=4)
    for mode in (["--level-turn"], ["--heading", "30"]):
        r = run_trimag("fit", log, "--target", "ardupilot", *mode, "-o", tmp_path / "cal.json")
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert mode[0] in r.stderr and "--target" in r.stderr and "trimag export" in r.stderr
        assert not (tmp_path / "cal.json").exists()


def test_an_ardupilot_fit_exported_to_px4_keeps_the_orientation_it_found(tmp_path: Path):
    """A fit for one firmware exported to the other writes the orientation the fit found (the enums share 0..40),
    and PX4's formula then gives the same field as ArduPilot's. Before: the 270 deg yaw found was dropped as "a
    rotation that a magnitude calibration does not determine" (CAL_MAG0_ROT 0: every heading 90 deg off)."""
    from trimag.models.firmware import PX4Magnetometer

    log = _write_log(tmp_path / "flight.bin", n=1500, seed=5)
    cal = tmp_path / "cal.json"
    assert run_trimag("fit", log, "--target", "ardupilot", "-o", cal).returncode == 0
    outputs = {}
    for to in ("ardupilot", "px4"):
        out = tmp_path / f"out.{to}"
        r = run_trimag("export", cal, "--to", to, "-o", out)
        assert r.returncode == 0, r.stderr
        outputs[to] = out
    px4 = {line.split()[2]: float(line.split()[3]) for line in outputs["px4"].read_text().splitlines()
           if line.startswith("param set")}
    assert px4["CAL_MAG0_ROT"] == 6 and px4["CAL_MAG_COMP_TYP"] == 2
    ap = ArduPilotCompass.from_parameters({**_param_file(outputs["ardupilot"]), "COMPASS_EXTERNAL": 1.0}, 0)
    mag = PX4Magnetometer.from_parameters(px4, 0)
    _, _, amps, raw = _flight(300, seed=31)
    assert np.allclose(mag.correct(raw / 1000.0, amps) * 1000.0, ap.correct(raw, amps), atol=1e-6)


def test_the_export_of_compass_2_writes_compass_2_s_parameters(tmp_path: Path):
    """``fit LOG --sensor 2`` then ``export`` (no ``--instance``) writes COMPASS_OFS2.., not compass 1's COMPASS_OFS..
    (before: compass 1's parameters were silently replaced by compass 2's calibration); an ``--instance`` that differs
    from the compass fitted is written as asked and said."""
    log = _write_log(tmp_path / "two.bin", n=800, seed=6, second=True)
    cal, param = tmp_path / "cal.json", tmp_path / "c.param"
    r = run_trimag("fit", log, "--sensor", "2", "--target", "ardupilot", "--motor", "none", "-o", cal)
    assert r.returncode == 0, r.stderr
    r = run_trimag("export", cal, "--to", "ardupilot", "-o", param)
    assert r.returncode == 0, r.stderr
    p = _param_file(param)
    assert "COMPASS_OFS2_X" in p and "COMPASS_ORIENT2" in p and "COMPASS_OFS_X" not in p
    r = run_trimag("export", cal, "--to", "ardupilot", "--instance", "1", "-o", param)
    assert r.returncode == 0 and "COMPASS_OFS_X" in _param_file(param) and "compass 2" in r.stdout


def test_a_current_logged_from_the_second_sample_still_gives_the_current_term(tmp_path: Path):
    """The battery's first message after the compass's first (as in the real UoB logs: one MAG sample before BAT
    starts): the rows without a current are dropped and counted, the current term is fitted. Before: the channel
    was left out whole for one empty row, and the fit offered no current term."""
    import json

    log = _write_log(tmp_path / "late.bin", n=1500, seed=7, late_battery=3)
    r = run_trimag("fit", log, "--target", "ardupilot", "--json", "-o", tmp_path / "cal.json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["firmware"]["motor_type"] == "current"
    assert "without a current_A value dropped" in r.stderr


def test_a_regressor_fit_exports_its_current_term_as_the_motor_term(tmp_path: Path):
    """``fit LOG --model interference12 --regressors current_A`` (a tumbled vehicle) then ``export --to ardupilot``:
    the orientation the attitudes determine and the current term as COMPASS_MOT with COMPASS_MOTCT 2."""
    log = _write_log(tmp_path / "tumble.bin", n=2500, seed=8, tilt=170.0)
    cal, param = tmp_path / "cal.json", tmp_path / "c.param"
    r = run_trimag("fit", log, "--model", "interference12", "--regressors", "current_A", "-o", cal)
    assert r.returncode == 0, r.stderr
    assert run_trimag("export", cal, "--to", "ardupilot", "-o", param).returncode == 0
    p = _param_file(param)
    assert p["COMPASS_ORIENT"] == 6 and p["COMPASS_MOTCT"] == 2
    assert np.allclose([p["COMPASS_MOT_X"], p["COMPASS_MOT_Y"], p["COMPASS_MOT_Z"]], TRUTH.motor, atol=0.3)


def test_an_old_px4_log_whose_readings_carry_the_rotation_is_not_exported_as_a_new_orientation(tmp_path: Path):
    """Review after the firmware merge: the real PX4 sdlog2 flight (px4tools, 2015) logs IMU.Mag after the drivers
    rotated it by CAL_MAG0_ROT (and calibrated it: PX4 before v1.12 rotated first, then offsets and scales). The fit
    took the logged readings as the sensor's own frame, said 'ROTATION_NONE (0) fits the field while the log's 6 sees
    the field reversed: chosen', and export wrote CAL_MAG0_ROT 0 with exit 0: loaded into the vehicle, its heading
    would turn by the 270 deg its driver no longer applies. The fit now says that the readings carry the rotation,
    records it, and export refuses to write an orientation found relative to rotated readings (exit 2, no file)."""
    log = TESTS_DIR / "data" / "logs" / "px4tools_01_07_59.px4log"
    cal = tmp_path / "px4.json"
    r = run_trimag("fit", log, "--target", "px4", "-o", cal)
    assert r.returncode == 0, r.stderr
    assert "v1.12" in r.stderr and "CAL_MAG0_ROT = 6" in r.stderr, r.stderr
    out = tmp_path / "px4.params"
    e = run_trimag("export", cal, "--to", "px4", "-o", out)
    assert e.returncode == 2, e.stderr
    line = e.stderr.strip()
    assert len(line.splitlines()) == 1 and "CAL_MAG0_ROT" in line and "v1.12" in line, line
    a = run_trimag("export", cal, "--to", "ardupilot", "-o", tmp_path / "ap.param")
    assert a.returncode == 2 and "v1.12" in a.stderr and not (tmp_path / "ap.param").exists(), a.stderr
    assert not out.exists()
    r = run_trimag("fit", log, "--target", "px4", "--sensor", "all", "--export-to", "px4", "--export-out",
                   tmp_path / "all.params", "-o", tmp_path / "all.json", timeout=600)  # ~18 s idle: bounded refits
    assert r.returncode == 2 and "v1.12" in r.stderr, r.stderr
    assert not list(tmp_path.glob("all*")), list(tmp_path.iterdir())  # nothing of the refused run is left


def test_a_log_that_never_turned_gets_no_offsets_from_the_ekf_yaw_that_used_the_compass(tmp_path: Path):
    """Found at the 2026-11-27 review: the real PX4 ULog (pyulog's sample_log_small, SITL, 6 s) never turned (the
    field stayed within 2 deg), the honest heading-free fit left 58 % of the field unexplained, and the fallback to
    the vector with the EKF's yaw (which fused this compass) wrote offsets (0.33, 0.43, -0.95) G, 0.6 G from the
    log's, with exit 0: offsets fitted to a heading the compass itself made, from one direction of the field. Now
    refused (exit 3, no file), naming --heading (the true heading at rest) and a calibration turn."""
    log = TESTS_DIR / "data" / "logs" / "pyulog_sample_log_small.ulg"
    out = tmp_path / "cal.json"
    r = run_trimag("fit", log, "--target", "px4", "--sensor", "vehicle_magnetometer", "-o", out)
    assert r.returncode == 3, r.stderr
    line = refusal_text(r.stderr)  # the verdict and its details
    assert "--heading" in line and "turn" in line, line
    assert not out.exists()


def test_a_log_of_a_firmware_without_compass_scale_gets_none_written(tmp_path: Path):
    """Unseen ArduCopter 3.4-3.6 logs have no COMPASS_SCALE among their parameters; fit --target wrote one. Now the
    fit says so, fits the gain into DIA, and export writes no COMPASS_SCALE; through the formula the same field."""
    log = _write_log(tmp_path / "old.bin", n=1500, seed=2, drop=("COMPASS_SCALE",))
    cal, param = tmp_path / "cal.json", tmp_path / "c.param"
    r = run_trimag("fit", log, "--target", "ardupilot", "-o", cal)
    assert r.returncode == 0, r.stderr
    assert "no COMPASS_SCALE" in r.stdout + r.stderr
    e = run_trimag("export", cal, "--to", "ardupilot", "-o", param)
    assert e.returncode == 0, e.stderr
    p = _param_file(param)
    assert not [k for k in p if k.startswith("COMPASS_SCALE")] and "COMPASS_DIA_X" in p


def test_a_px4_log_is_not_told_to_log_ardupilots_xky0(tmp_path: Path):
    """A PX4 flight (the bundled sdlog2 log) was told "Log XKY0 (EKF3's GSF yaw, ArduPilot 4.1+)" (issue 42, item 6):
    its advice is PX4's own."""
    r = run_trimag("fit", TESTS_DIR / "data" / "logs" / "px4tools_01_07_59.px4log", "--target", "px4",
                   "-o", tmp_path / "cal.json")
    line = next(x for x in (r.stdout + r.stderr).splitlines() if x.startswith("attitude:") and "heading-free" in x)
    assert r.returncode == 0 and "XKY0" not in line and "ArduPilot" not in line, line
    assert "PX4" in line, line


def test_a_gps_fix_off_the_earth_is_named_as_the_log_s(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 41, item 17: a GPS altitude of 2e7 m went into IGRF unnamed. The log's GPS fix is named, with the
    value, and the way round it (give the site, or the magnitude)."""
    import sys

    monkeypatch.setattr(sys.modules[__name__], "ALT", 2e7)
    log = _write_log(tmp_path / "flight.bin")
    r = run_trimag("fit", log, "-o", tmp_path / "cal.json", timeout=600)
    assert r.returncode == 2, r.stderr
    line = r.stderr.strip()
    assert len(line.splitlines()) == 1 and "GPS" in line and "2e+07 m" in line and "--igrf" in line, line
    assert not (tmp_path / "cal.json").exists()


def test_a_quick_recalibration_of_a_firmware_fit_keeps_its_orientation_level_and_motor_term(tmp_path: Path):
    """Issue 41 item 2: ``fit --prior`` of a ``--target ardupilot`` fit dropped the firmware record: ``export`` then
    wrote no COMPASS_ORIENT (the 270 deg yaw lost with a "note": 90 deg of heading error through ArduPilot's
    formula), offsets in the rotated frame and SCALE 1. The prior's orientation, level and motor term are kept and
    its offsets recomputed: the exported parameters correct a new flight at the noise floor."""
    fw, quick, param = tmp_path / "fw.json", tmp_path / "quick.json", tmp_path / "quick.param"
    assert run_trimag("fit", _write_log(tmp_path / "first.bin"), "--target", "ardupilot", "-o", fw).returncode == 0
    r = run_trimag("fit", _write_log(tmp_path / "second.bin", seed=9), "--prior", fw, "-o", quick)
    assert r.returncode == 0, r.stderr
    said = r.stdout
    r = run_trimag("export", quick, "--to", "ardupilot", "-o", param)
    assert r.returncode == 0, r.stderr
    assert "does not determine" not in r.stderr
    params = _param_file(param)
    first = _param_file(_export(fw, tmp_path / "fw.param"))
    assert params["COMPASS_ORIENT"] == 6 and params["COMPASS_MOTCT"] == 2
    for name in ("COMPASS_SCALE", "COMPASS_DIA_X", "COMPASS_ODI_Z", "COMPASS_MOT_Y"):
        assert params[name] == pytest.approx(first[name], rel=1e-6), name
    exported = ArduPilotCompass.from_parameters({**params, "COMPASS_EXTERNAL": 1.0}, 0)
    _, logged, amps, raw = _flight(2500, seed=30)
    h = body_field(logged, NED_mG)
    floor = np.sqrt(np.mean(np.sum((TRUTH.correct(raw, amps) - h) ** 2, axis=1)))
    got = np.sqrt(np.mean(np.sum((exported.correct(raw, amps) - h) ** 2, axis=1)))
    assert got <= 1.5 * floor, (got, floor)
    assert "orientation ROTATION_YAW_270" in said  # and the fit says what it kept


def _export(cal: Path, out: Path) -> Path:
    r = run_trimag("export", cal, "--to", "ardupilot", "-o", out)
    assert r.returncode == 0, r.stderr
    return out


def test_magnetometer_rows_stamped_early_are_dropped_and_counted(tmp_path: Path):
    """Issue 41 item 6: 100 of 2500 MAG rows stamped 50 s early took the attitude of another moment, silently (the
    heading error 1.48 -> 4.03 deg). They are dropped, counted and said; the fit is the undamaged log's."""
    import json

    fits = {}
    for name, early in (("clean", 0), ("early", 100)):
        cal = tmp_path / f"{name}.json"
        r = run_trimag("fit", _write_log(tmp_path / f"{name}.bin", early_mag=early), "--target", "ardupilot", "-o",
                       cal)
        assert r.returncode == 0, r.stderr
        fits[name] = (json.loads(cal.read_text()), r.stdout + r.stderr)
    clean, early = (np.array(fits[k][0]["diagnostics"]["firmware"]["offsets"]) for k in ("clean", "early"))
    assert np.abs(early - clean).max() < 1.0, (early, clean)  # mG
    assert "dropped 100 of 2500 MAG[0] samples whose time stamp is missing or goes back" in fits["early"][1]
    assert "goes back" not in fits["clean"][1]


def test_a_fixed_heading_on_a_log_that_turned_is_refused(tmp_path: Path):
    """Issue 41 item 5: `--heading DEG` on a flight that turned wrote offsets that made the heading worse (its own
    deviation card 45.9 -> 67.5 deg, exit 0) although the samples missed the expected field by 70 %."""
    out = tmp_path / "cal.json"
    r = run_trimag("fit", _write_log(tmp_path / "flight.bin", n=1500), "--heading", "90", "-o", out)
    assert r.returncode == 3, r.stderr
    assert "contradict a fixed heading" in r.stderr and "--level-turn" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not out.exists()
