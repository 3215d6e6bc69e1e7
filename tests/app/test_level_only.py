"""A vehicle that only turns level is never told to tumble (issue 38, item 7): a simulated boat's level turns with
`--igrf` were refused "record rotations about at least two more axes". With a field reference, the default fit of
such a log is the level-turn method (said, as `--level-turn` would be); another model or method is refused naming
`--level-turn` first."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from trimag.cli import main

from _helpers import BOAT_OFFSET, BOAT_SITE, simulate_boat


@pytest.fixture(scope="module")
def boat(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("boat") / "boat.csv"
    np.savetxt(path, simulate_boat(0)["raw"], delimiter=",", header="x,y,z", comments="", fmt="%.4f")
    return path


def test_a_level_log_with_a_field_reference_is_fitted_by_the_level_turn(boat: Path,
                                                                        capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["fit", str(boat), "--units", "mG", "--igrf", BOAT_SITE, "--json"]) == 0
    captured = capsys.readouterr()
    summary = json.loads(captured.out)
    assert "level_turn" in summary["diagnostics"]
    assert "--level-turn" in captured.err and "two more axes" not in captured.err
    assert np.allclose(summary["offset"][:2], BOAT_OFFSET[:2], atol=5.0)
    # the same as asking for it
    assert main(["fit", str(boat), "--units", "mG", "--igrf", BOAT_SITE, "--level-turn", "--json", "-q"]) == 0
    asked = json.loads(capsys.readouterr().out)
    assert np.allclose(asked["offset"], summary["offset"]) and np.allclose(asked["matrix"], summary["matrix"])


@pytest.mark.parametrize("more", [["--model", "scalar9"], ["--method", "ellipsoid-fit"]])
def test_another_model_or_method_names_the_level_turn_first(more: list[str], boat: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["fit", str(boat), "--units", "mG", "--igrf", BOAT_SITE, *more, "-q"]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--level-turn" in err[0], err
    assert err[0].index("--level-turn") < err[0].find("two more axes") or "two more axes" not in err[0]


def test_without_a_field_reference_the_plane_is_still_refused(boat: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["fit", str(boat), "--units", "mG", "-q"]) == 3
    err = capsys.readouterr().err
    assert "one plane" in err
