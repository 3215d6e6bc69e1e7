"""Accuracy benchmark: Monte Carlo accuracy of the ellipsoid estimators (trimag's and the installable peers')
against the Cramér–Rao bound. Results table in docs/accuracy.md.

Run from the repository root (this folder is not part of the installed package)::

    nice -n 10 python benchmarks/accuracy.py --out bench-accuracy              # full grid, 200 trials per cell
    nice -n 10 python benchmarks/accuracy.py --out bench-accuracy --quick      # 10 trials, N in {400, 2000}
    python benchmarks/accuracy.py --out DIR --sizes 400 --estimators ml magcc:lm --trials 50
    python benchmarks/accuracy.py --out ALL --merge PART1 PART2 ...        # one table from runs split by N/estimator

Peers need the optional extra: ``pip install trimag[bench]``.

Grid: ``sigma/F`` in {4e-4, 1e-2, 5e-2} x ``N`` in {400, 2000, 20000} x coverage in {full sphere, one hemisphere,
three great circles}; ``trials`` trials per cell with fixed seeds. Truth: a fixed hard + soft iron sensor with
``det W = 1`` and ``F = 1``. Every estimator gets the same raw samples and **no** magnitude and no noise level
(trimag's methods estimate both); peers that need a field magnitude are given ``F = 1``, magyc's TWOSTEP the true
noise level (it cannot estimate it). Results are compared in the gauge every method can be brought to:
upper-triangular ``W`` scaled to ``det W = 1``, and the offset.

Per cell and estimator: RMS error / sqrt(CRLB) of each of the 9 parameters (max over parameters reported), the
RMS error of the corrected field and of the corrected magnitude on 500 noise-free test directions spread over the
whole sphere (divided by their CRLB prediction), the 1-sigma coverage of trimag's reported uncertainty, failures
and time. The bound is :func:`trimag.quality.crlb.crlb` for the cell's directions (trial 0), ``known_magnitude=False``.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import io
import json
import time
import warnings
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from trimag.estimators import DEFAULT_METHOD, available_methods, get_estimator
from trimag.io.atomic import atomic_write_text
from trimag.models.ellipsoid import Ellipsoid, to_upper
from trimag.quality.crlb import UPPER, crlb
from trimag.quality.diagnostics import fibonacci_sphere
from trimag.simulate import great_circle_directions, hemisphere_directions, uniform_directions

__all__ = ["PEERS", "add_arguments", "main", "markdown_tables", "merge", "run", "summarise", "truth"]

SIGMAS = (4e-4, 1e-2, 5e-2)
SIZES = (400, 2000, 20000)
COVERAGES = ("full", "hemisphere", "circles")
NAMES = ("w11", "w12", "w13", "w22", "w23", "w33", "b_x", "b_y", "b_z")


def truth() -> Ellipsoid:
    """The simulated sensor: distortion ``D`` (det 1) and offset ``b`` (field unit, ``F = 1``)."""
    D = np.array([[1.08, 0.03, -0.02], [0.0, 0.93, 0.04], [0.0, 0.0, 1.0]])
    D = D / np.linalg.det(D) ** (1 / 3)
    return Ellipsoid.from_matrix_offset(np.linalg.inv(D), [0.2, -0.1, 0.15])


def _directions(coverage: str, n: int, seed: int) -> NDArray[np.float64]:
    if coverage == "full":
        return uniform_directions(n, seed)
    if coverage == "hemisphere":
        return hemisphere_directions(n, seed)
    return great_circle_directions(n)  # three orthogonal great circles, evenly sampled


# ---- estimators: (W, b) in the data's frame, any gauge -------------------------------------------------
Fit = Callable[[NDArray[np.float64], float], tuple[NDArray[np.float64], NDArray[np.float64], Any]]


def _trimag(method: str) -> Fit:
    cls = get_estimator(method)

    def fit(raw: NDArray[np.float64], sigma: float) -> tuple[NDArray[np.float64], NDArray[np.float64], Any]:
        cal = cls().fit(raw).calibration_
        return np.asarray(cal.matrix), np.asarray(cal.offset), cal.uncertainty

    return fit


def _magyc_ellipsoid(raw: NDArray[np.float64], sigma: float) -> tuple[Any, Any, Any]:
    import magyc

    hi, si, _ = magyc.ellipsoid_fit(raw)
    return np.linalg.inv(si), hi, None


def _magyc_twostep(raw: NDArray[np.float64], sigma: float) -> tuple[Any, Any, Any]:
    import magyc

    if not hasattr(np, "Inf"):  # magyc 1.0.0 uses np.Inf, removed in numpy 2 (magyc pins numpy < 2)
        setattr(np, "Inf", np.inf)  # noqa: B010
    hi, si, _ = magyc.twostep_hsi(raw, np.array([1.0, 0.0, 0.0]), measurement_noise_std=sigma)
    return np.linalg.inv(si), hi, None


def _magcc_lm(raw: NDArray[np.float64], sigma: float) -> tuple[Any, Any, Any]:
    from magcc.magcc import calibrate_lm

    with contextlib.redirect_stdout(io.StringIO()):
        hi, si, _, _ = calibrate_lm(raw, 1.0)
    return si, hi, None


def _magcc_lse(raw: NDArray[np.float64], sigma: float) -> tuple[Any, Any, Any]:
    from magcc.magcc import calibrate_lse

    with contextlib.redirect_stdout(io.StringIO()):
        hi, si, _, _ = calibrate_lse(raw, 1.0)
    return si, hi, None


def _mag_cal(raw: NDArray[np.float64], sigma: float) -> tuple[Any, Any, Any]:
    from mag_cal.sensor import Sensor

    s = Sensor()
    s.fit_ellipsoid(raw.copy())
    # Sensor.apply: (data - centre) @ transform, i.e. W = transform.T
    return np.asarray(s.transform).T, np.asarray(s.centre).ravel(), None


def _magcal(raw: NDArray[np.float64], sigma: float) -> tuple[Any, Any, Any]:
    from magcal import MagnetometerCalibrator

    with contextlib.redirect_stdout(io.StringIO()):
        p = MagnetometerCalibrator().ellipsoid_fit(raw)
    return np.real(p["transform_matrix"]), p["center"], None


#: Peer adapters: name -> (adapter, description).
PEERS: dict[str, tuple[Fit, str]] = {
    "magyc:ellipsoid_fit": (_magyc_ellipsoid, "magyc 1.0.0 ellipsoid_fit (algebraic, Bazhin port)"),
    "magyc:twostep_hsi": (_magyc_twostep, "magyc 1.0.0 twostep_hsi (Alonso-Shuster; given true sigma)"),
    "magcc:lm": (_magcc_lm, "magcc 0.1.1 calibrate_lm (magnitude LS, F given)"),
    "magcc:lse": (_magcc_lse, "magcc 0.1.1 calibrate_lse (algebraic)"),
    "circuitpython-mag-cal": (_mag_cal, "circuitpython-mag-cal 1.4.1 Sensor.fit_ellipsoid (algebraic)"),
    "magcal": (_magcal, "magcal 1.0.1 ellipsoid_fit (centre = data mean)"),
}


def _normalised(W: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    U = to_upper(W)
    U = U / abs(np.linalg.det(U)) ** (1 / 3)
    return np.concatenate([U[UPPER], np.asarray(b, dtype=np.float64).ravel()])


def _estimators(names: list[str] | None) -> dict[str, Fit]:
    out: dict[str, Fit] = {}
    for m in available_methods("ellipsoid"):
        out[m] = _trimag(m)
    out.update({k: v[0] for k, v in PEERS.items()})
    if names:
        unknown = [n for n in names if n not in out]
        if unknown:
            raise ValueError(f"unknown estimators {unknown}; choose from {sorted(out)}")
        out = {k: out[k] for k in names}
    return out


def run_cell(
    sigma: float, n: int, coverage: str, trials: int, seed: int, estimators: dict[str, Fit]
) -> list[dict[str, Any]]:
    """Monte Carlo of one cell; one summary row per estimator."""
    t_model = truth()
    W_t, b_t = t_model.correction()
    theta_t = _normalised(W_t, b_t)
    D_t = np.linalg.inv(W_t)
    test = fibonacci_sphere(500)
    X_test = test @ D_t.T + b_t
    y_true = test
    bound = crlb(t_model, _directions(coverage, n, seed), sigma, known_magnitude=False,
                 test_directions=test)
    crlb_std = bound.std[:9]
    errs: dict[str, list[Any]] = {k: [] for k in estimators}
    score: dict[str, dict[int, float]] = {k: {} for k in estimators}
    field: dict[str, list[float]] = {k: [] for k in estimators}
    mag: dict[str, list[float]] = {k: [] for k in estimators}
    inside: dict[str, list[Any]] = {k: [] for k in estimators}
    fails: dict[str, int] = dict.fromkeys(estimators, 0)
    times: dict[str, float] = dict.fromkeys(estimators, 0.0)
    for t in range(trials):
        rng = np.random.default_rng([seed, int(sigma * 1e7), n, COVERAGES.index(coverage), t])
        u = _directions(coverage, n, int(rng.integers(2**31)))
        raw = u @ D_t.T + b_t + rng.normal(scale=sigma, size=(n, 3))
        for name, fit in estimators.items():
            t0 = time.perf_counter()
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    W, b, unc = fit(raw.copy(), sigma)
                th = _normalised(np.asarray(W, dtype=np.float64), np.asarray(b, dtype=np.float64))
                if not np.all(np.isfinite(th)):
                    raise ValueError("non-finite result")
            except Exception:
                fails[name] += 1
                times[name] += time.perf_counter() - t0
                continue
            times[name] += time.perf_counter() - t0
            e = th - theta_t
            errs[name].append(e)
            score[name][t] = float(np.sum((e / crlb_std) ** 2))
            U = np.zeros((3, 3))
            U[UPPER] = th[:6]
            y = (X_test - th[6:]) @ U.T
            field[name].append(float(np.mean(np.sum((y - y_true) ** 2, axis=1))))
            mag[name].append(float(np.mean((np.linalg.norm(y, axis=1) - 1.0) ** 2)))
            if unc and "param_std" in unc:
                # reported std of W entries is in the det(W) = 1 gauge already (unknown magnitude)
                std = np.array(list(unc["param_std"].values())[:9], dtype=np.float64)
                inside[name].append(np.abs(e) <= std)
    rows = []
    default = DEFAULT_METHOD["ellipsoid"]
    for name in estimators:
        ok = len(errs[name])
        row: dict[str, Any] = {"sigma": sigma, "n": n, "coverage": coverage, "estimator": name,
                               "trials": trials, "failures": fails[name],
                               "time_per_fit_s": times[name] / max(trials, 1)}
        if ok:
            E = np.array(errs[name])
            ratio = np.sqrt(np.mean(E**2, axis=0)) / crlb_std
            row.update({f"ratio_{k}": float(v) for k, v in zip(NAMES, ratio, strict=True)})
            row["ratio_max"] = float(ratio.max())
            row["ratio_rms"] = float(np.sqrt(np.mean(ratio**2)))
            # Monte Carlo standard error of one parameter's ratio (chi distribution): ratio / sqrt(2 trials)
            row["ratio_se"] = float(row["ratio_rms"] / np.sqrt(2 * ok))
            row["field_rms"] = float(np.sqrt(np.mean(field[name])))
            row["magnitude_rms"] = float(np.sqrt(np.mean(mag[name])))
            row["ratio_field"] = row["field_rms"] / bound.field_rms
            row["ratio_magnitude"] = row["magnitude_rms"] / bound.magnitude_rms
            row["bias_max_sigma"] = float(np.max(np.abs(E.mean(axis=0)) / crlb_std))
            if inside[name]:
                row["coverage_1sigma"] = float(np.mean(inside[name]))
            if name != default and default in score and score[default]:
                common = sorted(set(score[name]) & set(score[default]))
                if len(common) > 1:
                    diff = np.array([score[default][t] - score[name][t] for t in common])
                    # paired comparison on the same data: mean of sum_k (e_k / crlb_k)^2, default minus this
                    row["paired_diff_vs_default"] = float(-diff.mean())
                    row["paired_se"] = float(diff.std(ddof=1) / np.sqrt(len(common)))
                    row["default_worse"] = bool(diff.mean() > 2 * row["paired_se"]) or (
                        fails[default] > fails[name])
        rows.append(row)
    return rows


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the grid and the estimators (the command line adds ``--out``, ``--trials`` ...: :func:`main`)."""
    parser.add_argument("--sigmas", type=float, nargs="+", default=None, help="sigma/F values (default: full grid)")
    parser.add_argument("--sizes", type=int, nargs="+", default=None, help="sample counts N")
    parser.add_argument("--coverages", nargs="+", default=None, choices=COVERAGES)
    parser.add_argument("--estimators", nargs="+", default=None, help="trimag methods and peer names")


