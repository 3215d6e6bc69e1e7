"""Parameters the log's firmware lacks, for every compass (issue 39, item 5): an ArduCopter 3.2 log has
``COMPASS_OFS2_X`` but no ``COMPASS_ORIENT2``; ``fit --sensor all --export-to ardupilot`` must not write it (the
firmware has no such parameter), and says so."""

from __future__ import annotations

import struct
from pathlib import Path

import pytest

from trimag.models.firmware import absent_parameters

from _helpers import TESTS_DIR, run_trimag

pytest.importorskip("pymavlink")

from test_fit_all import _write_boat_tlog


def test_the_parameters_a_complete_list_lacks_for_one_compass() -> None:
    params = {f"P{k}": 0.0 for k in range(300)}
    params.update({f"COMPASS_{p}{n}_{a}": 0.0 for p in ("OFS", "DIA", "ODI", "MOT") for n in ("", "2") for a in "XYZ"})
    params.update(COMPASS_SCALE=0.0, COMPASS_SCALE2=0.0, COMPASS_ORIENT=0.0, COMPASS_MOTCT=0.0)
    assert absent_parameters("ardupilot", params, 1) == ("COMPASS_ORIENT2",)
    assert absent_parameters("ardupilot", params, 0) == ()
    # a telemetry log that received a few parameters only says nothing
    few = {"COMPASS_OFS2_X": 0.0, "COMPASS_OFS2_Y": 0.0, "COMPASS_OFS2_Z": 0.0}
    assert absent_parameters("ardupilot", few, 1) == ()


def _with_parameters(log: Path, params: dict[str, float]) -> None:
    """Append ``params`` as PARAM_VALUE messages to a telemetry log (at its first time stamp)."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    link = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    data = log.read_bytes()
    t = struct.unpack(">Q", data[:8])[0]
    with log.open("ab") as fh:
        for k, (name, value) in enumerate(sorted(params.items())):
            fh.write(struct.pack(">Q", t) + link.param_value_encode(name.encode(), value, 9, len(params), k).pack(link))


def test_a_sensor_all_export_leaves_out_the_orientation_the_second_compass_lacks(tmp_path: Path) -> None:
    from trimag.io.logs import read_log

    # a whole parameter list of a real ArduPilot (the bundled ArduSub log's), the calibration neutral, and as
    # ArduCopter 3.2: no COMPASS_ORIENT2
    params = dict(read_log(TESTS_DIR / "data" / "logs" / "ardusub_small.BIN").parameters)
    for name in list(params):
        if name.startswith(("COMPASS_OFS", "COMPASS_ODI", "COMPASS_MOT")) and name != "COMPASS_MOTCT":
            params[name] = 0.0
        elif name.startswith("COMPASS_DIA"):
            params[name] = 1.0
        elif name.startswith(("COMPASS_SCALE", "COMPASS_ORIENT")):
            params[name] = 0.0
    params.update(COMPASS_EXTERNAL=1.0, COMPASS_EXTERN2=1.0, AHRS_ORIENTATION=0.0)
    del params["COMPASS_ORIENT2"]
    for name in ("AHRS_TRIM_X", "AHRS_TRIM_Y", "AHRS_TRIM_Z"):  # the boat's level turns leave compass 2's yaw
        params.pop(name, None)  # orientation weakly determined: the ArduSub board trim (1.5 deg) tips it to 90 deg
    log = tmp_path / "boat.tlog"
    _write_boat_tlog(log)
    _with_parameters(log, params)
    out, param = tmp_path / "cal.json", tmp_path / "compass.param"
    r = run_trimag("fit", log, "--sensor", "all", "--target", "ardupilot", "-o", out, "--export-to", "ardupilot",
                   "--export-out", param, timeout=600)
    assert r.returncode == 0, r.stderr
    written = {line.split(",")[0] for line in param.read_text().splitlines() if not line.startswith("#")}
    assert {"COMPASS_OFS2_X", "COMPASS_DIA2_X", "COMPASS_ORIENT"} <= written and "COMPASS_ORIENT2" not in written
    assert "not written: COMPASS_ORIENT2: the log's firmware has no such parameter" in r.stdout + r.stderr
