"""Speed and memory of a Tolles–Lawson fit and apply on long simulated flights (issue 21).

    python benchmarks/tolles_lawson.py --sizes 1e5,1e6 [--bootstrap 200]

Prints one line per size: seconds to fit (band-pass, ridge solve, bootstrap, diagnostics) and to apply, and the
peak memory each allocates beyond the data (tracemalloc, which numpy reports its arrays to; MB).
"""

from __future__ import annotations

import argparse
import time
import tracemalloc

import numpy as np

from trimag.estimators.tolles_lawson import fit_tolles_lawson
from trimag.simulate import simulate_aircraft


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--sizes", default="1e5,1e6")
    parser.add_argument("--bootstrap", type=int, default=200)
    args = parser.parse_args()
    print(f"{'N':>10}{'fit [s]':>10}{'apply [s]':>11}{'fit peak [MB]':>15}{'apply peak [MB]':>17}{'data [MB]':>11}"
          f"{'ratio':>8}")
    for size in (int(float(x)) for x in args.sizes.split(",")):
        seconds = size / 10.0 / 4.0 / 1.01  # four legs at 10 Hz (turns add ~1 %)
        sim = simulate_aircraft(seconds, turn_seconds=20.0, seed=0)
        data_mb = (sim.vector_nT.nbytes + sim.scalar_nT.nbytes) / 2**20
        t0 = time.perf_counter()
        comp = fit_tolles_lawson(sim.vector_nT, sim.scalar_nT, rate_hz=10.0, segments=sim.segments,
                                 bootstrap=args.bootstrap)
        t1 = time.perf_counter()
        out = comp.apply(sim.vector_nT, sim.scalar_nT)
        t2 = time.perf_counter()
        assert np.isfinite(out).all()
        tracemalloc.start()
        fit_tolles_lawson(sim.vector_nT, sim.scalar_nT, rate_hz=10.0, segments=sim.segments, bootstrap=args.bootstrap)
        fit_peak = tracemalloc.get_traced_memory()[1] / 2**20
        tracemalloc.reset_peak()
        comp.apply(sim.vector_nT, sim.scalar_nT)
        apply_peak = tracemalloc.get_traced_memory()[1] / 2**20
        tracemalloc.stop()
        print(f"{len(sim.scalar_nT):>10}{t1 - t0:10.2f}{t2 - t1:11.2f}{fit_peak:15.0f}{apply_peak:17.0f}{data_mb:11.0f}"
              f"{comp.stats['improvement_ratio']:8.0f}")


if __name__ == "__main__":
    main()
