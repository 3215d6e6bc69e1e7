"""The layout of a refusal (issue 42, item 6; docs/cli.md, "Errors"): autopilot refusals ran to 2 109 characters on one
line with the modes that help repeated once per compass. Now the first stderr line is the whole verdict (what is
wrong and what to do, at most 200 characters); the figures behind it follow as short lines (at most 120 characters)
indented by two spaces, each said once."""

from __future__ import annotations

from pathlib import Path

import pytest

from _helpers import SHARED_DATA, TESTS_DIR, refusal, run_trimag

LOGS = TESTS_DIR / "data" / "logs"
SHARED = SHARED_DATA / "flight-logs"
SITE = "51.5,-0.1,0,2022-06-01"

def _said_once(stderr: str, *phrases: str) -> None:
    for phrase in phrases:
        assert stderr.count(phrase) <= 1, (phrase, stderr)


@pytest.mark.parametrize(("log", "more"), [
    ("px4tools_01_07_59.px4log", []),  # barely turned: the 3-D fit refused
    ("px4tools_01_07_59.px4log", ["--sensor", "2", "--target", "px4"]),  # 59 % unexplained, a reversed orientation
    ("ardusub_small.BIN", []),  # static
    ("ardusub_small.BIN", ["--sensor", "2", "--target", "ardupilot", "--igrf", SITE]),  # offsets not excited
    ("ardusub_small.BIN", ["--sensor", "all", "--target", "ardupilot", "--igrf", SITE]),  # both compasses
    ("ardusub_small.BIN", ["--sensor", "all", "--target", "ardupilot"]),  # no GPS fix (246 characters before)
    ("pyulog_sample_log_small.ulg", ["--sensor", "all", "--target", "px4"]),  # three refusals (2 109 characters)
], ids=lambda v: v if isinstance(v, str) else " ".join(v))
def test_a_log_refusal_is_one_verdict_then_short_indented_lines(log: str, more: list[str], tmp_path: Path) -> None:
    r = run_trimag("fit", LOGS / log, *more, "-o", tmp_path / "cal.json", timeout=600)
    assert r.returncode in (2, 3), (r.returncode, r.stderr)
    verdict, details = refusal(r.stderr)
    _said_once(r.stderr, "cannot be tumbled", "--level-turn fits", "--prior CAL.json keeps")
    said = "\n".join([verdict, *details])
    assert "condition number" not in said
    assert not list(tmp_path.iterdir())
    if log.startswith("px4tools") and not more:  # the details keep what the one line said (test_log_refusals)
        assert "1 (IMU.Mag)" in said and "2 (IMU1.Mag)" in said and "--level-turn" in said, said


@pytest.mark.skipif(not SHARED.is_dir(), reason="needs ../shared/data/flight-logs")
@pytest.mark.parametrize("log", ["pymavlink_test.BIN", "methodicconfigurator_backend_log_80k.bin",
                                 "ardusub_small.tlog"])
def test_the_shared_logs_refusals_are_laid_out_so(log: str, tmp_path: Path) -> None:
    """The real logs' refusals under --target ardupilot, one compass and all of them (measured before: 587 to
    1 851 characters on one line)."""
    for sensor in ("1", "all"):
        r = run_trimag("fit", SHARED / log, "--target", "ardupilot", "--sensor", sensor, "-o", tmp_path / "c.json",
                       timeout=600)
        if r.returncode == 0:
            continue
        refusal(r.stderr)
        _said_once(r.stderr, "cannot be tumbled", "--level-turn fits")
