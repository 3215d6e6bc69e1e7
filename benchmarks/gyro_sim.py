"""The gyro-aided fit on simulated logs with known truth (issue 31; the tables are in docs/method-gyro.md).

1. Are the reported sigmas right? 20 logs per motion (60 s at 100 Hz, :func:`trimag.simulate.simulate_gyro`): the
   standard deviation and mean of the z-scores (error / reported sigma) of every parameter.
2. What the gyroscope adds on partial rotations: the field's body-frame direction within a cone (full aperture 90,
   60 and 30 degrees), ``ml`` against ``gyro`` on the same samples: the worst combination's sigma against a full
   sphere's, what each calls unidentified, the RMS error of the hard iron.
3. Fit time against the log's length.

    python benchmarks/gyro_sim.py [--logs 20]
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
from scipy.spatial.transform import Rotation

import trimag
from trimag.estimators.gyro import GyroAided
from trimag.quality.crlb import UPPER
from trimag.simulate import simulate_gyro

NAMES = ("w11", "w12", "w13", "w22", "w23", "w33", "hard_iron_x", "hard_iron_y", "hard_iron_z", "gyro_bias_x",
         "gyro_bias_y", "gyro_bias_z", "gyro_alignment_x", "gyro_alignment_y", "gyro_alignment_z")


def _fit(sim, F=None):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return GyroAided().fit(sim.raw, F, units="uT", attitude=sim.angular_rate()).calibration_


def z_scores(motion: str, logs: int) -> np.ndarray:
    z = []
    for seed in range(logs):
        sim = simulate_gyro(6000, seed, motion=motion)
        cal = _fit(sim, float(np.linalg.norm(sim.field_nav)))
        R = np.asarray(cal.diagnostics["gyro_alignment"]["matrix"])
        err = np.concatenate([cal.matrix[UPPER] - sim.matrix[UPPER], cal.offset - sim.offset,
                              np.asarray(cal.diagnostics["gyro"]["bias_rad_s"]) - sim.gyro_bias,
                              Rotation.from_matrix(R @ sim.alignment.T).as_rotvec()])
        std = np.array([cal.uncertainty["param_std"][k] for k in NAMES])
        z.append(err / std)
    return np.array(z)


def cone(aperture: float, seed: int = 3) -> dict[str, object]:
    sim = simulate_gyro(6000, seed, motion="cone", cone_deg=aperture)
    F = float(np.linalg.norm(sim.field_nav))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ml = trimag.fit(sim.raw, reference=F, units="uT")
    except trimag.IdentifiabilityError as exc:  # ml refuses (exit 3)
        ml = None
        refusal = str(exc).split(":")[0]
    cal = _fit(sim, F)
    ident = cal.diagnostics["identifiability"]
    if ml is None:
        return {"aperture": aperture, "ml_inflation": float("nan"), "ml_refused": refusal,
                "gyro_inflation": ident["std_inflation_vs_full_sphere"],
                "ml_unidentified": ["(refused: " + refusal + ")"], "gyro_unidentified": ident["unidentified"],
                "ml_hard_iron_err": float("nan"),
                "gyro_hard_iron_err": float(np.sqrt(np.mean((cal.offset - sim.offset) ** 2)))}
    return {"aperture": aperture, "ml_inflation": ml.diagnostics["identifiability"]["std_inflation_vs_full_sphere"],
            "gyro_inflation": ident["std_inflation_vs_full_sphere"],
            "ml_unidentified": ident["magnitude_only"]["unidentified"], "gyro_unidentified": ident["unidentified"],
            "ml_hard_iron_err": float(np.sqrt(np.mean((ml.offset - sim.offset) ** 2))),
            "gyro_hard_iron_err": float(np.sqrt(np.mean((cal.offset - sim.offset) ** 2)))}


def timing(n: int) -> float:
    sim = simulate_gyro(n, 0)
    _fit(sim)
    t0 = time.perf_counter()
    _fit(sim)
    return time.perf_counter() - t0


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--logs", type=int, default=20)
    p.add_argument("--skip-z", action="store_true", help="skip the z-score tables")
    args = p.parse_args()
    for motion in ("tumble", "cone"):
        if args.skip_z:
            break
        z = z_scores(motion, args.logs)
        print(f"\n{motion}, {args.logs} logs: | parameter | std of z | mean of z |")
        for k, name in enumerate(NAMES):
            print(f"| {name} | {z[:, k].std(ddof=1):.2f} | {z[:, k].mean():+.2f} |")
    print("\n| cone aperture | ml: worst combination vs full sphere | gyro | ml unidentified | gyro unidentified "
          "| hard iron RMS error ml / gyro (uT) |")
    for aperture in (90.0, 60.0, 30.0):
        r = cone(aperture)
        print(f"| {aperture:g} deg | {r['ml_inflation']:.3g}x | {r['gyro_inflation']:.3g}x | "
              f"{', '.join(r['ml_unidentified']) or '-'} | {', '.join(r['gyro_unidentified']) or '-'} | "
              f"{r['ml_hard_iron_err']:.3f} / {r['gyro_hard_iron_err']:.3f} |")
    print("\n| samples (100 Hz) | fit time (s) |")
    for n in (3000, 30000, 300000):
        print(f"| {n} | {timing(n):.3g} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
