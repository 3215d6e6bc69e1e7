"""Small-size checks of the speed benchmark's parts (the harness ``benchmarks/speed.py``; its full runs are
recorded in docs/performance.md)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from trimag.errors import TrimagInputError

from _helpers import BENCHMARKS_DIR, load_benchmark

speed = load_benchmark("speed")
_run_measured = speed._run_measured
fit_benchmark = speed.fit_benchmark
growth_exponents = speed.growth_exponents
speed_ratios = speed.speed_ratios
write_big_log = speed.write_big_log


def test_harness_has_run_and_options() -> None:
    module = speed
    assert callable(module.run) and callable(module.add_arguments)


def test_growth_exponent_recovers_power_law() -> None:
    rows = [{"estimator": "a", "n": n, "median_s": 1e-6 * n**1.0} for n in (1e3, 1e4, 1e5, 1e6)]
    rows += [{"estimator": "b", "n": n, "median_s": 1e-9 * n**1.5} for n in (1e4, 1e5, 1e6)]
    rows += [{"estimator": "c", "n": 1e6, "median_s": 1.0}, {"estimator": "c", "n": 1e7, "note": "skipped"}]
    e = growth_exponents(rows)
    assert e["a"]["exponent"] == pytest.approx(1.0) and e["a"]["n_min"] == 1e4  # 1e3 excluded
    assert e["b"]["exponent"] == pytest.approx(1.5)
    assert "c" not in e  # one measured size only


def test_ratio_uses_fastest_peer_of_equal_accuracy() -> None:
    rows = [
        {"estimator": "ml", "kind": "trimag", "model": "ellipsoid", "n": 10_000, "median_s": 0.01,
         "param_rms_error": 1.0e-4},
        {"estimator": "fast-biased", "kind": "peer", "model": "ellipsoid", "n": 10_000, "median_s": 0.001,
         "param_rms_error": 5e-4},
        {"estimator": "slow-good", "kind": "peer", "model": "ellipsoid", "n": 10_000, "median_s": 0.2,
         "param_rms_error": 1.05e-4},
        {"estimator": "slower-good", "kind": "peer", "model": "ellipsoid", "n": 10_000, "median_s": 0.5,
         "param_rms_error": 0.9e-4},
    ]
    (r,) = speed_ratios(rows)
    assert r["peer"] == "slow-good" and r["ratio"] == pytest.approx(20.0)
    assert r["fastest_peer"] == "fast-biased" and r["ratio_fastest_any"] == pytest.approx(0.1)
    rows[2]["param_rms_error"] = rows[3]["param_rms_error"] = 1.0  # no peer as accurate
    (r,) = speed_ratios(rows)
    assert r["ratio"] is None and r["note"] == "no peer reaches this accuracy"


def test_fit_benchmark_small(monkeypatch: pytest.MonkeyPatch) -> None:
    logged: list[str] = []
    rows, profiles = fit_benchmark([300, 600], repeats=2, budget=1e-9, seed=0, estimators=["ellipsoid-fit"],
                                   profile_at=300, log=logged.append)
    first, second = rows
    assert first["estimator"] == "ellipsoid-fit" and first["n"] == 300 and first["repeats"] == 2
    assert first["min_s"] <= first["median_s"] <= first["max_s"]
    assert first["param_rms_error"] < 0.01  # sigma/F = 1e-2, 300 samples
    assert "skipped: projected" in second["note"]  # the tiny budget skips N = 600
    assert "ellipsoid-fit" in profiles and "cumulative" in profiles["ellipsoid-fit"]
    with pytest.raises(TrimagInputError, match="unknown estimators"):
        fit_benchmark([300], repeats=1, budget=1.0, seed=0, estimators=["nope"], profile_at=None,
                      log=logged.append)


def test_accuracy_is_averaged_over_independent_data_sets() -> None:
    logged: list[str] = []
    rows, _ = fit_benchmark([300], repeats=1, budget=10.0, seed=0, estimators=["ellipsoid-fit"],
                            profile_at=None, log=logged.append, accuracy_sets=4)
    (row,) = rows
    assert row["accuracy_sets"] == 4 and "param_errors" not in row
    single, _ = fit_benchmark([300], repeats=1, budget=1e-9, seed=0, estimators=["ellipsoid-fit"],
                              profile_at=None, log=logged.append, accuracy_sets=4)
    assert single[0]["accuracy_sets"] == 1  # no time for extra sets within the budget
    # the first set is the timed one; the other three are different draws, so the RMS differs from it
    assert row["param_error_first_set"] == pytest.approx(single[0]["param_rms_error"])
    assert row["param_rms_error"] != pytest.approx(row["param_error_first_set"], rel=1e-3)
    assert 0 < row["param_rms_error"] < 0.01
    assert any("accuracy at N=300" in line and "(4 sets)" in line for line in logged)


def test_write_big_log_and_measure(tmp_path: Path) -> None:
    csv_path, pq_path = tmp_path / "big.csv", tmp_path / "big.parquet"
    write_big_log(csv_path, 1500, parquet=pq_path)
    a = pd.read_csv(csv_path)
    b = pd.read_parquet(pq_path)
    assert list(a.columns) == ["t", "bx", "by", "bz"] and len(a) == 1500
    np.testing.assert_allclose(a.to_numpy(), b.to_numpy())
    assert csv_path.read_text(encoding="utf-8").startswith("t,bx,by,bz\n")
    r = _run_measured([sys.executable, "-c", "import numpy; x = numpy.ones(30_000_000)"])
    assert r["peak_rss_mb"] > 200 and r["wall_s"] > 0  # 240 MB array
    with pytest.raises(RuntimeError, match="failed"):
        _run_measured([sys.executable, "-c", "raise SystemExit(3)"])


def test_rows_with_different_keys_keep_every_column(tmp_path: Path) -> None:
    _write_rows = speed._write_rows

    _write_rows(tmp_path / "f.csv", [{"n": 1, "median_s": 0.5}, {"n": 2, "note": "skipped: projected 40 s"}])
    df = pd.read_csv(tmp_path / "f.csv")
    assert list(df.columns) == ["n", "median_s", "note"]
    assert df["note"].iloc[1].startswith("skipped") and np.isnan(df["median_s"].iloc[1])


def test_accuracy_sets_below_one_is_refused(tmp_path: Path) -> None:
    with pytest.raises(TrimagInputError, match="--accuracy-sets must be at least 1"):
        speed.run(tmp_path, accuracy_sets=0, skip=("fits", "apply", "batch"))


def test_runs_as_a_script_from_the_repository_root(tmp_path: Path) -> None:
    """``python benchmarks/speed.py`` (the former ``trimag bench speed``): options, JSON summary, outputs."""
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "benchmarks/speed.py", "--out", str(out), "--skip", "fits", "apply",
                           "batch", "--json"], capture_output=True, text=True, cwd=BENCHMARKS_DIR.parent,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary["runtime_s"] > 0 and "cpu_count" in summary["machine"]
    assert (out / "speed.json").exists()


def test_spawned_workers_do_not_import_the_simulator() -> None:
    """The batch part's workers are spawned and run this script again (as ``__mp_main__``): it must not import
    ``trimag.simulate`` (scipy.spatial, 0.4 s per worker) or the accuracy harness at its top."""
    code = ("import runpy, sys; runpy.run_path('benchmarks/speed.py', run_name='__mp_main__'); "
            "print('trimag.simulate' in sys.modules, '_trimag_bench_accuracy' in sys.modules)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=BENCHMARKS_DIR.parent,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["False", "False"]


def test_not_a_trimag_subcommand_any_more(capsys: pytest.CaptureFixture[str]) -> None:
    from trimag.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["bench", "speed"])
    assert exc.value.code == 2 and "invalid choice: 'bench'" in capsys.readouterr().err


def test_a_verdict_without_a_peer_is_not_measured_and_names_the_missing_peers(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 42 item 3: asked to compare with peers that are not installed, the run printed "MET every method >= 5x
    faster than the fastest equally accurate peer" from no peer measurement at all."""
    monkeypatch.setattr(speed, "_peers", lambda only=None: {})  # as on a machine without the peers
    summary = speed.run(tmp_path, sizes=[1e4], repeats=1, accuracy_sets=1, skip=("apply", "batch"),
                        estimators=["ellipsoid-fit", "magcal", "circuitpython-mag-cal"])
    text = summary["text"]
    assert "MET" not in text and "MISS" not in text, text
    assert "not measured" in text, text
    assert "magcal" in text and "circuitpython-mag-cal" in text and "not installed" in text, text
    target = next(v for k, v in summary["targets"].items() if "5x faster" in k)
    assert target["met"] is None and sorted(target["missing_peers"]) == ["circuitpython-mag-cal", "magcal"]


