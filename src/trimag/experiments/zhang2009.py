"""``trimag reproduce zhang2009``: paper D (Zhang & Cheng 2009), the simple linear method from limited attitudes.

Three parts (methods.md, "Paper D"):

1. **The paper's case.** Sensor :data:`TRUTH` (alpha 0.8, beta 0.5, gamma 1.1 deg; K = (1.02, 0.99, 1.01);
   b = (0.03, 0.02, 0.01)) in a unit field, 40 noise-free samples on the attitude path :func:`paper_attitudes`.
   Table: the true ``W``, the paper's printed ``W`` (its first three values; the rest is lost in the OCR), and
   ``W`` from ``quadric``, ``lms`` and ``bfgs``, with every physical parameter's error and the identifiability
   report. The same path without the tilt (both turns about the vertical) shows which parameters a turn about
   one axis leaves undetermined (the fit refuses: exit 3).
2. **Full sphere.** 40 noise-free samples at uniformly random attitudes: all three methods agree.
3. **Noise sweep.** sigma in :data:`SIGMAS` (per axis, unit field) on both the paper's path and the full sphere,
   Monte Carlo: the median error of ``W`` and of the corrected field vector, per method.

The attitude path (our reading of the paper; its equation for the path is lost). The paper: "Phi starts at 0 deg,
one sample every 5 deg, 40 samples, i.e. the sensor turns 120 deg about Z and 200 deg in the horizontal plane".
We take sample ``k = 0..39`` at the attitude (body -> NED navigation frame, intrinsic Z-Y-Z)::

    R_k = Rz(psi_k) Ry(tilt) Rz(zeta_k),   psi_k = 5k deg (0..195: the 200 deg turn in the horizontal plane),
                                            zeta_k = 3k deg (0..117: the 120 deg turn about the sensor's Z),
                                            tilt = 90 deg (the sensor lies on its side on the turntable)

in the unit Earth field ``F_n = (cos I, 0, sin I)`` (NED) with inclination ``I = 45 deg`` (about that of Wuhan,
where the authors work). With ``tilt = 0`` both turns are about the vertical: a single-axis turn.
"""

from __future__ import annotations

import argparse
import math
import warnings
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from ..calibration import Calibration
from ..errors import IdentifiabilityError, TrimagInputError
from ..estimators.bfgs import BFGS
from ..estimators.lms import LMS
from ..estimators.quadric import Quadric
from ..models.zhang_cheng import ZhangCheng
from ..parallel import map_trials
from ..simulate import body_field, random_attitudes, uniform_directions
from ..solvers import identifiability_report
from ._output import jsonable, save_figure, write_csv

__all__ = [
    "FIELD_NAV",
    "INCLINATION_DEG",
    "METHODS",
    "PAPER_W_FIRST3",
    "SIGMAS",
    "TILT_DEG",
    "TRUTH",
    "add_arguments",
    "fit_all",
    "noise_sweep",
    "paper_attitudes",
    "paper_case",
    "run",
]

#: The paper's sensor (angles given in degrees, stored in radians).
TRUTH = ZhangCheng(
    alpha=math.radians(0.8), beta=math.radians(0.5), gamma=math.radians(1.1),
    kx=1.02, ky=0.99, kz=1.01, bx=0.03, by=0.02, bz=0.01,
)
#: The first three values of W as printed in the paper (the rest is cut off in the OCR).
PAPER_W_FIRST3 = (0.9616, 1.0209, 0.9806)
#: Inclination of the unit Earth field (our choice), degrees.
INCLINATION_DEG = 45.0
#: Tilt of the sensor's Z axis from the vertical on the turntable (our reading), degrees.
TILT_DEG = 90.0
#: Unit field in the NED navigation frame.
FIELD_NAV = np.array([math.cos(math.radians(INCLINATION_DEG)), 0.0, math.sin(math.radians(INCLINATION_DEG))])
#: Noise levels of the sweep (standard deviation per axis, unit field).
SIGMAS = (0.0, 1e-6, 1e-5, 1e-4, 1e-3, 1e-2)
#: The compared methods, in table order.
METHODS = ("quadric", "lms", "bfgs")
_ESTIMATORS = {"quadric": Quadric, "lms": LMS, "bfgs": BFGS}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Extra options of this experiment."""
    parser.add_argument("--tilt-deg", type=float, default=TILT_DEG, help="sensor Z tilt on the turntable")
    parser.add_argument("--inclination-deg", type=float, default=INCLINATION_DEG, help="field inclination")


def paper_attitudes(n: int = 40, *, tilt_deg: float = TILT_DEG) -> Rotation:
    """The paper's limited path: ``R_k = Rz(5k deg) Ry(tilt) Rz(3k deg)``, k = 0..n-1 (body -> NED)."""
    k = np.arange(n, dtype=np.float64)
    return Rotation.from_euler("ZYZ", np.column_stack([5.0 * k, np.full(n, tilt_deg), 3.0 * k]), degrees=True)


