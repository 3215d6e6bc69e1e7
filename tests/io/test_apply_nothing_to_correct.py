"""``trimag apply`` of a log none of whose rows has numeric x, y, z (issue 41, item 17): refused as ``fit`` refuses
it (exit 2, one line naming the columns), no output written (before: exit 0, "corrected 0 of 500 rows", an output
of empty corrected cells). A log with some such rows is still corrected, the rows counted."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from _helpers import run_trimag


def test_a_log_without_one_numeric_row_is_refused_and_a_partial_one_corrected(tmp_path: Path) -> None:
    rng = np.random.default_rng(9)
    u = rng.normal(size=(300, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    xyz = u * 500 + rng.normal(0, 2, (300, 3))
    good = tmp_path / "good.csv"
    np.savetxt(good, xyz, delimiter=",", header="x,y,z", comments="")
    cal = tmp_path / "cal.json"
    assert run_trimag("fit", good, "-o", cal, "-q").returncode == 0
    bad = tmp_path / "bad.csv"
    bad.write_text("x,y,z\n" + "".join(f"{a:.3f},{b:.3f},n/a\n" for a, b, _ in xyz))
    out = tmp_path / "out.csv"
    r = run_trimag("apply", cal, bad, "-o", out)
    assert r.returncode == 2, r.stderr
    assert "none of the 300 rows has three numeric, finite values in columns x, y, z: nothing to correct" \
        in r.stderr, r.stderr
    assert not out.exists()
    partial = tmp_path / "partial.csv"
    partial.write_text(good.read_text().replace(good.read_text().splitlines()[3] + "\n", "1,2,\n", 1))
    r = run_trimag("apply", cal, partial, "-o", out)
    assert r.returncode == 0 and out.exists() and "1 of 300 rows" in r.stderr, r.stderr
