"""The accuracy benchmark (``benchmarks/accuracy.py``) on a tiny grid (trimag's own estimators; the peers are
optional)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from _helpers import BENCHMARKS_DIR, load_benchmark

accuracy = load_benchmark("accuracy")


def test_accuracy_tiny_grid(tmp_path):
    summary = accuracy.run(tmp_path, trials=3, seed=0, json_mode=True, sizes=[400], sigmas=[0.01],
                           coverages=["full"], estimators=["ml", "ellipsoid-fit"])
    assert (tmp_path / "accuracy.csv").exists() and (tmp_path / "accuracy.md").exists()
    rows = json.loads((tmp_path / "accuracy.json").read_text())["rows"]
    assert [r["estimator"] for r in rows] == ["ml", "ellipsoid-fit"]
    ml = rows[0]
    assert ml["failures"] == 0
    # 3 trials: ratios are noisy but must be of order 1 for an estimator at the bound
    assert 0.2 < ml["ratio_rms"] < 3 and np.isfinite(ml["ratio_magnitude"])
    # the fraction of the 3 x 9 (trial, parameter) errors inside the reported 1 sigma: ~0.68 when the sigmas are
    # right (measured 22/27 here); sigmas halved would give ~0.38, doubled ~0.95
    inside = ml["coverage_1sigma"] * 27
    assert abs(inside - round(inside)) < 1e-9 and 0.4 < ml["coverage_1sigma"] < 0.95
    assert "paired_diff_vs_default" in rows[1]
    assert summary["cells"][0]["default_ratio_max"] == ml["ratio_max"]
    assert "| ml |" in summary["text"]


def test_truth_has_unit_determinant():
    W, _ = accuracy.truth().correction()
    assert abs(np.linalg.det(W) - 1) < 1e-12


def test_merge_parts_split_by_estimator(tmp_path):
    """Two runs with the same seed (the default in both, a different second estimator) merge into one table; a
    part with another seed is refused."""
    kw = {"trials": 3, "json_mode": True, "sizes": [300], "sigmas": [0.01], "coverages": ["circles"]}
    accuracy.run(tmp_path / "a", seed=0, estimators=["ml", "ellipsoid-fit"], **kw)
    accuracy.run(tmp_path / "b", seed=0, estimators=["ml", "als"], **kw)
    merged = accuracy.merge([tmp_path / "a", tmp_path / "b"], tmp_path / "all")
    rows = json.loads((tmp_path / "all" / "accuracy.json").read_text())["rows"]
    assert sorted(r["estimator"] for r in rows) == ["als", "ellipsoid-fit", "ml"]
    assert "| als |" in merged["text"] and "| ellipsoid-fit |" in merged["text"]
    accuracy.run(tmp_path / "c", seed=1, estimators=["ml"], **kw)
    with pytest.raises(ValueError, match="seed"):
        accuracy.merge([tmp_path / "a", tmp_path / "c"], tmp_path / "bad")


def test_runs_as_a_script_from_the_repository_root(tmp_path):
    """``python benchmarks/accuracy.py`` (the former ``trimag bench accuracy``): a run, then a merge of it."""
    root = BENCHMARKS_DIR.parent
    cmd = [sys.executable, "benchmarks/accuracy.py", "--trials", "2", "--sizes", "300", "--sigmas", "0.01",
           "--coverages", "full", "--estimators", "ml"]
    proc = subprocess.run([*cmd, "--out", str(tmp_path / "a"), "--json"], capture_output=True, text=True, cwd=root,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary["trials"] == 2 and summary["runtime_s"] > 0 and "| ml |" in summary["text"]
    proc = subprocess.run([*cmd, "--out", str(tmp_path / "all"), "--merge", str(tmp_path / "a"), "-q"],
                          capture_output=True, text=True, cwd=root, timeout=300)
    assert proc.returncode == 0 and proc.stdout == "", proc.stderr
    assert (tmp_path / "all" / "accuracy.md").read_text() == (tmp_path / "a" / "accuracy.md").read_text()
