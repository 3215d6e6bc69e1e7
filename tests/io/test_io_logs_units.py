"""DataFlash units from the log's own FMT/FMTU (issue 32 item 5): old ArduPilot ``CURR`` stores centivolts and
centiamps as integers (``Volt = 1239``, ``Curr = 72``) and ArduCopter 3.x ``CTUN.ThrOut`` throttle in 0..1000; read
as volts, amps and 0..1 they made current coefficients 100x off. Logs with ``FMTU`` state each field's multiplier."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _dataflash import write_dataflash

from trimag.io.logs import read_log

pytest.importorskip("pymavlink")

MAG_OLD = ("IhhhhhhhhhB", "TimeMS,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOfsX,MOfsY,MOfsZ,Health")


def _mag_rows(n: int) -> list[tuple]:
    return [(1000 + 100 * k, 200 + k, -50, 400, 0, 0, 0, 0, 0, 0, 1) for k in range(n)]


def test_old_curr_centiamps_and_ctun_throttle_per_mille_are_read_in_amps_and_0_to_1(tmp_path: Path):
    # ArduCopter 3.3 (dronekit-la-testdata log171): CURR IhhhHfh, CTUN Ihhhffecchh, GPS with Week and TimeMS
    path = write_dataflash(tmp_path / "old.bin", {
        "MAG": (*MAG_OLD, _mag_rows(40)),
        "CURR": ("IhhhHfh", "TimeMS,Throttle,Volt,Curr,Vcc,CurrTot,Volt2",
                 [(1000 + 100 * k, 450, 1239, 72 + k, 5000, 0.0, 0) for k in range(40)]),
        "CTUN": ("Ihhhffecchh", "TimeMS,ThrIn,AngBst,ThrOut,DAlt,Alt,BarAlt,DSAlt,SAlt,DCRt,CRt",
                 [(1000 + 100 * k, 400, 0, 450 + k, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 0) for k in range(40)]),
        "GPS": ("BIHBcLLeeEefI", "Status,TimeMS,Week,NSats,HDop,Lat,Lng,RelAlt,Alt,Spd,GCrs,VZ,T",
                [(3, 345_600_000, 1850, 10, 1.0, -35.3, 149.1, 10.0, 600.0, 0.0, 0.0, 0.0, 1000 + 100 * k)
                 for k in range(5)]),
    })
    log = read_log(path)
    current = log.channels["current_A"]
    assert current.unit == "A" and current.values[0] == pytest.approx(0.72)
    assert log.channels["voltage_V"].values[0] == pytest.approx(12.39)
    assert log.channels["throttle"].values[0] == pytest.approx(0.45)
    assert "CURR.Curr" in current.source and "0.01" in current.source
    assert log.gps is not None and log.gps["date"] == "2015-06-25"


def test_fmtu_multipliers_are_applied_to_integer_fields_and_floats_kept(tmp_path: Path):
    fmtu_rows = []
    path_types = {
        "MAG": (*MAG_OLD, _mag_rows(40)),
        "BAT": ("QfhB", "TimeUS,Volt,Curr,Inst", [(1_000_000 + 100_000 * k, 16.2, 1250, 0) for k in range(40)]),
        "CTUN": ("Qf", "TimeUS,ThO", [(1_000_000 + 100_000 * k, 0.37) for k in range(40)]),
        "MULT": ("QbD", "TimeUS,Id,Mult", [(0, ord("B"), 0.01), (0, ord("-"), 0.0), (0, ord("0"), 1.0)]),
        "UNIT": ("QbZ", "TimeUS,Id,Label", [(0, ord("A"), "A"), (0, ord("v"), "V"), (0, ord("-"), "")]),
        "FMTU": ("QBNN", "TimeUS,FmtType,UnitIds,MultIds", fmtu_rows),
    }
    fmtu_rows += [(0, 131, "-vA-", "-0B-"), (0, 132, "--", "--")]  # BAT is type 131 in write_dataflash's order
    path = write_dataflash(tmp_path / "fmtu.bin", {k: (v[0].replace("D", "d"), v[1], v[2]) for k, v in
                                                   path_types.items()})
    log = read_log(path)
    assert log.channels["current_A"].values[0] == pytest.approx(12.5)  # 1250 x 0.01 (FMTU multiplier B)
    assert log.channels["voltage_V"].values[0] == pytest.approx(16.2)
    assert log.channels["throttle"].values[0] == pytest.approx(0.37)
    assert np.isfinite(log.channels["current_A"].values).all()
