"""The lab user's two commands on BROAD (issue 31, item 3; the tables are in docs/vehicle.md, "Measured: BROAD").

BROAD (../shared/data/broad, CC BY 4.0) keeps the magnetometer and the optical attitudes in one .mat file; a lab
user has them as two files with their own time columns. This harness writes each trial so (``NN_mag.csv``: time,
mx, my, mz in uT; ``NN_att.csv``: t_att, the OptiTrack quaternion qw, qx, qy, qz (body -> ENU) and its position px,
py, pz in m, without the rows where the tracking was lost) and runs the commands a user would run, printing each:

1. ``trimag fit 01_mag.csv --model interference12 --attitude-file 01_att.csv ... --option estimate_background=true
   --option estimate_lag=true`` (no background flag: none is known indoors), then ``trimag evaluate`` of that
   calibration on every trial (the held-out field-direction error against the fitted background stored in it);
   the same at lag 0 for comparison.
2. The background's gradient (``--position-columns px,py,pz``): each trial's first half fitted (background and
   lag) with and without it, its second half held out.

    python benchmarks/broad_lab.py --broad ../shared/data/broad [--out DIR] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

TRIALS = ("01", "02", "03", "06")


def trimag_command() -> list[str]:
    exe = shutil.which("trimag") or str(Path(sys.executable).parent / "trimag")
    return [exe]


def run(*args: str) -> dict[str, Any]:
    """One ``trimag`` command (printed), its JSON output."""
    cmd = [*trimag_command(), *map(str, args), "--json"]
    print("$ trimag " + " ".join(Path(a).name if "/" in str(a) else str(a) for a in args), file=sys.stderr)
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"exit {proc.returncode}: {proc.stderr}")
    return dict(json.loads(proc.stdout))


def write_trial(folder: Path, out: Path, trial: str) -> tuple[Path, Path, int]:
    """The two files of one trial; returns their paths and the number of attitude rows dropped (tracking lost)."""
    import scipy.io as sio

    d = sio.loadmat(next(folder.glob(f"{trial}_*.mat")))
    fs = float(d["sampling_rate"].ravel()[0])
    t = np.arange(len(d["imu_mag"])) / fs
    m, q, p = d["imu_mag"], d["opt_quat"], d["opt_pos"]
    mag, att = out / f"{trial}_mag.csv", out / f"{trial}_att.csv"
    pd.DataFrame({"time": t, "mx": m[:, 0], "my": m[:, 1], "mz": m[:, 2]}).to_csv(mag, index=False)
    ok = np.isfinite(q).all(axis=1) & np.isfinite(p).all(axis=1)
    pd.DataFrame({"t_att": t[ok], "qw": q[ok, 0], "qx": q[ok, 1], "qy": q[ok, 2], "qz": q[ok, 3], "px": p[ok, 0],
                  "py": p[ok, 1], "pz": p[ok, 2]}).to_csv(att, index=False)
    return mag, att, int((~ok).sum())


def sync(att: Path) -> list[str]:
    return ["--attitude-file", str(att), "--quaternion-columns", "qw,qx,qy,qz", "--quaternion-frame", "enu",
            "--time-column", "time", "--attitude-time-column", "t_att"]


def lag_table(files: dict[str, tuple[Path, Path, int]], out: Path) -> dict[str, Any]:
    """Command 1: trial 01 fitted (background and lag), every trial evaluated; the same at lag 0."""
    mag, att, _ = files["01"]
    fit_args = [mag, "--units", "uT", "--model", "interference12", *sync(att), "--option", "estimate_background=true"]
    lagged = run("fit", *fit_args, "--option", "estimate_lag=true", "--option", "max_lag=0.3", "-o", out / "cal.json")
    plain = run("fit", *fit_args, "-o", out / "cal_lag0.json")
    rows = {}
    for trial, (m, a, _) in files.items():
        rows[trial] = {name: run("evaluate", out / cal, m, *sync(a))["angular_error_rms_deg"]
                       for name, cal in (("lag", "cal.json"), ("lag0", "cal_lag0.json"))}
    sync_info = lagged["time_sync"]
    return {"lag_s": sync_info["lag_s"], "lag_std_s": sync_info["lag_std_s"], "lag_rounds": sync_info["lag_rounds"],
            "background_ned": lagged["diagnostics"]["background_ned"], "rms_at_lag": sync_info["rms_at_lag"],
            "rms_at_zero": sync_info["rms_at_zero"], "vector_rms_after": plain["diagnostics"].get("residual_rms_axis"),
            "held_out_deg": rows}


def gradient_table(files: dict[str, tuple[Path, Path, int]], out: Path) -> dict[str, Any]:
    """Command 2 with positions: each trial's first half fitted (background and lag) with and without the gradient,
    its second half held out."""
    rows = {}
    for trial, (mag, att, _) in files.items():
        n = len(pd.read_csv(mag, usecols=["time"]))
        half = n // 2
        base = [mag, "--units", "uT", "--model", "interference12", *sync(att), "--option",
                "estimate_background=true", "--option", "estimate_lag=true", "--option", "max_lag=0.3", "--rows",
                f"0:{half}"]
        fits = {"without": run("fit", *base, "-o", out / f"{trial}_first.json"),
                "with": run("fit", *base, "--position-columns", "px,py,pz", "-o", out / f"{trial}_first_grad.json")}
        row: dict[str, Any] = {}
        for name, cal in (("without", f"{trial}_first.json"), ("with", f"{trial}_first_grad.json")):
            fitted = run("evaluate", out / cal, mag, *sync(att), "--rows", f"0:{half}")
            held = run("evaluate", out / cal, mag, *sync(att), "--rows", f"{half}:{n}")
            row[name] = {"fitted_deg": fitted["angular_error_rms_deg"], "held_out_deg": held["angular_error_rms_deg"],
                         "vector_rms_fitted": fitted["rms_after"], "vector_rms_held_out": held["rms_after"]}
        g = fits["with"]["diagnostics"]["background_gradient"]
        row["gradient"] = {"terms": g["terms"], "terms_std": g["terms_std"], "span_m": g["position_span_m"],
                           "lag_s": fits["with"]["time_sync"]["lag_s"]}
        rows[trial] = row
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--broad", type=Path, required=True, help="BROAD folder (../shared/data/broad)")
    p.add_argument("--out", type=Path, help="where to write the files and calibrations (default: a temporary folder)")
    p.add_argument("--json", type=Path, help="write the results here")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp)
        out.mkdir(parents=True, exist_ok=True)
        files = {trial: write_trial(args.broad, out, trial) for trial in TRIALS}
        results = {"dropped_attitude_rows": {t: f[2] for t, f in files.items()}, "lag": lag_table(files, out),
                   "gradient": gradient_table(files, out)}
    lag = results["lag"]
    print(f"lag (attitude - magnetometer) {lag['lag_s']:+.4f} +- {lag['lag_std_s']:.2g} s; background "
          f"{np.round(lag['background_ned'], 3).tolist()} uT")
    print("| trial | fit at lag 0 | fit at the estimated lag |\n|---|---|---|")
    for trial, r in lag["held_out_deg"].items():
        print(f"| {trial} | {r['lag0']:.2f} deg | {r['lag']:.2f} deg |")
    print("| trial | first half, without / with gradient | second half (held out), without / with |\n|---|---|---|")
    for trial, r in results["gradient"].items():
        print(f"| {trial} | {r['without']['fitted_deg']:.2f} / {r['with']['fitted_deg']:.2f} deg | "
              f"{r['without']['held_out_deg']:.2f} / {r['with']['held_out_deg']:.2f} deg |")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
