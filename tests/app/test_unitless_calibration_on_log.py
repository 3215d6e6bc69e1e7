"""Issue 41, item 17: a calibration fitted without `--units` evaluated (or applied) on a DataFlash log, which records
its compass in mG, passed without a word (the unit check lets an unknown unit through). Now a warning says it: the
calibration's unit is not known, the log's is mG."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from _helpers import TESTS_DIR, run_trimag, simulate_ellipsoid

LOG = TESTS_DIR / "data" / "logs" / "ardusub_small.BIN"


@pytest.mark.parametrize("units", [None, "mG"])
@pytest.mark.parametrize("command", ["evaluate", "apply"])
def test_a_calibration_without_a_unit_on_a_mg_log_is_flagged(command: str, units: str | None,
                                                              tmp_path: Path) -> None:
    log = tmp_path / "log.csv"
    np.savetxt(log, simulate_ellipsoid(300, noise=0.5, F=500.0), delimiter=",", header="x,y,z", comments="")
    cal = tmp_path / "cal.json"
    assert run_trimag("fit", log, *(["--units", units] if units else []), "-o", cal).returncode == 0
    out = ("-o", tmp_path / "out.csv") if command == "apply" else ()
    r = run_trimag(command, cal, LOG, *out)
    assert r.returncode == 0, r.stderr
    warned = [line for line in r.stderr.splitlines()
              if line.startswith("trimag: warning:") and "unit is not known" in line]
    if units is None:
        assert len(warned) == 1 and "mG" in warned[0], r.stderr
        assert len(warned[0]) <= 200
    else:
        assert not warned, r.stderr
