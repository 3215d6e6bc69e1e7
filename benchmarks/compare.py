"""A/B comparison of two trimag source trees in one time window (the host's noise moves whole runs by 30-40 %).

Alternates, each in its own process: a batch fit of a folder of logs with 1 and 2 workers (files per second), and
one ``trimag fit`` of a small log from the command line (wall time and peak memory). Used for the A/B numbers of
docs/performance-history.md ("What changed since run V").

    git worktree add /tmp/old <commit>
    python benchmarks/compare.py --old /tmp/old/src --new src --logs '/tmp/fleet/*.csv' --rounds 3

``--logs``: a glob of CSV logs (e.g. the 1000 x 5000-sample files ``benchmarks/speed.py`` writes for its batch
benchmark); the first one is also the log of the CLI fit.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import statistics
import subprocess
import sys
import tempfile

_BATCH = """
import json, shutil, sys
try:
    from trimag.app.batch import fit_batch
except ImportError:  # a tree from before the job packages (issue 29)
    from trimag.batch import fit_batch
from trimag.parallel import shutdown_pools
if __name__ == "__main__":
    out = {}
    for w in (1, 2):
        shutdown_pools()
        r = fit_batch(sys.argv[1], sys.argv[2] + f"/w{w}", workers=w, progress=False)
        out[w] = r.files_per_second
        shutil.rmtree(sys.argv[2] + f"/w{w}", ignore_errors=True)
    shutdown_pools()
    print(json.dumps(out))
"""


def _run(src: str, args: list[str]) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": os.path.abspath(src)}
    return subprocess.run(args, env=env, capture_output=True, text=True, check=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--old", required=True, help="src folder of the old tree")
    parser.add_argument("--new", required=True, help="src folder of the new tree")
    parser.add_argument("--logs", required=True, help="glob of CSV logs")
    parser.add_argument("--rounds", type=int, default=3)
    a = parser.parse_args()
    logs = sorted(glob.glob(a.logs))
    if not logs:
        sys.exit(f"no files match {a.logs!r}")
    results: dict[str, dict[str, list[float]]] = {k: {"batch1": [], "batch2": [], "cli_s": [], "cli_mb": []}
                                                   for k in ("old", "new")}
    with tempfile.TemporaryDirectory() as tmp:
        script = os.path.join(tmp, "batch.py")
        with open(script, "w") as fh:
            fh.write(_BATCH)
        for _ in range(a.rounds):
            for name, src in (("old", a.old), ("new", a.new)):
                fps = json.loads(_run(src, [sys.executable, script, a.logs, tmp]).stdout)
                results[name]["batch1"].append(fps["1"])
                results[name]["batch2"].append(fps["2"])
                out = _run(src, ["/usr/bin/time", "-f", "%e %M", sys.executable, "-m", "trimag", "fit", logs[0],
                                 "--out", os.path.join(tmp, "cal.json")])
                seconds, kb = out.stderr.strip().splitlines()[-1].split()
                results[name]["cli_s"].append(float(seconds))
                results[name]["cli_mb"].append(float(kb) / 1024)
    for name, r in results.items():
        print(name, {k: {"median": round(statistics.median(v), 2), "all": [round(x, 2) for x in v]}
                     for k, v in r.items()})


if __name__ == "__main__":
    main()
