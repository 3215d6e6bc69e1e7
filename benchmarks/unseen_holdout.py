"""trimag against a plain algebraic fit on real logs it was never tuned to: held-out halves (issue 32).

    python benchmarks/unseen_holdout.py --data /path/to/unseen [--out table.md]

For each log of :data:`LOGS` found under ``--data`` (the files are not in the repository: several have no licence;
where each comes from is in the table), as a new user would run it:

* the verdict of ``trimag fit FILE`` with no option (exit code, first line on stderr), and with the arguments the log
  needs (``ARGS``: columns, unit, format) on the whole log;
* held-out halves: ``trimag fit FILE ARGS --rows 0:N/2`` (its verdict), then ``trimag evaluate CAL FILE ARGS --rows
  N/2:N`` (no reference: the spread of ``|B|`` on the held-out half, before and after);
* the same halves with a plain algebraic fit: the unconstrained quadric (9 parameters, least squares on centred and
  scaled samples, the smallest right singular vector), fitted on the first half, its ``|W (x - c)|`` on the second.

Spreads are given in % of the field: the raw data's and trimag's by trimag's fitted F on the first half (or, when
trimag refuses that half, the raw data's by the algebraic fit's radius ``det(W)^(-1/3)``), the algebraic fit's as the
relative spread of its ``|W (x - c)|``. Nothing here is tuned to these logs.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from trimag.io import read_samples

#: name, file under --data, the arguments the log needs, source (repository@commit:path), licence
LOGS: list[tuple[str, str, list[str], str, str]] = [
    ("wrona-fxos8700", "wrona-fxos8700/mag-readings.txt", ["--units", "uT"],
     "michaelwro/mag-cal-example@226e2e6:examples/mag-readings.txt", "none"),
    ("gyrolib-rahrs", "gyrolib-rahrs/calibrationGyroLib.csv", ["--columns", "Mx,My,Mz", "--units", "counts"],
     "cran/RAHRS@0132d36:data/calibrationGyroLib.RData (as CSV)", "GPL (>= 3)"),
    ("missionbay-animaltrack", "missionbay-animaltrack/missionbay_calib2.csv",
     ["--columns", "mx_raw,my_raw,mz_raw", "--units", "counts"],
     "cran/animalTrack@c4e2b0e:data/missionbay_calib2.rda (as CSV)", "GPL (>= 2)"),
    ("csli-ak09940", "csli-ak09940/data2.csv", ["--units", "counts"], "z-devin/CSLI@2ce119b:data2.csv", "none"),
    ("ybabs-9axis", "ybabs-9axis/magnetometer.csv", ["--columns", "6,7,8", "--units", "counts"],
     "ybabs/MagCalib@1e2fe5a:magnetometer.csv", "none"),
    ("simorxb-phone", "simorxb-phone/MagnetometerUncalibrated.csv", [],
     "simorxb/quaternion-complementary-filter@8b7339a:MagnetometerUncalibrated.csv", "MIT"),
    ("emma-hmc5883l", "emma-hmc5883l/mag_uT.csv", ["--columns", "bx_uT,by_uT,bz_uT"],
     "emmaghita/esp32-magnetometer@3c6f3a1:mag_uT.csv", "none"),
    ("erle-copter", "erle-copter/218.BIN", [], "erlerobot/logs@3f7d4a0:pxf/copter/5-12-2014/218.BIN", "none"),
    ("sibi-matlabmobile", "sibi-matlabmobile/mag.csv", ["--units", "uT"],
     "SibiAkkash/IMU-robot-controller@262a630:data/mag.csv", "none"),
    ("oak-phone", "oak-phone/magnetometer.csv", ["--columns", "1,2,3", "--units", "uT"],
     "AustrianOakvn/Heading_Estimation@7e20fdd:data/20-10-2020/magnetometer.csv", "none"),
    ("rasteiro-eV50p-LSM9DS0", "rasteiro-robot/eV50p_Seq3_LSM9DS0.mat", ["--var", "SENSmag", "--units", "uT"],
     "miguelrasteiro/IMU_dataset@d4b4ca2:DataSets/eV50p/Sequencia3/LSM9DS0.mat", "MIT, but research-only note"),
    ("rasteiro-eV50p-MPU9150", "rasteiro-robot/eV50p_Seq3_MPU9150.mat", ["--var", "SENSmag", "--units", "mG"],
     "miguelrasteiro/IMU_dataset@d4b4ca2:DataSets/eV50p/Sequencia3/MPU9150.mat", "MIT, but research-only note"),
    ("rasteiro-eV50p-RM3100", "rasteiro-robot/eV50p_Seq3_MPU6500RM3100.mat", ["--var", "SENSmag", "--units", "uT"],
     "miguelrasteiro/IMU_dataset@d4b4ca2:DataSets/eV50p/Sequencia3/MPU6500RM3100.mat",
     "MIT, but research-only note"),
    ("rasteiro-V300-LSM9DS0", "rasteiro-robot/V300_Seq1_LSM9DS0.mat", ["--var", "SENSmag", "--units", "uT"],
     "miguelrasteiro/IMU_dataset@d4b4ca2:DataSets/V_300/Sequencia1/LSM9DS0.mat", "MIT, but research-only note"),
]


def _run(*args: str) -> tuple[int, str, dict | None]:
    p = subprocess.run(["trimag", *args], capture_output=True, text=True)
    lines = [ln.strip() for ln in p.stderr.splitlines() if ln.strip()]
    verdict = next((ln for ln in lines if ln.startswith("trimag:") or "warning:" in ln[:20]), "(no warning)")
    try:
        out = json.loads(p.stdout) if p.stdout.strip() else None
    except json.JSONDecodeError:
        out = None
    return p.returncode, verdict, out


def algebraic_fit(B: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """``(W, c)`` with ``|W (x - c)| = 1`` on the least-squares quadric through ``B`` (N, 3); None when it is not an
    ellipsoid."""
    c0 = B.mean(axis=0)
    s = float(np.abs(B - c0).max())
    u = (B - c0) / s
    x, y, z = u.T
    D = np.column_stack([x * x, y * y, z * z, 2 * y * z, 2 * x * z, 2 * x * y, 2 * x, 2 * y, 2 * z, np.ones(len(u))])
    a, b, c, f, g, h, p, q, r, d = np.linalg.svd(D, full_matrices=False)[2][-1]
    M = np.array([[a, h, g], [h, b, f], [g, f, c]])
    if np.trace(M) < 0:
        M, p, q, r, d = -M, -p, -q, -r, -d
    try:
        centre = -np.linalg.solve(M, [p, q, r])
        k = float(centre @ M @ centre - d)
        L = np.linalg.cholesky(M / k)
    except (np.linalg.LinAlgError, ZeroDivisionError):
        return None
    return L.T / s, c0 + s * centre


def _pct(x: float | None) -> str:
    return "–" if x is None else f"{x:.2f} %"


def _short(line: str, width: int = 110) -> str:
    line = line.replace("trimag: ", "").replace("|", "/")
    return line if len(line) <= width else line[: width - 1] + "…"


def row(data: Path, name: str, file: str, args: list[str], source: str, licence: str) -> str:
    path = data / file
    B = read_samples(path, **_read_arguments(args)).field
    n = len(B)
    half = f"0:{n // 2}"
    rest = f"{n // 2}:{n}"
    code0, line0, _ = _run("fit", str(path))
    code1, line1, _ = _run("fit", str(path), *args)
    with tempfile.TemporaryDirectory() as tmp:
        cal = str(Path(tmp) / "cal.json")
        code2, line2, fitted = _run("fit", str(path), *args, "--rows", half, "--json", "-o", cal)
        held = _run("evaluate", cal, str(path), *args, "--rows", rest, "--json")[2] if code2 == 0 else None
    alg = algebraic_fit(B[: n // 2])
    if alg is not None:
        W, c = alg
        radius = float(np.linalg.det(W)) ** (-1.0 / 3.0)
        test = np.linalg.norm((B[n // 2:] - c) @ W.T, axis=1)
        alg_txt = f"{100 * test.std() / test.mean():.2f} %"
        raw_txt = f"{100 * np.linalg.norm(B[n // 2:], axis=1).std() / radius:.2f} %"
    else:
        alg_txt, raw_txt = "not an ellipsoid", "–"
    if held is not None and fitted is not None:  # the raw spread in % of trimag's F when there is one
        F = fitted["reference"]["value"]
        raw_txt = f"{100 * held['std_norm_before'] / F:.2f} %"
        worse = " (worse than raw)" if held["worse_than_raw"] else ""
        trimag_txt = f"{100 * held['std_norm_after'] / F:.2f} %{worse}"
    else:
        trimag_txt = f"refused ({code2})"
    return (f"| {name} | `{source}` | {licence} | {n} | {code0}: {_short(line0)} | `{' '.join(args) or '(none)'}`: "
            f"{code1}: {_short(line1)} | {code2}: {_short(line2, 80)} | {raw_txt} | {trimag_txt} | {alg_txt} |")


def _read_arguments(args: list[str]) -> dict[str, str]:
    keys = {"--columns": "columns", "--var": "var", "--format": "fmt"}
    return {keys[a]: v for a, v in zip(args[::2], args[1::2], strict=False) if a in keys}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help="folder of the logs (LOGS gives each one's file under it)")
    parser.add_argument("--out", help="write the markdown table here too")
    a = parser.parse_args()
    data = Path(a.data)
    lines = ["| log | source | licence | N | `trimag fit FILE`: exit, first line | with ARGS, whole log: exit, first "
             "line | first half, ARGS: exit, first line | held-out half: raw spread | trimag (first-half fit) | plain "
             "algebraic (first-half fit) |", "|" + "---|" * 10]
    for name, file, args, source, licence in LOGS:
        if (data / file).exists():
            lines.append(row(data, name, file, args, source, licence))
            print(lines[-1], flush=True)
    if a.out:
        Path(a.out).write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