def field_nav(inclination_deg: float = INCLINATION_DEG) -> NDArray[np.float64]:
    """Unit field (NED) with the given inclination and zero declination."""
    inc = math.radians(inclination_deg)
    return np.array([math.cos(inc), 0.0, math.sin(inc)])


def _fit(method: str, V: NDArray[np.float64], **options: Any) -> Calibration | str:
    """Fit with a unit reference; the IdentifiabilityError message instead of numbers when refused."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            return _ESTIMATORS[method](**options).fit(V, 1.0).calibration_
        except (IdentifiabilityError, TrimagInputError) as exc:  # refused, or an iterative method diverged
            return str(exc)


def _param_errors(est: ZhangCheng, truth: ZhangCheng = TRUTH) -> dict[str, float]:
    """Absolute errors; angles in degrees (``alpha_deg`` ...), gains dimensionless, offsets in field units."""
    a, t = est.as_report(), truth.as_report()
    return {k: abs(a[k] - t[k]) for k in t}


def _vector_error(est: ZhangCheng, test: NDArray[np.float64], truth: ZhangCheng = TRUTH) -> float:
    """RMS of ``|B_hat - B|`` over test directions (unit field): how well the fit corrects the whole sphere."""
    return float(np.sqrt(np.mean(np.sum((est.correct(truth.distort(test)) - test) ** 2, axis=1))))


def fit_all(V: NDArray[np.float64], test: NDArray[np.float64], **options: Any) -> dict[str, dict[str, Any]]:
    """Fit ``V`` with every method; per method W, parameters, errors and fit statistics (or the refusal)."""
    w_true = TRUTH.w_vector()
    out: dict[str, dict[str, Any]] = {}
    for method in METHODS:
        res = _fit(method, V, **options.get(method, {}))
        if isinstance(res, str):
            out[method] = {"error": res}
            continue
        est = ZhangCheng.from_dict(res.params)
        w = est.w_vector()
        out[method] = {
            "W": w.tolist(),
            "W_error": float(np.max(np.abs(w - w_true))),
            "params": est.as_report(),
            "param_errors": _param_errors(est),
            "max_param_error": max(_param_errors(est).values()),
            "vector_error": _vector_error(est, test),
            "rms_after": float(res.stats["rms_after"]),
            "iterations": int(res.stats["iterations"]),
            "converged": bool(res.stats["converged"]),
            "rank": res.diagnostics.get("rank"),
            "condition_number": res.diagnostics.get("condition_number"),
            "undetermined": res.diagnostics.get("undetermined"),
        }
    return out


def paper_case(*, tilt_deg: float = TILT_DEG, inclination_deg: float = INCLINATION_DEG) -> dict[str, Any]:
    """Part 1: the paper's 40 noise-free samples, plus the single-axis (tilt 0) variant."""
    test = uniform_directions(2000, seed=12345)
    V = TRUTH.distort(body_field(paper_attitudes(40, tilt_deg=tilt_deg), field_nav(inclination_deg)))
    fits = fit_all(V, test)
    loose = _fit("bfgs", V, gtol=1e-5)
    if not isinstance(loose, str):
        est = ZhangCheng.from_dict(loose.params)
        fits["bfgs_gtol_1e-5"] = {
            "W": est.w_vector().tolist(),
            "W_error": float(np.max(np.abs(est.w_vector() - TRUTH.w_vector()))),
            "max_param_error": max(_param_errors(est).values()),
            "param_errors": _param_errors(est),
            "vector_error": _vector_error(est, test),
            "iterations": int(loose.stats["iterations"]),
        }
    report = identifiability_report(V, 1.0).as_dict()
    V0 = TRUTH.distort(body_field(paper_attitudes(40, tilt_deg=0.0), field_nav(inclination_deg)))
    single = identifiability_report(V0, 1.0).as_dict()
    refusal = _fit("quadric", V0)
    single["quadric_message"] = refusal if isinstance(refusal, str) else "fitted (unexpected)"
    return {
        "V": V,
        "fits": fits,
        "identifiability": report,
        "single_axis": single,
        "W_true": TRUTH.w_vector().tolist(),
    }


