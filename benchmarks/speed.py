"""Speed benchmark of trimag: fit time and peak memory against N (trimag methods and installed peers),
streaming ``apply``/``evaluate`` of a 1e7-row file, and batch throughput with 1 and 2 workers.

Results and the machine they were measured on are recorded in ``docs/performance.md``. Run from the repository
root (this folder is not part of the installed package)::

    python benchmarks/speed.py --out bench-speed            # the full run (~20 min on 2 cores)
    python benchmarks/speed.py --out /tmp/s --quick         # a fast check
    python benchmarks/speed.py --out /tmp/s --skip apply batch --sizes 1e4 1e5 1e6 --estimators ml

Three parts, all measured in one run (``docs/performance.md`` records a run and the command):

1. **Fits.** For N in {1e3, 1e4, 1e5, 1e6, 1e7}: every trimag method and every installed peer (the adapters of
   ``PEERS`` of ``benchmarks/accuracy.py``: magyc, magcc, circuitpython-mag-cal, magcal) on the same data.
   The ellipsoid methods and the peers share one simulated sensor (``accuracy.truth()``, ``F = 1``,
   ``sigma/F = 1e-2``, uniform directions); the methods of other models get a sensor of their own model
   (same distortion where the model can express it) with the reference/attitudes they need. Time: median of
   ``repeats`` runs (``time.perf_counter``, after a warm-up fit on 1000 samples); peak memory: one more run
   under ``tracemalloc`` (numpy allocations included; the input array is allocated before, so not counted).
   Accuracy (ellipsoid group): RMS error of the 9 parameters in the common gauge (upper-triangular ``W`` with
   ``det W = 1``, offset), RMS over ``accuracy_sets`` independent data sets (as many as fit in ``budget``;
   one set alone is mostly noise at N <= 1e5). Speed ratio of a trimag method at N: time of the fastest peer
   whose error is at most 1.1 x the method's own, divided by the method's time. A (method, N) whose time
   projected from the previous N exceeds ``budget`` seconds is skipped and marked so. The growth exponent is
   the least-squares slope of log(time) against log(N) over 1e4 <= N <= 1e7 (the sizes measured).
2. **apply / evaluate.** A CSV (and a Parquet) file of ``apply_rows`` rows (time, x, y, z) is written in a
   temporary folder, then ``trimag apply`` and ``trimag evaluate`` run as separate processes: wall time, rows
   per second and peak resident memory (``/usr/bin/time``, else polled with psutil).
3. **batch.** ``batch_files`` CSV files of ``batch_samples`` samples, fitted with ``trimag.app.batch.fit_batch``
   (default method ``ml``) with 1 and 2 workers (Dask processes, and threads for comparison): files per second.
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import importlib.util
import io
import json
import os
import platform
import pstats
import shutil
import subprocess
import sys
import tempfile
import time
import tracemalloc
import warnings
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from trimag.errors import TrimagInputError
from trimag.estimators import available_methods, get_estimator, make_estimator
from trimag.experiments._output import jsonable, save_figure, write_dict_csv

# Only what a batch worker imports anyway: the worker processes of the batch part are spawned, and a spawned
# process runs its parent's main module (this file) again. ``trimag.simulate`` (scipy.spatial, 0.4 s) and the
# accuracy harness are therefore imported inside the functions that use them (docs/performance.md, batch).
from trimag.io.atomic import atomic_write_text
from trimag.models import get_model
from trimag.models.ellipsoid import to_upper
from trimag.quality.crlb import UPPER

__all__ = ["add_arguments", "machine_facts", "main", "missing_peers", "peer_verdict", "run"]

SIZES = (1_000, 10_000, 100_000, 1_000_000, 10_000_000)
SIGMA = 1e-2
#: Data sets the parameter error of an ellipsoid estimator is averaged over (RMS), budget permitting.
ACCURACY_SETS = 8
ACCURACY_TOLERANCE = 1.1  # a peer "reaches the same accuracy" when its error <= 1.1 x the method's
TARGETS = {"ellipsoid-fit": 0.2, "ml": 1.5}  # seconds at N = 1e6 (issue 8)

# a distortion every model can take (small misalignment, gains, offset), field F = 1
_W = np.array([[1.05, 0.02, -0.01], [0.0, 0.96, 0.03], [0.0, 0.0, 1.0]])
_B = np.array([0.1, -0.05, 0.08])
_FIELD_NAV = np.array([0.45, 0.1, 0.88]) / np.linalg.norm([0.45, 0.1, 0.88])


# ----------------------------------------------------------------------------------------------- data
def _accuracy() -> ModuleType:
    """The accuracy harness beside this file (its simulated sensor ``truth()`` and peer adapters ``PEERS``).

    ``benchmarks/`` is not a package, so the module is loaded from its path, once per process, under the name
    ``_trimag_bench_accuracy`` (the name the tests' ``load_benchmark("accuracy")`` uses too).
    """
    name = "_trimag_bench_accuracy"
    module = sys.modules.get(name)
    if module is None:
        spec = importlib.util.spec_from_file_location(name, Path(__file__).resolve().with_name("accuracy.py"))
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        try:
            spec.loader.exec_module(module)
        except BaseException:
            del sys.modules[name]
            raise
    return module


def _ellipsoid_data(n: int, seed: int) -> NDArray[np.float64]:
    from trimag.simulate import uniform_directions

    u = uniform_directions(n, seed)
    rng = np.random.default_rng(seed + 1)
    raw = _accuracy().truth().distort(u)
    raw += rng.normal(scale=SIGMA, size=raw.shape)
    return raw


def _model_truth(model: str) -> Any:
    M = get_model(model)
    if model == "ortho-gain":
        d = get_model("ortho-gain-bias").from_matrix_offset(_W, _B).as_dict()
        return M.from_dict({k: v for k, v in d.items() if k not in ("bx", "by", "bz")})
    if model == "scalar9":
        return M.from_matrix_offset(_W, _B, gauge="magnitude")  # type: ignore[call-arg]
    return M.from_matrix_offset(_W, _B)


def _model_data(model: str, n: int, seed: int) -> tuple[NDArray[np.float64], Any, Any]:
    """Raw samples, reference and attitude for a method of ``model`` (not the ellipsoid)."""
    from trimag.simulate import simulate

    vector = model == "interference12"
    attitudes = "axes" if model in ("ortho-gain", "ortho-gain-bias") else "random"
    sim = simulate(_model_truth(model), n=n, field_nav=_FIELD_NAV, noise=SIGMA, attitudes=attitudes, seed=seed)
    if vector:
        return sim.raw, _FIELD_NAV.copy(), sim.attitude
    return sim.raw, 1.0, None


def _gyro_data(n: int, seed: int) -> tuple[NDArray[np.float64], Any, Any]:
    """Samples, field magnitude and gyroscope of the gyro-aided fit (:func:`trimag.simulate.simulate_gyro`, 100 Hz)."""
    from trimag.simulate import simulate_gyro

    sim = simulate_gyro(n, seed)
    return sim.raw, float(np.linalg.norm(sim.field_nav)), sim.angular_rate()


#: Methods timed on data of their own (the gyro-aided fit needs the gyroscope's angular rate beside the samples).
_OWN_DATA: dict[str, Callable[[int, int], tuple[NDArray[np.float64], Any, Any]]] = {"gyro": _gyro_data}


# ------------------------------------------------------------------------------------------ estimators
FitFn = Callable[[], tuple[NDArray[np.float64], NDArray[np.float64]] | None]


def _trimag_runner(method: str, model: str, raw: NDArray[np.float64], ref: Any, att: Any) -> FitFn:
    def fit() -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        est = make_estimator(model, method)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            est.fit(raw, ref, attitude=att)
        cal = est.calibration_
        return np.asarray(cal.matrix), np.asarray(cal.offset)

    return fit


def _peer_runner(adapter: Callable[..., Any], raw: NDArray[np.float64]) -> FitFn:
    def fit() -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
            warnings.simplefilter("ignore")
            W, b, _ = adapter(raw, SIGMA)
        return np.real(np.asarray(W, dtype=complex)).astype(float), np.asarray(b, dtype=float).ravel()

    return fit


def _peers(only: list[str] | None = None) -> dict[str, tuple[Callable[..., Any], str]]:
    """The peers of ``benchmarks/accuracy.py`` that import here (name -> (adapter, description)); with
    ``only``, just those names."""
    out = {}
    for name, (adapter, desc) in _accuracy().PEERS.items():
        if only is not None and name not in only:
            continue
        module = {"magyc": "magyc", "magcc": "magcc.magcc", "circuitpython-mag-cal": "mag_cal.sensor",
                  "magcal": "magcal"}[name.split(":")[0]]
        try:
            __import__(module)
        except Exception:
            continue
        out[name] = (adapter, desc)
    return out


def _param_error(W: NDArray[np.float64], b: NDArray[np.float64]) -> float:
    """RMS error of the 9 parameters in the gauge upper-triangular W, det W = 1 (ellipsoid group)."""
    def norm(W: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
        U = to_upper(W)
        U = U / abs(np.linalg.det(U)) ** (1 / 3)
        return np.concatenate([U[UPPER], np.asarray(b, dtype=float).ravel()])

    W0, b0 = _accuracy().truth().correction()
    return float(np.sqrt(np.mean((norm(W, b) - norm(W0, b0)) ** 2)))


def _measure(fit: FitFn, repeats: int) -> tuple[list[float], Any]:
    times = []
    out = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fit()
        times.append(time.perf_counter() - t0)
    return times, out


def _peak_memory(fit: FitFn) -> float:
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        base = tracemalloc.get_traced_memory()[0]
        fit()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    return (peak - base) / 1e6


def _profile(fit: FitFn, top: int = 12) -> str:
    pr = cProfile.Profile()
    pr.enable()
    fit()
    pr.disable()
    buf = io.StringIO()
    pstats.Stats(pr, stream=buf).strip_dirs().sort_stats("cumulative").print_stats(top)
    return buf.getvalue()


#: Bytes of the array :func:`_settle_allocator` allocates and frees.
SETTLE_BYTES = 8 << 20


def _settle_allocator() -> None:
    """Allocate and free one 8 MiB array before any timing.

    glibc's malloc maps every fresh array above its mmap threshold (128 KiB at start) and pays a page fault per
    4 KiB at first touch (~2 us each on this machine); freeing a mapped block raises the threshold to that
    block's size. A process that has loaded or made a log of a few MiB is in the raised state; this benchmark's
    process reaches it only after the first large size, so without this step the fit times at small N (trimag's
    and the peers' alike) depended on which measurement ran before (measured: 320-460 faults, ~1 ms, per fit at
    N = 1e4 for ``ellipsoid-fit`` and ``circuitpython-mag-cal``).
    """
    block = np.ones(SETTLE_BYTES // 8)
    del block


def fit_benchmark(
    sizes: list[int], *, repeats: int, budget: float, seed: int, estimators: list[str] | None,
    profile_at: int | None, log: Callable[[str], None], accuracy_sets: int = ACCURACY_SETS,
) -> tuple[list[dict[str, Any]], dict[str, str]]:
    """Time and memory of every estimator at every size, and the parameter error of the ellipsoid estimators
    over ``accuracy_sets`` data sets (:func:`_accuracy_sets`); returns rows and cProfile texts."""
    _settle_allocator()
    methods = [(m, get_estimator(m).models[0]) for m in available_methods()]
    peers = _peers(estimators or None)
    names = [m for m, _ in methods] + list(_accuracy().PEERS)
    if estimators:
        unknown = sorted(set(estimators) - set(names))
        if unknown:
            raise TrimagInputError(f"unknown estimators {unknown}; choose from {names}")
        methods = [(m, mod) for m, mod in methods if m in estimators]
        peers = {k: v for k, v in peers.items() if k in estimators}
    last: dict[str, tuple[int, float]] = {}
    dead: set[str] = set()
    rows: list[dict[str, Any]] = []
    profiles: dict[str, str] = {}
    warm = {}
    for n in sizes:
        datasets: dict[str, tuple[NDArray[np.float64], Any, Any]] = {"ellipsoid": (_ellipsoid_data(n, seed), 1.0,
                                                                                   None)}
        for model in {mod for _, mod in methods} - {"ellipsoid"}:
            datasets[model] = _model_data(model, n, seed)
        runners: list[tuple[str, str, FitFn, FitFn]] = []
        for m, model in methods:
            if m in _OWN_DATA:  # a method that needs more than the group's samples: its own simulated sensor
                runners.append((m, f"{m} (own sensor)", _trimag_runner(m, model, *_OWN_DATA[m](n, seed)),
                                _trimag_runner(m, model, *_OWN_DATA[m](min(n, 1000), seed))))
                continue
            raw, ref, att = datasets[model]
            ref_arg = None if model == "ellipsoid" else ref  # ellipsoid group: no magnitude, as the peers get
            # the warm-up fit takes 1000 samples spread over the whole log: the first 1000 of a long one cover only
            # a small arc of its turns, which a pair method cannot fit (`--sizes 1e7` alone failed wen2008's warm-up)
            step = max(1, n // 1000)
            small = raw[::step][:1000], _subsample_ref(ref_arg, step), (att[::step][:1000] if att is not None else None)
            runners.append((m, model, _trimag_runner(m, model, raw, ref_arg, att), _trimag_runner(m, model, *small)))
        for name, (adapter, _) in peers.items():
            raw = datasets["ellipsoid"][0]
            runners.append((name, "ellipsoid (peer)", _peer_runner(adapter, raw),
                            _peer_runner(adapter, raw[:: max(1, n // 1000)][:1000])))
        for name, model, fit, small_fit in runners:
            row: dict[str, Any] = {"estimator": name, "kind": "peer" if "peer" in model else "trimag",
                                   "model": model.replace(" (peer)", ""), "n": n}
            if name in dead:
                row["note"] = "skipped: failed at a smaller N"
                rows.append(row)
                continue
            if name in last:
                n0, t0 = last[name]
                projected = t0 * n / n0
                if projected > budget:
                    row["note"] = f"skipped: projected {projected:.0f} s per fit > budget {budget:g} s"
                    rows.append(row)
                    log(f"  {name:24s} N={n:>9,d}  {row['note']}")
                    continue
            try:
                if name not in warm:
                    small_fit()
                    warm[name] = True
                times, out = _measure(fit, repeats)
                row.update(median_s=float(np.median(times)), min_s=float(np.min(times)),
                           max_s=float(np.max(times)), repeats=repeats)
                last[name] = (n, row["median_s"])
                row["peak_mb"] = _peak_memory(fit) if row["median_s"] * 1.5 < budget else None
                if row["model"] == "ellipsoid" and out is not None:
                    row["param_errors"] = [_param_error(*out)]
                if profile_at is not None and n == profile_at and row["kind"] == "trimag" and model == "ellipsoid":
                    profiles[name] = _profile(fit)
                log(f"  {name:24s} N={n:>9,d}  {row['median_s']:.4g} s  "
                    f"{'' if row['peak_mb'] is None else format(row['peak_mb'], '.1f') + ' MB'}")
            except Exception as exc:
                row["error"] = f"{type(exc).__name__}: {str(exc)[:200]}"
                dead.add(name)
                log(f"  {name:24s} N={n:>9,d}  ERROR {row['error']}")
            rows.append(row)
        del datasets, runners
        _accuracy_sets(rows, n, seed=seed, sets=accuracy_sets, budget=budget, methods=dict(methods),
                       peers=peers, log=log)
    return rows, profiles


def _subsample_ref(ref: Any, step: int) -> Any:
    """The reference of a subsample ``[::step][:1000]``: a per-sample array is subsampled, anything else kept."""
    if isinstance(ref, np.ndarray) and ref.ndim == 1 and len(ref) > 1000:
        return ref[::step][:1000]
    return ref


def _accuracy_sets(
    rows: list[dict[str, Any]], n: int, *, seed: int, sets: int, budget: float, methods: dict[str, str],
    peers: dict[str, tuple[Callable[..., Any], str]], log: Callable[[str], None],
) -> None:
    """Add the parameter errors on ``sets - 1`` more data sets (seeds ``seed + 1 ...``) to the ellipsoid rows at
    ``n`` and set ``param_rms_error`` (RMS over the sets) and ``accuracy_sets``.

    One data set decides nothing at N <= 1e5: there the error is mostly noise, and two estimators of equal
    accuracy differ by a factor of 1.5 or more from one draw to the next. An estimator gets as many extra sets
    as fit in ``budget`` seconds (at least the timed one); data sets are generated one at a time, so memory
    stays that of one set.
    """
    todo = [r for r in rows if r["n"] == n and r["model"] == "ellipsoid" and "param_errors" in r]
    for r in todo:
        r["extra_sets"] = min(sets - 1, int(budget // max(r["median_s"], 1e-9)))
    for k in range(1, sets):
        active = [r for r in todo if r["extra_sets"] >= k]
        if not active:
            break
        raw = _ellipsoid_data(n, seed + 1000 * k)  # far from the seeds of other N (seed + 1 is the noise stream)
        for r in active:
            name = r["estimator"]
            fit = (_trimag_runner(name, methods[name], raw, None, None) if r["kind"] == "trimag"
                   else _peer_runner(peers[name][0], raw))
            try:
                r["param_errors"].append(_param_error(*fit()))  # type: ignore[misc]
            except Exception as exc:  # a peer failing on one draw: recorded, the sets it did finish count
                r["accuracy_note"] = f"set {k}: {type(exc).__name__}: {str(exc)[:120]}"
        del raw
    for r in todo:
        errs = np.asarray(r.pop("param_errors"))
        r.pop("extra_sets")
        r["param_rms_error"] = float(np.sqrt(np.mean(errs**2)))
        r["param_error_first_set"] = float(errs[0])
        r["accuracy_sets"] = len(errs)
    if todo:
        log(f"  accuracy at N={n:,}: " + ", ".join(f"{r['estimator']} {r['param_rms_error']:.3g} "
                                                 f"({r['accuracy_sets']} sets)" for r in todo))


def speed_ratios(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per ellipsoid trimag method and N: the fastest peer reaching its accuracy, and the ratio peer/trimag."""
    out = []
    by_n: dict[int, list[dict[str, Any]]] = {}
    for r in rows:
        by_n.setdefault(r["n"], []).append(r)
    for n, rs in sorted(by_n.items()):
        peers = [r for r in rs if r["kind"] == "peer" and "median_s" in r]
        for r in rs:
            if r["kind"] != "trimag" or r["model"] != "ellipsoid" or "median_s" not in r:
                continue
            err = r.get("param_rms_error", np.inf)
            good = [p for p in peers if p.get("param_rms_error", np.inf) <= ACCURACY_TOLERANCE * err]
            fastest_any = min(peers, key=lambda p: p["median_s"]) if peers else None
            entry: dict[str, Any] = {"method": r["estimator"], "n": n, "time_s": r["median_s"],
                                     "param_rms_error": err, "accuracy_sets": r.get("accuracy_sets")}
            if good:
                best = min(good, key=lambda p: p["median_s"])
                entry.update(peer=best["estimator"], peer_time_s=best["median_s"],
                             peer_error=best.get("param_rms_error"), peer_accuracy_sets=best.get("accuracy_sets"),
                             ratio=best["median_s"] / r["median_s"])
            else:
                entry.update(peer=None, ratio=None, note="no peer reaches this accuracy")
            if fastest_any is not None:
                entry.update(fastest_peer=fastest_any["estimator"],
                             fastest_peer_error=fastest_any.get("param_rms_error"),
                             ratio_fastest_any=fastest_any["median_s"] / r["median_s"])
            out.append(entry)
    return out


def missing_peers(estimators: list[str] | None) -> list[str]:
    """The peers asked for (all of ``benchmarks/accuracy.py``'s without ``estimators``) that are not installed."""
    asked = [p for p in _accuracy().PEERS if estimators is None or p in estimators]
    installed = _peers(estimators)
    return [p for p in asked if p not in installed]


def peer_verdict(ratios: list[dict[str, Any]], missing: list[str]) -> dict[str, Any]:
    """The "5x faster than the fastest equally accurate peer" target from the measurements that ran (N >= 1e4).

    ``met`` is None ("not measured") when a peer asked for is not installed (``missing``: the fastest equally
    accurate peer may be one of them) or no peer was measured at any size; a (method, N) without a peer measured
    there is listed in ``not_measured_at``, never counted as met."""
    five_x = [r for r in ratios if r["n"] >= 10_000]
    measured = [r for r in five_x if r.get("fastest_peer") is not None]  # a peer ran at this N
    rated = [r for r in measured if r["ratio"] is not None]
    return {
        "met": None if missing or not measured else all(r["ratio"] >= 5 for r in rated),
        "missing_peers": list(missing),
        "worst": min(rated, key=lambda r: r["ratio"], default=None),
        "met_at": [f"{r['method']}@{r['n']:.0e} {r['ratio']:.3g}x" for r in rated if r["ratio"] >= 5],
        "missed_at": [f"{r['method']}@{r['n']:.0e} {r['ratio']:.3g}x" for r in rated if r["ratio"] < 5],
        "no_equally_accurate_peer": [f"{r['method']}@{r['n']:.0e}" for r in measured if r["ratio"] is None],
        "not_measured_at": [f"{r['method']}@{r['n']:.0e}" for r in five_x if r.get("fastest_peer") is None],
    }


def growth_exponents(rows: list[dict[str, Any]], lo: int = 10_000) -> dict[str, dict[str, Any]]:
    """Least-squares slope of log(time) on log(N) for N >= ``lo`` (at least 2 sizes measured)."""
    out: dict[str, dict[str, Any]] = {}
    names = dict.fromkeys(r["estimator"] for r in rows)
    for name in names:
        pts = [(r["n"], r["median_s"]) for r in rows if r["estimator"] == name and "median_s" in r and r["n"] >= lo]
        if len(pts) >= 2:
            x = np.log10([p[0] for p in pts])
            y = np.log10([p[1] for p in pts])
            slope = float(np.polyfit(x, y, 1)[0])
            out[name] = {"exponent": slope, "n_min": min(p[0] for p in pts), "n_max": max(p[0] for p in pts)}
    return out


# ------------------------------------------------------------------------------------ apply / batch
def write_big_log(path: Path, n: int, *, seed: int = 5, parquet: Path | None = None) -> None:
    """A log of ``n`` rows ``t,bx,by,bz`` (nT, 2 decimals) written with pyarrow in slices (bounded memory)."""
    import pyarrow as pa
    import pyarrow.csv as pacsv
    import pyarrow.parquet as pq

    from trimag.simulate import uniform_directions

    truth = _accuracy().truth
    step = 1_000_000
    csv_writer = None
    pq_writer = None
    fh = path.open("wb")
    try:
        fh.write(b"t,bx,by,bz\n")  # pyarrow would quote the names
        for k, start in enumerate(range(0, n, step)):
            m = min(step, n - start)
            raw = np.round(truth().distort(uniform_directions(m, seed + k)) * 48000.0
                           + np.random.default_rng(seed + k).normal(scale=30.0, size=(m, 3)), 2)
            table = pa.table({"t": np.round((start + np.arange(m)) * 0.01, 2), "bx": raw[:, 0],
                              "by": raw[:, 1], "bz": raw[:, 2]})
            if csv_writer is None:
                csv_writer = pacsv.CSVWriter(fh, table.schema, write_options=pacsv.WriteOptions(
                    include_header=False, quoting_style="none"))
            csv_writer.write_table(table)
            if parquet is not None:
                if pq_writer is None:
                    pq_writer = pq.ParquetWriter(parquet, table.schema)
                pq_writer.write_table(table)
    finally:
        if csv_writer is not None:
            csv_writer.close()
        if pq_writer is not None:
            pq_writer.close()
        fh.close()


def _run_measured(cmd: list[str]) -> dict[str, Any]:
    """Run a command; wall time and peak RSS (MB) of the process."""
    time_bin = shutil.which("time") or ("/usr/bin/time" if os.path.exists("/usr/bin/time") else None)
    t0 = time.perf_counter()
    if time_bin:
        fd, stats = tempfile.mkstemp(suffix=".time")
        os.close(fd)
        proc = subprocess.run([time_bin, "-f", "%M %e", "-o", stats, *cmd], capture_output=True, text=True)
        wall = time.perf_counter() - t0
        try:
            rss_kb = float(Path(stats).read_text().split()[-2])
        finally:
            os.unlink(stats)
        peak = rss_kb / 1024
        how = "/usr/bin/time %M"
    else:  # pragma: no cover - fallback without GNU time
        import psutil

        p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        ps = psutil.Process(p.pid)
        peak_b = 0
        while p.poll() is None:
            with contextlib.suppress(psutil.Error):
                peak_b = max(peak_b, ps.memory_info().rss)
            time.sleep(0.05)
        out, err = p.communicate()
        proc = subprocess.CompletedProcess(cmd, p.returncode, out, err)
        wall = time.perf_counter() - t0
        peak = peak_b / 2**20
        how = "psutil polling (50 ms)"
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}): {proc.stderr.strip()[-300:]}")
    return {"wall_s": wall, "peak_rss_mb": peak, "memory_by": how}