def run(
    out_dir: Path, *, quick: bool = False, trials: int | None = None, seed: int = 0, workers: int = 1,
    json_mode: bool = False, sigmas: list[float] | None = None, sizes: list[int] | None = None,
    coverages: list[str] | None = None, estimators: list[str] | None = None, **extra: Any,
) -> dict[str, Any]:
    """Run the grid; write ``accuracy.csv`` and ``accuracy.json`` into ``out_dir``; return the summary.

    ``quick``: 10 trials, N in {400, 2000}. Default ``trials``: 200.
    """
    out_dir = Path(out_dir)
    trials = trials or (10 if quick else 200)
    sig = list(sigmas or SIGMAS)
    ns = list(sizes or ((400, 2000) if quick else SIZES))
    covs = list(coverages or COVERAGES)
    est = _estimators(estimators)
    cells = [(s, n, c) for s in sig for n in ns for c in covs]
    rows: list[dict[str, Any]] = []
    progress: Any = None
    try:
        from rich.console import Console
        from rich.progress import Progress

        progress = Progress(transient=True, console=Console(stderr=True)) if not json_mode else None
    except ImportError:  # pragma: no cover
        progress = None
    if workers > 1:
        from trimag.parallel import map_trials

        for cell_rows in map_trials(
            partial(_cell_star, trials=trials, seed=seed, estimators=estimators), cells, workers=workers,
            progress="accuracy",
        ):
            rows.extend(cell_rows)
    else:
        task = None
        if progress is not None:
            progress.start()
            task = progress.add_task("accuracy", total=len(cells))
        try:
            for s, n, c in cells:
                rows.extend(run_cell(s, n, c, trials, seed, est))
                write_rows(out_dir, rows)  # partial results survive an interrupted run
                if progress is not None:
                    progress.advance(task)
        finally:
            if progress is not None:
                progress.stop()
    write_rows(out_dir, rows)
    summary = summarise(rows)
    summary["text"] = markdown_tables(rows)
    atomic_write_text(out_dir / "accuracy.md", summary["text"])
    summary.update({"trials": trials, "seed": seed, "default_method": DEFAULT_METHOD["ellipsoid"],
                    "peers": {k: v[1] for k, v in PEERS.items()}})
    atomic_write_text(out_dir / "accuracy.json", json.dumps({"summary": summary, "rows": rows}, indent=1))
    return summary


