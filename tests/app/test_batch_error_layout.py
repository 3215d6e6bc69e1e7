"""``batch`` says each failed file's verdict in one short line and keeps the figures behind it in the summary.

A refusal is one verdict line and its indented details (docs/cli.md, "Errors"); batch printed each failed file's
verdict and details joined into one line of 900+ characters (a static autopilot log's refusal with its modes for a
vehicle that cannot be tumbled), and its summary held them joined in ``error``. Now the line on stderr is the verdict,
the summary's ``error`` the verdict and ``error_details`` the details.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import pandas as pd

TESTS_DIR = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(TESTS_DIR))

from _helpers import run_trimag, write_sphere_csv  # noqa: E402


def test_a_failed_file_is_one_verdict_line_and_its_details_go_to_the_summary(tmp_path: Path) -> None:
    logs = tmp_path / "logs"
    logs.mkdir()
    shutil.copy(TESTS_DIR / "data" / "logs" / "ardusub_small.BIN", logs / "static.BIN")
    write_sphere_csv(logs / "lab.csv")
    out = tmp_path / "out"
    r = run_trimag("batch", str(logs / "*"), "--out", out)
    assert r.returncode == 3, r.stderr
    failed = [line for line in r.stderr.splitlines() if "static.BIN" in line]
    assert len(failed) == 1, r.stderr
    assert len(failed[0]) <= 200 + len(str(logs / "static.BIN")), failed[0]
    assert "cannot be tumbled" not in r.stderr, r.stderr
    summary = pd.read_csv(out / "summary.csv", keep_default_na=False)
    row = summary[summary["file"].str.endswith("static.BIN")].iloc[0]
    assert row["error"] and "cannot be tumbled" not in row["error"], row["error"]
    assert "cannot be tumbled" in row["error_details"], row["error_details"]
    good = summary[summary["file"].str.endswith("lab.csv")].iloc[0]
    assert good["error"] == "" and good["error_details"] == ""
