"""trimag's firmware-space fit against pymavlink's MAGFit (``magfit_WMM.py``) on real DataFlash logs (issue 30).

    python benchmarks/magfit_compare.py LOG.bin [LOG.bin ...] [--out table.md]

For each log with MAG, ATT and a GPS fix, both tools fit the first half of compass 1's samples and are judged on
the second half (held out), each through ArduPilot's own formula (``trimag.models.firmware.ArduPilotCompass``):

- **MAGFit** is run as a user runs it (``MPLBACKEND=Agg magfit_WMM.py --save-params``) on a copy of the log cut at
  the half (and, in a 4.1+ log, without the other compasses' MAG messages, which MAGFit mixes into one fit), in
  three variants: default (offsets + scale), ``--elliptical``, and ``--elliptical --cmot`` where the log has a
  battery current; ``--att-source ATT`` where the log lacks ``AHRS_EKF_TYPE`` (ArduPilot 3.x); the variant with the
  lowest held-out error is reported (an optimistic choice for MAGFit).
- **trimag**: ``trimag fit LOG --sensor 1 --target ardupilot --rows 0:HALF`` then ``trimag export``.

Both tools' parameters are judged as the log's firmware loads them: a part its parameter list lacks
(``trimag.models.firmware.absent_features``: ``COMPASS_SCALE`` before ArduPilot 4.0, ``DIA/ODI`` before 3.4) is
ignored by that firmware, so it is dropped before the judge (MAGFit writes ``COMPASS_SCALE`` for any version).

Field error on the held-out half, two ways:

- ``magfit``: MAGFit's own cost (``wmm_error``): the mean length of ``expected - corrected``, the expected field
  being MAGFit's Earth field (pymavlink's WMM table) rotated by ATT's roll and pitch (plus ``AHRS_TRIM``) and the
  heading of the corrected field itself (blind to heading errors);
- ``vector``: the RMS length of ``IGRF vector rotated by ATT's attitude - corrected`` (heading errors included).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _magfit_script() -> Path:
    import pymavlink

    return Path(pymavlink.__file__).parent / "tools" / "magfit_WMM.py"


def _first_half_copy(log: Path, t_mid_us: float, out: Path) -> bool:
    """The log up to ``t_mid_us`` (MAG time), without the MAG messages of compasses other than instance 0.

    Returns whether the log's MAG messages carry an instance field (ArduPilot 4.1+: one MAG for every compass),
    which MAGFit reads as one compass (its ``--mag N`` reads the ``MAGN`` messages of older logs)."""
    from trimag.io.logs.dataflash import _decode, _scan

    data = np.memmap(log, dtype=np.uint8, mode="r")
    lengths, formats, starts = _scan(data, {"MAG"})
    mag_type = next(t for t, (n, _, _) in formats.items() if n == "MAG")
    positions = starts.get(mag_type, [])
    name, fmt, cols = formats[mag_type]
    fields = _decode(log, data, name, fmt, cols, positions, lengths[mag_type])
    assert fields is not None
    time = np.asarray(fields["TimeUS"] if "TimeUS" in fields else fields["TimeMS"] * 1000, dtype=float)
    cut = positions[int(np.searchsorted(time, t_mid_us))] if time[-1] > t_mid_us else len(data)
    drop = [p for p, i in zip(positions, fields.get("I", np.zeros(len(positions))), strict=True) if i != 0]
    pieces, start = [], 0
    for p in drop:
        if p >= cut:
            break
        pieces.append(bytes(data[start:p]))
        start = p + lengths[mag_type]
    pieces.append(bytes(data[start:cut]))
    out.write_bytes(b"".join(pieces))
    return "I" in fields


def _params(path: Path) -> dict[str, float]:
    out = {}
    for line in path.read_text().splitlines():
        parts = line.replace(",", " ").split()
        if len(parts) == 2 and not line.startswith("#"):
            out[parts[0]] = float(parts[1])
    return out


def _run_magfit(half: Path, params: dict[str, float], has_current: bool,
                mag: int = 1) -> dict[str, dict[str, float]]:
    variants = {"default": [], "elliptical": ["--elliptical"]}
    if has_current:
        variants["elliptical+cmot"] = ["--elliptical", "--cmot"]
    base = ["--save-params", "--iter", "300", "--mag", str(mag)]
    if "AHRS_EKF_TYPE" not in params:
        base += ["--att-source", "ATT"]
    out = {}
    for name, flags in variants.items():
        target = half.with_name(half.stem + f"-magfit-mag-{mag}.param")
        target.unlink(missing_ok=True)
        proc = subprocess.run([sys.executable, str(_magfit_script()), *base, *flags, str(half)],
                              capture_output=True, text=True, env={**os.environ, "MPLBACKEND": "Agg"}, timeout=1800)
        if proc.returncode == 0 and target.exists():
            out[name] = _params(target)
        else:
            out[name] = {"_failed": 1.0, "_message": (proc.stdout + proc.stderr).strip().splitlines()[-1:]}  # type: ignore
    return out


def _errors(compass: Any, raw: np.ndarray, motor: np.ndarray | None, att_deg: np.ndarray,
            ned_igrf: np.ndarray, magfit_field: np.ndarray, declination: float) -> tuple[float, float]:
    """(MAGFit's mean error with the heading from the corrected field, vector RMS against IGRF and ATT)."""
    from trimag.fields.attitude import body_field, from_euler
    from trimag.models.firmware import euler_matrix

    B = compass.correct(raw, motor if compass.motor_type else None)
    yaw, pitch, roll = att_deg.T
    err = np.empty(len(B))
    for k in range(len(B)):  # magfit_WMM.get_yaw and expected_field, written out
        dcm = euler_matrix(roll[k], pitch[k], yaw[k])
        c = dcm[2]
        cos_pitch_sq = 1.0 - c[0] * c[0]
        m = B[k]
        head_y = m[1] * c[2] - m[2] * c[1]
        head_x = m[0] * cos_pitch_sq - c[0] * (m[1] * c[1] + m[2] * c[2])
        heading = np.degrees(np.arctan2(-head_y, head_x)) + declination
        expected = euler_matrix(roll[k], pitch[k], heading).T @ magfit_field
        err[k] = np.linalg.norm(expected - m)
    h = body_field(from_euler(yaw, pitch, roll), ned_igrf)
    return float(err.mean()), float(np.sqrt(np.mean(np.sum((B - h) ** 2, axis=1))))


def compare(log: Path, work: Path, compass: int = 1, magfit: bool = True) -> dict[str, Any]:
    """Compass ``compass`` (1-based) of ``log``: fitted by MAGFit and trimag on its first half, judged on the second.

    The row also has trimag's exit code (``trimag_exit``), its verdict against the log's calibration on the rows it
    did not fit (``trimag_verdict``), the heading turned through on the fitted half (``yaw_span_deg``: unwrapped, 5th
    to 95th percentile) and
    the largest tilt (``tilt_max_deg``); ``magfit=False`` leaves MAGFit out (trimag's A/B runs)."""
    from pymavlink import mavextra

    from trimag.fields.reference import igrf
    from trimag.io.logs import read_log
    from trimag.models.firmware import ArduPilotCompass, absent_features, without_features

    vlog = read_log(log)
    mag = vlog.choose(str(compass))
    df, _ = vlog.table(str(compass))
    ok = np.isfinite(df[["yaw_deg", "pitch_deg", "roll_deg"]].to_numpy()).all(axis=1)
    n = len(df)
    half = n // 2
    params = vlog.parameters
    gps = vlog.gps
    row: dict[str, Any] = {"log": log.name, "vehicle": vlog.vehicle, "compass": compass, "n_fit": half,
                           "n_heldout": n - half}
    yaw = df["yaw_deg"].to_numpy()[:half]
    yaw = yaw[np.isfinite(yaw)]
    unwrapped = np.degrees(np.unwrap(np.radians(yaw))) if len(yaw) else np.zeros(1)
    row["yaw_span_deg"] = float(np.ptp(np.percentile(unwrapped, [5, 95])))  # an EKF's yaw reset is not a turn
    row["tilt_max_deg"] = float(np.nanmax(np.abs(df[["pitch_deg", "roll_deg"]].to_numpy()))) if ok.any() else 0.0
    if gps is None or n < 60 or not ok.any():
        row["note"] = "no GPS fix, attitude or too few samples"
        return row
    held = ArduPilotCompass.from_parameters(params, compass - 1)
    R0 = held.rotation
    for column in ("current_A", "throttle"):  # rows where a motor channel is missing cannot be corrected by it
        if column in df:
            ok &= np.isfinite(df[column].to_numpy())
    test = np.arange(half, n)
    test = test[ok[test]]
    raw_chip = mag.field[test] @ R0  # the firmware's input: R0^T v
    trim = np.degrees([params.get("AHRS_TRIM_Z", 0.0), params.get("AHRS_TRIM_Y", 0.0), params.get("AHRS_TRIM_X", 0.0)])
    att = df[["yaw_deg", "pitch_deg", "roll_deg"]].to_numpy()[test] + trim
    ned = np.asarray(igrf(gps["lat_deg"], gps["lon_deg"], gps["alt_m"], gps["date"]).ned_nT) / 100.0
    ef = mavextra.expected_earth_field_lat_lon(gps["lat_deg"], gps["lon_deg"])
    magfit_field = np.array([ef.x, ef.y, ef.z])
    declination = mavextra.get_mag_field_ef(gps["lat_deg"], gps["lon_deg"])[0]
    channels = {"current": df["current_A"].to_numpy()[test] if "current_A" in df else None,
                "throttle": df["throttle"].to_numpy()[test] if "throttle" in df else None}

    absent = absent_features("ardupilot", params)  # what the log's firmware lacks, it ignores: judged as loaded
    row["absent"] = list(absent)

    def judge(p: dict[str, float]) -> tuple[float, float]:
        p = without_features("ardupilot", p, absent)
        loaded = ArduPilotCompass.from_parameters({**params, **p}, compass - 1)
        return _errors(loaded, raw_chip, channels.get(loaded.motor_type or ""), att, ned, magfit_field,
                       declination)

    row["before"] = judge({})
    t_mid = float(mag.time_s[half]) * 1e6
    cut = work / f"{log.stem}-half.bin"
    instanced = _first_half_copy(log, t_mid, cut)
    if not magfit:
        results = {}
        row["magfit_note"] = "not run"
    elif instanced and compass > 1:  # MAGFit reads MAGn messages: a 4.1+ log's other instances are not its to fit
        results: dict[str, dict[str, float]] = {}
        row["magfit_note"] = "MAGFit fits only instance 0 of a 4.1+ log (MAG with an instance field)"
    else:
        results = _run_magfit(cut, params, "current_A" in df and np.ptp(df["current_A"].dropna()) > 0,
                              mag=1 if instanced else compass)
    best = None
    for name, p in results.items():
        if "_failed" in p:
            row[f"magfit_{name}"] = "failed"
            continue
        e = judge(p)
        row[f"magfit_{name}"] = e
        if best is None or e[0] < best[1][0]:
            best = (name, e)
    row["magfit_best"] = best
    cal, param = work / f"{log.stem}-trimag.json", work / f"{log.stem}-trimag.param"
    fit = subprocess.run([sys.executable, "-m", "trimag", "fit", str(log), "--sensor", str(compass), "--target",
                          "ardupilot", "--rows", f"0:{half}", "--json", "-o", str(cal)], capture_output=True, text=True)
    row["trimag_exit"] = fit.returncode
    if fit.returncode != 0:
        row["trimag"] = fit.stderr.strip().splitlines()[-1]
        return row
    summary = json.loads(fit.stdout)
    row["trimag_verdict"] = summary.get("firmware", {}).get("verdict")
    exp = subprocess.run([sys.executable, "-m", "trimag", "export", str(cal), "--to", "ardupilot", "-o", str(param)],
                         capture_output=True, text=True)
    if exp.returncode != 0:
        row["trimag"] = exp.stderr.strip()
        return row
    p = _params(param)
    row["trimag_level"] = f"{summary['firmware']['level']}" + (f"+{summary['firmware']['motor_type']}"
                                                               if summary["firmware"]["motor_type"] else "")
    row["trimag"] = judge(p)
    return row


def _table(rows: list[dict[str, Any]]) -> str:
    lines = ["| log | vehicle | fit / held-out samples | before | MAGFit (best variant) | trimag (level) |",
             "|---|---|---|---|---|---|"]

    def cell(e: Any) -> str:
        return f"{e[0]:.1f} / {e[1]:.1f}" if isinstance(e, tuple) else str(e)

    for r in rows:
        best = r.get("magfit_best")
        mf = f"{cell(best[1])} ({best[0]})" if best else "failed"
        tr = f"{cell(r['trimag'])} ({r.get('trimag_level', '-')})" if "trimag" in r else r.get("note", "")
        lines.append(f"| {r['log']} | {r.get('vehicle')} | {r['n_fit']} / {r['n_heldout']} | "
                     f"{cell(r.get('before', '-'))} | {mf} | {tr} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("logs", nargs="+", type=Path)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for log in args.logs:
            row = compare(log, Path(tmp))
            print(json.dumps(row, default=str), flush=True)
            rows.append(row)
    text = ("held-out (second half) field error, mGauss: MAGFit's cost (mean, heading from the corrected field) / "
            "vector RMS against IGRF rotated by ATT\n\n" + _table(rows) + "\n")
    print(text)
    if args.out:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
