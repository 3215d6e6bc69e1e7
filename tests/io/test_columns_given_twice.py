"""``--columns x,x,z`` (one column named for two axes; issue 41, item 17) is refused as the user's mistake, naming
the column, exit 2, in fit, apply and evaluate (before: fit refused with exit 3 "all samples lie in one line (the
sensor turned about a single axis, or not at all) ... record rotations", wrong about the cause; apply and evaluate
wrote or printed results of a sensor with two equal axes)."""

from __future__ import annotations

from pathlib import Path

import pytest

from _helpers import run_trimag, write_sphere_csv


@pytest.mark.parametrize("command", ["fit", "apply", "evaluate"])
def test_a_column_named_for_two_axes_is_refused(tmp_path: Path, command: str) -> None:
    log = write_sphere_csv(tmp_path / "log.csv", seed=5, header="mx,my,mz")
    cal = tmp_path / "cal.json"
    assert run_trimag("fit", log, "-o", cal, "-q").returncode == 0
    out = tmp_path / "out.csv"
    args = {"fit": ["fit", log], "apply": ["apply", cal, log, "-o", out], "evaluate": ["evaluate", cal, log]}[command]
    r = run_trimag(*args, "--columns", "mx,mx,2", "-q")
    assert r.returncode == 2, (r.returncode, r.stderr)
    assert "--columns names the column 'mx' for more than one axis (mx, mx, 2)" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not out.exists()
