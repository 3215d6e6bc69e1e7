"""Write the reference calibration files that ``tests/test_reference_files.py`` reads back.

One calibration file per error model registered in :data:`trimag.models.MODELS` (ellipsoid, ortho-gain,
ortho-gain-bias, scalar9, interference12, zhang-cheng), one ellipsoid calibration with regressor terms
(``ellipsoid-regressors``: format 2.0.0; its rows carry ``current`` and ``temperature``) and one Tolles–Lawson
compensation file, each fitted with
trimag's public API (:func:`trimag.fit`, :func:`trimag.estimators.tolles_lawson.fit_tolles_lawson`) on fixed-seed
simulated data (:mod:`trimag.simulate`). Beside each ``NAME.json``:

``NAME.in.csv``
    a few raw rows in nT, rounded to 0.01 nT as a log would hold them (``bx,by,bz``; for ``tolles-lawson``
    ``t,bx,by,bz,scalar``: consecutive rows of the simulated flight, 10 Hz);
``NAME.out.csv``
    what ``apply`` of the trimag that wrote the file gave for those rows, at full precision (``bx,by,bz``
    corrected; for ``tolles-lawson`` ``interference,compensated`` in nT).

These files stand for calibrations written by an earlier trimag: the test checks that today's code still reads
each one (format and version) and maps ``in`` to ``out`` to 1e-9 relative. They are **not** regenerated when the
code changes: a failing test means files in users' hands would now be read differently. Regenerate one only for a
deliberate change of the file format or of ``apply``'s maths (with a new format version and, for an older major
version, a migration in ``trimag.io.legacy``), and say so in the commit.

Usage, from the repository root::

    python tests/data/calibrations/make.py                  # write the files of models that have none yet
    python tests/data/calibrations/make.py scalar9 --overwrite   # rewrite one model's files
"""

from __future__ import annotations

import argparse
import csv
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

import trimag
from trimag.estimators.tolles_lawson import fit_tolles_lawson
from trimag.models import ErrorModel, available_models, get_model
from trimag.simulate import current_profile, simulate, simulate_aircraft, temperature_ramp

HERE = Path(__file__).resolve().parent
COMPENSATION = "tolles-lawson"
REGRESSORS = "ellipsoid-regressors"

F_NT = 48_000.0  # field magnitude, nT
FIELD_NED = F_NT * np.array([0.45, 0.1, 0.88]) / np.linalg.norm([0.45, 0.1, 0.88])  # inclination ~ 62 deg
NOISE_NT = 20.0
N_SAMPLES = 600
N_ROWS = 6  # rows of each .in.csv
SEED = 2024
# the sensor's true correction: gains, non-orthogonality and a hard-iron offset every model can express
TRUE_MATRIX = np.array([[1.05, 0.02, -0.01], [0.0, 0.96, 0.03], [0.0, 0.0, 1.0]])
TRUE_OFFSET = np.array([420.0, -250.0, 130.0])


def _truth(model: str) -> ErrorModel:
    """The simulated sensor in ``model``'s own parameters."""
    cls = get_model(model)
    if model == "ortho-gain":  # no offset in this model
        params = get_model("ortho-gain-bias").from_matrix_offset(TRUE_MATRIX, TRUE_OFFSET).as_dict()
        return cls.from_dict({k: v for k, v in params.items() if k not in ("bx", "by", "bz")})
    if model == "scalar9":
        return cls.from_matrix_offset(TRUE_MATRIX, TRUE_OFFSET, gauge="magnitude")  # type: ignore[call-arg]
    return cls.from_matrix_offset(TRUE_MATRIX, TRUE_OFFSET)


def _write_csv(path: Path, header: Sequence[str], rows: NDArray[np.float64], *, decimals: int | None) -> None:
    """Rows as text: rounded to ``decimals`` or, with ``None``, Python's shortest round-trip repr."""
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(header)
        for row in rows:
            w.writerow([f"{v:.{decimals}f}" if decimals is not None else repr(float(v)) for v in row])


def read_rows(path: Path) -> NDArray[np.float64]:
    """A file written by :func:`_write_csv` as a (rows, columns) float array (every value parsed exactly)."""
    return np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)


