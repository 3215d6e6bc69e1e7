"""`trimag fit LOG --target ardupilot` of a large simulated DataFlash log, A/B of two source trees (issue 40 item 3).

    python benchmarks/firmware_large_log.py --new src [--old /tmp/old/src] [--hours 5] [--rounds 3] [--log PATH]

Builds (once, cached at ``--log``, by default in the system's temporary folder: never in the repository) a binary
DataFlash log of a simulated ArduCopter flight as ``tests/app/test_firmware_fit.py`` writes it, at the scale of the
issue's field log: ``--hours`` at 10 Hz of MAG (the firmware's corrected field, int16), ATT, BAT, CTUN's throttle,
with GPS at 1 Hz and IMU at 100 Hz as ballast (5 h: 180 000 compass samples, 120 MB). The compass is mounted yawed
270 deg (COMPASS_ORIENT 6) while the log says 0, with offsets, a soft-iron matrix and a current term to find (the
test's TRUTH), so the orientation search, the heading-free levels (3 motor variants), the halves check and the
heading check all run.

Each round runs the command once per tree, alternating, each in its own process (wall time, user CPU time and peak
resident memory from ``/usr/bin/time``); the medians over the rounds and the median of the paired new/old ratios
are printed, and the fitted parameters of the two trees compared (those that differ, new - old).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

LAT, LON, ALT, WEEK, MS = 52.8, -4.12, 30.0, 2269, 388_800_000  # as tests/app/test_firmware_fit.py

_TYPES = {"B": "u1", "b": "i1", "h": "<i2", "H": "<u2", "i": "<i4", "I": "<u4", "f": "<f4", "d": "<f8", "Q": "<u8",
          "q": "<i8", "c": "<i2", "C": "<u2", "e": "<i4", "E": "<u4", "L": "<i4", "n": "S4", "N": "S16", "Z": "S64"}
_SCALE = {"c": 100.0, "C": 100.0, "e": 100.0, "E": 100.0, "L": 1e7}


def _records(type_id: int, fmt: str, columns: list[np.ndarray]) -> bytes:
    """One message type's records, vectorised (``0xA3 0x95 TYPE PAYLOAD``; scaled formats in physical units)."""
    n = len(columns[0])
    dtype = np.dtype([("h1", "u1"), ("h2", "u1"), ("id", "u1")] + [(f"f{k}", _TYPES[c]) for k, c in enumerate(fmt)])
    out = np.zeros(n, dtype=dtype)
    out["h1"], out["h2"], out["id"] = 0xA3, 0x95, type_id
    for k, (c, col) in enumerate(zip(fmt, columns, strict=True)):
        out[f"f{k}"] = np.round(np.asarray(col) * _SCALE[c]) if c in _SCALE else col
    return out.tobytes()


def _fmt(type_id: int, name: str, fmt: str, cols: str) -> bytes:
    import struct

    length = 3 + np.dtype([(f"f{k}", _TYPES[c]) for k, c in enumerate(fmt)]).itemsize
    return b"\xa3\x95\x80" + struct.pack("<BB4s16s64s", type_id, length, name.encode(), fmt.encode(), cols.encode())


def build_log(path: Path, hours: float, seed: int = 1) -> Path:
    """The simulated flight (module docstring) written to ``path``."""
    from scipy.spatial.transform import Rotation

    from trimag.fields.attitude import body_field
    from trimag.fields.reference import igrf
    from trimag.models.firmware import ArduPilotCompass
    from trimag.simulate import current_profile

    truth = ArduPilotCompass(orientation=6, offsets=[120.0, -80.0, 40.0], scale=1.05, diagonal=[1.02, 0.97, 1.01],
                             offdiagonal=[0.02, -0.01, 0.03], motor=[2.0, -1.5, 3.0], motor_type="current")
    onboard = ArduPilotCompass(orientation=0, offsets=[10.0, 5.0, -3.0])
    ned = np.asarray(igrf(LAT, LON, ALT, "2023-07-06").ned_nT) / 100.0
    n = int(hours * 3600 * 10)
    rng = np.random.default_rng(seed)
    yaw = np.cumsum(rng.normal(0, 3, n)) % 360
    pitch = np.clip(np.cumsum(rng.normal(0, 2, n)), -35, 35)
    roll = np.clip(np.cumsum(rng.normal(0, 2, n)), -35, 35)
    true = Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll]), degrees=True)
    logged = Rotation.from_rotvec(np.radians(rng.normal(0, [0.5, 0.5, 1.0], (n, 3)))) * true
    amps = current_profile(n, seed + 1, max_current=30.0)
    raw = truth.uncorrect(body_field(true, ned), amps) + rng.normal(0, 2.0, (n, 3))
    mag = np.trunc(onboard.correct(raw))
    throttle = np.clip(0.35 + amps / 60.0 + rng.normal(0, 0.02, n), 0.0, 1.0)  # a third motor variant
    t_us = 10_000_000 + np.arange(n, dtype=np.int64) * 100_000
    ypr = logged.as_euler("ZYX", degrees=True)
    params = {**onboard.parameters(0), "COMPASS_EXTERNAL": 1.0, "COMPASS_DIA_X": 1.0, "COMPASS_DIA_Y": 1.0,
              "COMPASS_DIA_Z": 1.0, "COMPASS_MOTCT": 0.0, "COMPASS_USE": 1.0}
    zeros, ones = np.zeros(n), np.ones(n)
    types = [
        ("MSG", "QZ", "TimeUS,Message", [np.array([1000]), np.array([b"ArduCopter V4.3.6 (simulated)"])]),
        ("PARM", "QNf", "TimeUS,Name,Value", [np.full(len(params), 1000), np.array([k.encode() for k in params]),
                                              np.array(list(params.values()))]),
        ("MAG", "QBhhhhhhhhhBI", "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S",
         [t_us, zeros, *mag.T, 10 * ones, 5 * ones, -3 * ones, zeros, zeros, zeros, ones, t_us]),
        ("ATT", "QccccCCCCB", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw,AEKF",
         [t_us, zeros, ypr[:, 2], zeros, ypr[:, 1], zeros, ypr[:, 0] % 360.0, zeros, zeros, 3 * ones]),
        ("BAT", "QBfffffcfB", "TimeUS,Instance,Volt,VoltR,Curr,CurrTot,EnrgTot,Temp,Res,RemPct",
         [t_us, zeros, 16 * ones, 16 * ones, amps, zeros, zeros, 25 * ones, zeros, 80 * ones]),
        ("CTUN", "Qff", "TimeUS,ThI,ThO", [t_us, throttle, throttle]),
        ("GPS", "QBBIHBcLLeffffB", "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,Yaw,U",
         [t_us[::10], *(np.full(len(t_us[::10]), v) for v in (0, 3, MS, WEEK, 12, 0.8, LAT, LON, ALT, 0, 0, 0, 0,
                                                                1))]),
    ]
    t_imu = 10_000_000 + np.arange(10 * n, dtype=np.int64) * 10_000  # 100 Hz ballast, as a real log's size
    gyro = rng.normal(0, 0.01, (10 * n, 3))
    types.append(("IMU", "QBffffffIIfBBHH", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz",
                  [t_imu, np.zeros(10 * n), *gyro.T, np.zeros(10 * n), np.zeros(10 * n), np.full(10 * n, -9.81),
                   *(np.zeros(10 * n) for _ in range(3)), np.ones(10 * n), np.ones(10 * n), np.full(10 * n, 400),
                   np.full(10 * n, 400)]))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".part")
    with tmp.open("wb") as fh:
        fh.write(b"\xa3\x95\x80" + __import__("struct").pack("<BB4s16s64s", 128, 89, b"FMT", b"BBnNZ",
                                                               b"Type,Length,Name,Format,Columns"))
        for k, (name, fmt, cols, _) in enumerate(types):
            fh.write(_fmt(130 + k, name, fmt, cols))
        for k, (_, fmt, _, columns) in enumerate(types):
            fh.write(_records(130 + k, fmt, columns))
    tmp.replace(path)
    return path