def full_sphere(n: int = 40, *, seed: int = 0) -> dict[str, Any]:
    """Part 2: ``n`` noise-free samples at uniformly random attitudes."""
    test = uniform_directions(2000, seed=12345)
    V = TRUTH.distort(body_field(random_attitudes(n, seed), FIELD_NAV))
    fits = fit_all(V, test)
    ws = [np.array(f["W"]) for f in fits.values() if "W" in f]
    spread = float(max(np.max(np.abs(a - b)) for a in ws for b in ws)) if len(ws) > 1 else math.nan
    return {"n": n, "fits": fits, "identifiability": identifiability_report(V, 1.0).as_dict(), "max_W_spread": spread}


def _sweep_cell(args: tuple[str, float, int, int, float, float]) -> dict[str, Any]:
    path, sigma, trials, seed, tilt_deg, inclination_deg = args
    test = uniform_directions(2000, seed=12345)
    rng = np.random.default_rng([seed, round(sigma * 1e9), 0 if path == "paper" else 1])
    per: dict[str, dict[str, list[float]]] = {m: {"W": [], "vec": [], "rms": []} for m in METHODS}
    failed = dict.fromkeys(METHODS, 0)
    for _ in range(trials):
        if path == "paper":
            B = body_field(paper_attitudes(40, tilt_deg=tilt_deg), field_nav(inclination_deg))
        else:
            B = body_field(random_attitudes(40, rng), FIELD_NAV)
        V = TRUTH.distort(B) + (rng.normal(scale=sigma, size=B.shape) if sigma > 0 else 0.0)
        for method, r in fit_all(V, test).items():
            if "error" in r:
                failed[method] += 1
                continue
            per[method]["W"].append(r["W_error"])
            per[method]["vec"].append(r["vector_error"])
            per[method]["rms"].append(r["rms_after"])
    row: dict[str, Any] = {"path": path, "sigma": sigma, "trials": trials,
                           "uncorrected_vector_error": _vector_error(ZhangCheng(), test)}
    for m in METHODS:
        row[f"{m}_W_error_median"] = float(np.median(per[m]["W"])) if per[m]["W"] else None
        row[f"{m}_vector_error_median"] = float(np.median(per[m]["vec"])) if per[m]["vec"] else None
        row[f"{m}_rms_after_median"] = float(np.median(per[m]["rms"])) if per[m]["rms"] else None
        row[f"{m}_refused"] = failed[m]
    return row


def noise_sweep(
    *, trials: int, seed: int, workers: int = 1, sigmas: tuple[float, ...] = SIGMAS,
    tilt_deg: float = TILT_DEG, inclination_deg: float = INCLINATION_DEG,
) -> list[dict[str, Any]]:
    """Part 3: Monte Carlo over sigma on the paper's path and on the full sphere (40 samples each)."""
    cells = [(p, s, trials, seed, tilt_deg, inclination_deg) for p in ("paper", "sphere") for s in sigmas]
    return map_trials(_sweep_cell, cells, workers=workers, progress="noise sweep")


# ---------------------------------------------------------------------------------------------- output
def _figure(out: Path, sweep: list[dict[str, Any]], V: NDArray[np.float64]) -> str:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 4), layout="constrained")
    ax0 = fig.add_subplot(1, 3, 1, projection="3d")
    az, pol = np.meshgrid(np.linspace(0, 2 * np.pi, 25), np.linspace(0, np.pi, 13))
    ax0.plot_wireframe(np.sin(pol) * np.cos(az), np.sin(pol) * np.sin(az), np.cos(pol), color="0.85", lw=0.4)
    ax0.scatter(*V.T, c=np.arange(len(V)), cmap="viridis", s=12)
    ax0.set_title("raw output, paper's 40 samples")
    for j, path in enumerate(("paper", "sphere")):
        ax = fig.add_subplot(1, 3, 2 + j)
        rows = [r for r in sweep if r["path"] == path and r["sigma"] > 0]
        s = [r["sigma"] for r in rows]
        for m, mark in zip(METHODS, ("o-", "s--", "^:"), strict=True):
            y = [r[f"{m}_vector_error_median"] for r in rows]
            ax.loglog(s, [np.nan if v is None else v for v in y], mark, label=m)
        ax.loglog(s, s, "k-", lw=0.6, label="sigma")
        ax.loglog(s, [r["uncorrected_vector_error"] for r in rows], "k:", lw=0.8, label="uncorrected")
        ax.set_xlabel("noise sigma per axis (unit field)")
        ax.set_ylabel("median RMS |B_hat - B| over the sphere")
        ax.set_title("paper's 40-sample path" if path == "paper" else "40 samples, full sphere")
        ax.grid(True, which="both", lw=0.3)
        ax.legend(fontsize=8)
    save_figure(fig, out / "noise_sweep.png")
    return "noise_sweep.png"


