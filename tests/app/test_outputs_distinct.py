"""No output replaces an input, and no two outputs are one file (issue 41, item 3): every command refuses (exit 2,
one line, nothing written) before it writes, through links and relative paths too
(``io.atomic.check_distinct_outputs``)."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest

from trimag.errors import TrimagInputError

from _helpers import REPO_DIR, TESTS_DIR, run_trimag

DEMO = REPO_DIR / "src" / "trimag" / "data" / "qmc5883l_noisy_raw_data.csv"


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file() and not p.is_symlink()}


def _refused(r, folder: Path, before: dict[str, bytes], *words: str) -> None:
    assert r.returncode == 2, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr
    for word in words:
        assert word in r.stderr, r.stderr
    assert _snapshot(folder) == before  # nothing written, nothing replaced


@pytest.fixture
def lab(tmp_path: Path) -> Path:
    shutil.copy(DEMO, tmp_path / "in.csv")
    r = run_trimag("fit", tmp_path / "in.csv", "--units", "counts", "-o", tmp_path / "cal.json")
    assert r.returncode == 0, r.stderr
    return tmp_path


def test_fit_output_is_its_input(lab: Path):
    before = _snapshot(lab)
    _refused(run_trimag("fit", "in.csv", "--units", "counts", "-o", "./in.csv", cwd=lab), lab, before,
             "would replace the input", "in.csv")


def test_fit_output_through_a_symlink_to_its_input(lab: Path):
    os.symlink(lab / "in.csv", lab / "link.csv")
    before = _snapshot(lab)
    _refused(run_trimag("fit", lab / "link.csv", "--units", "counts", "-o", lab / "sub" / ".." / "in.csv"), lab,
             before, "would replace the input")


def test_fit_report_and_calibration_are_one_file(lab: Path):
    before = _snapshot(lab)
    _refused(run_trimag("fit", "in.csv", "--units", "counts", "-o", "r.png", "--report", "r.png", cwd=lab), lab,
             before, "same file")


def test_fit_prior_replaced_by_the_output(lab: Path):
    before = _snapshot(lab)
    _refused(run_trimag("fit", "in.csv", "--units", "counts", "--prior", "cal.json", "-o", "cal.json", cwd=lab),
             lab, before, "--prior")


def test_export_output_is_the_calibration(lab: Path):
    before = _snapshot(lab)
    _refused(run_trimag("export", "cal.json", "--to", "ardupilot", "-o", "cal.json", cwd=lab), lab, before,
             "calibration")
    json.loads((lab / "cal.json").read_text())  # still the calibration


def test_apply_output_is_its_input(lab: Path):
    before = _snapshot(lab)
    _refused(run_trimag("apply", "cal.json", "in.csv", "-o", "in.csv", cwd=lab), lab, before, "in.csv")


def test_simulate_truth_is_its_output(tmp_path: Path):
    (tmp_path / "p.json").write_text(json.dumps({"offset": [1.0, 2.0, 3.0]}))
    before = _snapshot(tmp_path)
    simulate = ("simulate", "--model", "ellipsoid", "--params", "p.json", "--n", "100")
    _refused(run_trimag(*simulate, "-o", "s.csv", "--truth", "s.csv", cwd=tmp_path), tmp_path, before, "same file")
    _refused(run_trimag(*simulate, "-o", "p.json", cwd=tmp_path), tmp_path, before, "would replace")


def test_all_compasses_parameter_file_is_a_compass_calibration(tmp_path: Path):
    shutil.copy(TESTS_DIR / "data" / "logs" / "ardusub_small.BIN", tmp_path / "f.bin")
    before = _snapshot(tmp_path)
    _refused(run_trimag("fit", "f.bin", "--sensor", "all", "--export-to", "ardupilot", "--export-out", "c-1.json",
                        "-o", "c.json", cwd=tmp_path), tmp_path, before, "same file", "c-1.json")


def test_batch_summary_is_one_of_its_inputs(lab: Path):
    shutil.copy(lab / "in.csv", lab / "summary.csv")
    before = _snapshot(lab)
    _refused(run_trimag("batch", str(lab / "*.csv"), "--units", "counts", "--out", lab), lab, before,
             "summary.csv")


def test_the_check_itself(tmp_path: Path):
    from trimag.io.atomic import check_distinct_outputs, same_file

    a = tmp_path / "a.txt"
    a.write_text("x")
    os.link(a, tmp_path / "hard.txt")
    assert same_file(a, tmp_path / "hard.txt") and same_file(tmp_path / "new", tmp_path / "x" / ".." / "new")
    assert not same_file(a, tmp_path / "b.txt")
    check_distinct_outputs({"path": a, "prior": None}, {"out": "-", "report": tmp_path / "r.png"})  # passes
    with pytest.raises(TrimagInputError, match=r"`out` .* would replace the input "):
        check_distinct_outputs({"the input": a}, {"out": tmp_path / "hard.txt"})
