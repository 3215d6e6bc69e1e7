"""Speed benchmark of trimag: fit time and peak memory against N (trimag methods and installed peers),
streaming ``apply``/``evaluate`` of a 1e7-row file, and batch throughput with 1 and 2 workers.

A thin wrapper of ``trimag bench speed`` (``src/trimag/experiments/speed.py``); results and the machine they
were measured on are recorded in ``docs/performance.md``.

Usage::

    python benchmarks/speed.py --out bench-speed            # the full run (~20 min on 2 cores)
    python benchmarks/speed.py --out /tmp/s --quick         # a fast check
    python benchmarks/speed.py --out /tmp/s --skip apply batch --sizes 1e4 1e5 1e6 --estimators ml
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    # imported here, not at the top: the batch benchmark's worker processes are spawned, and a spawned process
    # imports the parent's main module (this file) again; at the top this import cost each worker 0.4 s
    from trimag.experiments import speed

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="bench-speed", help="output folder")
    parser.add_argument("--quick", action="store_true", help="small sizes, for a fast check")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true", help="print the JSON summary on stdout")
    speed.add_arguments(parser)
    args = vars(parser.parse_args(argv))
    out, quick, seed, as_json = args.pop("out"), args.pop("quick"), args.pop("seed"), args.pop("json")
    summary = speed.run(Path(out), quick=quick, trials=None, seed=seed, workers=1, json_mode=as_json, **args)
    if as_json:
        print(json.dumps(summary, allow_nan=False, default=float))
    else:
        print(summary.get("text", ""))
        print(f"outputs in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
