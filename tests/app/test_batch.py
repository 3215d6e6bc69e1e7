"""Tests of trimag.app.batch and ``trimag batch``: one calibration per file, a summary table, bad files reported."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from trimag import Calibration
from trimag.app.batch import SUMMARY_COLUMNS, calibration_names, expand_inputs, fit_batch
from trimag.cli import main
from trimag.errors import TrimagInputError

from _helpers import ellipsoid_truth, simulate_ellipsoid


def _write_log(path: Path, seed: int, n: int = 400) -> None:
    raw = simulate_ellipsoid(n, noise=20.0, seed=seed)
    t = np.arange(n) * 0.01
    np.savetxt(path, np.column_stack([t, raw]), delimiter=",", header="t,bx,by,bz", comments="", fmt="%.6f")


@pytest.fixture
def fleet(tmp_path: Path) -> Path:
    """Four good logs, one with too few rows (identifiability), one unreadable (input error)."""
    d = tmp_path / "fleet"
    d.mkdir()
    for i in range(4):
        _write_log(d / f"sensor{i}.csv", seed=i)
    (d / "short.csv").write_text("t,bx,by,bz\n0,1,2,3\n0.1,2,3,4\n", encoding="utf-8")
    (d / "garbage.csv").write_text("this is not\na magnetometer log\n", encoding="utf-8")
    return d


def _check_result(table: pd.DataFrame, fleet: Path, out: Path) -> None:
    assert list(table.columns) == list(SUMMARY_COLUMNS)
    names = [Path(f).name for f in table["file"]]
    assert names == sorted(names) and len(names) == 6
    by = table.set_index(table["file"].map(lambda f: Path(f).name))
    _W, b = ellipsoid_truth()
    for i in range(4):
        row = by.loc[f"sensor{i}.csv"]
        assert row["error"] == "" and row["n"] == 400 and bool(row["converged"])
        assert row["rms_after"] < 0.1 * row["rms_before"]
        cal = Calibration.from_file(row["calibration"])
        assert np.allclose(cal.offset, b, atol=30.0)  # 20 nT noise, 400 samples
        assert Path(row["calibration"]) == out / f"sensor{i}.json"
    assert by.loc["short.csv", "error_type"] == "identifiability"
    assert "too few" in by.loc["short.csv", "error"]
    assert by.loc["garbage.csv", "error_type"] == "input"
    assert pd.isna(by.loc["garbage.csv", "rms_after"]) and pd.isna(by.loc["garbage.csv", "calibration"])
    # both summary files hold the same table
    csv = pd.read_csv(out / "summary.csv", keep_default_na=False, na_values=[""])
    pq = pd.read_parquet(out / "summary.parquet")
    assert list(csv.columns) == list(pq.columns) == list(SUMMARY_COLUMNS)
    assert list(csv["file"]) == list(pq["file"]) == list(table["file"])
    np.testing.assert_allclose(csv["rms_after"], pq["rms_after"].to_numpy(dtype=float), rtol=1e-12)
    assert not list(out.glob(".*.tmp"))


def test_fit_batch_in_process(fleet: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    res = fit_batch(str(fleet / "*.csv"), out, method="ml", progress=False)
    _check_result(res.table, fleet, out)
    assert res.n_files == 6 and res.n_failed == 2
    assert res.exit_code() == 2  # first failure in file order is garbage.csv, an input error
    s = res.summary()
    assert s["n_fitted"] == 4 and {f["file"] for f in s["failed"]} == {
        str(fleet / "garbage.csv"), str(fleet / "short.csv")}
    json.dumps(s, allow_nan=False)


@pytest.fixture(scope="module")
def cluster():  # type: ignore[no-untyped-def]
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=":0") as lc:
        yield lc


def test_fit_batch_on_distributed_cluster(fleet: Path, tmp_path: Path, cluster) -> None:  # type: ignore[no-untyped-def]
    local = fit_batch(str(fleet / "*.csv"), tmp_path / "local", method="ml", progress=False)
    out = tmp_path / "dist"
    res = fit_batch(str(fleet / "*.csv"), out, method="ml", scheduler=cluster.scheduler_address,
                    chunksize=1, progress=False)
    _check_result(res.table, fleet, out)
    pd.testing.assert_series_equal(res.table["rms_after"], local.table["rms_after"])
    pd.testing.assert_series_equal(res.table["error"], local.table["error"])


def test_cli_batch_json(fleet: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "cli"
    code = main(["batch", str(fleet / "sensor*.csv"), "--out", str(out), "--method", "ml", "--units", "nT",
                 "--reference", "48000", "--json"])
    assert code == 0
    s = json.loads(capsys.readouterr().out)
    assert s["n_files"] == 4 and s["n_failed"] == 0 and s["files_per_second"] > 0
    cal = Calibration.from_file(out / "sensor0.json")
    assert cal.units == "nT" and cal.method == "ml"
    assert abs(np.linalg.norm(cal.apply(simulate_ellipsoid(50, seed=9)), axis=1).mean() - 48000) < 50


def test_cli_batch_bad_file_reported_not_fatal(fleet: Path, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "cli2"
    code = main(["batch", str(fleet / "sensor1.csv"), str(fleet / "short.csv"), "--out", str(out)])
    captured = capsys.readouterr()
    assert code == 3  # the identifiability failure's exit code
    assert "short.csv" in captured.err and "fitted 1 of 2 files" in captured.out
    assert (out / "sensor1.json").exists() and (out / "summary.parquet").exists()


def test_cli_batch_no_match_and_bad_method(tmp_path: Path, fleet: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["batch", str(tmp_path / "none" / "*.csv"), "--out", str(tmp_path / "o")]) == 2
    assert "matches no file" in capsys.readouterr().err
    assert main(["batch", str(fleet / "*.csv"), "--out", str(tmp_path / "o"), "--method", "nope"]) == 2
    assert not (tmp_path / "o" / "summary.csv").exists()


def test_expand_inputs_and_names(tmp_path: Path) -> None:
    for sub in ("a", "b"):
        (tmp_path / sub).mkdir()
        (tmp_path / sub / "run.csv").write_text("x\n", encoding="utf-8")
    (tmp_path / "a" / "run.parquet").write_text("x", encoding="utf-8")
    files = expand_inputs([str(tmp_path / "**" / "run.csv"), str(tmp_path / "a" / "run.csv")])
    assert [f.parent.name for f in files] == ["a", "b"]  # duplicates removed, sorted
    assert calibration_names(files) == ["a__run", "b__run"]
    assert calibration_names([tmp_path / "a" / "run.csv", tmp_path / "a" / "run.parquet"]) == [
        "run_csv", "run_parquet"]
    with pytest.raises(TrimagInputError, match="matches no file"):
        expand_inputs(str(tmp_path / "*.txt"))


def test_fit_batch_on_process_cluster(fleet: Path, tmp_path: Path) -> None:
    """Worker processes: the task (a partial of fit_one) and the rows really cross process boundaries."""
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                  dashboard_address=":0") as lc:
        res = fit_batch([str(fleet / "sensor0.csv"), str(fleet / "short.csv")], tmp_path / "p",
                        scheduler=lc.scheduler_address, progress=False)
    assert list(res.table["error_type"]) == ["", "identifiability"]
    assert res.table["rms_after"].iloc[0] < 0.1 * res.table["rms_before"].iloc[0]
    assert (tmp_path / "p" / "sensor0.json").exists()


def test_fit_batch_takes_one_request_for_every_file(fleet: Path, tmp_path: Path) -> None:
    """``trimag batch`` hands fit_batch one FitRequest (its path and output replaced per file): the same table as
    the flat arguments; a request with fit arguments is refused before any work."""
    from trimag.app.requests import FitRequest

    flat = fit_batch(str(fleet / "*.csv"), tmp_path / "flat", method="ml", progress=False)
    typed = fit_batch(str(fleet / "*.csv"), tmp_path / "typed", request=FitRequest.of("", method="ml"),
                      progress=False)
    cols = ["file", "n", "n_used", "rms_before", "rms_after", "converged", "error", "error_type"]
    pd.testing.assert_frame_equal(flat.table[cols], typed.table[cols])
    assert typed.n_failed == 2
    with pytest.raises(TrimagInputError, match="not both"):
        fit_batch(str(fleet / "*.csv"), tmp_path / "both", request=FitRequest.of("", method="ml"), units="nT")
    assert not (tmp_path / "both").exists()


def test_cli_batch_passes_sensor_to_every_file(fleet: Path, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    """``batch --sensor`` was accepted and dropped (every file read with its default magnetometer): it now reaches
    each file's reader, which refuses it for a table (a table has one magnetometer)."""
    code = main(["batch", str(fleet / "sensor0.csv"), "--out", str(tmp_path / "o"), "--sensor", "1"])
    assert code == 2
    err = capsys.readouterr().err
    assert "sensor0.csv" in err and "--sensor picks a magnetometer of an autopilot log" in err