def apply_benchmark(n_rows: int, tmp: Path, log: Callable[[str], None]) -> list[dict[str, Any]]:
    """``trimag apply`` / ``evaluate`` on CSV and Parquet files of ``n_rows`` rows, as separate processes."""
    from trimag import fit as trimag_fit

    csv_path, pq_path = tmp / f"big_{n_rows}.csv", tmp / f"big_{n_rows}.parquet"
    t0 = time.perf_counter()
    write_big_log(csv_path, n_rows, parquet=pq_path)
    log(f"  wrote {csv_path} ({csv_path.stat().st_size / 1e6:.0f} MB) and {pq_path.name} in "
        f"{time.perf_counter() - t0:.1f} s")
    cal_path = tmp / "cal.json"
    trimag_fit(_ellipsoid_data(5000, 3) * 48000.0, method="ml", units="nT").to_file(cal_path)
    exe = [sys.executable, "-m", "trimag.cli"]
    rows = []
    for src in (csv_path, pq_path):
        out = tmp / f"out{src.suffix}"
        for what, cmd in (("apply", [*exe, "apply", str(cal_path), str(src), "-o", str(out), "-q"]),
                          ("evaluate", [*exe, "evaluate", str(cal_path), str(src), "--json"])):
            r = _run_measured(cmd)
            r.update(command=f"trimag {what} {src.suffix[1:]}", rows=n_rows,
                     input_mb=src.stat().st_size / 1e6, rows_per_s=n_rows / r["wall_s"])
            rows.append(r)
            log(f"  {r['command']:24s} {r['wall_s']:.1f} s  {r['rows_per_s']:,.0f} rows/s  "
                f"peak {r['peak_rss_mb']:.0f} MB")
            out.unlink(missing_ok=True)
    return rows


