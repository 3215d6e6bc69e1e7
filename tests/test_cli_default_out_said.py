"""Issue 41, item 17: `export`/`apply` without `-o` said "no -o given: writing cal.param" and then refused (a missing
or unusable calibration): nothing was written, yet the user was told of a file. Now the default name is said only once
the file is written."""

from __future__ import annotations

from pathlib import Path

from _helpers import refusal, run_trimag, simulate_ellipsoid


def test_a_refused_export_or_apply_names_no_default_output(tmp_path: Path) -> None:
    missing = tmp_path / "cal.json"
    r = run_trimag("export", missing, "--to", "ardupilot")
    assert r.returncode == 2, r.stderr
    verdict, _ = refusal(r.stderr)
    assert "cal.json" in verdict and "cal.param" not in r.stderr, r.stderr
    log = tmp_path / "log.csv"
    log.write_text("x,y,z\n1,2,3\n")
    r = run_trimag("apply", missing, log)
    assert r.returncode == 2 and "log-corrected.csv" not in r.stderr, r.stderr
    refusal(r.stderr)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["log.csv"]


def test_a_written_default_output_is_named_after_it_is_written(tmp_path: Path) -> None:
    import numpy as np

    log = tmp_path / "log.csv"
    np.savetxt(log, simulate_ellipsoid(300, noise=20.0), delimiter=",", header="x,y,z", comments="")
    cal = tmp_path / "cal.json"
    assert run_trimag("fit", log, "--units", "nT", "-o", cal).returncode == 0
    r = run_trimag("export", cal, "--to", "px4", "-q")
    assert r.returncode == 0 and (tmp_path / "cal.params").is_file(), r.stderr
    assert "no -o given: wrote" in r.stderr and "cal.params" in r.stderr, r.stderr
