"""Risk of ``ml``'s balanced-offset test (docs/method-ml.md, step 6): gain on balanced designs, cost on nearly
balanced ones.

Three complete, evenly sampled great circles (600 directions); ``m`` consecutive samples dropped from the first
circle make the design slightly unbalanced. For each ``m``: the imbalance in units of the test's standard error,
how often the test accepts balance, and the RMS offset error of ``balance="auto"`` over that of the plain ML
(``balance="never"``) on the same noisy data.

    python benchmarks/balance_risk.py                    # sigma/F = 5e-2, 150 trials per row (about 20 s)
    python benchmarks/balance_risk.py --sigma 0.01 --trials 50
"""

from __future__ import annotations

import argparse
import warnings

import numpy as np

import trimag
from trimag.simulate import great_circle_directions

SOFT_IRON = np.array([[1.08, 0.03, -0.02], [0.0, 0.93, 0.04], [0.0, 0.0, 1.0]])  # raw = SOFT_IRON @ u + b
HARD_IRON = np.array([0.2, -0.1, 0.15])


def risk_table(sigma: float, trials: int, drops: list[int], n: int = 600) -> list[dict[str, float]]:
    """One row per ``m`` in ``drops``: imbalance / test std, acceptance rate, RMS offset error auto / ML."""
    base = great_circle_directions(n)
    rows = []
    for m in drops:
        u = base[m:]
        se_d = np.sqrt(2.0) * sigma / np.sqrt(len(u))  # std of mean(x) - b_ml per axis on circles, about
        shift = float(np.linalg.norm(SOFT_IRON @ u.mean(axis=0)))
        rng = np.random.default_rng(m)
        err_auto, err_ml, accepted = [], [], []
        for _ in range(trials):
            raw = u @ SOFT_IRON.T + HARD_IRON + sigma * rng.normal(size=u.shape)
            auto = trimag.fit(raw, method="ml")
            plain = trimag.fit(raw, method="ml", balance="never")
            err_auto.append(auto.offset - HARD_IRON)
            err_ml.append(plain.offset - HARD_IRON)
            accepted.append(auto.diagnostics["balanced_offset"]["applied"])
        rms_auto = float(np.sqrt(np.mean(np.sum(np.square(err_auto), axis=1))))
        rms_ml = float(np.sqrt(np.mean(np.sum(np.square(err_ml), axis=1))))
        rows.append({"dropped": m, "imbalance_over_se": shift / se_d, "accepted": float(np.mean(accepted)),
                     "rms_ratio_auto_over_ml": rms_auto / rms_ml})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sigma", type=float, default=0.05, help="noise per axis / field magnitude")
    parser.add_argument("--trials", type=int, default=150)
    parser.add_argument("--drops", type=int, nargs="+", default=[0, 1, 2, 3, 4, 6, 8, 12, 16])
    args = parser.parse_args()
    warnings.simplefilter("ignore")
    print("| dropped samples m | imbalance / test std | accepted | RMS offset error, auto / ML |")
    print("|---|---|---|---|")
    for r in risk_table(args.sigma, args.trials, args.drops):
        print(f"| {r['dropped']} | {r['imbalance_over_se']:.2f} | {100 * r['accepted']:.0f} % | "
              f"{r['rms_ratio_auto_over_ml']:.2f} |")


if __name__ == "__main__":
    main()
