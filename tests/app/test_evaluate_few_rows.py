"""``trimag evaluate CAL LOG`` of one or a few rows without a reference (issue 41, item 17): the field F is then
the corrected rows' own mean, so RMS(|B| - F) after correction is 0 for one row whatever the calibration; refused
(exit 3) saying so and what to give. With a reference the same rows are evaluated (before: exit 0, "RMS after 0",
a perfect-looking table for a row of 1,2,3 against a calibration of a 500-unit field)."""

from __future__ import annotations

from pathlib import Path

from _helpers import run_trimag, write_sphere_csv


def test_one_row_against_its_own_mean_is_refused_and_with_a_reference_evaluated(tmp_path: Path) -> None:
    log = write_sphere_csv(tmp_path / "log.csv", seed=6)
    cal = tmp_path / "cal.json"
    assert run_trimag("fit", log, "-o", cal, "-q").returncode == 0
    one = tmp_path / "one.csv"
    one.write_text("x,y,z\n1,2,3\n")
    r = run_trimag("evaluate", cal, one)
    assert r.returncode == 3, (r.returncode, r.stdout)
    assert "1 row with x, y, z: without a reference the field F is the corrected rows' own mean" in r.stderr
    assert "--reference F" in r.stderr and "cannot identify" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
    r = run_trimag("evaluate", cal, one, "--reference", "500")
    assert r.returncode == 0, r.stderr
    r = run_trimag("evaluate", cal, log)  # enough rows: evaluated against their own mean as before
    assert r.returncode == 0, r.stderr
