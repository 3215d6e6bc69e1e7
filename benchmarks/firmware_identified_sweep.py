"""Short simulated flights: how well the firmware fit of each source tree predicts a second flight (issue 38,
``_identified``'s noise rule and what a level holds).

    python benchmarks/firmware_identified_sweep.py --new src --old /tmp/old/src

For every case (samples 40, 80, 200; the random walk's tilt bound 5, 15, 35 deg; sensor noise 2 and 10 mGauss; four
seeds, two with a compass far from the log's calibration, diagonal (1.1, 0.9, 1.2) and an off-diagonal 0.05, two
near it, diagonal (1.02, 0.99, 1.0)) a flight is simulated as ``tests/vehicle/test_firmware.py`` does (offsets, a
30 A current term, the log's calibration the identity with zero offsets), ``fit_firmware`` fits it (level and motor
``auto``, vector residual) and its parameters are put through ArduPilot's formula on a second flight of 2000 samples
tilted up to 35 deg (its own attitudes and current profile): the vector RMS against the true field, mGauss. Each tree
runs in its own process; printed: per case both RMS, and the geometric mean of new / old by group (far or near,
samples) with how many cases are more than 1 % better or worse.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
CASES = [(n, tilt, noise, seed) for n in (40, 80, 200) for tilt in (5.0, 15.0, 35.0) for noise in (2.0, 10.0)
         for seed in (1, 2, 3, 4)]


def _run_cases() -> dict[str, float | None]:
    """The second-flight RMS of every case with the trimag on ``sys.path`` (run in a child process)."""
    sys.path.insert(0, str(HERE.parent / "tests" / "vehicle"))
    import test_firmware as tf  # the tests' flight simulator

    from trimag.errors import TrimagError
    from trimag.models.firmware import ArduPilotCompass
    from trimag.vehicle.firmware import fit_firmware

    out: dict[str, float | None] = {}
    for n, tilt, noise, seed in CASES:
        tf.NOISE_mG = noise
        far = seed in (1, 2)
        truth = ArduPilotCompass(orientation=0, offsets=[120.0, -80.0, 40.0], scale=1.0,
                                 diagonal=[1.1, 0.9, 1.2] if far else [1.02, 0.99, 1.0],
                                 offdiagonal=[0.05, 0.0, 0.0] if far else [0.01, 0.0, 0.0],
                                 motor=[2.0, -1.5, 3.0], motor_type="current")
        held = ArduPilotCompass(orientation=0, offsets=[0.0, 0.0, 0.0])
        raw, h, x = tf.simulate(truth, n, seed=seed, max_tilt_deg=tilt, yaw_step_deg=8.0)
        raw2, h2, x2 = tf.simulate(truth, 2000, seed=seed + 50, max_tilt_deg=35.0)
        try:
            fit = fit_firmware("ardupilot", raw, field_body=h, held=held, applied_orientation=0,
                               motor_values={"current": x})
        except TrimagError:
            out[str((n, tilt, noise, seed))] = None
            continue
        B = fit.compass.correct(raw2, x2)
        out[str((n, tilt, noise, seed))] = float(np.sqrt(np.mean(np.sum((B - h2) ** 2, axis=1))))
    return out


def _tree(src: Path) -> dict[str, float | None]:
    env = {**os.environ, "PYTHONPATH": str(src.resolve())}
    proc = subprocess.run([sys.executable, __file__, "--child"], env=env, capture_output=True, text=True, check=True)
    return json.loads(proc.stdout)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--new", type=Path, default=HERE.parent / "src", help="the source tree to judge (its src)")
    ap.add_argument("--old", type=Path, required=False, help="the source tree to compare with (its src)")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(_run_cases()))
        return
    new = _tree(args.new)
    old = _tree(args.old) if args.old else None
    print("case (samples, tilt bound deg, noise mG, seed)  second-flight RMS, mGauss: new" + (" / old" if old else ""))
    for key, value in new.items():
        other = f" / {old[key]:.1f}" if old and old[key] is not None else (" / refused" if old else "")
        print(f"{key:<28} {'refused' if value is None else f'{value:.1f}'}{other}")
    if not old:
        return
    for group, seeds in (("far", (1, 2)), ("near", (3, 4))):
        for n in (40, 80, 200):
            keys = [k for k in new if new[k] and old[k] and int(k.strip("()").split(",")[0]) == n
                    and int(k.strip("()").split(",")[3]) in seeds]
            ratio = np.array([new[k] / old[k] for k in keys])  # type: ignore[operator]
            print(f"{group:<5} {n:>4} samples: new/old geometric mean {np.exp(np.mean(np.log(ratio))):.3f}, "
                  f"better {int(np.sum(ratio < 0.99))}, worse {int(np.sum(ratio > 1.01))} of {len(keys)}")
    keys = [k for k in new if new[k] and old[k]]
    ratio = np.array([new[k] / old[k] for k in keys])  # type: ignore[operator]
    print(f"all: new/old geometric mean {np.exp(np.mean(np.log(ratio))):.3f}, better {int(np.sum(ratio < 0.99))}, "
          f"worse {int(np.sum(ratio > 1.01))} of {len(keys)}")


if __name__ == "__main__":
    main()
