"""A/B of single fits between two source trees, alternating in one time window (medians of rounds).

    git worktree add /tmp/old <commit>
    python benchmarks/ab_fits.py --old /tmp/old/src --new src --sizes 1e4,1e5,1e6 --methods ml,ellipsoid-fit
    python benchmarks/ab_fits.py ... --methods ortho-gain-bias:pairwise,scalar9:gauss-newton,zhang-cheng:quadric

A method is ``METHOD`` (model ellipsoid) or ``MODEL:METHOD`` (scalar9 and zhang-cheng get the reference 48000 nT;
interference12 random attitudes and its background).

Each round runs every (tree, size, method) in a fresh process: the minimum of 5 fits (after one warm-up) and the
process's peak resident memory.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys

_CODE = """
import json, resource, sys, time, warnings
import numpy as np
import trimag
warnings.simplefilter("ignore")
n, spec = int(float(sys.argv[1])), sys.argv[2]
model, method = spec.split(":") if ":" in spec else ("ellipsoid", spec)
kw = {"reference": 48000.0} if model in ("scalar9", "zhang-cheng") else {}
rng = np.random.default_rng(0)
u = rng.normal(size=(n, 3)); u /= np.linalg.norm(u, axis=1, keepdims=True)
W = np.array([[0.95, 0.03, -0.02], [0.0, 1.04, 0.05], [0.0, 0.0, 1.01]])
B = np.linalg.solve(W, (48000 * u).T).T + [1200.0, -850.0, 400.0] + rng.normal(scale=50.0, size=u.shape)
if model == "interference12":  # random attitudes, a known background, paper C's K and c
    from scipy.spatial.transform import Rotation
    H_n = np.array([20000.0, 1000.0, 43000.0])
    att = Rotation.random(n, random_state=1)
    K = np.array([[1.02, 0.01, -0.02], [0.03, 0.97, 0.01], [0.0, 0.02, 1.01]])
    B = att.inv().apply(H_n) @ K.T + [200.0, -100.0, 50.0] + rng.normal(scale=50.0, size=u.shape)
    kw = {"reference": H_n, "attitude": att}
trimag.fit(B, model=model, method=method, units="nT", **kw)
times = []
for _ in range(5):
    t = time.perf_counter(); trimag.fit(B, model=model, method=method, units="nT", **kw)
    times.append(time.perf_counter() - t)
print(json.dumps({"s": min(times), "mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--old", required=True)
    parser.add_argument("--new", required=True)
    parser.add_argument("--sizes", default="1e4,1e5,1e6")
    parser.add_argument("--methods", default="ml,ellipsoid-fit")
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    results: dict[tuple[str, str, str], list[dict[str, float]]] = {}
    for _ in range(args.rounds):
        for size in args.sizes.split(","):
            for method in args.methods.split(","):
                for label, src in (("old", args.old), ("new", args.new)):
                    env = {**os.environ, "PYTHONPATH": os.path.abspath(src)}
                    out = subprocess.run([sys.executable, "-c", _CODE, size, method], env=env, capture_output=True,
                                         text=True, check=True)
                    results.setdefault((size, method, label), []).append(json.loads(out.stdout))
    print(f"{'N':>6} {'method':30} {'old [ms]':>9} {'new [ms]':>9} {'new/old':>8} {'old MB':>7} {'new MB':>7}")
    for size in args.sizes.split(","):
        for method in args.methods.split(","):
            o = results[(size, method, "old")]
            n = results[(size, method, "new")]
            to = statistics.median(r["s"] for r in o) * 1e3
            tn = statistics.median(r["s"] for r in n) * 1e3
            mo = statistics.median(r["mb"] for r in o)
            mn = statistics.median(r["mb"] for r in n)
            print(f"{size:>6} {method:30} {to:9.2f} {tn:9.2f} {tn / to:8.2f} {mo:7.0f} {mn:7.0f}")


if __name__ == "__main__":
    main()
