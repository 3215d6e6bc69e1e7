"""trimag against a naive floor, as paired ratios, for one or two source trees in one time window (issue 42 item 5).

    python benchmarks/floor_ratios.py --new src [--old /tmp/old/src] [--rounds 5] [--rows 1e6] [--skip cli|fits]

Two measurements, each a ratio to a floor measured in the same round (the host's load moves whole runs by 30-40 %,
a ratio within a round much less):

1. **The whole command.** ``trimag fit CSV --units nT -o cal.json`` of a ``--rows`` CSV log (``t,bx,by,bz``,
   ``benchmarks/speed.py``'s ``write_big_log``, written once to the system's temporary folder) as a process, wall
   time, against the naive floor: a process that imports numpy and pyarrow, reads the same CSV with
   ``pyarrow.csv.read_csv`` and solves one algebraic ellipsoid least squares (``numpy.linalg.lstsq``, 9 columns).
2. **The estimators.** In one process per tree: ``trimag.fit(B, method=M)`` (the default ``ml`` and
   ``ellipsoid-fit``) on ``--rows`` simulated samples, the minimum of 3 fits after a warm-up, divided by the
   minimum of 3 of the numpy floor (the same algebraic lstsq) on the same array in the same process.

Each round runs the floor and every tree alternately; printed: the median over the rounds of the per-round ratios.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_FLOOR_CLI = """
import sys
import numpy as np
import pyarrow.csv as pacsv
t = pacsv.read_csv(sys.argv[1])
x = np.column_stack([t.column(c).to_numpy() for c in ("bx", "by", "bz")])
x = (x - x.mean(axis=0)) / x.std()
D = np.column_stack([x * x, 2 * x[:, 0] * x[:, 1], 2 * x[:, 0] * x[:, 2], 2 * x[:, 1] * x[:, 2], 2 * x])
coef = np.linalg.lstsq(D, np.ones(len(x)), rcond=None)[0]
print(coef[0])
"""

_FITS = """
import json, sys, time, warnings
import numpy as np
import trimag
warnings.simplefilter("ignore")
n = int(float(sys.argv[1]))
rng = np.random.default_rng(0)
u = rng.normal(size=(n, 3)); u /= np.linalg.norm(u, axis=1, keepdims=True)
W = np.array([[0.95, 0.03, -0.02], [0.0, 1.04, 0.05], [0.0, 0.0, 1.01]])
B = np.linalg.solve(W, (48000 * u).T).T + [1200.0, -850.0, 400.0] + rng.normal(scale=50.0, size=u.shape)

def floor():
    x = (B - B.mean(axis=0)) / B.std()
    D = np.column_stack([x * x, 2 * x[:, 0] * x[:, 1], 2 * x[:, 0] * x[:, 2], 2 * x[:, 1] * x[:, 2], 2 * x])
    return np.linalg.lstsq(D, np.ones(len(x)), rcond=None)[0]

def best(f):
    f()
    times = []
    for _ in range(3):
        t = time.perf_counter(); f(); times.append(time.perf_counter() - t)
    return min(times)

out = {}
for method in sys.argv[2].split(","):
    kw = {} if method == "default" else {"method": method}
    t_floor = best(floor)
    out[method] = best(lambda: trimag.fit(B, units="nT", **kw)) / t_floor
print(json.dumps(out))
"""


def _wall(args: list[str], env: dict[str, str]) -> float:
    t = time.perf_counter()
    subprocess.run(args, env=env, capture_output=True, text=True, check=True)
    return time.perf_counter() - t


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--new", default=str(ROOT / "src"))
    parser.add_argument("--old", help="src folder of the tree to compare with")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--rows", type=float, default=1e6)
    parser.add_argument("--methods", default="default,ellipsoid-fit")
    parser.add_argument("--skip", nargs="*", default=(), choices=("cli", "fits"))
    a = parser.parse_args()
    trees = [("old", a.old), ("new", a.new)] if a.old else [("new", a.new)]
    n = int(a.rows)
    cli: dict[str, list[float]] = {k: [] for k, _ in trees}
    fits: dict[str, dict[str, list[float]]] = {k: {} for k, _ in trees}
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tempfile.gettempdir()) / "trimag-bench" / f"big_{n}.csv"
        if "cli" not in a.skip and not log.exists():
            log.parent.mkdir(parents=True, exist_ok=True)
            sys.path.insert(0, str(ROOT / "benchmarks"))
            sys.path.insert(0, a.new)
            from speed import write_big_log

            write_big_log(log, n)
        floor_script = Path(tmp) / "floor.py"
        floor_script.write_text(_FLOOR_CLI)
        fits_script = Path(tmp) / "fits.py"
        fits_script.write_text(_FITS)
        for k in range(a.rounds):
            for name, src in trees:
                env = {**os.environ, "PYTHONPATH": os.path.abspath(src)}
                if "cli" not in a.skip:
                    floor = _wall([sys.executable, str(floor_script), str(log)], env)
                    fit = _wall([sys.executable, "-m", "trimag", "fit", str(log), "--units", "nT", "-o",
                                 str(Path(tmp) / f"{name}.json")], env)
                    cli[name].append(fit / floor)
                    print(f"round {k + 1} {name}: fit {fit:.2f} s, floor {floor:.2f} s, ratio {fit / floor:.3f}",
                          flush=True)
                if "fits" not in a.skip:
                    out = json.loads(subprocess.run([sys.executable, str(fits_script), str(n), a.methods], env=env,
                                                    capture_output=True, text=True, check=True).stdout)
                    for method, ratio in out.items():
                        fits[name].setdefault(method, []).append(ratio)
                    print(f"round {k + 1} {name}: fits / numpy floor {out}", flush=True)
    for name, _ in trees:
        if cli[name]:
            print(f"{name}: trimag fit of {n:.0e} CSV rows / naive floor: median {statistics.median(cli[name]):.3f} "
                  f"({[round(r, 3) for r in cli[name]]})")
        for method, ratios in fits[name].items():
            print(f"{name}: {method} at N={n:.0e} / numpy floor: median {statistics.median(ratios):.3f} "
                  f"({[round(r, 3) for r in ratios]})")


if __name__ == "__main__":
    main()
