"""The lean install (issue 22, item 10): pyarrow, h5py, Dask and the log readers are optional extras.

Each test runs the command in a fresh interpreter in which the extra's packages cannot be imported
(``sys.modules[name] = None`` before trimag is imported: ``import name`` then raises ImportError, as when the
package is not installed). A feature that needs a missing extra exits 2 with one line naming it; everything else
works without it, with the same results.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from _helpers import run_trimag, simulate_ellipsoid

ROOT = Path(__file__).resolve().parents[1]
LOGS = Path(__file__).parent / "data" / "logs"

#: the top-level packages each extra installs (and the ones they pull in that trimag imports)
BLOCKED = {
    "parquet": ("pyarrow",),
    "mat": ("h5py",),
    "batch": ("dask", "distributed"),
    "logs": ("pymavlink", "pyulog", "rosbags"),
    "review": ("plotly",),
}
EVERY_EXTRA = tuple(name for names in BLOCKED.values() for name in names)


def run_without(blocked: tuple[str, ...], *args: object, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    """``trimag ARGS`` in a fresh interpreter where the ``blocked`` packages cannot be imported (none blocked: the
    command as every other test runs it, forked from the zygote that has imported them all)."""
    if not blocked:
        return run_trimag(*map(str, args), cwd=cwd, timeout=300)
    code = (
        "import sys\n"
        f"for name in {list(blocked)!r}:\n"
        "    sys.modules[name] = None\n"
        "from trimag.cli import main\n"
        "raise SystemExit(main(sys.argv[1:]))\n"
    )
    env = {**os.environ, "MPLBACKEND": "Agg"}
    return subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=300, env=env)


def assert_needs_extra(proc: subprocess.CompletedProcess[str], extra: str) -> None:
    """Exit 2, one line on stderr naming ``pip install "trimag[extra]"``, no traceback."""
    assert proc.returncode == 2, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, proc.stderr
    assert f'pip install "trimag[{extra}]"' in lines[0], lines[0]
    assert "Traceback" not in proc.stderr


@pytest.fixture
def log_csv(tmp_path: Path) -> Path:
    raw = simulate_ellipsoid(1500, noise=5.0, seed=3)
    path = tmp_path / "log.csv"
    t = np.arange(len(raw)) * 0.02
    np.savetxt(path, np.column_stack([t, raw]), delimiter=",", header="t,bx,by,bz", comments="", fmt="%.6f")
    return path


def test_pyproject_core_is_lean_and_test_installs_every_extra() -> None:
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    core = " ".join(meta["dependencies"])
    for heavy in ("pyarrow", "h5py", "dask", "distributed", "pymavlink"):
        assert heavy not in core
    extras = meta["optional-dependencies"]
    assert set(BLOCKED) <= set(extras)
    assert any("pyarrow" in d for d in extras["parquet"])
    assert any("h5py" in d for d in extras["mat"])
    assert any("dask[distributed]" in d for d in extras["batch"])

    def closure(name: str) -> set[str]:  # the extras `trimag[name]` installs, through self-references
        out = {name}
        for dep in extras[name]:
            if dep.startswith("trimag["):
                for sub in dep[len("trimag["):dep.index("]")].split(","):
                    out |= closure(sub.strip())
        return out

    assert set(BLOCKED) <= closure("test"), "CI installs [test]: it must pull every extra"


def test_core_commands_work_without_any_extra(log_csv: Path, tmp_path: Path) -> None:
    """fit, apply, evaluate, simulate and demo with every optional package missing; same numbers as with them."""
    cal = tmp_path / "cal.json"
    proc = run_without(EVERY_EXTRA, "fit", log_csv, "--units", "nT", "-o", cal, "--json")
    assert proc.returncode == 0, proc.stderr
    lean = json.loads(proc.stdout)
    proc = run_without((), "fit", log_csv, "--units", "nT", "--json")
    assert proc.returncode == 0, proc.stderr
    full = json.loads(proc.stdout)
    np.testing.assert_array_equal(lean["matrix"], full["matrix"])
    np.testing.assert_array_equal(lean["offset"], full["offset"])

    out_lean, out_full = tmp_path / "lean.csv", tmp_path / "full.csv"
    for blocked, out in ((EVERY_EXTRA, out_lean), ((), out_full)):
        proc = run_without(blocked, "apply", cal, log_csv, "-o", out, "--chunk-rows", "400")
        assert proc.returncode == 0, proc.stderr
    assert out_lean.read_bytes() == out_full.read_bytes()  # pandas' reader and writer: the same cells

    proc = run_without(EVERY_EXTRA, "evaluate", cal, log_csv, "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["rms_after"] < json.loads(proc.stdout)["rms_before"]

    proc = run_without(EVERY_EXTRA, "demo", "--out", tmp_path / "demo", "-q")
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "demo" / "trimag-demo-calibration.json").exists()


def test_csv_reader_without_pyarrow_gives_the_same_samples(tmp_path: Path) -> None:
    """read_samples through pandas alone (pyarrow blocked in-process) equals the pyarrow path, cell for cell."""
    path = tmp_path / "mixed.csv"
    path.write_text("t,bx,by,bz,label\n0,1.5,2,3,a\n1,,2,3,b\n2,4e3,-5,6.25,c\n3,x,1,1,d\n4,7,8,9,\"q,r\"\n")
    code = (
        "import sys, json\n"
        "if sys.argv[2] == 'lean':\n"
        "    sys.modules['pyarrow'] = None\n"
        "from trimag.io import read_samples\n"
        "s = read_samples(sys.argv[1])\n"
        "print(json.dumps({'field': s.field.tolist(), 'table': s.table.astype(str).values.tolist(),\n"
        "                  'columns': list(s.columns), 'dropped': s.dropped_index}))\n"
    )
    outs = [subprocess.run([sys.executable, "-c", code, str(path), mode], capture_output=True, text=True,
                           check=True).stdout for mode in ("lean", "full")]
    assert json.loads(outs[0]) == json.loads(outs[1])
    assert json.loads(outs[0])["dropped"] == [1, 3]


def test_parquet_needs_the_parquet_extra(log_csv: Path, tmp_path: Path) -> None:
    pq_file = tmp_path / "log.parquet"
    pd.read_csv(log_csv).to_parquet(pq_file)
    assert_needs_extra(run_without(BLOCKED["parquet"], "fit", pq_file), "parquet")
    cal = tmp_path / "cal.json"
    assert run_without((), "fit", log_csv, "-o", cal, "-q").returncode == 0
    out = tmp_path / "out.parquet"
    assert_needs_extra(run_without(BLOCKED["parquet"], "apply", cal, log_csv, "-o", out), "parquet")
    assert not out.exists() and list(tmp_path.glob(".*")) == []  # refused before any work: no partial file
    assert_needs_extra(run_without(BLOCKED["parquet"], "evaluate", cal, pq_file), "parquet")


def test_mat_v73_needs_the_mat_extra(tmp_path: Path) -> None:
    import h5py
    import scipy.io

    raw = simulate_ellipsoid(800, noise=5.0, seed=4)
    v73 = tmp_path / "v73.mat"
    with h5py.File(v73, "w") as h5:  # HDF5 layout as MATLAB -v7.3 writes a 3 x N variable
        h5["mag"] = raw.T
    assert_needs_extra(run_without(BLOCKED["mat"], "fit", v73), "mat")
    assert run_without((), "fit", v73, "-q").returncode == 0
    v5 = tmp_path / "v5.mat"
    scipy.io.savemat(v5, {"mag": raw})
    proc = run_without(BLOCKED["mat"], "fit", v5, "-q")  # MAT v4-v7.2 are read by scipy: no extra needed
    assert proc.returncode == 0, proc.stderr
    junk = tmp_path / "junk.mat"
    junk.write_bytes(b"not a mat file at all" * 40)
    proc = run_without(BLOCKED["mat"], "fit", junk)  # not HDF5: the file is named, not the extra
    assert proc.returncode == 2 and "trimag[mat]" not in proc.stderr and "Traceback" not in proc.stderr


def test_local_batch_runs_without_dask_and_a_cluster_needs_the_batch_extra(log_csv: Path, tmp_path: Path) -> None:
    fleet = tmp_path / "fleet"
    fleet.mkdir()
    for k in range(3):
        (fleet / f"s{k}.csv").write_bytes(log_csv.read_bytes())
    blocked = BLOCKED["batch"] + BLOCKED["parquet"]
    proc = run_without(blocked, "batch", fleet / "*.csv", "--out", tmp_path / "cals", "--workers", "2", "--json")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary["n_fitted"] == 3 and "summary_parquet" not in summary["outputs"]
    assert sorted(p.name for p in (tmp_path / "cals").iterdir()) == ["s0.json", "s1.json", "s2.json", "summary.csv"]
    proc = run_without(BLOCKED["batch"], "batch", fleet / "*.csv", "--out", tmp_path / "c2",
                       "--scheduler", "tcp://127.0.0.1:9")
    assert_needs_extra(proc, "batch")


def test_autopilot_logs_need_the_logs_extra(tmp_path: Path) -> None:
    assert_needs_extra(run_without(BLOCKED["logs"], "fit", LOGS / "pyulog_sample_log_small.ulg"), "logs")
    tlog = tmp_path / "flight.tlog"
    tlog.write_bytes(b"\xfe" * 64)
    assert_needs_extra(run_without(BLOCKED["logs"], "fit", tlog), "logs")
    # DataFlash .bin logs are parsed by trimag itself: they need no extra
    proc = run_without(BLOCKED["logs"], "fit", LOGS / "ardusub_small.BIN")
    assert proc.returncode in (0, 3) and "trimag[logs]" not in proc.stderr, proc.stderr


def test_an_unguarded_import_of_an_extra_still_exits_2(monkeypatch: pytest.MonkeyPatch,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    """A code path that imports an optional package without ``require`` is caught by the CLI: exit 2, the extra
    named; a missing module that is not an extra is a bug (exit 1)."""
    from trimag import app, cli

    def needs_pyarrow(*args: object, **kwargs: object) -> None:
        raise ModuleNotFoundError("No module named 'pyarrow'", name="pyarrow")

    monkeypatch.setattr(app, "simulate_to_file", needs_pyarrow)
    argv = ["simulate", "--model", "ellipsoid", "--params", "p.json", "--n", "10", "-o", "x.csv"]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert 'pip install "trimag[parquet]"' in err and len(err.strip().splitlines()) == 1

    def needs_nothing_known(*args: object, **kwargs: object) -> None:
        raise ModuleNotFoundError("No module named 'trimag_gone'", name="trimag_gone")

    monkeypatch.setattr(app, "simulate_to_file", needs_nothing_known)
    assert cli.main(argv) == 1
    assert "a bug in trimag" in capsys.readouterr().err


def test_the_review_and_the_html_report_need_the_review_extra(tmp_path: Path) -> None:
    """``trimag review`` and ``fit --report report.html`` (issue 40) say the review extra before any work; the PNG
    report needs no extra."""
    log = LOGS / "ardusub_small.BIN"
    assert_needs_extra(run_without(BLOCKED["review"], "review", log, "--no-browser", "--port", "0"), "review")
    report = tmp_path / "report.html"
    proc = run_without(BLOCKED["review"], "fit", log, "--target", "ardupilot", "--igrf", "47.6,-122.3,0,2021-06-01",
                       "--sensor", "2", "--report", report)
    assert_needs_extra(proc, "review")
    assert not report.exists()
