"""Accuracy benchmark: trimag's ellipsoid estimators and the installable peers against the Cramér–Rao bound.

Thin wrapper of ``trimag bench accuracy`` (``trimag.experiments.accuracy``); results table in docs/accuracy.md.

    nice -n 10 python benchmarks/accuracy.py --out bench-accuracy              # full grid, 200 trials per cell
    nice -n 10 python benchmarks/accuracy.py --out bench-accuracy --quick      # 10 trials, N in {400, 2000}
    python benchmarks/accuracy.py --out DIR --sizes 400 --estimators ml magcc:lm --trials 50
    python benchmarks/accuracy.py --out ALL --merge PART1 PART2 ...        # one table from runs split by N/estimator

Peers need the optional extra: ``pip install trimag[bench]``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from trimag.experiments import accuracy


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="bench-accuracy", help="output folder (accuracy.csv/.json/.md)")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--trials", type=int, default=None, help="trials per cell (default 200)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=1, help="processes (one cell each)")
    parser.add_argument("--json", action="store_true", help="print the JSON summary on stdout")
    parser.add_argument("--merge", nargs="+", default=None, metavar="DIR",
                        help="merge the accuracy.json of these earlier runs (same seed) into --out; no new trials")
    accuracy.add_arguments(parser)
    args = vars(parser.parse_args(argv))
    out, as_json, parts = Path(args.pop("out")), args.pop("json"), args.pop("merge")
    if parts:
        merged = accuracy.merge([Path(p) for p in parts], out)
        print(json.dumps(merged) if as_json else merged["text"])
        return 0
    summary = accuracy.run(out, json_mode=as_json, **args)
    print(json.dumps(summary) if as_json else summary["text"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