def test_a_verdict_comes_only_from_the_peers_that_ran() -> None:
    """A peer measured at some sizes only: the sizes without one are 'not measured', never counted as met."""
    rows = [{"estimator": "ellipsoid-fit", "kind": "trimag", "model": "ellipsoid", "n": n, "median_s": 0.01,
             "param_rms_error": 1e-4} for n in (10_000, 100_000)]
    rows.append({"estimator": "magcal", "kind": "peer", "model": "ellipsoid", "n": 10_000, "median_s": 0.1,
                 "param_rms_error": 1e-4})
    rows.append({"estimator": "magcal", "kind": "peer", "model": "ellipsoid", "n": 100_000,
                 "error": "MemoryError: "})
    verdict = speed.peer_verdict(speed.speed_ratios(rows), missing=[])
    assert verdict["met"] is True and verdict["met_at"] == ["ellipsoid-fit@1e+04 10x"]
    assert verdict["not_measured_at"] == ["ellipsoid-fit@1e+05"]
    assert speed.peer_verdict(speed.speed_ratios(rows[:2]), missing=["magcal"])["met"] is None


def test_the_gyro_aided_fit_is_timed_on_data_with_a_gyroscope() -> None:
    """Issue 42 item 3: ``speed.py --quick`` printed ``gyro ... ERROR TrimagInputError: the gyro-aided fit needs the
    gyroscope's angular rate``: it was given the ellipsoid group's samples, without one."""
    logged: list[str] = []
    rows, _ = fit_benchmark([1000], repeats=1, budget=10.0, seed=0, estimators=["gyro"], profile_at=None,
                            log=logged.append, accuracy_sets=1)
    (row,) = rows
    assert "error" not in row, row
    assert row["median_s"] > 0 and row["model"] == "gyro (own sensor)"
    assert not any("ERROR" in line for line in logged), logged
