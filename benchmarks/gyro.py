"""The gyro-aided fit on real logs, against ``ml`` and MAGYC on the same held-out halves (issue 31; the table is in
docs/method-gyro.md).

Every log is cut at its middle sample: each method is fitted on the first half and judged on the second.

* **Direction error** (logs with a truth attitude): the held-out corrected field's directions ``y_i``, turned by the
  attitude ``C_i`` (body -> the truth frame) after one rotation ``R`` (magnetometer -> body), should all be the
  room's one field direction ``u``. ``R`` and ``u`` (5 numbers) are fitted on the held-out half itself (the best
  rotation into the motion-capture frame: every method gets its own), and the error is the RMS angle between
  ``C_i R y_i`` and ``u``, degrees, on at most 6000 evenly spread held-out samples.
  The truth is taken at the magnetometer's instants: the lag between the two clocks (a magnetometer's filter delays
  its output) is estimated on the held-out raw samples and applied for every method alike
  (:func:`truth_at_magnetometer`).
* **|B| std**: the standard deviation of the held-out corrected magnitude (every log; the unit of the log).

Methods: ``ml`` (trimag's magnitude-only default), ``gyro`` (trimag's gyro-aided fit, defaults), MAGYC-LS and
MAGYC-NLS (``pip install magyc`` 1.0.0, Rodríguez-Martín et al.; run in their own interpreter, ``--magyc``, since
the package needs numpy < 2; their corrected output is rebuilt as ``(m - hi) @ inv(si).T``: the package's own is
scrambled by a reshape, its (N, 3) result laid out column by column). MAGYC takes one time vector for both sensors:
a gyroscope with its own clock is interpolated to the magnetometer's stamps for it; trimag's fit integrates it
on its own stamps.

Logs: BROAD trials 01, 02, 03, 06 (``--broad``, ../shared/data/broad, CC BY 4.0: myon aktos-t, uT, 285.7 Hz,
OptiTrack attitude); the robot logs of miguelrasteiro/IMU_dataset (``--unseen DIR``: a folder of your own; research
use only, not redistributed, not in ../shared: an ABB robot turning boards with an LSM9DS0, an MPU9150 and an RM3100
beside an MPU6500; the robot's attitude as truth); the simorxb Sensor Logger phone export (MIT; no truth attitude).

    python benchmarks/gyro.py --broad ../shared/data/broad --unseen UNSEEN_DIR \\
        --magyc MAGYC_VENV/bin/python --json docs/results/gyro-heldout.json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

import trimag
from trimag.estimators.gyro import GyroAided
from trimag.fields.gyro import AngularRate


@dataclass
class Log:
    """One log: magnetometer times and samples, the gyroscope (own stamps, rad/s), the truth attitude (body ->
    truth frame, per magnetometer sample; None without one) and, for MAGYC, the magnetometer in the gyroscope's
    axes (when a board's documentation gives the permutation)."""

    name: str
    t: np.ndarray
    mag: np.ndarray
    t_gyro: np.ndarray
    gyro: np.ndarray
    truth: Rotation | None
    unit: str
    mag_for_magyc: np.ndarray | None = None

    @property
    def same_rows(self) -> bool:
        return self.t_gyro is self.t


def broad(folder: Path, trial: str) -> Log:
    import scipy.io as sio

    path = next(folder.glob(f"{trial}_*.mat"))
    d = sio.loadmat(path)
    fs = float(d["sampling_rate"].ravel()[0])
    t = np.arange(len(d["imu_mag"])) / fs
    q = d["opt_quat"]
    ok = np.isfinite(q).all(axis=1)
    truth = Rotation.from_quat(np.where(ok[:, None], q, [1.0, 0, 0, 0]), scalar_first=True)
    log = Log(f"BROAD {path.stem[:2]} ({path.stem[3:].replace('_', ' ')})", t, d["imu_mag"].astype(float), t,
              d["imu_gyr"].astype(float), truth, "uT")
    log.truth_ok = ok  # type: ignore[attr-defined]
    return log


#: The rasteiro boards: file, the gyroscope's unit, the magnetometer's axes in the gyroscope's (TestScript.m).
RASTEIRO = {
    "eV50p_Seq3_MPU6500RM3100": ("deg/s", lambda m: np.column_stack([-m[:, 1], -m[:, 0], -m[:, 2]])),
    "eV50p_Seq3_MPU9150": ("deg/s", None),
    "eV50p_Seq3_LSM9DS0": ("rad/s", None),
    "V300_Seq1_LSM9DS0": ("rad/s", None),
}


def rasteiro(folder: Path, name: str) -> Log:
    import scipy.io as sio

    unit, permute = RASTEIRO[name]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        d = sio.loadmat(folder / "rasteiro-robot" / f"{name}.mat")
    m, g = d["SENSmag"].T.astype(float), d["SENSgyro"].T.astype(float)
    q, t = d["ABBquaternion"].T, d["MATLABtime"].ravel()
    ok = (np.linalg.norm(m, axis=1) > 0) & np.isfinite(m).all(1) & np.isfinite(g).all(1) & np.isfinite(q).all(1)
    ok &= np.linalg.norm(q, axis=1) > 0.5
    idx = np.flatnonzero(ok)
    idx = idx[np.concatenate([[True], np.diff(t[idx]) > 0])]
    m, g, q, t = m[idx], g[idx], q[idx], t[idx]
    if unit == "deg/s":
        g = np.radians(g)
    truth = Rotation.from_quat(q, scalar_first=True).inv()  # the robot's quaternion is world -> tool
    return Log(f"robot {name.replace('_', ' ')}", t, m, t, g, truth, "uT",
               permute(m) if permute is not None else None)


def simorxb(folder: Path) -> Log:
    import pandas as pd

    base = folder / "simorxb-phone"
    mag = pd.read_csv(base / "MagnetometerUncalibrated.csv")
    gyr = pd.read_csv(base / "GyroscopeUncalibrated.csv")
    t, tg = mag["seconds_elapsed"].to_numpy(float), gyr["seconds_elapsed"].to_numpy(float)
    inside = (t >= tg[0]) & (t <= tg[-1])
    return Log("phone simorxb (Sensor Logger)", t[inside], mag[["x", "y", "z"]].to_numpy(float)[inside], tg,
               gyr[["x", "y", "z"]].to_numpy(float), None, "uT")


def direction_error(y: np.ndarray, truth: Rotation, max_samples: int = 6000) -> float:
    """RMS angle (degrees) between ``C_i R y_i`` and one direction ``u``, with ``R`` and ``u`` fitted (module
    docstring): alternating Wahba / mean-direction steps from the 24 axis-aligned rotations, the best polished by
    least squares on the angles."""
    idx = np.linspace(0, len(y) - 1, min(len(y), max_samples)).astype(int)
    d = y[idx] / np.linalg.norm(y[idx], axis=1, keepdims=True)
    C = truth[idx]

    def angles(p: np.ndarray) -> np.ndarray:
        w = C.apply(Rotation.from_rotvec(p[:3]).apply(d))
        u = np.array([np.cos(p[4]) * np.cos(p[3]), np.cos(p[4]) * np.sin(p[3]), np.sin(p[4])])
        return np.arctan2(np.linalg.norm(np.cross(w, u), axis=1), w @ u)

    best: tuple[float, np.ndarray] | None = None
    for R in Rotation.create_group("O"):
        for _ in range(10):
            u = C.apply(R.apply(d)).mean(axis=0)
            u /= np.linalg.norm(u)
            R, _ = Rotation.align_vectors(C.inv().apply(np.tile(u, (len(d), 1))), d)
        u = C.apply(R.apply(d)).mean(axis=0)
        u /= np.linalg.norm(u)
        p = np.r_[R.as_rotvec(), np.arctan2(u[1], u[0]), np.arcsin(np.clip(u[2], -1, 1))]
        cost = float(np.mean(angles(p) ** 2))
        if best is None or cost < best[0]:
            best = (cost, p)
    assert best is not None
    res = least_squares(angles, best[1])
    return float(np.degrees(np.sqrt(np.mean(res.fun**2))))


def truth_at_magnetometer(log: Log, rows: slice) -> tuple[tuple[Rotation, np.ndarray], float]:
    """The truth attitude at the held-out magnetometer samples, after the lag between the two (a magnetometer's
    output is delayed by its filter: 11 ms against BROAD's optical attitudes): the lag (truth clock - magnetometer
    clock) that best fits paper C's vector model to the raw held-out samples with a fitted background
    (:func:`trimag.vehicle.timesync.estimate_lag`, the lab workflow's own search), then slerp. The same truth for
    every method. Returns ``((attitudes, which held-out samples have one), lag)``."""
    from scipy.spatial.transform import Slerp

    from trimag.estimators.linear_vector import fit_with_background
    from trimag.vehicle.timesync import AttitudeStream, estimate_lag, interpolate_attitude

    ok = getattr(log, "truth_ok", np.ones(len(log.t), dtype=bool))
    t, m = log.t[rows], log.mag[rows]
    stream = AttitudeStream(log.t[ok], log.truth[ok])
    lag = 0.0
    for _ in range(2):  # the background at the lag, the lag against it
        rot, inside = interpolate_attitude(stream, t, lag)
        _, _, background, _ = fit_with_background(m[inside], rot, 1.0)
        lag = float(estimate_lag(m, t, stream, background, max_lag=0.1)["lag_s"])
    tq = t + lag
    keep = (tq >= stream.times[0]) & (tq <= stream.times[-1])
    return (Slerp(stream.times, stream.rotation)(tq[keep]), keep), lag


def _half(log: Log) -> tuple[slice, slice]:
    h = len(log.t) // 2
    return slice(0, h), slice(h, len(log.t))


def fit_ml(log: Log, rows: slice) -> tuple[np.ndarray, np.ndarray]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = trimag.fit(log.mag[rows], units=log.unit)
    return np.asarray(cal.matrix), np.asarray(cal.offset)


def fit_gyro(log: Log, rows: slice, estimate_lag: bool = False) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    t = log.t[rows]
    if log.same_rows and not estimate_lag:
        gyro = AngularRate.same_rows(t, log.gyro[rows])
    elif log.same_rows:  # the lag fitted: the magnetometer's first and last 0.5 s (the lag search's) left out
        inside = (t >= t[0] + 0.5) & (t <= t[-1] - 0.5)
        gyro = AngularRate(t[inside], t, log.gyro[rows], 0.0, True, log.name)
        rows = np.arange(len(log.t))[rows][inside]  # type: ignore[assignment]
    else:
        keep = (log.t_gyro >= t[0] - 1.0) & (log.t_gyro <= t[-1] + 1.0)
        gyro = AngularRate(t, log.t_gyro[keep], log.gyro[keep], 0.0, True, log.name)
        inside = (t >= gyro.gyro_time_s[0] + 0.5) & (t <= gyro.gyro_time_s[-1] - 0.5)
        gyro = AngularRate(t[inside], gyro.gyro_time_s, gyro.rate, 0.0, True, log.name)
        rows = np.flatnonzero(np.arange(len(log.t))[rows] >= 0)[inside]  # type: ignore[assignment]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = GyroAided().fit(log.mag[rows], None, units=log.unit, attitude=gyro).calibration_
    return np.asarray(cal.matrix), np.asarray(cal.offset), cal.diagnostics["gyro"]


def fit_magyc(log: Log, rows: slice, python: str) -> dict[str, tuple[np.ndarray, np.ndarray, float]]:
    """MAGYC-LS and -NLS in their own interpreter: (correction matrix inv(si), hard iron, seconds) each."""
    t = log.t[rows]
    m = (log.mag_for_magyc if log.mag_for_magyc is not None else log.mag)[rows]
    w = log.gyro[rows] if log.same_rows else np.column_stack([np.interp(t, log.t_gyro, log.gyro[:, k])
                                                               for k in range(3)])
    script = (
        "import sys, time, warnings, numpy as np\nwarnings.simplefilter('ignore')\nimport magyc\n"
        "d = np.load(sys.argv[1]); out = {}\n"
        "t0 = time.time(); hi, si, _ = magyc.magyc_ls(d['m'], d['w'], d['t']); out['ls'] = (hi, si, time.time() - t0)\n"
        "t0 = time.time(); hi, si, wb, _, _ = magyc.magyc_nls(d['m'], d['w'], d['t'])\n"
        "out['nls'] = (hi, si, time.time() - t0)\n"
        "np.savez(sys.argv[2], **{f'{k}_{n}': np.asarray(v[i]) for k, v in out.items() "
        "for i, n in enumerate(('hi', 'si', 'time'))})\n"
    )
    with tempfile.TemporaryDirectory() as tmp:
        src, dst, code = Path(tmp) / "in.npz", Path(tmp) / "out.npz", Path(tmp) / "run.py"
        np.savez(src, m=m, w=w, t=t)
        code.write_text(script)
        subprocess.run([python, str(code), str(src), str(dst)], check=True, capture_output=True)
        o = np.load(dst)
        return {k: (np.linalg.inv(o[f"{k}_si"]), o[f"{k}_hi"], float(o[f"{k}_time"])) for k in ("ls", "nls")}


def evaluate(log: Log, magyc: str | None) -> dict[str, Any]:
    fit_rows, test_rows = _half(log)
    test_mag = log.mag[test_rows]
    magyc_mag = (log.mag_for_magyc if log.mag_for_magyc is not None else log.mag)[test_rows]
    corrections: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {"raw": (np.eye(3), np.zeros(3), test_mag)}
    times: dict[str, float] = {}
    t0 = time.perf_counter()
    W, b = fit_ml(log, fit_rows)
    times["ml"] = time.perf_counter() - t0
    corrections["ml"] = (W, b, test_mag)
    t0 = time.perf_counter()
    W, b, gyro_diag = fit_gyro(log, fit_rows)
    times["gyro"] = time.perf_counter() - t0
    corrections["gyro"] = (W, b, test_mag)
    if log.same_rows:  # the same rows: the lag between the magnetometer and the gyroscope held at 0 by default
        W, b, lag_diag = fit_gyro(log, fit_rows, estimate_lag=True)
        corrections["gyro, lag fitted"] = (W, b, test_mag)
        gyro_diag = {**gyro_diag, "lag_fitted_s": lag_diag["lag_s"]}
    if magyc:
        for k, (W, b, seconds) in fit_magyc(log, fit_rows, magyc).items():
            corrections[f"MAGYC-{k.upper()}"] = (W, b, magyc_mag)
            times[f"MAGYC-{k.upper()}"] = seconds
    out: dict[str, Any] = {"log": log.name, "n_fit": fit_rows.stop, "n_test": len(test_mag), "unit": log.unit,
                           "gyro": {k: gyro_diag[k] for k in ("bias_rad_s", "lag_s", "vector_rms", "n_segments",
                                                              "lag_fitted_s") if k in gyro_diag},
                           "methods": {}}
    truth = None
    if log.truth is not None:
        truth, out["truth_lag_s"] = truth_at_magnetometer(log, test_rows)
    for name, (W, b, data) in corrections.items():
        y = (data - b) @ W.T
        row: dict[str, Any] = {"B_std": float(np.linalg.norm(y, axis=1).std()), "fit_seconds": times.get(name)}
        if truth is not None:
            rot, keep = truth
            row["direction_deg"] = direction_error(y[keep], rot)
        out["methods"][name] = row
    return out


def table(results: list[dict[str, Any]]) -> str:
    methods = ["raw", "ml", "gyro", "gyro, lag fitted", "MAGYC-LS", "MAGYC-NLS"]
    lines = ["| log | held-out samples | " + " | ".join(methods) + " |", "|---|---|" + "---|" * len(methods)]
    for r in results:
        cells = []
        for m in methods:
            v = r["methods"].get(m)
            if v is None:
                cells.append("-")
            elif "direction_deg" in v:
                cells.append(f"{v['direction_deg']:.2f} deg ({v['B_std']:.3g})")
            else:
                cells.append(f"({v['B_std']:.3g})")
        lines.append(f"| {r['log']} | {r['n_test']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--broad", type=Path, help="BROAD folder (../shared/data/broad)")
    p.add_argument("--unseen", type=Path, help="folder of the unseen logs (rasteiro-robot, simorxb-phone)")
    p.add_argument("--magyc", help="a Python with `magyc` installed (its own venv: numpy < 2)")
    p.add_argument("--json", type=Path, help="write the results here")
    args = p.parse_args(argv)
    logs: list[Log] = []
    if args.broad:
        logs += [broad(args.broad, trial) for trial in ("01", "02", "03", "06")]
    if args.unseen:
        logs += [rasteiro(args.unseen, name) for name in RASTEIRO
                 if (args.unseen / "rasteiro-robot" / f"{name}.mat").exists()]
        if (args.unseen / "simorxb-phone").exists():
            logs.append(simorxb(args.unseen))
    results = []
    for log in logs:
        r = evaluate(log, args.magyc)
        results.append(r)
        print(json.dumps({"log": r["log"], **{m: v for m, v in r["methods"].items()}}), file=sys.stderr)
    print(table(results))
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
