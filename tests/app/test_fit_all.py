"""All compasses of a log in one run (issue 30, item 6; docs/autopilot.md "All compasses of a log"):
``trimag fit LOG --sensor all`` fits each magnetometer, writes one parameter file with every instance, and compares
them (offset, fitted field magnitude, heading difference between compasses). Before: ``--sensor all`` was "no
magnetometer 'all'" and a multi-compass parameter file took one export per compass, joined by hand."""

from __future__ import annotations

import datetime as dt
import json
import struct
from pathlib import Path

import numpy as np
import pytest

from trimag import Calibration
from trimag.errors import TrimagInputError
from trimag.io.export_instances import export_instances

from _helpers import BOAT_SITE, refusal, refusal_text, run_trimag, simulate_boat

pytest.importorskip("pymavlink")

#: the second compass: another hard iron and soft iron, the same body field
SECOND_MATRIX = np.array([[0.98, -0.01, 0.005], [-0.01, 1.03, 0.01], [0.005, 0.01, 1.005]])
SECOND_OFFSET = np.array([-40.0, 95.0, -30.0])


def _write_boat_tlog(path: Path, second_moves: float = 0.0) -> tuple[dict, dict]:
    """A boat's telemetry log: two compasses (RAW_IMU, SCALED_IMU2) turning level twice, its attitude and a GPS
    position at :data:`BOAT_SITE`; no onboard calibration (no parameters). ``second_moves``: the second compass's
    hard iron moves by this much (mG, along y) halfway."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink
    from scipy.spatial.transform import Rotation

    from trimag.simulate import body_field

    one = simulate_boat(seed=21)
    h = body_field(Rotation.from_euler("ZYX", one["ypr"], degrees=True), one["field_ned"])  # the same headings
    two = {"raw": h @ np.linalg.inv(SECOND_MATRIX).T + SECOND_OFFSET + np.random.default_rng(23).normal(0, 2, h.shape),
           "offset": SECOND_OFFSET}
    two["raw"][len(h) // 2:, 1] += second_moves
    lat, lon = (float(v) for v in BOAT_SITE.split(",")[:2])
    t0 = dt.datetime(2026, 6, 1, 12, tzinfo=dt.UTC).timestamp()
    link = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    with path.open("wb") as fh:
        def put(t: float, msg) -> None:
            fh.write(struct.pack(">Q", int(t * 1e6)) + msg.pack(link))

        for i in range(len(one["raw"])):
            t = t0 + 0.1 * i
            m1 = np.round(one["raw"][i]).astype(int).tolist()
            m2 = np.round(two["raw"][i]).astype(int).tolist()
            put(t, link.raw_imu_encode(int(t * 1e6), 0, 0, -1000, 0, 0, 0, *m1))
            put(t, link.scaled_imu2_encode(int(i * 100), 0, 0, -1000, 0, 0, 0, *m2))
            yaw, pitch, roll = np.radians(one["ypr"][i])
            put(t, link.attitude_encode(int(i * 100), roll, pitch, yaw if yaw <= np.pi else yaw - 2 * np.pi, 0, 0, 0))
            if i % 10 == 0:
                put(t, link.global_position_int_encode(int(i * 100), int(lat * 1e7), int(lon * 1e7), 40_000, 0, 0, 0,
                                                        0, 0))
    return one, two


def test_every_compass_fitted_compared_and_written_to_one_file(tmp_path: Path) -> None:
    log = tmp_path / "boat.tlog"
    one, _ = _write_boat_tlog(log)
    out, param = tmp_path / "cal.json", tmp_path / "compass.param"
    r = run_trimag("fit", log, "--sensor", "all", "--level-turn", "-o", out, "--export-to", "ardupilot",
                   "--export-out", param, "--json")
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert set(summary["compasses"]) == {"1", "2"} and summary["refused"] == {}
    cal1, cal2 = Calibration.from_file(tmp_path / "cal-1.json"), Calibration.from_file(tmp_path / "cal-2.json")
    # 1 mG rounding of the telemetry's integers on top of the 2 mG noise
    assert np.abs(cal1.offset - one["offset"]).max() < 3.0
    assert np.abs(cal2.offset - SECOND_OFFSET).max() < 3.0
    p = {k: float(v) for k, v in (line.split(",") for line in param.read_text().splitlines()
                                  if not line.startswith("#"))}
    np.testing.assert_allclose([p["COMPASS_OFS_X"], p["COMPASS_OFS2_X"]], [-cal1.offset[0], -cal2.offset[0]])
    assert {"COMPASS_DIA_Z", "COMPASS_DIA2_Z", "COMPASS_ODI2_Y"} <= set(p)
    names = [line.split(",")[0] for line in param.read_text().splitlines() if not line.startswith("#")]
    assert names == sorted(names)  # as MAGFit's files
    rows = {row["compass"]: row for row in summary["comparison"]["compasses"]}
    after, before = rows[2]["heading_difference_after_deg"], rows[2]["heading_difference_before_deg"]
    assert after["rms"] < 1.0 < 10.0 < before["rms"]  # the raw compasses disagree by tens of degrees
    assert abs(rows[1]["field_magnitude"] - rows[2]["field_magnitude"]) < 2.0


def test_the_table_names_each_compass(tmp_path: Path) -> None:
    log = tmp_path / "boat.tlog"
    _write_boat_tlog(log)
    r = run_trimag("fit", log, "--sensor", "all", "--level-turn")
    assert r.returncode == 0, r.stderr
    assert "compasses fitted: 1, 2" in r.stdout and "heading - compass 1" in r.stdout
    assert "RAW_IMU" in r.stdout and "SCALED_IMU2" in r.stdout


def test_each_compass_s_warnings_and_policy_verdict_reach_the_user(tmp_path: Path) -> None:
    """Review of issue 30 item 6: ``--sensor all`` printed no compass's warnings (compass 1's were filtered out,
    the others' never shown: a real log's 'two halves differ by 8.3 sigma' vanished) and exited 0 when a compass
    failed ``--policy`` (``--sensor N`` exits 4). Each compass's warnings are printed naming it; a rejected
    compass makes the run exit 4, naming it; the files are still written, as for one compass."""
    log = tmp_path / "boat.tlog"
    _write_boat_tlog(log, second_moves=25.0)
    single = run_trimag("fit", log, "--sensor", "2", "--level-turn")
    assert single.returncode == 0 and "two halves" in single.stderr, single.stderr
    policy = tmp_path / "policy.toml"
    policy.write_text("[limits]\nmax_offset = 100\n")  # compass 1's offset reaches 120 mG, compass 2's 95 (+25)
    assert run_trimag("fit", log, "--sensor", "1", "--level-turn", "--policy", policy).returncode == 4
    out = tmp_path / "cal.json"
    r = run_trimag("fit", log, "--sensor", "all", "--level-turn", "--policy", policy, "-o", out)
    assert r.returncode == 4, (r.returncode, r.stderr)
    warnings = [line for line in r.stderr.splitlines() if "warning" in line]
    assert any("compass 2" in line and "two halves" in line for line in warnings), r.stderr
    assert any("compass 1" in line and "rejected" in line and "max_offset" in line for line in r.stderr.splitlines())
    assert (tmp_path / "cal-1.json").exists() and (tmp_path / "cal-2.json").exists()


def test_a_compass_that_cannot_be_fitted_is_named_and_the_others_written(tmp_path: Path) -> None:
    """The real ArduSub log (two static compasses): with --heading both get offsets; without, both are refused and
    the run exits 3 naming each."""
    from _helpers import TESTS_DIR

    sub = TESTS_DIR / "data" / "logs" / "ardusub_small.BIN"
    r = run_trimag("fit", sub, "--sensor", "all")
    assert r.returncode == 3
    verdict, _ = refusal(r.stderr)  # both refused for the same reason: said once, naming both
    assert "every compass (1, 2)" in verdict and "barely turned" in refusal_text(r.stderr), r.stderr
    param = tmp_path / "sub.param"
    r = run_trimag("fit", sub, "--sensor", "all", "--heading", "0", "--igrf", "40,-120,0,2023-01-01", "--export-to",
                   "px4", "--export-out", param)
    assert r.returncode == 0, r.stderr
    text = param.read_text()
    assert "param set CAL_MAG0_XOFF" in text and "param set CAL_MAG1_XOFF" in text


def test_export_instances_joins_and_refuses() -> None:
    a = Calibration.from_matrix_offset(np.eye(3), [10.0, 0.0, 0.0], units="mG")
    b = Calibration.from_matrix_offset(np.eye(3), [0.0, 20.0, 0.0], units="mG")
    exp = export_instances([(b, 3), (a, 1)], "ardupilot")
    assert exp.parameters["COMPASS_OFS_X"] == -10.0 and exp.parameters["COMPASS_OFS3_Y"] == -20.0
    px4 = export_instances([(a, 1), (b, 2)], "px4")
    assert "param set CAL_MAG0_XOFF 0.01" in px4.text and "param set CAL_MAG1_YOFF 0.02" in px4.text
    with pytest.raises(TrimagInputError, match="twice"):
        export_instances([(a, 1), (b, 1)], "ardupilot")
    with pytest.raises(TrimagInputError, match="ardupilot or px4"):
        export_instances([(a, 1)], "json")


def test_sensor_all_refusals(tmp_path: Path) -> None:
    data = tmp_path / "d.csv"
    data.write_text("x,y,z\n1,2,3\n4,5,6\n")
    r = run_trimag("fit", data, "--sensor", "all")
    assert r.returncode == 2 and "autopilot log" in r.stderr
    r = run_trimag("fit", data, "--export-to", "ardupilot", "--export-out", tmp_path / "x.param")
    assert r.returncode == 2 and "--sensor all" in r.stderr


def test_the_parameter_file_leaves_out_what_the_policy_rejected(tmp_path: Path) -> None:
    """Issue 41, item 9: ``--export-to --policy`` wrote the parameter file when every compass was rejected (exit 4,
    but the parameters of fits trimag itself rejected were ready to load). A rejected compass is left out (named);
    none left: no parameter file, exit 4, saying ``--force``; ``--force`` writes them all."""
    log = tmp_path / "boat.tlog"
    _write_boat_tlog(log)
    policy = tmp_path / "policy.toml"
    policy.write_text("[limits]\nmax_offset = 100\n")  # compass 1's offset reaches 120 mG, compass 2's 95
    param = tmp_path / "compass.param"
    argv = ["fit", log, "--sensor", "all", "--level-turn", "-o", tmp_path / "cal.json", "--export-to", "ardupilot",
            "--export-out", param]
    r = run_trimag(*argv, "--policy", policy)
    assert r.returncode == 4, r.stderr
    text = param.read_text()
    assert "COMPASS_OFS2_X" in text and "COMPASS_OFS_X" not in text  # compass 1 left out
    assert any("compass 1" in line and "left out" in line for line in r.stderr.splitlines()), r.stderr
    param.unlink()
    policy.write_text("[limits]\nmax_offset = 10\n")  # both rejected
    r = run_trimag(*argv, "--policy", policy)
    assert r.returncode == 4 and not param.exists(), r.stderr
    assert "--force" in r.stderr.strip().splitlines()[-1]
    r = run_trimag(*argv, "--policy", policy, "--force")
    assert r.returncode == 4 and "COMPASS_OFS_X" in param.read_text() and "COMPASS_OFS2_X" in param.read_text()
