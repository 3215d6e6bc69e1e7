"""Do the reported sigmas hold on real logs? The interleaved-halves test of issue 22.

    python benchmarks/honest_sigma.py [--shared ../shared/data] [--method ml]

Each real log of the shared data folder is cut into blocks of 50 consecutive samples; the even blocks and the odd
blocks are fitted separately (two interleaved halves) and, separately, the first and the second half. For each
pair, ``z = (p1 - p2) / sqrt(s1^2 + s2^2)`` over the model's parameters (the reported sigmas ``s``); its RMS should
be about 1 when the sigmas hold. First half against second half also shows whether the log drifted.
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import numpy as np
import scipy.io

import trimag
import trimag.errors

ROOT = Path(__file__).resolve().parents[1]


def _logs(shared: Path) -> dict[str, tuple[np.ndarray, str]]:
    from trimag.io import read_samples

    def csv(path: Path, cols: str) -> np.ndarray:
        return read_samples(path, columns=cols).field

    out: dict[str, tuple[np.ndarray, str]] = {}
    q = shared / "qmc5883l-suarez" / "noisy_raw_data.csv"
    if q.exists():
        out["qmc5883l noisy (counts)"] = (csv(q, "mx,my,mz"), "counts")
    h = shared / "hmc5883l-sunsided" / "full-sphere_hmc5883l_compass.mat"
    if h.exists():
        out["hmc5883l full sphere (G)"] = (read_samples(h, columns="1,2,3").field, "G")
    c = shared / "ck-explorer-accmag" / "acc_mag_log.csv"
    if c.exists():
        out["ck-explorer acc_mag (G)"] = (csv(c, "mx,my,mz"), "G")
    s = shared / "smartphone-kritiksoman" / "data_mag.txt"
    if s.exists():
        out["smartphone (uT?)"] = (csv(s, "x,y,z"), "uT")
    for name in ("01_undisturbed_slow_rotation_A", "06_undisturbed_fast_rotation_A"):
        b = shared / "broad" / f"{name}.mat"
        if b.exists():
            out[f"BROAD {name[:2]} (uT)"] = (np.asarray(scipy.io.loadmat(b)["imu_mag"], float), "uT")
    return out


def _fit(B: np.ndarray, unit: str, method: str) -> tuple[np.ndarray, np.ndarray, float]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = trimag.fit(B, model="ellipsoid", method=method, units=unit)
    std = cal.uncertainty["param_std"]
    names = [n for n in std if n != "F" and n in cal.params]
    p = np.array([cal.params[n] for n in names])
    s = np.array([np.nan if std[n] is None else std[n] for n in names])
    return p, s, float(cal.uncertainty.get("inflation", {}).get("total", 1.0))


def _z(a: tuple[np.ndarray, np.ndarray, float], b: tuple[np.ndarray, np.ndarray, float]) -> float:
    z = (a[0] - b[0]) / np.sqrt(a[1] ** 2 + b[1] ** 2)
    z = z[np.isfinite(z)]
    return float(np.sqrt(np.mean(z**2)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--shared", default=str(ROOT.parent / "shared" / "data"))
    parser.add_argument("--method", default="ml")
    parser.add_argument("--block", type=int, default=50)
    args = parser.parse_args()
    print(f"{'log':30s}{'N':>7}{'RMS z interleaved':>19}{'RMS z 1st/2nd half':>20}{'inflation':>11}")
    for name, (B, unit) in _logs(Path(args.shared)).items():
        B = B[np.isfinite(B).all(axis=1)]
        blocks = (np.arange(len(B)) // args.block) % 2
        half = np.arange(len(B)) < len(B) // 2
        try:
            even, odd = _fit(B[blocks == 0], unit, args.method), _fit(B[blocks == 1], unit, args.method)
        except trimag.errors.TrimagError as exc:
            print(f"{name:30s}{len(B):>7}   not identifiable: {str(exc)[:60]}")
            continue
        try:
            first, second = _fit(B[half], unit, args.method), _fit(B[~half], unit, args.method)
            z_halves = f"{_z(first, second):>20.2f}"
        except trimag.errors.TrimagError:
            z_halves = f"{'(a half unidentified)':>20}"
        print(f"{name:30s}{len(B):>7}{_z(even, odd):>19.2f}{z_halves}{even[2]:>11.2f}")


if __name__ == "__main__":
    main()
