"""A live recording's samples file keeps its unit: ``trimag fit`` and ``trimag live --replay`` of it use the unit
the recording had (issue 39, item 8: a file whose first line said "unit G" was refitted with unit "unknown")."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from _live_helpers import sensor

from trimag.cli import main
from trimag.live import LiveSession
from trimag.live.sources import Batch, replay_source
from trimag.simulate import uniform_directions


@pytest.mark.parametrize(("unit", "scale"), [("G", 1e-3), ("uT", 0.1), ("counts", 1.0)])
def test_the_samples_file_of_a_recording_is_refitted_in_its_unit(unit: str, scale: float, tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    session = LiveSession(units=unit, source="test")
    session.add(Batch(sensor(uniform_directions(600, seed=21)) * scale))
    written = session.save(tmp_path / "cal.json")
    samples = Path(written["samples"])
    assert f"unit {unit}" in samples.read_text().splitlines()[0]
    assert main(["fit", str(samples), "--json", "-q"]) == 0
    assert json.loads(capsys.readouterr().out)["units"] == unit
    first = next(replay_source(samples, rate=None))
    assert first.units == unit


def test_a_samples_file_of_an_earlier_version_is_read_in_the_unit_its_first_line_states(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Files written before the unit went into the column names: ``x,y,z`` under "# ...; unit G"."""
    samples = tmp_path / "old-samples.csv"
    raw = sensor(uniform_directions(600, seed=22)) * 1e-3
    samples.write_text("# trimag live recording (serial /dev/ttyUSB0); unit G\nx,y,z\n"
                       + "\n".join(",".join(f"{v:.9g}" for v in row) for row in raw) + "\n")
    assert main(["fit", str(samples), "--json"]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["units"] == "G" and "first line" in captured.err
    assert main(["fit", str(samples), "--units", "uT", "-q"]) == 2
    assert "first line says unit G" in capsys.readouterr().err
    assert next(replay_source(samples, rate=None)).units == "G"