def write_calibration(model: str) -> None:
    """Fit ``model`` (its default method) on a simulated sensor; write the file, in and out rows."""
    vector = model == "interference12"  # fitted against the background field vector and the attitudes
    attitudes = "axes" if model in ("ortho-gain", "ortho-gain-bias") else "random"  # paper A: axis turns
    sim = simulate(_truth(model), n=N_SAMPLES, field_nav=FIELD_NED, noise=NOISE_NT, attitudes=attitudes, seed=SEED)
    if vector:
        cal = trimag.fit(sim.raw, model, reference=FIELD_NED, units="nT", attitude=sim.attitude)
    else:
        cal = trimag.fit(sim.raw, model, reference=F_NT, units="nT")
    cal.to_file(HERE / f"{model}.json")
    rows = np.round(sim.raw[:: len(sim.raw) // N_ROWS][:N_ROWS], 2)
    _write_csv(HERE / f"{model}.in.csv", ["bx", "by", "bz"], rows, decimals=2)
    rows = read_rows(HERE / f"{model}.in.csv")  # exactly what the test will read
    _write_csv(HERE / f"{model}.out.csv", ["bx", "by", "bz"], cal.apply(rows), decimals=None)


def write_regressors() -> None:
    """Fit ``ellipsoid`` with a current (30, -20, 50 nT/A) and a temperature (2, 1, -3 nT/degC) term."""
    sim = simulate(_truth("ellipsoid"), n=N_SAMPLES, field_nav=FIELD_NED, noise=NOISE_NT, seed=SEED)
    rng = np.random.default_rng(SEED)
    current, temperature = current_profile(N_SAMPLES, rng), temperature_ramp(N_SAMPLES, rng)
    raw = sim.raw + np.outer(current, [30.0, -20.0, 50.0]) + np.outer(temperature, [2.0, 1.0, -3.0])
    cal = trimag.fit(raw, reference=F_NT, units="nT", regressors={"current": current, "temperature": temperature})
    cal.to_file(HERE / f"{REGRESSORS}.json")
    table = np.column_stack([raw, current, temperature])
    rows = np.round(table[:: len(raw) // N_ROWS][:N_ROWS], 2)
    _write_csv(HERE / f"{REGRESSORS}.in.csv", ["bx", "by", "bz", "current", "temperature"], rows, decimals=2)
    rows = read_rows(HERE / f"{REGRESSORS}.in.csv")
    out = cal.apply(rows[:, :3], regressors={"current": rows[:, 3], "temperature": rows[:, 4]})
    _write_csv(HERE / f"{REGRESSORS}.out.csv", ["bx", "by", "bz"], out, decimals=None)


def write_compensation() -> None:
    """Fit a Tolles–Lawson compensation on a simulated calibration box; write the file, in and out rows."""
    box = simulate_aircraft(60.0, rate_hz=10.0, seed=SEED)
    comp = fit_tolles_lawson(
        box.vector_nT, box.scalar_nT, rate_hz=box.rate_hz, segments=box.segments, bootstrap=50, seed=SEED,
        sensors={"source": f"trimag.simulate.simulate_aircraft(60.0, rate_hz=10.0, seed={SEED})",
                 "vector_columns": ["bx", "by", "bz"], "scalar_column": "scalar", "time_column": "t",
                 "units": "nT", "input_units": "nT"},
    )
    comp.to_file(HERE / f"{COMPENSATION}.json")
    start = box.segments[1][0] + 100  # 1.2 s of the manoeuvres on the second heading
    sl = slice(start, start + 12)
    rows = np.column_stack([box.time_s[sl], box.vector_nT[sl], box.scalar_nT[sl]])
    _write_csv(HERE / f"{COMPENSATION}.in.csv", ["t", "bx", "by", "bz", "scalar"], rows, decimals=2)
    rows = read_rows(HERE / f"{COMPENSATION}.in.csv")
    interference = comp.interference(rows[:, 1:4], rows[:, 4])
    compensated = comp.apply(rows[:, 1:4], rows[:, 4])
    _write_csv(HERE / f"{COMPENSATION}.out.csv", ["interference", "compensated"],
               np.column_stack([interference, compensated]), decimals=None)


def main(argv: Sequence[str] | None = None) -> int:
    names = [*available_models(), REGRESSORS, COMPENSATION]
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("names", nargs="*", metavar="NAME",
                        help=f"files to write (default: every one that is missing): {', '.join(names)}")
    parser.add_argument("--overwrite", action="store_true", help="rewrite files that exist (see the docstring)")
    args = parser.parse_args(argv)
    unknown = sorted(set(args.names) - set(names))
    if unknown:
        parser.error(f"unknown {', '.join(unknown)}; choose from {', '.join(names)}")
    for name in args.names or names:
        if (HERE / f"{name}.json").exists() and not args.overwrite:
            print(f"{name}.json exists; kept (--overwrite to rewrite it)")
            continue
        if name == COMPENSATION:
            write_compensation()
        elif name == REGRESSORS:
            write_regressors()
        else:
            write_calibration(name)
        print(f"wrote {name}.json, {name}.in.csv, {name}.out.csv")
    return 0


if __name__ == "__main__":
    sys.exit(main())