def merge(parts: list[Path], out_dir: Path) -> dict[str, Any]:
    """Merge the ``accuracy.json`` of several runs (e.g. the grid split by N or by estimator, same seed) into
    one ``accuracy.csv/.json/.md`` in ``out_dir``.

    Rows are keyed by (sigma, N, coverage, estimator); a key present in several parts must have the same
    trial count and results in each (the same seed gives the same data), else :class:`ValueError`. The
    paired comparisons against the default method stay those computed within each part.
    """
    rows: dict[tuple[Any, ...], dict[str, Any]] = {}
    meta: dict[str, Any] = {}
    for part in parts:
        data = json.loads((Path(part) / "accuracy.json").read_text())
        seeds = {data["summary"].get("seed")}
        if meta and meta.get("seed") not in seeds:
            raise ValueError(f"{part}: seed {seeds} differs from the other parts' {meta.get('seed')}")
        meta.setdefault("seed", data["summary"].get("seed"))
        for r in data["rows"]:
            key = (r["sigma"], r["n"], r["coverage"], r["estimator"])
            if key in rows:
                old = rows[key]
                if old["trials"] != r["trials"] or not np.isclose(old.get("ratio_max", np.nan),
                                                                  r.get("ratio_max", np.nan), equal_nan=True):
                    if old["estimator"] != DEFAULT_METHOD["ellipsoid"]:
                        raise ValueError(f"{part}: {key} differs from an earlier part")
                    # the default appears in every part for the paired comparisons; keep the most trials
                    if r["trials"] <= old["trials"]:
                        continue
                else:
                    continue
            rows[key] = r
    merged = sorted(rows.values(), key=lambda r: (r["sigma"], r["n"], r["coverage"], r["estimator"]))
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_rows(out_dir, merged)
    summary = summarise(merged)
    summary["text"] = markdown_tables(merged)
    summary.update({"seed": meta.get("seed"), "parts": [str(p) for p in parts],
                    "default_method": DEFAULT_METHOD["ellipsoid"], "peers": {k: v[1] for k, v in PEERS.items()}})
    atomic_write_text(out_dir / "accuracy.md", summary["text"])
    atomic_write_text(out_dir / "accuracy.json", json.dumps({"summary": summary, "rows": merged}, indent=1))
    return summary