def _fit(src: str, log: Path, out: Path) -> tuple[float, float, float, dict[str, float], str]:
    env = {**os.environ, "PYTHONPATH": os.path.abspath(src)}
    r = subprocess.run(["/usr/bin/time", "-f", "%e %U %M", sys.executable, "-m", "trimag", "fit", str(log), "--target",
                        "ardupilot", "--json", "-o", str(out)], env=env, capture_output=True, text=True)
    seconds, user, kb = r.stderr.strip().splitlines()[-1].split()
    if r.returncode != 0:
        raise SystemExit(f"{src}: exit {r.returncode}: {r.stderr[-2000:]}")
    fw = json.loads(r.stdout)["firmware"]
    params = {k: float(v) for k, v in fw.items() if k.isupper() and isinstance(v, int | float)}
    if not params:  # the parameters are in the calibration file
        cal = json.loads(out.read_text())
        params = {k: float(v) for k, v in cal.get("params", {}).items()}
    return float(seconds), float(user), float(kb) / 1024, params, str(fw.get("level"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--new", default=str(ROOT / "src"), help="src folder of the tree to measure")
    parser.add_argument("--old", help="src folder of the tree to compare with (alternating, one time window)")
    parser.add_argument("--hours", type=float, default=5.0)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--log", help="where the simulated log is kept (built when absent)")
    a = parser.parse_args()
    log = Path(a.log) if a.log else Path(tempfile.gettempdir()) / "trimag-bench" / f"flight_{a.hours:g}h.bin"
    if not log.exists():
        build_log(log, a.hours)
    print(f"log: {log} ({log.stat().st_size / 1e6:.0f} MB, {int(a.hours * 36000)} compass samples)")
    trees = [("old", a.old), ("new", a.new)] if a.old else [("new", a.new)]
    times: dict[str, list[float]] = {k: [] for k, _ in trees}
    cpu: dict[str, list[float]] = {k: [] for k, _ in trees}
    peaks: dict[str, list[float]] = {k: [] for k, _ in trees}
    params: dict[str, list[dict[str, float]]] = {k: [] for k, _ in trees}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(a.rounds):
            for name, src in trees:
                s, user, mb, p, level = _fit(src, log, Path(tmp) / f"{name}.json")
                times[name].append(s)
                cpu[name].append(user)
                peaks[name].append(mb)
                params[name].append(p)
                print(f"  {name}: {s:.2f} s wall, {user:.2f} s user CPU, {mb:.0f} MB, level {level}", flush=True)
    for name, _ in trees:
        print(f"{name}: median {statistics.median(times[name]):.2f} s wall (all {times[name]}), "
              f"{statistics.median(cpu[name]):.2f} s user CPU, peak RSS median "
              f"{statistics.median(peaks[name]):.0f} MB")
    if a.old:
        ratios = [n / o for o, n in zip(times["old"], times["new"], strict=True)]
        print(f"new/old: median of paired ratios {statistics.median(ratios):.3f} ({[round(r, 3) for r in ratios]})")
        old, new = params["old"][0], params["new"][0]
        diffs = {k: new[k] - old[k] for k in old if k in new and old[k] != new[k]}
        print("parameters that differ (new - old):", {k: f"{v:.3g}" for k, v in diffs.items()} or "none")


if __name__ == "__main__":
    main()
