"""Issue 41, item 17: `--reference 1e308` was taken and reported as "the data's median |B| is 47795.3, 4.78e-304x the
reference field" (fit) or printed RMS nan with numpy's overflow warning (evaluate); `--reference 1e-300` was an
internal error in fit. A reference that is no field magnitude in any unit (not finite, <= 0, outside 1e-9 to 1e12) is
refused in one line naming the option, exit 2."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from _helpers import refusal, run_trimag, simulate_ellipsoid


@pytest.fixture(scope="module")
def log_and_cal(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("reference")
    log = folder / "log.csv"
    np.savetxt(log, simulate_ellipsoid(300, noise=20.0), delimiter=",", header="x,y,z", comments="")
    cal = folder / "cal.json"
    assert run_trimag("fit", log, "--units", "nT", "-o", cal).returncode == 0
    return log, cal


@pytest.mark.parametrize("value", ["1e308", "1e-300", "2e12", "inf", "nan", "-5", "0"])
@pytest.mark.parametrize("command", ["fit", "evaluate"])
def test_an_impossible_reference_is_refused_naming_the_option(command: str, value: str,
                                                              log_and_cal: tuple[Path, Path], tmp_path: Path) -> None:
    log, cal = log_and_cal
    out = tmp_path / "c.json"
    args = ("fit", log, "-o", out) if command == "fit" else ("evaluate", cal, log)
    r = run_trimag(*args, f"--reference={value}")
    assert r.returncode == 2, (r.returncode, r.stderr)
    verdict, details = refusal(r.stderr)
    assert verdict.startswith("trimag: error: --reference") and not details, r.stderr
    assert "x the reference field" not in verdict and "Warning" not in r.stderr, r.stderr
    assert not out.exists()


def test_a_plausible_reference_in_any_unit_is_taken(log_and_cal: tuple[Path, Path], tmp_path: Path) -> None:
    log, cal = log_and_cal
    assert run_trimag("fit", log, "--reference", "48000", "-o", tmp_path / "c.json").returncode == 0
    assert run_trimag("evaluate", cal, log, "--reference", "48000").returncode == 0