def _cell_star(cell: tuple[Any, ...], *, trials: int, seed: int, estimators: Any) -> Any:
    """``_cell_by_name`` for one ``(sigma, n, coverage)`` cell (a picklable single-argument task)."""
    s, n, c = cell
    return _cell_by_name(s, n, c, trials, seed, estimators)


def _cell_by_name(
    s: float, n: int, c: str, trials: int, seed: int, estimators: list[str] | None
) -> list[dict[str, Any]]:
    return run_cell(s, n, c, trials, seed, _estimators(estimators))


def write_rows(out_dir: Path, rows: list[dict[str, Any]]) -> None:
    """Write ``accuracy.csv`` (one row per cell and estimator) atomically."""
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=keys)
    w.writeheader()
    w.writerows(rows)
    atomic_write_text(Path(out_dir) / "accuracy.csv", buf.getvalue())


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per cell: the default method's ratios, the best peer (smallest max ratio), and whether any peer is
    better than the default: a paired comparison on the same trials of ``sum_k (e_k / sqrt(CRLB_k))^2``, "better"
    meaning lower by more than two standard errors (or fewer failures)."""
    default = DEFAULT_METHOD["ellipsoid"]
    cells: dict[tuple[Any, ...], list[dict[str, Any]]] = {}
    for r in rows:
        cells.setdefault((r["sigma"], r["n"], r["coverage"]), []).append(r)
    out = []
    for (s, n, c), rs in cells.items():
        d = next((r for r in rs if r["estimator"] == default), None)
        peers = [r for r in rs if r["estimator"] in PEERS and "ratio_max" in r and r["failures"] == 0]
        best_peer = min(peers, key=lambda r: r["ratio_max"]) if peers else None
        entry: dict[str, Any] = {"sigma": s, "n": n, "coverage": c}
        if d and "ratio_max" in d:
            entry.update({"default_ratio_max": d["ratio_max"], "default_ratio_magnitude": d["ratio_magnitude"],
                          "default_coverage_1sigma": d.get("coverage_1sigma")})
        if best_peer:
            entry.update({"best_peer": best_peer["estimator"], "best_peer_ratio_max": best_peer["ratio_max"],
                          "best_peer_ratio_magnitude": best_peer["ratio_magnitude"]})
        peer_rows = [r for r in rs if r["estimator"] in PEERS]
        if d and "ratio_max" in d and peer_rows:
            worse = [r["estimator"] for r in peer_rows if r.get("default_worse")]
            entry["peers_better_than_default"] = worse
            entry["default_not_worse"] = not worse
        out.append(entry)
    return {"cells": out}


def markdown_tables(rows: list[dict[str, Any]]) -> str:
    """Markdown tables, one per noise level: rows = estimators, columns = (N, coverage) cells; each entry
    ``max parameter ratio / corrected-magnitude ratio`` (``fail k`` when some trials failed)."""
    out = []
    sigmas = sorted({r["sigma"] for r in rows})
    cells = sorted({(r["n"], r["coverage"]) for r in rows}, key=lambda c: (c[0], COVERAGES.index(c[1])))
    names = list(dict.fromkeys(r["estimator"] for r in rows))
    short = {"full": "full", "hemisphere": "hemi", "circles": "circles"}
    for s in sigmas:
        out.append(f"\n**sigma/F = {s:g}** (entries: max over the 9 parameters of RMS/sqrt(CRLB) / "
                   "RMS corrected-magnitude error / its CRLB)\n")
        out.append("| estimator | " + " | ".join(f"N={n} {short[c]}" for n, c in cells) + " |")
        out.append("|---|" + "---|" * len(cells))
        for name in names:
            entries = []
            for n, c in cells:
                r = next((x for x in rows if x["sigma"] == s and x["n"] == n and x["coverage"] == c
                          and x["estimator"] == name), None)
                if r is None:
                    entries.append("")
                elif "ratio_max" not in r:
                    entries.append(f"fail {r['failures']}/{r['trials']}")
                else:
                    e = f"{r['ratio_max']:.3g} / {r['ratio_magnitude']:.3g}"
                    if r["failures"]:
                        e += f" (fail {r['failures']})"
                    entries.append(e)
            out.append(f"| {name} | " + " | ".join(entries) + " |")
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    """The command line: ``python benchmarks/accuracy.py --out DIR [options]``; returns the exit code."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="bench-accuracy", help="output folder (accuracy.csv/.json/.md)")
    parser.add_argument("--quick", action="store_true", help="10 trials, N in {400, 2000}")
    parser.add_argument("--trials", type=int, default=None, help="trials per cell (default 200)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=1, help="processes (one cell each)")
    parser.add_argument("--json", action="store_true", help="print the JSON summary on stdout")
    parser.add_argument("-q", "--quiet", action="store_true", help="print nothing on success")
    parser.add_argument("--merge", nargs="+", default=None, metavar="DIR",
                        help="merge the accuracy.json of these earlier runs (same seed) into --out; no new trials")
    add_arguments(parser)
    args = vars(parser.parse_args(argv))
    out, as_json, quiet, parts = Path(args.pop("out")), args.pop("json"), args.pop("quiet"), args.pop("merge")
    t0 = time.monotonic()
    if parts:
        summary = merge([Path(p) for p in parts], out)
    else:
        summary = run(out, json_mode=as_json, **args)
    summary.setdefault("runtime_s", time.monotonic() - t0)
    if as_json:
        print(json.dumps(summary, default=float))
    elif not quiet:
        print(summary["text"])
        print(f"done in {summary['runtime_s']:.1f} s; outputs in {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
