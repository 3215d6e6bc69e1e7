"""Held-out value of the eddy-current (dB/dt) terms of ``interference12`` on real data (issue 21, item 5).

    python benchmarks/eddy.py broad     # BROAD: IMU magnetometer vs optical orientation, 4 trials
    python benchmarks/eddy.py magnav    # MagNav.jl's 100 s SGL segment: fluxgate A against mag_1_c
    python benchmarks/eddy.py joint     # simulated aircraft: separate vs joint scalar+vector fit

Every number is held out: fitted on one part (a half of a trial, or one trial) and scored on another. The data are
read from ``../shared/data`` (never copied into the repository). See docs/method-tolles-lawson.md, "Past
Tolles–Lawson".
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

import trimag
from trimag.fields.attitude import body_field, from_quaternion
from trimag.vehicle.eddy import EDDY_NAMES, eddy_values, free_mask
from trimag.vehicle.regressors import fit_regressors

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
BROAD = ("01_undisturbed_slow_rotation_A.mat", "02_undisturbed_slow_rotation_B.mat",
         "03_undisturbed_slow_rotation_C.mat", "06_undisturbed_fast_rotation_A.mat")


def _stack(values: dict[str, NDArray[np.float64]]) -> NDArray[np.float64]:
    return np.column_stack([values[n] for n in EDDY_NAMES])


# ------------------------------------------------------------------------------------------------ BROAD
def _load_broad(name: str) -> tuple[NDArray[np.float64], Rotation, NDArray[np.float64], float]:
    """Magnetometer (uT), optical attitudes, dB/dt (uT/s; segments cut where the optical track is lost), rate."""
    import scipy.io as sio

    d = sio.loadmat(str(SHARED / "broad" / name))
    mag = np.asarray(d["imu_mag"], dtype=np.float64)
    q = np.asarray(d["opt_quat"], dtype=np.float64)
    fs = float(np.ravel(d["sampling_rate"])[0])
    ok = np.isfinite(mag).all(axis=1) & np.isfinite(q).all(axis=1)
    t = np.arange(len(mag)) / fs
    dB = _stack(eddy_values(mag[ok], time_s=t[ok])[0])
    return mag[ok], from_quaternion(q[ok], scalar_first=True, frame="enu"), dB, fs


def _errors(corrected: NDArray[np.float64], expected: NDArray[np.float64]) -> tuple[float, float]:
    """Vector RMS (data unit) and RMS angle (deg) between corrected and expected body-frame fields."""
    e = np.sqrt(np.mean(np.sum((corrected - expected) ** 2, axis=1)))
    cos = np.einsum("ij,ij->i", corrected, expected) / (np.linalg.norm(corrected, axis=1)
                                                         * np.linalg.norm(expected, axis=1))
    return float(e), float(np.sqrt(np.mean(np.degrees(np.arccos(np.clip(cos, -1, 1))) ** 2)))


def _fit_vector(mag: NDArray[np.float64], att: Rotation, dB: NDArray[np.float64] | None,
                terms: int = 9) -> tuple[trimag.Calibration, NDArray[np.float64]]:
    """interference12 with a jointly fitted background (|H_n| = mean |B|), optionally with eddy terms."""
    base = trimag.fit(mag, model="interference12", units="uT", attitude=att, estimate_background=True)
    H_n = np.asarray(base.diagnostics["background_ned"])
    if dB is None:
        return base, H_n
    values = dict(zip(EDDY_NAMES, dB.T, strict=True))
    return fit_regressors(base, mag, values, attitude=att, free=free_mask(terms)), H_n


def _score(cal: trimag.Calibration, H_n: NDArray[np.float64], mag: NDArray[np.float64], att: Rotation,
           dB: NDArray[np.float64]) -> tuple[float, float]:
    values = dict(zip(EDDY_NAMES, dB.T, strict=True)) if cal.regressors is not None else None
    return _errors(cal.apply(mag, regressors=values), body_field(att, H_n))


def run_broad() -> list[dict[str, Any]]:
    data = {name: _load_broad(name) for name in BROAD}
    rows = []
    for name, (mag, att, dB, fs) in data.items():
        half = len(mag) // 2
        parts = {"first": slice(0, half), "second": slice(half, None)}
        for fit_part, test_part in (("first", "second"), ("second", "first")):
            f, s = parts[fit_part], parts[test_part]
            row: dict[str, Any] = {"fit": f"{name[:2]} {fit_part} half", "test": f"{name[:2]} {test_part} half",
                                   "rate_hz": fs}
            for label, terms in (("none", None), ("eddy3", 3), ("eddy9", 9)):
                cal, H_n = _fit_vector(mag[f], att[f], None if terms is None else dB[f], terms or 9)
                row[label] = _score(cal, H_n, mag[s], att[s], dB[s])
                if terms == 3:
                    row["lag_ms"] = (-1e3 * np.diag(np.asarray(cal.regressors["coefficients"]))).tolist()
            rows.append(row)
    mag, att, dB, fs = data[BROAD[0]]
    fits = {label: _fit_vector(mag, att, None if t is None else dB, t or 9)
            for label, t in (("none", None), ("eddy3", 3), ("eddy9", 9))}
    for name in BROAD[1:]:
        m, a, d, _ = data[name]
        row = {"fit": f"{BROAD[0][:2]} whole", "test": f"{name[:2]} whole", "rate_hz": fs}
        for label, (cal, H_n) in fits.items():
            row[label] = _score(cal, H_n, m, a, d)
        rows.append(row)
    return rows


def _print_broad(rows: list[dict[str, Any]]) -> None:
    print("BROAD (uT; held out): vector RMS / RMS angle (deg) of interference12 without and with eddy terms")
    print(f"{'fit on':<18}{'scored on':<18}{'no eddy':>16}{'eddy=3':>16}{'eddy=9':>16}   lag from eddy=3 (ms)")
    for r in rows:
        cells = "".join(f"{r[k][0]:8.3f} /{r[k][1]:6.3f}" for k in ("none", "eddy3", "eddy9"))
        lag = " ".join(f"{v:5.1f}" for v in r["lag_ms"]) if "lag_ms" in r else ""
        print(f"{r['fit']:<18}{r['test']:<18}{cells}   {lag}")


# ------------------------------------------------------------------------------------------------ MagNav
def run_magnav() -> dict[str, Any]:
    """Fluxgate A's magnitude against MagNav's compensated scalar ``mag_1_c``, held-out halves (50 s each).

    The 100 s segment has no attitudes (the vector model's background cannot be formed) and its field directions
    stay within a 23-degree cone, so the full nonlinear magnitude fit of ``K``, ``c`` (and ``E``) is refused as
    unidentifiable (all samples within a plane of the noise). Measured instead: its first-order form. To first
    order in the interference, ``|K^-1 (H - c - E dH/dt)| - |H|`` is linear in the direction cosines ``u``:
    ``u.c`` (permanent), ``|H| u_i u_j`` (the symmetric part of ``K - I``: induced) and ``u_i dH_j/dt`` (eddy),
    i.e. the Tolles–Lawson design of the fluxgate itself; it is fitted (band-passed 0.1-0.9 Hz, as TL) to
    ``|H| - mag_1_c`` without and with the eddy terms, and scored on the other half.
    """
    import scipy.io as sio

    from trimag.aircraft.filtering import BandPass
    from trimag.estimators.tolles_lawson import fit_tolles_lawson

    d = sio.loadmat(str(SHARED / "magnav-tl" / "test_data_TL.mat"), squeeze_me=True,
                    struct_as_record=False)["TL_data"]
    fs = float(d.fs)
    B = np.column_stack([d.flux_a_x, d.flux_a_y, d.flux_a_z]).astype(np.float64)
    target = np.linalg.norm(B, axis=1) - np.asarray(d.mag_1_c, dtype=np.float64) + 50_000.0
    bp = BandPass(0.1, 0.9, fs, 4, 20)
    half = len(B) // 2
    parts = {"first": slice(0, half), "second": slice(half, None)}
    rows = []
    for fit_part, test_part in (("first", "second"), ("second", "first")):
        f, s = parts[fit_part], parts[test_part]
        row: dict[str, Any] = {"fit": fit_part, "test": test_part, "raw": float(np.std(bp.apply(target[s])))}
        for label, terms in (("none", "permanent,induced"), ("eddy9", "permanent,induced,eddy")):
            for ridge in (0.0, "cv"):
                comp = fit_tolles_lawson(B[f], target[f], rate_hz=fs, terms=terms, ridge=ridge, bootstrap=0)
                row[f"{label}_{'ls' if ridge == 0.0 else 'cv'}"] = float(np.std(bp.apply(comp.apply(B[s], target[s]))))
        rows.append(row)
    return {"rows": rows}


def _print_magnav(r: dict[str, Any]) -> None:
    print("MagNav SGL segment: fluxgate A |B| - mag_1_c, std of the 0.1-0.9 Hz band-passed difference (nT), held "
          "out; first-order vector model (permanent + induced = 9 terms), + eddy (9 more)")
    print(f"{'fit on':<8}{'scored on':<11}{'raw':>8}{'no eddy LS':>12}{'eddy LS':>10}{'no eddy cv':>12}{'eddy cv':>10}")
    for w in r["rows"]:
        print(f"{w['fit']:<8}{w['test']:<11}{w['raw']:8.3f}{w['none_ls']:12.3f}{w['eddy9_ls']:10.3f}"
              f"{w['none_cv']:12.3f}{w['eddy9_cv']:10.3f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("what", choices=("broad", "magnav", "joint"))
    args = parser.parse_args()
    if args.what == "broad":
        if not (SHARED / "broad" / BROAD[0]).exists():
            sys.exit(f"BROAD data not found in {SHARED / 'broad'}")
        _print_broad(run_broad())
    elif args.what == "magnav":
        if not (SHARED / "magnav-tl" / "test_data_TL.mat").exists():
            sys.exit(f"MagNav data not found in {SHARED / 'magnav-tl'}")
        _print_magnav(run_magnav())
    else:
        from joint_fit import main as joint_main  # type: ignore[import-not-found]

        joint_main()


if __name__ == "__main__":
    main()