def _w_table_text(case: dict[str, Any]) -> str:
    fits = case["fits"]
    head = f"{'W entry':>8} {'true':>13} {'paper':>8}" + "".join(f" {m:>13}" for m in METHODS)
    lines = [head]
    terms = ("xx", "yy", "zz", "xy", "xz", "yz", "x", "y", "z", "1")
    for i, t in enumerate(terms):
        paper = f"{PAPER_W_FIRST3[i]:8.4f}" if i < 3 else f"{'--':>8}"
        vals = "".join(
            f" {fits[m]['W'][i]:13.8f}" if "W" in fits[m] else f" {'refused':>13}" for m in METHODS
        )
        lines.append(f"{t:>8} {case['W_true'][i]:13.8f} {paper}{vals}")
    return "\n".join(lines)


def _param_table_text(case: dict[str, Any]) -> str:
    fits = case["fits"]
    names = list(TRUTH.as_report())
    truth = TRUTH.as_report()
    lines = [f"{'param':>10} {'true':>10}" + "".join(f" {m + ' err':>13}" for m in METHODS)]
    for n in names:
        vals = "".join(
            f" {fits[m]['param_errors'][n]:13.3e}" if "param_errors" in fits[m] else f" {'--':>13}"
            for m in METHODS
        )
        lines.append(f"{n:>10} {truth[n]:10.5f}{vals}")
    return "\n".join(lines)


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
    """Run the three parts, write CSV tables and a PNG figure into ``out_dir``, return the JSON summary.

    ``extra`` may hold ``tilt_deg``, ``inclination_deg`` (the attitude path) and ``sigmas`` (the sweep's noise
    levels, default :data:`SIGMAS`).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    n_trials = trials if trials is not None else (5 if quick else 20)
    tilt = float(extra.get("tilt_deg", TILT_DEG) or TILT_DEG)
    inc = float(extra.get("inclination_deg", INCLINATION_DEG) or INCLINATION_DEG)

    case = paper_case(tilt_deg=tilt, inclination_deg=inc)
    sphere = full_sphere(40, seed=seed)
    sigmas = tuple(float(x) for x in (extra.get("sigmas") or SIGMAS))
    sweep = noise_sweep(trials=n_trials, seed=seed, workers=workers, sigmas=sigmas, tilt_deg=tilt,
                        inclination_deg=inc)

    _write_tables(out, case, sphere, sweep)
    figure = _figure(out, sweep, case["V"])
    text = _text(case, sphere, sweep, tilt=tilt, inc=inc, n_trials=n_trials, figure=figure)
    summary = _summary(case, sphere, sweep, tilt=tilt, inc=inc, n_trials=n_trials, seed=seed, figure=figure,
                       text=text)
    cleaned: dict[str, Any] = jsonable(summary)
    return cleaned


def _write_tables(out: Path, case: dict[str, Any], sphere: dict[str, Any], sweep: list[dict[str, Any]]) -> None:
    """Write ``w_table.csv``, ``param_errors.csv`` and ``noise_sweep.csv`` into ``out``."""
    terms = ("xx", "yy", "zz", "xy", "xz", "yz", "x", "y", "z", "1")
    w_rows = []
    for i, t in enumerate(terms):
        row: list[Any] = [t, case["W_true"][i], PAPER_W_FIRST3[i] if i < 3 else None]
        for part in (case, sphere):
            row += [part["fits"][m]["W"][i] if "W" in part["fits"][m] else None for m in METHODS]
        w_rows.append(row)
    write_csv(out / "w_table.csv",
         ["term", "W_true", "W_paper", *[f"{p}_{m}" for p in ("paper_path", "full_sphere") for m in METHODS]],
         w_rows)
    p_rows = []
    for n, v in TRUTH.as_report().items():
        row = [n, v]
        for part in (case, sphere):
            row += [part["fits"][m]["param_errors"][n] if "param_errors" in part["fits"][m] else None
                    for m in METHODS]
        p_rows.append(row)
    write_csv(out / "param_errors.csv",
         ["param", "true", *[f"{p}_{m}_abs_error" for p in ("paper_path", "full_sphere") for m in METHODS]],
         p_rows)
    sweep_keys = list(sweep[0].keys())
    write_csv(out / "noise_sweep.csv", sweep_keys, [[r[k] for k in sweep_keys] for r in sweep])


def _text(
    case: dict[str, Any], sphere: dict[str, Any], sweep: list[dict[str, Any]], *, tilt: float, inc: float,
    n_trials: int, figure: str,
) -> str:
    """The reproduction's text summary."""
    ident = case["identifiability"]
    single = case["single_axis"]
    fits = case["fits"]
    text = [
        "Paper D reproduction (trimag reproduce zhang2009)",
        "true sensor: " + ", ".join(f"{k}={v:.6g}" for k, v in TRUTH.as_report().items()),
        f"attitude path: R_k = Rz(5k deg) Ry({tilt:g} deg) Rz(3k deg), k = 0..39 (body -> NED); unit field, "
        f"inclination {inc:g} deg, declination 0",
        f"quadric design on this path: rank {ident['rank']} of {ident['n_columns']}, condition number "
        f"{ident['condition_number']:.3g}; physical Jacobian rank {ident['physical_rank']} of 9, condition "
        f"{ident['physical_condition_number']:.3g}; undetermined: {ident['undetermined'] or 'none'}",
        "",
        "W on the paper's 40 noise-free samples:",
        _w_table_text(case),
        "",
        "absolute parameter errors (angles in degrees):",
        _param_table_text(case),
        "",
        "summary (paper's path, noise-free): "
        + "; ".join(
            f"{m}: max|W err| {fits[m]['W_error']:.2e}, max param err {fits[m]['max_param_error']:.2e}, "
            f"{fits[m]['iterations']} iterations"
            for m in (*METHODS, "bfgs_gtol_1e-5") if m in fits and "W_error" in fits[m]
        ),
        "",
        f"same path with tilt 0 (both turns about the vertical): rank {single['rank']} of {single['n_columns']}; "
        f"undetermined: {', '.join(single['undetermined'])}",
        f"quadric refuses: {single['quadric_message']}",
        "",
        f"full sphere, 40 noise-free samples: max |W| spread between methods {sphere['max_W_spread']:.2e}; "
        + "; ".join(f"{m}: max|W err| {sphere['fits'][m].get('W_error', math.nan):.2e}" for m in METHODS),
        "",
        f"noise sweep ({n_trials} trials per cell; median RMS |B_hat - B| over the sphere):",
        f"{'path':>7} {'sigma':>8}" + "".join(f" {m:>10}" for m in METHODS) + f" {'uncorrected':>11}",
    ]
    for r in sweep:
        text.append(
            f"{r['path']:>7} {r['sigma']:8.0e}"
            + "".join(
                f" {r[f'{m}_vector_error_median']:10.2e}" if r[f"{m}_vector_error_median"] is not None
                else f" {'refused':>10}"
                for m in METHODS
            )
            + f" {r['uncorrected_vector_error']:11.2e}"
        )
    text.append(f"outputs: w_table.csv, param_errors.csv, noise_sweep.csv, {figure}")
    return "\n".join(text)


