"""``trimag reproduce vehicle12``: paper C (12-coefficient vehicle-interference compensation).

Simulation of the paper's turntable experiment (methods.md, paper C):

* a fluxgate on a non-magnetic three-axis turntable in the IGRF field of the paper's laboratory (Zhangzhou,
  24.44 N 117.80 E, 2014-01-01: NED (36648, -2264, 27069) nT, |F| = 45617 nT);
* the five iron blocks of the paper (100x50x30, 200x50x20, 500x300x1, 500x400x1, 500x500x1 mm at 150, 162,
  175, 321, 416 mm) as point dipoles fixed to the turntable: an induced moment ``V X H`` with the
  shape-limited susceptibility tensor ``X = diag(chi / (1 + N_k chi))`` (``N_k`` the demagnetising factors
  of the equivalent ellipsoid, Osborn/Carlson: ``N_a = abc/3 R_D(b^2, c^2, a^2)``), and a permanent
  moment ``V M_r``;
* error sources: fluxgate noise (per axis), the FVM400's 1 nT resolution, turntable angle errors, and the
  magnetic history of the steel (irreversible/hysteretic magnetisation: each block's induced moment is
  perturbed at every attitude by an isotropic random moment of relative size ``hysteresis``), which is the
  only one of them that makes the 12 "constant" coefficients not quite constant;
* the background ``H_n`` is, as in the paper, the mean of an iron-free run at the 10 fitting attitudes
  (:func:`trimag.fields.attitude.background_from_samples`); the "true" total field of a test attitude is the
  iron-free reading at that attitude (the paper's procedure).

Strong case: all five blocks, fit at 10 attitudes, test at 10 others. Weak case: block 1 only, same 10
fitting attitudes, 5 test attitudes. Metrics: total-field error before/after per attitude, compensation rate
``(|e_b| - |e_a|) / |e_b|`` and precision ``|e_a| / F`` (:mod:`trimag.quality.metrics`), their mean and spread
(standard deviation over the test attitudes, ddof=0; the paper's "均方差"), per-axis vector errors.

Real data: BROAD (``$TRIMAG_SHARED_DATA/broad`` or ``../shared/data/broad``) trials with optical-reference
quaternions (body -> ENU,
scalar first, verified against gravity); fit on one trial, test on the others. No iron-free run or local
field vector exists there, so the background is fitted jointly (``estimate_background``) with ``|H_n|``
fixed to the mean measured magnitude of the fitting trial; see ``docs/method-linear-vector.md``.

The Monte Carlo runs go through :func:`trimag.parallel.map_trials` (``workers``): each run is
:func:`case_trial` with its own seed from :func:`trimag.parallel.trial_seeds`, so the numbers do not depend on
the number of workers.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation
from scipy.special import elliprd

from ..errors import TrimagInputError
from ..estimators.linear_vector import LinearVector
from ..fields.attitude import background_from_samples, body_field, from_euler, from_quaternion
from ..fields.reference import igrf
from ..io.atomic import atomic_write_text
from ..models.interference12 import Interference12
from ..parallel import map_trials, trial_seeds
from ..quality.metrics import compensation_precision, compensation_rate, rms
from ..solvers import fit_with_background, solve_interference
from ._data import shared_data_dir
from ._output import write_dict_csv

__all__ = [
    "BLOCKS",
    "FIT_ATTITUDES",
    "PAPER",
    "TEST_ATTITUDES",
    "WEAK_TEST_ATTITUDES",
    "Setup",
    "add_arguments",
    "block_setup",
    "case_trial",
    "demagnetising_factors",
    "run",
    "run_broad",
    "run_case",
]

#: The paper's blocks: (dimensions mm (x, y, z), centre distance from the sensor mm).
BLOCKS: tuple[tuple[tuple[float, float, float], float], ...] = (
    ((100.0, 50.0, 30.0), 150.0),
    ((200.0, 50.0, 20.0), 162.0),
    ((500.0, 300.0, 1.0), 175.0),
    ((500.0, 400.0, 1.0), 321.0),
    ((500.0, 500.0, 1.0), 416.0),
)

#: Turntable attitudes (yaw/heading, pitch, roll) in degrees, Z-Y-X NED (docs/conventions-attitude.md).
FIT_ATTITUDES = np.array(
    [
        [0, 0, 0], [36, 20, -30], [72, -20, 30], [108, 40, 15], [144, -40, -15],
        [180, 10, 45], [216, -10, -45], [252, 30, 20], [288, -30, -20], [324, 0, 60],
    ],
    dtype=np.float64,
)
TEST_ATTITUDES = np.array(
    [
        [18, 10, 10], [54, -15, 25], [90, 25, -20], [126, -30, 5], [162, 35, -35],
        [198, -5, 30], [234, 15, -10], [270, -25, 40], [306, 5, -25], [342, -35, 15],
    ],
    dtype=np.float64,
)
WEAK_TEST_ATTITUDES = TEST_ATTITUDES[[0, 2, 4, 6, 8]]

#: The laboratory of the paper (Xiamen University Tan Kah Kee College, Zhangzhou) and a date near it.
LAB = (24.44, 117.80, 0.0, "2014-01-01")

#: Numbers the paper reports (Tables 2, 3 and the text).
PAPER: dict[str, Any] = {
    "strong": {"rms_after": 88.0, "rate_spread": 0.015, "precision_spread": 0.0019, "n_test": 10},
    "weak": {"rate_spread": 0.021, "precision_spread": 0.0001, "n_test": 5},
    "note": "spread = the paper's 均方差 of the per-attitude rate / precision",
}

#: Default physical assumptions (see the module docstring and docs/method-linear-vector.md).
DEFAULTS: dict[str, float] = {
    "susceptibility": 100.0,  # intrinsic chi of mild steel in a 50 uT field (initial permeability ~100)
    "remanence": 100.0,  # A/m, weakly magnetised mild steel
    "elevation_deg": 30.0,  # blocks lie on the turntable surface, 30 degrees below the sensor's horizon
    "noise": 2.0,  # nT per axis (fluxgate + laboratory)
    "quantum": 1.0,  # nT, FVM400 resolution
    "attitude_error_deg": 0.01,  # turntable angle error (std per axis)
    # relative irreversible magnetisation per attitude; the one tuned value (strong RMS near paper's 88 nT)
    "hysteresis": 0.012,
}


def demagnetising_factors(dims: tuple[float, float, float]) -> NDArray[np.float64]:
    """Demagnetising factors (3,) of the ellipsoid with semi-axes ``dims / 2`` (sum 1).

    ``N_a = abc/3 R_D(b^2, c^2, a^2)`` (Carlson's symmetric elliptic integral; equivalent to Osborn 1945).
    """
    a, b, c = (0.5 * float(d) for d in dims)
    abc3 = a * b * c / 3.0
    return np.array(
        [
            abc3 * elliprd(b * b, c * c, a * a),
            abc3 * elliprd(c * c, a * a, b * b),
            abc3 * elliprd(a * a, b * b, c * c),
        ]
    )


@dataclass(frozen=True)
class Setup:
    """The iron on the turntable, in the body frame: ``H_m = K H_b + c`` with ``K = I + sum_i G_i X_i``.

    ``G`` (n, 3, 3): dipole geometry ``V/(4 pi r^3) (3 d d^T - I)`` (dimensionless per unit susceptibility),
    ``X`` (n, 3, 3): susceptibility tensors, ``c`` (3,) permanent field (nT).
    """

    G: NDArray[np.float64]
    X: NDArray[np.float64]
    c: NDArray[np.float64]

    @property
    def K(self) -> NDArray[np.float64]:
        return np.eye(3) + np.einsum("nij,njk->ik", self.G, self.X)

    def model(self) -> Interference12:
        return Interference12.from_K_c(self.K, self.c)


def block_setup(
    blocks: tuple[tuple[tuple[float, float, float], float], ...] = BLOCKS,
    *,
    susceptibility: float = DEFAULTS["susceptibility"],
    remanence: float = DEFAULTS["remanence"],
    elevation_deg: float = DEFAULTS["elevation_deg"],
) -> Setup:
    """Dipole model of ``blocks`` at azimuths 0, 72, 144, ... degrees, ``elevation_deg`` below the sensor.

    Blocks lie flat (thinnest side along body z). Remanence directions are fixed (seed 2014): random for the
    compact blocks, in-plane for the 1 mm plates (shape anisotropy).
    """
    rng = np.random.default_rng(2014)
    el = np.radians(elevation_deg)
    G, X, c = [], [], np.zeros(3)
    for i, (dims, r_mm) in enumerate(blocks):
        az = np.radians(72.0 * i)
        d = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        V = float(np.prod(dims)) * 1e-9  # m^3
        r = r_mm * 1e-3
        g = V / (4 * np.pi * r**3) * (3 * np.outer(d, d) - np.eye(3))
        N = demagnetising_factors(dims)
        X.append(np.diag(susceptibility / (1.0 + N * susceptibility)))
        G.append(g)
        u = rng.normal(size=3)
        if min(dims) < 0.05 * max(dims):
            u[int(np.argmin(dims))] = 0.0
        u /= np.linalg.norm(u)
        # B = mu0/(4 pi r^3) (3 d d^T - I) m, m = V M_r; in nT
        c = c + 1e-7 / r**3 * (3 * np.outer(d, d) - np.eye(3)) @ (V * remanence * u) * 1e9
    return Setup(np.array(G), np.array(X), c)


def _measure(
    setup: Setup | None,
    att_true: Rotation,
    H_n: NDArray[np.float64],
    *,
    noise: float,
    quantum: float,
    hysteresis: float,
    rng: np.random.Generator,
) -> NDArray[np.float64]:
    """What the fluxgate reads at the true attitudes (with iron when ``setup`` is given), nT."""
    H_b = body_field(att_true, H_n)
    H = H_b.copy()
    if setup is not None:
        induced = np.einsum("nij,mj->mni", setup.X, H_b)  # (m, n_blocks, 3): X_i H_b
        if hysteresis > 0:
            size = np.linalg.norm(induced, axis=2, keepdims=True)
            induced = induced + hysteresis * size * rng.normal(size=induced.shape) / np.sqrt(3.0)
        H = H + np.einsum("nij,mnj->mi", setup.G, induced) + setup.c
    if noise > 0:
        H = H + rng.normal(scale=noise, size=H.shape)
    if quantum > 0:
        H = np.round(H / quantum) * quantum
    return H


def _perturb(att: Rotation, sigma_deg: float, rng: np.random.Generator) -> Rotation:
    if sigma_deg <= 0:
        return att
    return att * Rotation.from_rotvec(np.radians(sigma_deg) * rng.normal(size=(len(att), 3)))


def run_case(
    setup: Setup,
    fit_euler: NDArray[np.float64],
    test_euler: NDArray[np.float64],
    H_n: NDArray[np.float64],
    *,
    rng: np.random.Generator,
    noise: float,
    quantum: float,
    attitude_error_deg: float,
    hysteresis: float,
) -> dict[str, Any]:
    """One run of the paper's procedure: iron-free background, fit at ``fit_euler``, test at ``test_euler``.

    Returns per-test-attitude arrays (``true``, ``measured``, ``compensated`` totals, ``err_before``,
    ``err_after``, ``rate``, ``precision``, ``vec_before``/``vec_after`` (n, 3)) and the fitted model.
    """
    kw = {"noise": noise, "quantum": quantum, "hysteresis": hysteresis, "rng": rng}
    R_fit = from_euler(fit_euler[:, 0], fit_euler[:, 1], fit_euler[:, 2])
    R_test = from_euler(test_euler[:, 0], test_euler[:, 1], test_euler[:, 2])
    R_fit_true = _perturb(R_fit, attitude_error_deg, rng)
    R_test_true = _perturb(R_test, attitude_error_deg, rng)
    free_fit = _measure(None, R_fit_true, H_n, **kw)  # type: ignore[arg-type]
    H_n_hat, _ = background_from_samples(free_fit, R_fit)
    H_m_fit = _measure(setup, R_fit_true, H_n, **kw)  # type: ignore[arg-type]
    est = LinearVector().fit(H_m_fit, H_n_hat, units="nT", attitude=R_fit)
    cal = est.calibration_
    free_test = _measure(None, R_test_true, H_n, **kw)  # type: ignore[arg-type]
    H_m_test = _measure(setup, R_test_true, H_n, **kw)  # type: ignore[arg-type]
    comp = cal.apply(H_m_test)
    true = np.linalg.norm(free_test, axis=1)
    measured = np.linalg.norm(H_m_test, axis=1)
    compensated = np.linalg.norm(comp, axis=1)
    e_b, e_a = measured - true, compensated - true
    return {
        "true": true, "measured": measured, "compensated": compensated, "err_before": e_b, "err_after": e_a,
        "rate": compensation_rate(e_b, e_a), "precision": compensation_precision(e_a, true),
        "vec_before": H_m_test - free_test, "vec_after": comp - free_test,
        "fitted": Interference12.from_dict(cal.params), "cond": est.cond_, "background": H_n_hat,
    }


def case_trial(
    trial_seed: int,
    *,
    setup: Setup,
    fit_euler: NDArray[np.float64],
    test_euler: NDArray[np.float64],
    H_n: NDArray[np.float64],
    noise: float,
    quantum: float,
    attitude_error_deg: float,
    hysteresis: float,
) -> dict[str, Any]:
    """One Monte Carlo run of :func:`run_case` with its own generator ``np.random.default_rng(trial_seed)``.

    Module-level (picklable) so that :func:`trimag.parallel.map_trials` can run it in worker processes; the
    settings come through :func:`functools.partial`. Returns :func:`run_case`'s dict (a few small arrays).
    """
    rng = np.random.default_rng(trial_seed)
    return run_case(setup, fit_euler, test_euler, H_n, rng=rng, noise=noise, quantum=quantum,
                    attitude_error_deg=attitude_error_deg, hysteresis=hysteresis)


def _summary(cases: list[dict[str, Any]]) -> dict[str, Any]:
    """Mean over Monte Carlo runs of the per-run statistics over the test attitudes."""
    per_run = {
        "rms_before": [rms(c["err_before"]) for c in cases],
        "rms_after": [rms(c["err_after"]) for c in cases],
        "rate_mean": [float(np.mean(c["rate"])) for c in cases],
        "rate_std": [float(np.std(c["rate"])) for c in cases],
        "precision_mean": [float(np.mean(c["precision"])) for c in cases],
        "precision_std": [float(np.std(c["precision"])) for c in cases],
        "precision_rms": [rms(c["precision"]) for c in cases],
        "rate_shortfall_rms": [rms(1.0 - c["rate"]) for c in cases],
        "vector_rms_before": [rms(np.linalg.norm(c["vec_before"], axis=1)) for c in cases],
        "vector_rms_after": [rms(np.linalg.norm(c["vec_after"], axis=1)) for c in cases],
    }
    out: dict[str, Any] = {k: float(np.mean(v)) for k, v in per_run.items()}
    out["rms_after_p10_p90"] = [float(np.percentile(per_run["rms_after"], q)) for q in (10, 90)]
    out["rate_std_p10_p90"] = [float(np.percentile(per_run["rate_std"], q)) for q in (10, 90)]
    for key in ("before", "after"):
        ms = [np.mean(c[f"vec_{key}"] ** 2, axis=0) for c in cases]
        out[f"axis_rms_{key}"] = np.sqrt(np.mean(ms, axis=0)).tolist()
    out["n_runs"] = len(cases)
    out["n_test"] = len(cases[0]["rate"])
    return out


def _table(case: dict[str, Any], euler: NDArray[np.float64]) -> list[dict[str, float]]:
    rows = []
    for i, (y, p, r) in enumerate(euler):
        rows.append(
            {
                "yaw_deg": y, "pitch_deg": p, "roll_deg": r,
                "F_true_nT": case["true"][i], "F_measured_nT": case["measured"][i],
                "F_compensated_nT": case["compensated"][i],
                "error_before_nT": case["err_before"][i], "error_after_nT": case["err_after"][i],
                "rate_pct": 100 * case["rate"][i], "precision_pct": 100 * case["precision"][i],
                "dx_after_nT": case["vec_after"][i, 0], "dy_after_nT": case["vec_after"][i, 1],
                "dz_after_nT": case["vec_after"][i, 2],
            }
        )
    return rows


def _format_table(rows: list[dict[str, float]], title: str) -> str:
    head = f"{'yaw':>5}{'pitch':>6}{'roll':>6}{'F true':>10}{'F meas':>10}{'F comp':>10}{'err bef':>9}" \
           f"{'err aft':>9}{'rate %':>8}{'prec %':>8}"
    lines = [title, head]
    for r in rows:
        lines.append(
            f"{r['yaw_deg']:5.0f}{r['pitch_deg']:6.0f}{r['roll_deg']:6.0f}{r['F_true_nT']:10.0f}"
            f"{r['F_measured_nT']:10.0f}{r['F_compensated_nT']:10.0f}{r['error_before_nT']:9.0f}"
            f"{r['error_after_nT']:9.1f}{r['rate_pct']:8.2f}{r['precision_pct']:8.3f}"
        )
    return "\n".join(lines)


def _noise_free_check(setup: Setup, H_n: NDArray[np.float64]) -> float:
    """Largest coefficient error of a noise-free fit at the 10 fitting attitudes."""
    R = from_euler(FIT_ATTITUDES[:, 0], FIT_ATTITUDES[:, 1], FIT_ATTITUDES[:, 2])
    truth = setup.model()
    K, c, _ = solve_interference(truth.distort(body_field(R, H_n)), body_field(R, H_n))
    return float(np.max(np.abs(Interference12.from_K_c(K, c).as_vector() - truth.as_vector())))


# ---------------------------------------------------------------------------------------------- real data
BROAD_DIR = Path(os.environ["TRIMAG_BROAD_DIR"]) if os.environ.get("TRIMAG_BROAD_DIR") else shared_data_dir() / "broad"
BROAD_FIT = "01_undisturbed_slow_rotation_A.mat"
BROAD_TEST = ("02_undisturbed_slow_rotation_B.mat", "03_undisturbed_slow_rotation_C.mat",
              "06_undisturbed_fast_rotation_A.mat")


def _load_broad(path: Path) -> tuple[NDArray[np.float64], Rotation, dict[str, Any]]:
    import scipy.io as sio

    d = sio.loadmat(str(path))
    mag = np.asarray(d["imu_mag"], dtype=np.float64)
    q = np.asarray(d["opt_quat"], dtype=np.float64)
    ok = np.isfinite(mag).all(axis=1) & np.isfinite(q).all(axis=1)
    att = from_quaternion(q[ok], scalar_first=True, frame="enu")
    acc = np.asarray(d["imu_acc"], dtype=np.float64)[ok]
    # convention check: a resting IMU's accelerometer reads +g along "up" (ENU z = NED -z), in the body frame
    g_body = att.inv().apply([0.0, 0.0, -9.81])
    acc_err = float(np.median(np.linalg.norm(acc - g_body, axis=1)))
    info = {"file": path.name, "n_rows": len(mag), "n_dropped_nan": int((~ok).sum()),
            "median_acc_minus_gravity_mps2": acc_err}
    return mag[ok], att, info


def run_broad(data_dir: Path = BROAD_DIR, *, step: int = 1) -> dict[str, Any]:
    """Fit on BROAD trial 01 (joint background), test on trials 02, 03, 06; errors in uT.

    Returns a dict with per-trial before/after total-field and vector RMS, the fitted background, its
    inclination and that of IGRF at TU Berlin, or ``{"skipped": reason}`` when the data are absent.
    """
    if not (data_dir / BROAD_FIT).exists():
        return {"skipped": f"BROAD data not found in {data_dir} (shared data absent)"}
    mag, att, info_fit = _load_broad(data_dir / BROAD_FIT)
    mag, att = mag[::step], att[::step]
    F = float(np.mean(np.linalg.norm(mag, axis=1)))
    K, c, H_n, info = fit_with_background(mag, att, F)
    model = Interference12.from_K_c(K, c)
    berlin = igrf(52.512, 13.327, 40.0, "2021-01-01")
    incl = float(np.degrees(np.arctan2(H_n[2], np.hypot(H_n[0], H_n[1]))))
    out: dict[str, Any] = {
        "fit_trial": info_fit, "units": "uT", "background_ned_fitted": H_n.tolist(),
        "background_magnitude": F,
        "inclination_fitted_deg": incl, "inclination_igrf_berlin_deg": berlin.inclination_deg,
        "condition_number": info["condition_number"],
        "linear_condition_number": info["linear_condition_number"],
        "K": K.tolist(), "c": c.tolist(), "trials": {},
    }
    for name in (BROAD_FIT, *BROAD_TEST):
        path = data_dir / name
        if not path.exists():
            out["trials"][name] = {"skipped": "file absent"}
            continue
        m, a, inf = _load_broad(path)
        H_b = body_field(a, H_n)
        # in-sample floor: the same joint fit made on this trial itself
        K_s, c_s, _, _ = fit_with_background(m[::step], a[::step], F)
        e_self = np.linalg.norm(Interference12.from_K_c(K_s, c_s).correct(m), axis=1) - F
        # K, c from the fit trial, background re-measured on this trial (mean of the rotated compensated data)
        comp = model.correct(m)
        H_n_own, _ = background_from_samples(comp, a)
        H_b_own = body_field(a, H_n_own)
        F_own = float(np.linalg.norm(H_n_own))
        e_b = np.linalg.norm(m, axis=1) - F
        e_a = np.linalg.norm(comp, axis=1) - F
        out["trials"][name] = {
            **inf,
            "role": "fit" if name == BROAD_FIT else "test",
            "n_used": len(m),
            "total_rms_before": rms(e_b), "total_rms_after": rms(e_a),
            "total_rms_after_self_fit": rms(e_self),
            "background_own_ned": H_n_own.tolist(),
            "total_rms_after_own_background": rms(np.linalg.norm(comp, axis=1) - F_own),
            "vector_rms_after_own_background": rms(np.linalg.norm(comp - H_b_own, axis=1)),
            "mean_magnitude": float(np.mean(np.linalg.norm(m, axis=1))),
            "vector_rms_before": rms(np.linalg.norm(m - H_b, axis=1)),
            "vector_rms_after": rms(np.linalg.norm(comp - H_b, axis=1)),
            "axis_rms_before": np.sqrt(np.mean((m - H_b) ** 2, axis=0)).tolist(),
            "axis_rms_after": np.sqrt(np.mean((comp - H_b) ** 2, axis=0)).tolist(),
        }
    return out


# ---------------------------------------------------------------------------------------------- entry point
def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of this experiment (physical assumptions of the simulation)."""
    g = parser.add_argument_group("vehicle12 simulation")
    g.add_argument("--susceptibility", type=float, default=DEFAULTS["susceptibility"])
    g.add_argument("--remanence", type=float, default=DEFAULTS["remanence"], help="A/m")
    g.add_argument("--noise", type=float, default=DEFAULTS["noise"], help="nT per axis")
    g.add_argument("--attitude-error", type=float, default=DEFAULTS["attitude_error_deg"], help="degrees")
    g.add_argument("--hysteresis", type=float, default=DEFAULTS["hysteresis"])
    g.add_argument("--no-real", action="store_true", help="skip the BROAD real-data part")


def _figure(strong: dict[str, Any], weak: dict[str, Any], path: Path) -> None:
    from matplotlib.figure import Figure

    from ..quality.report import save_figure

    fig = Figure(figsize=(10, 4))
    fig.subplots_adjust(left=0.07, right=0.98, bottom=0.13, top=0.9, wspace=0.25)
    for ax, case, title in zip(fig.subplots(1, 2), (strong, weak), ("strong (5 blocks)", "weak (block 1)"),
                               strict=True):
        k = np.arange(len(case["true"])) + 1
        ax.bar(k - 0.2, np.abs(case["err_before"]), 0.4, label="|error| before")
        ax.bar(k + 0.2, np.abs(case["err_after"]), 0.4, label="|error| after")
        ax.set_yscale("log")
        ax.set_xlabel("test attitude")
        ax.set_ylabel("total-field error (nT)")
        ax.set_title(title)
        ax.legend(fontsize=8, loc="upper right", framealpha=0.8)
    save_figure(fig, path)


def run(
    out_dir: Path,
    *,
    quick: bool = False,
    trials: int | None = None,
    seed: int = 0,
    workers: int = 1,
    json_mode: bool = False,
    **extra: Any,
) -> dict[str, Any]:
    """Run the strong/weak simulation (``trials`` Monte Carlo runs, default 200, quick 20; on ``workers``
    processes via :func:`trimag.parallel.map_trials`) and BROAD."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    p = {k: float(extra[k]) if extra.get(k) is not None else v for k, v in DEFAULTS.items()}
    if extra.get("attitude_error") is not None:
        p["attitude_error_deg"] = float(extra["attitude_error"])
    n_runs = trials or (20 if quick else 200)
    if n_runs < 1:
        raise TrimagInputError(f"--trials must be >= 1; got {n_runs}")
    H_n = igrf(*LAB).ned_nT
    strong_setup = block_setup(susceptibility=p["susceptibility"], remanence=p["remanence"],
                               elevation_deg=p["elevation_deg"])
    weak_setup = block_setup(BLOCKS[:1], susceptibility=p["susceptibility"], remanence=p["remanence"],
                             elevation_deg=p["elevation_deg"])
    kw = {"noise": p["noise"], "quantum": p["quantum"], "attitude_error_deg": p["attitude_error_deg"],
          "hysteresis": p["hysteresis"]}
    progress = not json_mode

    def runs(setup: Setup, test_euler: NDArray[np.float64], seeds: list[int], label: str,
             **over: float) -> list[dict[str, Any]]:
        settings: dict[str, Any] = {**kw, **over}
        fn = partial(case_trial, setup=setup, fit_euler=FIT_ATTITUDES, test_euler=test_euler, H_n=H_n,
                     **settings)
        return map_trials(fn, seeds, workers=workers, progress=label if progress else False)

    seeds = trial_seeds(seed, 2 * n_runs)
    strong_runs = runs(strong_setup, TEST_ATTITUDES, seeds[:n_runs], "strong-case runs")
    weak_runs = runs(weak_setup, WEAK_TEST_ATTITUDES, seeds[n_runs:], "weak-case runs")
    strong, weak = _summary(strong_runs), _summary(weak_runs)
    budget = _error_budget(runs, strong_setup, weak_setup, n_runs, seed)
    table_strong = _table(strong_runs[0], TEST_ATTITUDES)
    table_weak = _table(weak_runs[0], WEAK_TEST_ATTITUDES)
    write_dict_csv(out_dir / "vehicle12_table2_strong.csv", table_strong)
    write_dict_csv(out_dir / "vehicle12_table3_weak.csv", table_weak)
    _figure(strong_runs[0], weak_runs[0], out_dir / "vehicle12_errors.png")
    real = {"skipped": "--no-real"} if extra.get("no_real") else run_broad(step=4 if quick else 1)
    summary: dict[str, Any] = {
        "strong": strong,
        "weak": weak,
        "paper": PAPER,
        "assumptions": {**p, "background": "mean of a simulated iron-free run at the 10 fitting attitudes",
                        "field_ned_nT": H_n.tolist(), "lab": list(LAB)},
        "interference": {
            "strong_K": strong_setup.K.tolist(), "strong_c_nT": strong_setup.c.tolist(),
            "weak_K": weak_setup.K.tolist(), "weak_c_nT": weak_setup.c.tolist(),
        },
        "noise_free_max_coefficient_error": _noise_free_check(strong_setup, H_n),
        "error_budget_rms_after_nT": budget,
        "real_broad": real,
        "outputs": ["vehicle12_table2_strong.csv", "vehicle12_table3_weak.csv", "vehicle12_errors.png",
                    "vehicle12_summary.json"],
    }
    text = "\n\n".join(
        [
            _format_table(table_strong, "Strong interference (5 blocks), run 0 (cf. paper Table 2), nT"),
            _format_table(table_weak, "Weak interference (block 1), run 0 (cf. paper Table 3), nT"),
            _comparison_text(strong, weak, n_runs),
            _real_text(real),
        ]
    )
    summary["text"] = text
    import json

    atomic_write_text(out_dir / "vehicle12_summary.json", json.dumps(summary, indent=2, default=float))
    atomic_write_text(out_dir / "vehicle12_report.txt", text + "\n")
    return summary


def _error_budget(
    runs: Callable[..., list[dict[str, Any]]], strong_setup: Setup, weak_setup: Setup, n_runs: int, seed: int
) -> dict[str, dict[str, float]]:
    """Which source makes the after-compensation error: RMS after with noise and quantisation only, then the
    turntable error added, then hysteresis (fewer runs; every row reuses the same trial seeds)."""
    budget = {}
    n_b = max(n_runs // 4, 5)
    seeds_b = trial_seeds(seed + 1, 2 * n_b)
    for label, over in (("noise+quantisation", {"attitude_error_deg": 0.0, "hysteresis": 0.0}),
                        ("+turntable error", {"hysteresis": 0.0}), ("+hysteresis (all)", {})):
        cases = runs(strong_setup, TEST_ATTITUDES, seeds_b[:n_b], f"error budget {label}", **over)
        weak_cases = runs(weak_setup, WEAK_TEST_ATTITUDES, seeds_b[n_b:], f"error budget {label}", **over)
        budget[label] = {"strong_rms_after": _summary(cases)["rms_after"],
                         "weak_rms_after": _summary(weak_cases)["rms_after"]}
    return budget


def _comparison_text(strong: dict[str, Any], weak: dict[str, Any], n_runs: int) -> str:
    lines = [
        f"Strong vs weak (mean over {n_runs} simulated runs; spread = std over test attitudes)",
        f"{'':28}{'strong':>12}{'weak':>12}{'paper strong':>14}{'paper weak':>12}",
        f"{'RMS error before (nT)':28}{strong['rms_before']:12.1f}{weak['rms_before']:12.1f}{'-':>14}"
        f"{'-':>12}",
        f"{'RMS error after (nT)':28}{strong['rms_after']:12.1f}{weak['rms_after']:12.1f}{88:14.0f}{'-':>12}",
        f"{'rate mean (%)':28}{100 * strong['rate_mean']:12.2f}{100 * weak['rate_mean']:12.2f}{'-':>14}"
        f"{'-':>12}",
        f"{'rate spread (%)':28}{100 * strong['rate_std']:12.2f}{100 * weak['rate_std']:12.2f}{1.5:14.1f}"
        f"{2.1:12.1f}",
        f"{'precision mean (%)':28}{100 * strong['precision_mean']:12.4f}{100 * weak['precision_mean']:12.4f}"
        f"{'-':>14}{'-':>12}",
        f"{'precision spread (%)':28}{100 * strong['precision_std']:12.4f}{100 * weak['precision_std']:12.4f}"
        f"{0.19:14.2f}{0.01:12.2f}",
        f"{'precision RMS (%)':28}{100 * strong['precision_rms']:12.4f}{100 * weak['precision_rms']:12.4f}"
        f"{'-':>14}{'-':>12}",
        f"{'RMS of 1 - rate (%)':28}{100 * strong['rate_shortfall_rms']:12.2f}"
        f"{100 * weak['rate_shortfall_rms']:12.2f}{'-':>14}{'-':>12}",
        f"{'rate spread p10..p90 (%)':28}{_pct_range(strong['rate_std_p10_p90']):>12}"
        f"{_pct_range(weak['rate_std_p10_p90']):>12}",
    ]
    return "\n".join(lines)


def _pct_range(v: list[float]) -> str:
    return f"{100 * v[0]:.1f}..{100 * v[1]:.1f}"


def _real_text(real: dict[str, Any]) -> str:
    if "skipped" in real:
        return f"BROAD real data: skipped ({real['skipped']})"
    lines = [
        f"BROAD real data (uT): fit on {real['fit_trial']['file']} with a jointly fitted background "
        f"(|H_n| = {real['background_magnitude']:.2f} uT fixed, inclination "
        f"{real['inclination_fitted_deg']:.1f} "
        f"deg vs IGRF Berlin {real['inclination_igrf_berlin_deg']:.1f} deg)",
        f"{'trial':36}{'role':>5}{'NaN rows':>9}{'|B| RMS bef':>12}{'aft':>7}{'self':>7}{'vec RMS bef':>12}"
        f"{'aft':>7}{'own-bg |B|':>11}{'vec':>7}",
    ]
    for name, t in real["trials"].items():
        if "skipped" in t:
            lines.append(f"{name:40} skipped: {t['skipped']}")
            continue
        lines.append(
            f"{name:36}{t['role']:>5}{t['n_dropped_nan']:9d}{t['total_rms_before']:12.3f}{t['total_rms_after']:7.3f}"
            f"{t['total_rms_after_self_fit']:7.3f}{t['vector_rms_before']:12.3f}{t['vector_rms_after']:7.3f}"
            f"{t['total_rms_after_own_background']:11.3f}{t['vector_rms_after_own_background']:7.3f}"
        )
    return "\n".join(lines)
