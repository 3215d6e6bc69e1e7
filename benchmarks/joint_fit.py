"""Does a joint fit of the fluxgate (interference12 + eddy) with the scalar magnetometer help? (issue 21, item 5)

    python benchmarks/joint_fit.py [--seeds 5] [--attitude-noise-deg 0.05]

Simulated calibration boxes (:func:`trimag.simulate.simulate_aircraft`, 60 s per heading at 10 Hz) with a fluxgate
``H_m = K H_b + c + E dH_m/dt`` (0.5 nT noise) and a scalar magnetometer; the INS attitudes that form the vector
reference carry errors (white ``--attitude-noise-deg`` per axis plus a slow drift of the same size). Three fits of
K, c, E on one box, scored on another box (other seed, other manoeuvres) against the true body field:

* ``vector``: trimag's interference12 with eddy terms (``option eddy=9``), vector reference from the INS attitudes;
* ``joint``: :func:`trimag.vehicle.joint.fit_joint_scalar`, the vector rows stacked with magnitude rows
  ``|K^-1 (H_m - c - E dH/dt)| - (S - d)`` against the Tolles–Lawson-compensated scalar ``S`` (its own TL fit on the
  same box, with a free offset ``d``), each kind of row weighted by the inverse of its residual RMS.

(The magnitude rows alone, without attitudes, are degenerate with the free offset: the scale collapses.)

Prints the held-out vector RMS and magnitude RMS (nT) per seed and their medians; then the scalar magnetometer's
own TL (the same aircraft on every box), fitted with the raw fluxgate, the vector-only corrected, the jointly
corrected fluxgate, or the true body field as its direction-cosine source, scored on the other box (mean
band-passed std of the compensated scalar over the legs, nT; the scalar's noise is 0.01 nT).
"""

from __future__ import annotations

import argparse

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

import trimag
from trimag.estimators.tolles_lawson import fit_tolles_lawson
from trimag.simulate import simulate_aircraft
from trimag.vehicle.eddy import EDDY_NAMES, eddy_values, free_mask
from trimag.vehicle.joint import fit_joint_scalar
from trimag.vehicle.regressors import fit_regressors

K_TRUE = np.eye(3) + np.array([[0.02, 0.01, -0.005], [0.0, -0.01, 0.008], [0.004, 0.0, 0.015]])
C_TRUE = np.array([300.0, -150.0, 80.0])
E_TRUE = np.array([[-0.05, 0.01, 0.0], [0.0, -0.03, 0.02], [0.01, 0.0, -0.04]])
EARTH = np.array([18_000.0, 1_000.0, 46_000.0])


#: the scalar magnetometer's TL coefficients (18, MagNav order), the same aircraft on every box
TL_TRUE = simulate_aircraft(10.0, seed=12345).coefficients


def _box(seed: int, att_noise_deg: float):
    sim = simulate_aircraft(60.0, vector_K=K_TRUE, vector_c=C_TRUE, vector_E=E_TRUE, vector_noise_nT=0.5,
                            earth_ned_nT=EARTH, seed=seed, coefficients=TL_TRUE)
    rng = np.random.default_rng(1000 + seed)
    n = len(sim.time_s)
    drift = np.cumsum(rng.normal(size=(n, 3)), axis=0)
    drift = drift - drift.mean(axis=0)
    drift *= att_noise_deg / max(float(drift.std()), 1e-12)
    ins = sim.attitude_deg + rng.normal(scale=att_noise_deg, size=(n, 3)) + drift
    dB = np.column_stack([eddy_values(sim.vector_nT, time_s=sim.time_s)[0][k] for k in EDDY_NAMES])
    return sim, Rotation.from_euler("ZYX", ins, degrees=True), dB


def _fit_vector(sim, ins: Rotation, dB: NDArray[np.float64]) -> trimag.Calibration:
    base = trimag.fit(sim.vector_nT, model="interference12", reference=EARTH, attitude=ins, units="nT")
    return fit_regressors(base, sim.vector_nT, dict(zip(EDDY_NAMES, dB.T, strict=True)), attitude=ins,
                          free=free_mask(9))


