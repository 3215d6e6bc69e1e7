"""Issue 41, item 17: `--rows 10:5` said "the row selection (rows 10:5) matched no rows" (fit) or "no rows with finite
x, y, z values to evaluate" (evaluate), as if the file were short of rows. A range whose START is at or after its STOP
is the user's mistake: refused, exit 2, naming the range, for every command and reader that takes `--rows`."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from _helpers import TESTS_DIR, refusal, run_trimag, simulate_ellipsoid


@pytest.fixture
def log_and_cal(tmp_path: Path) -> tuple[Path, Path]:
    log = tmp_path / "log.csv"
    np.savetxt(log, simulate_ellipsoid(300, noise=20.0), delimiter=",", header="x,y,z", comments="")
    cal = tmp_path / "cal.json"
    assert run_trimag("fit", log, "--units", "nT", "-o", cal).returncode == 0
    return log, cal


@pytest.mark.parametrize("command", ["fit", "fit-firmware", "evaluate", "evaluate-chunked"])
def test_a_reversed_row_range_is_refused_naming_it(command: str, log_and_cal: tuple[Path, Path],
                                                   tmp_path: Path) -> None:
    log, cal = log_and_cal
    out = tmp_path / "out.json"
    args = {"fit": ("fit", log, "-o", out),
            "fit-firmware": ("fit", TESTS_DIR / "data" / "logs" / "ardusub_small.BIN", "--target", "ardupilot",
                             "-o", out),
            "evaluate": ("evaluate", cal, log),
            "evaluate-chunked": ("evaluate", cal, log, "--chunk-rows", "50")}[command]
    r = run_trimag(*args, "--rows", "10:5")
    assert r.returncode == 2, r.stderr
    verdict, _ = refusal(r.stderr)
    assert "10:5" in verdict and "START" in verdict and "STOP" in verdict, verdict
    assert "matched no rows" not in verdict and "finite" not in verdict, verdict
    assert not out.exists()


def test_an_empty_range_from_the_end_is_refused_and_a_valid_one_is_not(log_and_cal: tuple[Path, Path],
                                                                      tmp_path: Path) -> None:
    log, _ = log_and_cal
    r = run_trimag("fit", log, "--rows", "-5:-10", "-o", tmp_path / "a.json")
    assert r.returncode == 2 and "-5:-10" in refusal(r.stderr)[0], r.stderr
    assert run_trimag("fit", log, "--rows", "-200:", "--units", "nT", "-o", tmp_path / "b.json").returncode == 0
