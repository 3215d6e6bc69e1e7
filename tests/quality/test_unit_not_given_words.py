"""Issue 41, item 17: a fit without `--units` printed "unknown" as if it were a unit ("reference F = 48033.1 unknown
(mean)", "[unknown]", "hard_iron_x = 1197.89 +- 1.65 unknown", export's "this calibration is in 'unknown'"). Now it
says "unit not given", and a fit whose numbers depend on the unit names `--units`."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from _helpers import refusal, run_trimag, simulate_ellipsoid


def _unknown_as_unit(text: str) -> list[str]:
    """Lines that print "unknown" where a unit goes: after a number, or as a table's unit heading."""
    return [line for line in text.splitlines()
            if re.search(r"\d \(?unknown\b|\[unknown\b|in 'unknown'", line)]


def test_a_fit_without_units_says_the_unit_is_not_given(tmp_path: Path) -> None:
    log = tmp_path / "log.csv"
    np.savetxt(log, simulate_ellipsoid(300, noise=20.0), delimiter=",", header="x,y,z", comments="")
    cal = tmp_path / "cal.json"
    fit = run_trimag("fit", log, "-o", cal)
    assert fit.returncode == 0, fit.stderr
    assert not _unknown_as_unit(fit.stdout + fit.stderr), fit.stdout
    assert "[unit not given]" in fit.stdout and "--units" in fit.stdout, fit.stdout
    assert re.search(r"hard_iron_x += \S+ \+- \S+ \(unit not given\)", fit.stdout), fit.stdout
    ev = run_trimag("evaluate", cal, log)
    assert ev.returncode == 0 and not _unknown_as_unit(ev.stdout + ev.stderr), ev.stdout
    assert "unit not given" in ev.stdout, ev.stdout
    ap = run_trimag("apply", cal, log, "-o", tmp_path / "out.csv")
    assert ap.returncode == 0 and "(unit not given)" in ap.stdout, ap.stdout
    ex = run_trimag("export", cal, "--to", "ardupilot", "-o", tmp_path / "c.param")
    assert ex.returncode == 2, ex.stderr
    verdict, _ = refusal(ex.stderr)
    assert not _unknown_as_unit(verdict) and "no unit" in verdict and "--units" in verdict, verdict


def test_a_fit_with_units_prints_them(tmp_path: Path) -> None:
    log = tmp_path / "log.csv"
    np.savetxt(log, simulate_ellipsoid(300, noise=20.0), delimiter=",", header="x,y,z", comments="")
    fit = run_trimag("fit", log, "--units", "nT", "-o", tmp_path / "cal.json")
    assert fit.returncode == 0 and "[nT]" in fit.stdout and "unit not given" not in fit.stdout, fit.stdout