def _compensated_scalar(sim) -> NDArray[np.float64]:
    comp = fit_tolles_lawson(sim.vector_nT, sim.scalar_nT, rate_hz=sim.rate_hz, segments=sim.segments, bootstrap=0)
    # the simulated fluxgate does not see the geology (a real one does): removed from the scalar
    return np.asarray(comp.apply(sim.vector_nT, sim.scalar_nT), dtype=np.float64) - sim.geology_nT


def _score(cal: trimag.Calibration, sim, dB: NDArray[np.float64]) -> tuple[float, float]:
    H = cal.apply(sim.vector_nT, regressors=dict(zip(EDDY_NAMES, dB.T, strict=True)))
    truth = sim.body_nT
    return (float(np.sqrt(np.mean(np.sum((H - truth) ** 2, axis=1)))),
            float(np.sqrt(np.mean((np.linalg.norm(H, axis=1) - np.linalg.norm(truth, axis=1)) ** 2))))


def _tl_held_out(X_fit: NDArray[np.float64], sim, X_test: NDArray[np.float64], test) -> float:
    """The scalar's TL fitted with ``X_fit`` as its vector source on ``sim``, scored on ``test`` (``X_test``): the
    mean band-passed (0.1-0.9 Hz) std of the compensated scalar over the test box's legs, nT."""
    from trimag.aircraft.filtering import BandPass

    bp = BandPass(0.1, 0.9, test.rate_hz, 4, 20)
    comp = fit_tolles_lawson(X_fit, sim.scalar_nT, rate_hz=sim.rate_hz, segments=sim.segments, bootstrap=0)
    out = comp.apply(X_test, test.scalar_nT)
    return float(np.mean([np.std(bp.apply(out[a:b])) for a, b in test.segments]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--attitude-noise-deg", type=float, default=0.05)
    args = parser.parse_args()
    print(f"held-out vector RMS / magnitude RMS (nT), INS attitude errors {args.attitude_noise_deg} deg white + drift")
    print(f"{'':>17}{'fluxgate K, c, E':^36}{'scalar TL (band-passed std) from the fluxgate':^36}")
    print(f"{'fit box':>8}{'test box':>9}{'vector':>18}{'joint':>18}{'raw':>9}{'vector':>9}{'joint':>9}{'truth':>9}")
    rows: list[list[tuple[float, float]]] = []
    tl: list[list[float]] = []
    for seed in range(args.seeds):
        sim, ins, dB = _box(2 * seed, args.attitude_noise_deg)
        test, _, dB_t = _box(2 * seed + 1, args.attitude_noise_deg)
        S = _compensated_scalar(sim)
        vector = _fit_vector(sim, ins, dB)
        joint = fit_joint_scalar(vector, sim.vector_nT, S, attitude=ins, background=EARTH,
                                 regressors=dict(zip(EDDY_NAMES, dB.T, strict=True)))
        row = [_score(cal, test, dB_t) for cal in (vector, joint)]
        rows.append(row)

        def corrected(cal: trimag.Calibration, box, d: NDArray[np.float64]) -> NDArray[np.float64]:
            return cal.apply(box.vector_nT, regressors=dict(zip(EDDY_NAMES, d.T, strict=True)))

        tl.append([_tl_held_out(sim.vector_nT, sim, test.vector_nT, test),
                   *(_tl_held_out(corrected(cal, sim, dB), sim, corrected(cal, test, dB_t), test)
                     for cal in (vector, joint)),
                   _tl_held_out(sim.body_nT, sim, test.body_nT, test)])
        print(f"{2 * seed:>8}{2 * seed + 1:>9}" + "".join(f"{v:9.2f} /{m:7.2f}" for v, m in row)
              + "".join(f"{v:9.4f}" for v in tl[-1]))
    med = np.median(np.asarray(rows), axis=0)
    print(f"{'median':>17}" + "".join(f"{v:9.2f} /{m:7.2f}" for v, m in med)
          + "".join(f"{v:9.4f}" for v in np.median(np.asarray(tl), axis=0)))


if __name__ == "__main__":
    main()
