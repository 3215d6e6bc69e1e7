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
