"""When the background's gradient helps and when it does not (issue 31, item 4; the table is in docs/vehicle.md).

Simulated lab recordings (:func:`trimag.simulate.simulate_room`: 3000 samples at 50 Hz, 20 nT noise, the sensor
carried within 0.3 m of a point) fitted with ``estimate_background`` with and without the gradient
(:func:`trimag.vehicle.gradient.fit_background_gradient`), judged on a second recording (the held-out angular error
between the corrected field and the background each calibration predicts there):

* a linear gradient (the model holds), held out in the same place and 0.6 m away;
* a uniform background (nothing to fit: 5 terms more than needed);
* a steel object (a dipole of 1 A m^2, 0.6 m from the fitted place): a gradient is its linear part near where it
  was fitted, held out in the same place and 0.3 m nearer to it.

    python benchmarks/gradient_room.py
"""

from __future__ import annotations

import warnings

import numpy as np

import trimag
from trimag.fields.attitude import body_field
from trimag.simulate import simulate_room
from trimag.vehicle.gradient import background_at, fit_background_gradient


def angle_deg(cal, sim, gradient: bool) -> float:
    Hn = background_at(cal, sim.positions) if gradient else np.asarray(cal.diagnostics["background_ned"])
    expected = body_field(sim.attitude, Hn)
    y = cal.apply(sim.raw)
    cos = np.sum(y * expected, axis=1) / np.linalg.norm(y, axis=1) / np.linalg.norm(expected, axis=1)
    return float(np.degrees(np.sqrt(np.mean(np.arccos(np.clip(cos, -1, 1)) ** 2))))


def case(name: str, fit_kw: dict, held_kw: dict, seeds=range(5)) -> str:
    rows = []
    for seed in seeds:
        fit = simulate_room(3000, 100 + seed, reach_m=0.3, **fit_kw)
        held = simulate_room(3000, 200 + seed, reach_m=0.3, **held_kw)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            base = trimag.fit(fit.raw, model="interference12", attitude=fit.attitude, units="nT",
                              estimate_background=True)
        grad = fit_background_gradient(base, fit.raw, fit.attitude, fit.positions)
        rows.append([angle_deg(base, fit, False), angle_deg(grad, fit, True), angle_deg(base, held, False),
                     angle_deg(grad, held, True)])
    m = np.mean(rows, axis=0)
    return f"| {name} | {m[0]:.3f} / {m[1]:.3f} deg | {m[2]:.3f} / {m[3]:.3f} deg |"


def main() -> int:
    flat = {"gradient_terms": (0.0, 0.0, 0.0, 0.0, 0.0)}
    dipole = {**flat, "dipole_at_m": (0.6, 0.0, 0.0), "dipole_moment_Am2": (0.0, 0.7, 0.7)}
    print("| room | fitted recording: without / with gradient | held-out recording: without / with |")
    print("|---|---|---|")
    print(case("linear gradient, held out in the same place", {}, {}))
    print(case("linear gradient, held out 0.6 m away", {}, {"centre_m": (0.0, 0.6, 0.0)}))
    print(case("uniform background", flat, flat))
    print(case("steel 0.6 m away, held out in the same place", dipole, dipole))
    print(case("steel 0.6 m away, held out 0.3 m nearer to it", dipole, {**dipole, "centre_m": (0.3, 0.0, 0.0)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
