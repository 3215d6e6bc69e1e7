"""Reading speed and memory of a large ArduPilot DataFlash log (issue 19).

    python benchmarks/read_logs.py [--copies 340] [--log PATH]

Builds a ~100 MB binary DataFlash log by concatenating a small real one (default: tests/data/logs/ardusub_small.BIN,
340 copies) and times `trimag.io.logs.read_log` (the numpy reader, only the message types trimag needs) against
pymavlink's message-by-message reading of the same types. Peak memory is the process's maximum resident set
(resource.getrusage) of a fresh subprocess per reader.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_TRIMAG = """
import resource, sys, time
t = time.perf_counter()
from trimag.io.logs import read_log
log = read_log(sys.argv[1])
df, _ = log.table()
print(time.perf_counter() - t, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, len(df))
"""
_PYMAVLINK = """
import resource, sys, time
t = time.perf_counter()
from pymavlink import mavutil
m = mavutil.mavlink_connection(sys.argv[1])
n = 0
while m.recv_match(type=["MAG", "MAG2", "MAG3", "ATT", "BAT", "CURR", "RCOU", "GPS", "PARM", "CTUN"]) is not None:
    n += 1
print(time.perf_counter() - t, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, n)
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--copies", type=int, default=340)
    parser.add_argument("--log", default=str(ROOT / "tests" / "data" / "logs" / "ardusub_small.BIN"))
    parser.add_argument("--skip-pymavlink", action="store_true")
    args = parser.parse_args()
    chunk = Path(args.log).read_bytes()
    with tempfile.TemporaryDirectory() as tmp:
        big = Path(tmp) / "big.bin"
        with big.open("wb") as fh:
            for _ in range(args.copies):
                fh.write(chunk)
        size_mb = big.stat().st_size / 1e6
        print(f"log: {size_mb:.0f} MB ({args.copies} copies of {Path(args.log).name})")
        runs = [("trimag (numpy DataFlash reader)", _TRIMAG)]
        if not args.skip_pymavlink:
            runs.append(("pymavlink recv_match, same types", _PYMAVLINK))
        for label, code in runs:
            t0 = time.perf_counter()
            out = subprocess.run([sys.executable, "-c", code, str(big)], capture_output=True, text=True, check=True)
            seconds, peak_mb, n = out.stdout.split()
            print(f"{label:36s} {float(seconds):7.2f} s  peak RSS {float(peak_mb):6.0f} MB  ({n} rows/messages; "
                  f"wall {time.perf_counter() - t0:.1f} s)")


if __name__ == "__main__":
    main()