def test_cli_batch_fits_the_vector_model_with_attitudes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``batch`` had no attitude, background or time flags: an interference12 fleet (and its eddy terms, which
    need the sample rate) could not be fitted in a batch at all."""
    import pandas as pd
    from scipy.spatial.transform import Rotation

    K = np.array([[1.03, 0.02, -0.01], [0.01, 0.97, 0.02], [0.0, -0.02, 1.02]])
    c = np.array([150.0, -80.0, 40.0])
    H_n = np.array([18_000.0, 1_000.0, 45_000.0])
    for seed in (1, 2):
        att = Rotation.random(600, random_state=seed)
        H_b = att.inv().apply(H_n)
        H_m = H_b @ K.T + c + np.random.default_rng(seed).normal(scale=5.0, size=H_b.shape)
        q = att.as_quat()  # x, y, z, w
        pd.DataFrame({"t": np.arange(600) * 0.1, "x": H_m[:, 0], "y": H_m[:, 1], "z": H_m[:, 2],
                      "qw": q[:, 3], "qx": q[:, 0], "qy": q[:, 1], "qz": q[:, 2]}).to_csv(
            tmp_path / f"box{seed}.csv", index=False)
    out = tmp_path / "out"
    code = main(["batch", str(tmp_path / "box*.csv"), "--out", str(out), "--model", "interference12",
                 "--columns", "x,y,z", "--quaternion-columns", "qw,qx,qy,qz", "--background-ned", "18000,1000,45000",
                 "--units", "nT", "--time-column", "t", "--option", "eddy=3", "--json"])
    assert code == 0, capsys.readouterr().err
    for seed in (1, 2):
        cal = Calibration.from_file(out / f"box{seed}.json")
        assert cal.model == "interference12" and cal.regressors is not None
        assert cal.regressors["eddy"]["rate_hz"] == pytest.approx(10.0)
        np.testing.assert_allclose(cal.offset, c, atol=5.0)


# ------------------------------------------------ a worker that dies, the user's files, stale outputs (issue 33)
def _worker_pids(parent: int) -> list[int]:
    """The pool's worker processes under ``parent`` (spawned: ``multiprocessing.spawn``), not its resource
    tracker."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        if ppid == parent and "spawn_main" in cmdline:
            pids.append(int(entry.name))
    return pids


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc to find the worker processes")
def test_a_file_whose_worker_is_killed_is_reported_and_the_batch_finishes(tmp_path: Path) -> None:
    """A file that kills its worker (the kernel's out-of-memory killer on 20 MB of one wide line in the issue)
    stopped the batch: exit 1, no summary, a temporary folder left. Here every worker holding the culprit's
    decompressed copy is killed, as the OOM killer would, each time the culprit is tried."""
    import gzip
    import os
    import signal
    import subprocess
    import time

    from _helpers import trimag_command

    fleet = tmp_path / "fleet"
    fleet.mkdir()
    for i in range(4):
        _write_log(fleet / f"sensor{i}.csv", seed=i)
    raw = simulate_ellipsoid(150_000, noise=20.0, seed=9)
    with gzip.open(fleet / "culprit.csv.gz", "wt", compresslevel=1) as fh:
        np.savetxt(fh, raw, delimiter=",", header="bx,by,bz", comments="", fmt="%.2f")
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    out = tmp_path / "out"
    proc = subprocess.Popen([*trimag_command(), "batch", str(fleet / "*"), "--out", str(out), "--workers", "2",
                             "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "TMPDIR": str(scratch)})
    kills = 0
    seen: set[Path] = set()
    deadline = time.monotonic() + 240
    while proc.poll() is None and time.monotonic() < deadline:
        try:
            copies = set(scratch.glob("trimag-*/**/culprit.csv"))
        except OSError:  # a folder removed while it was listed
            copies = set()
        for copy in copies - seen:  # a new try at the culprit
            seen.add(copy)
            for pid in _worker_pids(proc.pid):
                try:
                    os.kill(pid, signal.SIGKILL)
                    kills += 1
                except ProcessLookupError:
                    pass
        time.sleep(0.02)
    stdout, stderr = proc.communicate(timeout=60)
    assert kills >= 2, (kills, stderr)  # killed at the first try and again when tried alone
    assert proc.returncode == 2, stderr
    assert "Traceback" not in stderr and "internal error" not in stderr
    summary = json.loads(stdout)
    assert summary["n_files"] == 5 and summary["n_fitted"] == 4
    assert [Path(f["file"]).name for f in summary["failed"]] == ["culprit.csv.gz"]
    assert "died" in summary["failed"][0]["error"]
    table = pd.read_csv(out / "summary.csv")
    assert len(table) == 5 and all((out / f"sensor{i}.json").exists() for i in range(4))
    assert not (out / "culprit.json").exists()
    assert not list(scratch.iterdir())  # the batch's temporary folders are removed, the dead worker's too


def test_a_file_that_cannot_be_read_or_written_is_an_input_error_as_in_fit(tmp_path: Path, fleet: Path,
                                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """An OSError (an unreadable file, an output that cannot be written) was an "internal error" in batch where
    `fit` says exit 2."""
    from trimag.app.batch import fit_one
    from trimag.app.requests import FitRequest

    blocker = tmp_path / "not-a-folder"
    blocker.write_text("")
    row = fit_one((str(fleet / "sensor0.csv"), str(blocker / "sensor0.json")), FitRequest.of(""))
    assert row["error_type"] == "input" and "cannot read or write" in row["error"], row
    assert "internal error" not in row["error"]


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root reads a chmod-000 file")
def test_a_chmod_000_file_exits_2_in_batch_as_in_fit(tmp_path: Path, fleet: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    locked = fleet / "sensor3.csv"
    locked.chmod(0)
    try:
        assert main(["fit", str(locked), "-q"]) == 2
        capsys.readouterr()
        assert main(["batch", str(locked), "--out", str(tmp_path / "o")]) == 2
        assert "internal error" not in capsys.readouterr().err
    finally:
        locked.chmod(0o644)


def test_a_failing_file_leaves_no_stale_calibration(tmp_path: Path, fleet: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    assert main(["batch", str(fleet / "sensor*.csv"), "--out", str(out), "-q"]) == 0
    assert (out / "sensor2.json").exists()
    (fleet / "sensor2.csv").write_text("this is not\na magnetometer log\n", encoding="utf-8")
    assert main(["batch", str(fleet / "sensor*.csv"), "--out", str(out), "-q"]) == 2
    assert not (out / "sensor2.json").exists()  # the earlier run's calibration would pass for this input's
    assert (out / "sensor1.json").exists()
    table = pd.read_csv(out / "summary.csv")
    assert table.loc[table["file"].str.endswith("sensor2.csv"), "error"].str.len().item() > 0


def test_the_input_limits_hold_in_the_worker_processes(tmp_path: Path, fleet: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    """--max-fields reaches the workers (the limits are a context of this process, handed to each task)."""
    wide = fleet / "wide.csv"
    wide.write_text(",".join(["note"] * 200) + "\n" + (fleet / "sensor0.csv").read_text(), encoding="utf-8")
    out = tmp_path / "out"
    argv = ["batch", str(wide), str(fleet / "sensor1.csv"), "--out", str(out), "--workers", "2", "--json"]
    assert main([*argv, "--max-fields", "50"]) == 2
    captured = capsys.readouterr()
    failed = json.loads(captured.out)["failed"]
    assert [Path(f["file"]).name for f in failed] == ["wide.csv"] and "more than 50" in failed[0]["error"]
    assert "--max-fields" in captured.err
    assert main(argv) == 0


def test_batch_checks_every_calibration_against_a_policy(fleet: Path, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    """A fleet's calibrations are accepted or rejected as ``fit --policy`` does it, one verdict per file in the
    summary and exit 4 when any is rejected (review of the chained features: batch had no --policy; a user had to
    fit each file again to learn which to reject)."""
    strict, loose = tmp_path / "strict.toml", tmp_path / "loose.toml"
    strict.write_text("[limits]\nmax_rms_after = 0\n")
    loose.write_text("[limits]\nmax_rms_after = 1e9\n")
    argv = ["batch", str(fleet / "sensor*.csv"), "--units", "nT", "--json"]
    assert main([*argv, "--out", str(tmp_path / "a"), "--policy", str(strict)]) == 4
    s = json.loads(capsys.readouterr().out)
    assert s["n_rejected"] == 4 and s["n_failed"] == 0
    table = pd.read_csv(tmp_path / "a" / "summary.csv", keep_default_na=False, na_values=[""])
    assert list(table["accepted"]) == [False] * 4 and all("max_rms_after" in r for r in table["rejected_by"])
    assert main([*argv, "--out", str(tmp_path / "b"), "--policy", str(loose)]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["n_rejected"] == 0
    table = pd.read_csv(tmp_path / "b" / "summary.csv", keep_default_na=False, na_values=[""])
    assert list(table["accepted"]) == [True] * 4
    # one rule passed and one failed: rejected, as fit rejects it (a list of passed rules was read as the verdict)
    mixed = tmp_path / "mixed.toml"
    mixed.write_text("[limits]\nmax_rms_after = 0\nmax_offset = 1e9\n")
    assert main([*argv, "--out", str(tmp_path / "m"), "--policy", str(mixed)]) == 4
    assert json.loads(capsys.readouterr().out)["n_rejected"] == 4
    table = pd.read_csv(tmp_path / "m" / "summary.csv", keep_default_na=False, na_values=[""])
    assert list(table["accepted"]) == [False] * 4
    assert main([*argv, "--out", str(tmp_path / "c")]) == 0  # no policy: no verdict
    capsys.readouterr()
    assert pd.read_csv(tmp_path / "c" / "summary.csv", keep_default_na=False, na_values=[""])["accepted"].isna().all()
    # a policy that cannot be read is refused once, before any file is fitted (was: each file failed with it)
    assert main([*argv, "--out", str(tmp_path / "d"), "--policy", str(tmp_path / "nope.toml")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "nope.toml" in err and not (tmp_path / "d").exists()