def batch_benchmark(n_files: int, n_samples: int, tmp: Path, log: Callable[[str], None],
                    workers_list: tuple[int, ...] = (1, 2)) -> list[dict[str, Any]]:
    """``fit_batch`` over ``n_files`` CSV logs: files per second with 1 and 2 workers (processes / threads)."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    from trimag.app.batch import fit_batch
    from trimag.parallel import shutdown_pools

    d = tmp / "fleet"
    d.mkdir(exist_ok=True)
    for i in range(n_files):
        raw = np.round(_ellipsoid_data(n_samples, 1000 + i) * 48000.0, 2)
        with (d / f"s{i:04d}.csv").open("wb") as fh:
            fh.write(b"x,y,z\n")
            pacsv.write_csv(pa.table({"x": raw[:, 0], "y": raw[:, 1], "z": raw[:, 2]}), fh,
                            write_options=pacsv.WriteOptions(include_header=False, quoting_style="none"))
    rows = []
    configs = [(1, None)] + [(w, b) for w in workers_list if w > 1 for b in ("processes", "threads")]
    for w, backend in configs:
        shutdown_pools()  # every configuration pays its own worker start-up
        out = tmp / f"batch_out_{w}_{backend}"
        res = fit_batch(str(d / "*.csv"), out, workers=w, backend=backend, progress=False)
        rows.append({"workers": w, "backend": backend or "in-process", "files": n_files, "samples": n_samples,
                     "method": "ml", "seconds": res.seconds, "files_per_s": res.files_per_second,
                     "failed": res.n_failed})
        log(f"  batch workers={w} {backend or 'in-process':10s} {res.seconds:.1f} s  "
            f"{res.files_per_second:.1f} files/s")
        shutil.rmtree(out, ignore_errors=True)
    shutdown_pools()
    return rows


# ------------------------------------------------------------------------------------------- report
def machine_facts() -> dict[str, Any]:
    """CPU, cores, memory, versions and load: the context a timing needs."""
    import scipy

    facts: dict[str, Any] = {"python": platform.python_version(), "numpy": np.__version__,
                             "scipy": scipy.__version__, "platform": platform.platform(),
                             "cpu_count": os.cpu_count()}
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                facts["cpu"] = line.split(":", 1)[1].strip()
                break
    with contextlib.suppress(ImportError):
        import psutil

        facts["memory_gb"] = round(psutil.virtual_memory().total / 2**30, 1)
    with contextlib.suppress(OSError):
        facts["load_average"] = os.getloadavg()
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
        if var in os.environ:
            facts[var] = os.environ[var]
    return facts


def _write_rows(path: Path, rows: list[dict[str, Any]]) -> None:
    """CSV of rows whose keys differ (skipped/failed rows have no timings): the union of keys, in order."""
    keys: dict[str, None] = {}
    for r in rows:
        keys.update(dict.fromkeys(r))
    write_dict_csv(path, [{k: r.get(k) for k in keys} for r in rows])


def _figure(rows: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5.5))
    ax.set_prop_cycle(color=[plt.get_cmap("tab20")(i / 19) for i in range(20)])
    for name in dict.fromkeys(r["estimator"] for r in rows):
        pts = [(r["n"], r["median_s"]) for r in rows if r["estimator"] == name and "median_s" in r]
        if pts:
            peer = any(r["kind"] == "peer" for r in rows if r["estimator"] == name)
            ax.loglog(*zip(*pts, strict=True), "--" if peer else "-", marker="o", ms=3, label=name)
    ax.set_xlabel("N (samples)")
    ax.set_ylabel("fit time, median (s)")
    ax.set_title("benchmarks/speed.py: fit time against N (solid: trimag, dashed: peers)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    save_figure(fig, path)
    plt.close(fig)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the three parts (the command line adds ``--out``, ``--quick`` ...: :func:`main`)."""
    parser.add_argument("--sizes", type=float, nargs="+", default=None, help="N values (default 1e3 ... 1e7)")
    parser.add_argument("--repeats", type=int, default=None, help="timed fits per (estimator, N) (default 5)")
    parser.add_argument("--budget", type=float, default=None,
                        help="skip an (estimator, N) whose projected time per fit exceeds this (s; default 30)")
    parser.add_argument("--estimators", nargs="+", default=None, help="trimag methods and peer names")
    parser.add_argument("--apply-rows", type=float, default=None, help="rows of the apply benchmark (1e7)")
    parser.add_argument("--batch-files", type=int, default=None, help="files of the batch benchmark (1000)")
    parser.add_argument("--batch-samples", type=int, default=None, help="samples per batch file (5000)")
    parser.add_argument("--accuracy-sets", type=int, default=None,
                        help=f"data sets the parameter error is averaged over, budget permitting "
                             f"(default {ACCURACY_SETS})")
    parser.add_argument("--skip", nargs="+", default=(), choices=("fits", "apply", "batch"),
                        help="parts not to run")
    parser.add_argument("--tmp", default=None, help="folder for the big generated files (default: system temp)")


