"""``fit --sensor all --export-to`` writes every compass's motor term into one file: the note that
``COMPASS_MOTCT`` is one parameter for all magnetometers is said once, not once per compass (it was said for each
compass with a motor term, telling "the others keep their motor terms" although the others were in the same file)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

TESTS_DIR = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(TESTS_DIR))
pytest.importorskip("pymavlink")

from _two_compass_flight import write_two_compass_flight  # noqa: E402

from _helpers import run_trimag  # noqa: E402


def test_the_one_motor_channel_is_said_once_for_a_file_of_every_compass(tmp_path: Path) -> None:
    log = write_two_compass_flight(tmp_path / "two.BIN", n=1500)
    r = run_trimag("fit", log, "--sensor", "all", "--target", "ardupilot", "--export-to", "ardupilot",
                   "--export-out", tmp_path / "two.param", "-o", tmp_path / "two.json")
    assert r.returncode == 0, r.stderr
    said = (r.stdout + r.stderr).count("applies to every magnetometer")
    assert said == 1, r.stdout
    assert "COMPASS_MOTCT" in (tmp_path / "two.param").read_text()
