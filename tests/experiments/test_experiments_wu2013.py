"""``trimag reproduce wu2013`` (paper A): outputs, summary keys, and the real-data part."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import trimag
from trimag.experiments import get_experiment
from trimag.experiments.wu2013 import attitudes_for, fig3_trial, fig5_trial, load_real_log, run

from _helpers import SHARED_DATA, requires_shared


def test_registered():
    assert get_experiment("wu2013").run is run


def test_attitudes_full_turns_about_three_axes():
    att = attitudes_for(301, "axes")
    assert len(att) == 301
    rotvec = att.as_rotvec()
    # first third: rotations about x only
    assert np.allclose(rotvec[:101, 1:], 0) and np.ptp(rotvec[:101, 0]) > 3
    assert len(attitudes_for(10, "random", 0)) == 10


def test_trials_are_reproducible_and_noise_free_exact():
    j, rel = fig3_trial((50, 0.0, 7))
    assert j < 1e-12 and rel < 1e-9
    assert fig3_trial((50, 1e-3, 7)) == fig3_trial((50, 1e-3, 7))
    row = fig5_trial((1e-3, 3))
    assert set(row) >= {"J_pairwise", "J_old", "J_geometric", "J_pairwise_old_params"}
    assert all(np.isfinite(v) and v > 0 for v in row.values())


def test_run_quick_without_shared_data(tmp_path):
    summary = run(tmp_path / "out", quick=True, trials=2, seed=1, json_mode=True, data_dir=tmp_path / "none")
    out = tmp_path / "out"
    for name in ("fig3_J_vs_N", "fig4_J_vs_N_large", "fig5_J_vs_sigma"):
        assert (out / f"{name}.png").stat().st_size > 1000
        assert (out / f"{name}.csv").read_text().count("\n") > 2
    json.dumps(summary, allow_nan=False)  # the CLI prints it strictly
    assert {"fig3", "fig5", "runtime_s"} <= set(summary)
    assert set(summary["fig3"][0]) == {"sigma", "N", "J_median", "J_p90"}
    assert {"sigma", "J_pairwise", "J_old", "J_geometric"} <= set(summary["fig5"][0])
    assert {r["sigma"] for r in summary["fig3"]} == {0.0, 1e-4, 1e-3, 1e-2}
    assert max(r["N"] for r in summary["fig3"]) >= 1000
    assert "skipped" in summary["fig6"] and "absent" in summary["fig6"]["skipped"]
    assert "Fig. 6: skipped" in summary["text"]
    assert summary["checks"]["noise_free_max_rel_param_error"] < 1e-9
    assert not list(out.glob(".*"))  # no temporary files left behind


@requires_shared
def test_real_log_loader_and_fig6(tmp_path):
    path = SHARED_DATA / "qmc5883l-suarez" / "noisy_raw_data.csv"
    B, unit, note = load_real_log(path)
    assert unit == "counts" and B.shape == (22743 - 3000, 3) and "60" in note
    from trimag.experiments.wu2013 import real_log_figure

    res = real_log_figure(path, tmp_path, stride=4)
    assert (tmp_path / res["figure"]).exists()
    assert res["rel_std_after_pairwise"] < res["rel_std_before"]
    assert res["rel_std_after_geometric"] < res["rel_std_before"]


def test_the_stride_note_reads_as_english(tmp_path):
    """"every 2th sample used" in `trimag reproduce wu2013`'s Fig. 6 line (issue 42, item 6): 2nd, 3rd, 4th, 11th."""
    from trimag.experiments.wu2013 import real_log_figure

    demo = Path(trimag.__file__).parent / "data" / "qmc5883l_noisy_raw_data.csv"
    notes = {stride: real_log_figure(demo, tmp_path, stride=stride)["note"] for stride in (2, 3)}
    assert "every 2nd sample used" in notes[2] and "every 3rd sample used" in notes[3], notes


@pytest.mark.skipif(not (SHARED_DATA / "broad").exists(), reason="shared data absent")
def test_broad_loader():
    B, unit, _ = load_real_log(SHARED_DATA / "broad" / "01_undisturbed_slow_rotation_A.mat")
    assert unit == "uT" and B.shape[1] == 3 and np.isfinite(B).all()