def run(
    out_dir: Path, *, quick: bool = False, trials: int | None = None, seed: int = 0, workers: int = 1,
    json_mode: bool = False, sizes: list[float] | None = None, repeats: int | None = None,
    budget: float | None = None, estimators: list[str] | None = None, apply_rows: float | None = None,
    batch_files: int | None = None, batch_samples: int | None = None, skip: tuple[str, ...] | list[str] = (),
    tmp: str | None = None, accuracy_sets: int | None = None, **extra: Any,
) -> dict[str, Any]:
    """Run the benchmark; write ``fits.csv``, ``ratios.csv``, ``apply.csv``, ``batch.csv``, ``speed.json``,
    ``profiles.txt`` and ``fit_times.png`` into ``out_dir``; return the summary.

    ``quick``: N up to 1e5, 3 repeats, 2e5 apply rows, 40 batch files of 2000 samples. ``trials`` is an alias of
    ``repeats``. ``workers`` is not used by the fits (timed one at a time on purpose); batch uses 1 and 2.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    ns = [int(s) for s in (sizes or (SIZES[:3] if quick else SIZES))]
    reps = int(repeats or trials or (3 if quick else 5))
    budget_s = float(budget or (5.0 if quick else 30.0))
    n_apply = int(apply_rows or (200_000 if quick else 10_000_000))
    n_files = int(batch_files or (40 if quick else 1000))
    n_samples = int(batch_samples or (2000 if quick else 5000))
    n_sets = int(accuracy_sets if accuracy_sets is not None else (3 if quick else ACCURACY_SETS))
    if n_sets < 1:
        raise TrimagInputError(f"--accuracy-sets must be at least 1; got {n_sets}")

    def log(msg: str) -> None:
        sys.stderr.write(msg + "\n")
        sys.stderr.flush()

    facts_start = machine_facts()
    summary: dict[str, Any] = {"machine": facts_start, "sizes": ns, "repeats": reps, "budget_s": budget_s,
                               "accuracy_sets": n_sets,
                               "sigma_over_F": SIGMA, "command": " ".join(sys.argv)}
    if "fits" not in skip:
        log(f"fits: N in {ns}, {reps} repeats, budget {budget_s:g} s")
        profile_at = 1_000_000 if 1_000_000 in ns else max(ns)
        rows, profiles = fit_benchmark(ns, repeats=reps, budget=budget_s, seed=seed, estimators=estimators,
                                       profile_at=profile_at, log=log, accuracy_sets=n_sets)
        _write_rows(out_dir / "fits.csv", rows)
        ratios = speed_ratios(rows)
        if ratios:
            _write_rows(out_dir / "ratios.csv", ratios)
        exps = growth_exponents(rows)
        if profiles:
            atomic_write_text(out_dir / "profiles.txt", "\n".join(
                f"===== {k} at N = {profile_at:,} =====\n{v}" for k, v in profiles.items()))
        _figure(rows, out_dir / "fit_times.png")
        targets = {}
        for method, limit in TARGETS.items():
            hit = [r for r in rows if r["estimator"] == method and r["n"] == 1_000_000 and "median_s" in r]
            if hit:
                targets[f"{method} at 1e6 < {limit} s"] = {"time_s": hit[0]["median_s"],
                                                         "met": hit[0]["median_s"] < limit}
        targets["every method >= 5x faster than the fastest equally accurate peer (N >= 1e4)"] = peer_verdict(
            ratios, missing=missing_peers(estimators))
        summary.update(fits=rows, ratios=ratios, exponents=exps, targets=targets)
        # the fits take the longest: keep their summary even if a later part fails
        atomic_write_text(out_dir / "speed.json", json.dumps(jsonable(summary), indent=1) + "\n")
    if tmp is not None:
        Path(tmp).mkdir(parents=True, exist_ok=True)
    tmp_root = Path(tempfile.mkdtemp(prefix="trimag-speed-", dir=tmp))
    try:
        if "apply" not in skip:
            log(f"apply/evaluate: {n_apply:,} rows")
            apply_rows_ = apply_benchmark(n_apply, tmp_root, log)
            _write_rows(out_dir / "apply.csv", apply_rows_)
            summary["apply"] = apply_rows_
            csv_apply = [r for r in apply_rows_ if r["command"] == "trimag apply csv"]
            if csv_apply:
                summary.setdefault("targets", {})[f"apply on {n_apply:.0e} CSV rows: peak < 500 MB"] = {
                    "peak_rss_mb": csv_apply[0]["peak_rss_mb"], "met": csv_apply[0]["peak_rss_mb"] < 500}
        if "batch" not in skip:
            log(f"batch: {n_files} files x {n_samples} samples")
            batch_rows = batch_benchmark(n_files, n_samples, tmp_root, log)
            _write_rows(out_dir / "batch.csv", batch_rows)
            summary["batch"] = batch_rows
    finally:
        shutil.rmtree(tmp_root, ignore_errors=True)
    summary["machine_end"] = {"load_average": machine_facts().get("load_average")}
    atomic_write_text(out_dir / "speed.json", json.dumps(jsonable(summary), indent=1) + "\n")
    summary["text"] = _text(summary)
    return dict(jsonable(summary))


def _text(s: dict[str, Any]) -> str:
    lines = []
    for name, t in s.get("targets", {}).items():
        verdict = "not measured" if t.get("met") is None else ("MET " if t["met"] else "MISS")
        lines.append(f"{verdict}  {name}: "
                     + ", ".join(f"{k}={v:.4g}" for k, v in t.items() if isinstance(v, float)))
        if t.get("missing_peers"):
            lines.append(f"        missing peers (not installed): {', '.join(t['missing_peers'])}")
        lines += [f"        {k}: {', '.join(v)}" for k, v in t.items()
                  if isinstance(v, list) and v and k != "missing_peers"]
    for name, e in s.get("exponents", {}).items():
        lines.append(f"growth exponent {name}: {e['exponent']:.2f} (N {e['n_min']:.0e}..{e['n_max']:.0e})")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """The command line: ``python benchmarks/speed.py --out DIR [options]``; returns the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="bench-speed", help="output folder")
    parser.add_argument("--quick", action="store_true", help="small sizes, for a fast check")
    parser.add_argument("--trials", type=int, default=None, help="alias of --repeats")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true", help="print the JSON summary on stdout")
    parser.add_argument("-q", "--quiet", action="store_true", help="print nothing on success")
    add_arguments(parser)
    args = vars(parser.parse_args(argv))
    out, quick, trials, seed = args.pop("out"), args.pop("quick"), args.pop("trials"), args.pop("seed")
    as_json, quiet = args.pop("json"), args.pop("quiet")
    t0 = time.monotonic()
    summary = run(Path(out), quick=quick, trials=trials, seed=seed, workers=1, json_mode=as_json, **args)
    summary.setdefault("runtime_s", time.monotonic() - t0)
    if as_json:
        print(json.dumps(summary, allow_nan=False, default=float))
    elif not quiet:
        print(summary.get("text", ""))
        print(f"done in {summary['runtime_s']:.1f} s; outputs in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