def _summary(
    case: dict[str, Any], sphere: dict[str, Any], sweep: list[dict[str, Any]], *, tilt: float, inc: float,
    n_trials: int, seed: int, figure: str, text: str,
) -> dict[str, Any]:
    """The JSON summary (before :func:`jsonable`)."""
    ident = case["identifiability"]
    single = case["single_axis"]
    fits = case["fits"]
    return {
        "W_true": case["W_true"],
        "W_paper_first3": list(PAPER_W_FIRST3),
        **{f"W_{m}": fits[m].get("W") for m in METHODS},
        "param_errors": {m: fits[m].get("param_errors") for m in METHODS},
        "max_param_error": {m: fits[m].get("max_param_error") for m in METHODS},
        "W_error": {m: fits[m].get("W_error") for m in METHODS},
        "iterations": {m: fits[m].get("iterations") for m in METHODS},
        "bfgs_gtol_1e-5": {k: v for k, v in fits.get("bfgs_gtol_1e-5", {}).items() if k != "W"},
        "identifiability": ident,
        "single_axis_variant": single,
        "attitude_path": {
            "formula": "R_k = Rz(5k deg) Ry(tilt) Rz(3k deg), k=0..39, intrinsic ZYZ, body -> NED",
            "tilt_deg": tilt,
            "field_nav": field_nav(inc).tolist(),
            "inclination_deg": inc,
        },
        "full_sphere": {
            "max_W_spread": sphere["max_W_spread"],
            **{f"W_{m}": sphere["fits"][m].get("W") for m in METHODS},
            "W_error": {m: sphere["fits"][m].get("W_error") for m in METHODS},
            "max_param_error": {m: sphere["fits"][m].get("max_param_error") for m in METHODS},
            "identifiability": sphere["identifiability"],
        },
        "noise_sweep": sweep,
        "trials": n_trials,
        "seed": seed,
        "outputs": ["w_table.csv", "param_errors.csv", "noise_sweep.csv", figure],
        "text": text,
    }
