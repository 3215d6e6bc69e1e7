"""Peak memory of `trimag fit` per byte of a CSV log, for short and for long rows (issue 41, item 10).

    python benchmarks/fit_memory.py [--mb 30,100] [--out FILE.csv]

Writes, in a temporary folder, CSV logs of about the sizes given (MB): "short" rows of three integers (a sensor's
counts on a sphere of radius 500, many rows repeated: 10-13 bytes per row), "ones" rows that are all `1,2,3` (the
issue's case: 6 bytes per row, every row a duplicate; the fit refuses it, exit 3, after reading), "timed" rows of a
sample number and the three integers (``t,x,y,z``: about 20 bytes per row) and "long" rows of twelve columns with
six decimals (a lab log with time, temperature, accelerometer...: about 110 bytes per row).
Each log is fitted by `trimag fit LOG -q` in a fresh process; its peak resident memory is read with os.wait4 (that
process alone). The baseline is the same command on a 400-row log (the interpreter and its libraries). Printed
and written per file: size, rows, peak MB, and (peak - baseline) / size, the bytes of memory per byte of input.
The machine is shared: keep the sizes at most a few hundred MB.
"""

from __future__ import annotations

import argparse
import csv
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np


def _sphere_counts(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return np.round(u * 500.0 + [30.0, -20.0, 10.0]).astype(np.int64)


def write_log(path: Path, kind: str, mb: float, seed: int = 0) -> int:
    """A CSV log of ``kind`` (``short``, ``ones``, ``timed``, ``long``) of about ``mb`` megabytes; returns its rows."""
    target = int(mb * 1e6)
    rows = 0
    with path.open("w") as fh:
        if kind == "long":
            fh.write("t,x,y,z,temp,ax,ay,az,gx,gy,gz,current\n")
        elif kind == "timed":
            fh.write("t,x,y,z\n")
        else:
            fh.write("x,y,z\n")
        block = 200_000
        while fh.tell() < target:
            if kind == "ones":
                fh.write("1,2,3\n" * block)
            elif kind == "short":
                np.savetxt(fh, _sphere_counts(block, seed + rows), fmt="%d", delimiter=",")
            elif kind == "timed":
                counts = _sphere_counts(block, seed + rows)
                np.savetxt(fh, np.column_stack([rows + np.arange(block), counts]), fmt="%d", delimiter=",")
            else:
                rng = np.random.default_rng(seed + rows)
                xyz = _sphere_counts(block, seed + rows).astype(float) + rng.normal(0, 0.5, (block, 3))
                other = rng.normal(0, 1, (block, 8))
                t = (rows + np.arange(block)) * 0.01
                np.savetxt(fh, np.column_stack([t, xyz, other]), fmt="%.6f", delimiter=",")
            rows += block
    return rows


def peak_mb(path: Path) -> tuple[float, int]:
    """Peak resident memory (MB) of ``trimag fit PATH -q`` in a fresh process, and its exit code."""
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    proc = subprocess.Popen([sys.executable, "-m", "trimag", "fit", str(path), "-q"], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, env=env)
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return usage.ru_maxrss / 1024.0, proc.returncode


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mb", default="30,100", help="sizes of the logs, MB (comma-separated)")
    parser.add_argument("--kinds", default="short,ones,timed,long")
    parser.add_argument("--out", help="also write the table as CSV")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        small = Path(tmp) / "small.csv"
        np.savetxt(small, _sphere_counts(400, 1), fmt="%d", delimiter=",", header="x,y,z", comments="")
        base, _ = peak_mb(small)
        print(f"baseline (400 rows): {base:.0f} MB")
        table = []
        for mb in (float(v) for v in args.mb.split(",")):
            for kind in args.kinds.split(","):
                path = Path(tmp) / f"{kind}-{mb:g}.csv"
                rows = write_log(path, kind, mb)
                size = path.stat().st_size
                peak, code = peak_mb(path)
                path.unlink()
                row = {"kind": kind, "mb": round(size / 1e6, 1), "rows": rows, "bytes_per_row": round(size / rows, 1),
                       "exit": code, "peak_mb": round(peak), "baseline_mb": round(base),
                       "peak_bytes_per_input_byte": round((peak - base) * 1048576 / size, 1)}
                table.append(row)
                print(row, flush=True)
    if args.out:
        with open(args.out, "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(table[0]))
            writer.writeheader()
            writer.writerows(table)


if __name__ == "__main__":
    main()
