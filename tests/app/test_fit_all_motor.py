"""One motor channel for one vehicle (issue 39, item 6): `fit LOG --sensor all --target ardupilot` (motor auto) on a
log whose compasses prefer current and throttle was refused (exit 2, "fit them with the same motor channel").
COMPASS_MOTCT is one parameter: the channel that serves all compasses best (summed held-out RMS) is chosen and
said, and every compass's file and the parameter file use it.

A simulated ArduCopter flight written as a DataFlash log: compass 1 with a current term, compass 2 with a throttle
term; BAT logs the current, CTUN the throttle (independent profiles)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from trimag import Calibration
from trimag.cli import main
from trimag.fields.attitude import body_field
from trimag.fields.reference import igrf
from trimag.models.firmware import ArduPilotCompass
from trimag.simulate import current_profile

from _helpers import TESTS_DIR

pytest.importorskip("pymavlink")

LAT, LON, ALT, WEEK, MS = 52.8, -4.12, 30.0, 2269, 388_800_000  # 2023-07-06
FIRST = ArduPilotCompass(orientation=0, offsets=[120.0, -80.0, 40.0], diagonal=[1.02, 0.97, 1.01],
                         motor=[4.0, -3.0, 5.0], motor_type="current")
SECOND = ArduPilotCompass(orientation=0, offsets=[-60.0, 90.0, -25.0], diagonal=[1.01, 1.0, 0.99],
                          motor=[60.0, -40.0, 80.0], motor_type="throttle")


def _write_log(path: Path, n: int = 2500, seed: int = 4) -> Path:
    sys.path.insert(0, str(TESTS_DIR / "io"))
    from _dataflash import write_dataflash

    rng = np.random.default_rng(seed)
    ned = np.asarray(igrf(LAT, LON, ALT, "2023-07-06").ned_nT) / 100.0
    yaw = np.cumsum(rng.normal(0, 3, n)) % 360
    pitch = np.clip(np.cumsum(rng.normal(0, 2, n)), -35.0, 35.0)
    roll = np.clip(np.cumsum(rng.normal(0, 2, n)), -35.0, 35.0)
    ypr = np.column_stack([yaw, pitch, roll])
    true = Rotation.from_euler("ZYX", ypr, degrees=True)
    amps = current_profile(n, seed + 1, max_current=30.0)
    throttle = current_profile(n, seed + 2, max_current=1.0)
    h = body_field(true, ned)
    raw1 = FIRST.uncorrect(h, amps) + rng.normal(0, 2.0, (n, 3))
    raw2 = SECOND.uncorrect(h, throttle) + rng.normal(0, 2.0, (n, 3))
    t_us = 10_000_000 + np.arange(n) * 100_000  # 10 Hz
    rows = [(int(t), 0, *map(int, m), 0, 0, 0, 0, 0, 0, 1, int(t)) for t, m in zip(t_us, np.trunc(raw1), strict=True)]
    rows += [(int(t) + 500, 1, *map(int, m), 0, 0, 0, 0, 0, 0, 1, int(t)) for t, m in
             zip(t_us, np.trunc(raw2), strict=True)]
    rows.sort(key=lambda row: row[0])
    params = {"COMPASS_EXTERNAL": 1.0, "COMPASS_MOTCT": 0.0, "COMPASS_USE": 1.0, "COMPASS_ORIENT": 0.0,
              "COMPASS_ORIENT2": 0.0, "COMPASS_EXTERN2": 1.0}
    return write_dataflash(path, {
        "MSG": ("QZ", "TimeUS,Message", [(1000, "ArduCopter V4.3.6 (simulated)")]),
        "PARM": ("QNf", "TimeUS,Name,Value", [(1000, k, v) for k, v in params.items()]),
        "MAG": ("QBhhhhhhhhhBI", "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S", rows),
        "ATT": ("QccccCCCCB", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw,AEKF",
                [(int(t), 0.0, r, 0.0, p, 0.0, y % 360.0, 0.0, 0.0, 3)
                 for t, (y, p, r) in zip(t_us, ypr, strict=True)]),
        "BAT": ("QBfffffcfB", "TimeUS,Instance,Volt,VoltR,Curr,CurrTot,EnrgTot,Temp,Res,RemPct",
                [(int(t), 0, 16.0, 16.0, float(a), 0.0, 0.0, 25.0, 0.0, 80)
                 for t, a in zip(t_us, amps, strict=True)]),
        "CTUN": ("Qf", "TimeUS,ThO", [(int(t), float(x)) for t, x in zip(t_us, throttle, strict=True)]),
        "GPS": ("QBBIHBcLLeffffB", "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,Yaw,U",
                [(int(t), 0, 3, MS, WEEK, 12, 0.8, LAT, LON, ALT, 0.0, 0.0, 0.0, 0.0, 1) for t in t_us[::10]]),
    })


def test_every_compass_gets_the_one_motor_channel_that_serves_them_best(tmp_path: Path,
                                                                        capsys: pytest.CaptureFixture[str]) -> None:
    log = _write_log(tmp_path / "flight.bin")
    # alone, each compass prefers its own channel
    chosen = {}
    for sensor in ("1", "2"):
        assert main(["fit", str(log), "--sensor", sensor, "--target", "ardupilot", "--json", "-q"]) == 0
        chosen[sensor] = json.loads(capsys.readouterr().out)["diagnostics"]["firmware"]["motor_type"]
    assert chosen == {"1": "current", "2": "throttle"}
    cal, param = tmp_path / "cal.json", tmp_path / "compass.param"
    code = main(["fit", str(log), "--sensor", "all", "--target", "ardupilot", "-o", str(cal), "--export-to",
                 "ardupilot", "--export-out", str(param)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    said = next(line for line in (captured.out + captured.err).splitlines() if "one motor channel" in line)
    channel = "current" if "current serves them best" in said else "throttle"
    assert f"{channel} serves them best" in said and "summed held-out RMS" in said
    types = {Calibration.from_file(tmp_path / f"cal-{n}.json").diagnostics["firmware"]["motor_type"] for n in (1, 2)}
    assert types <= {channel, None}
    values = dict(line.split(",") for line in param.read_text().splitlines() if line and not line.startswith("#"))
    assert float(values["COMPASS_MOTCT"]) == (2.0 if channel == "current" else 1.0)
