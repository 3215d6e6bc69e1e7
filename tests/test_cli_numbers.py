"""Every option that takes numbers accepts a leading minus sign (issue 38, item 8): a southern latitude, a western
longitude, a negative background component or heading, given as the next word, as a user types it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from trimag.cli import build_parser, main

from _helpers import simulate_ellipsoid


@pytest.mark.parametrize(("argv", "dest", "value"), [
    (["fit", "log.csv", "--igrf", "-33.9,151.2,0,2024-01-01"], "igrf_spec", "-33.9,151.2,0,2024-01-01"),
    (["fit", "log.csv", "--igrf", "-.5,-70,0,2024-01-01"], "igrf_spec", "-.5,-70,0,2024-01-01"),
    (["fit", "log.csv", "--background-ned", "-20000,100,-43000"], "background_ned", "-20000,100,-43000"),
    (["fit", "log.csv", "--heading", "-30.5"], "heading", -30.5),
    (["fit", "log.csv", "--reference", "-1e3"], "reference", "-1e3"),
    (["evaluate", "c.json", "log.csv", "--igrf", "-45,-70.2,10,2022-01-01"], "igrf_spec", "-45,-70.2,10,2022-01-01"),
    (["evaluate", "c.json", "log.csv", "--declination", "-12.5"], "declination", "-12.5"),
    (["evaluate", "c.json", "log.csv", "--background-ned", "-1,-2,-3"], "background_ned", "-1,-2,-3"),
    (["batch", "a.csv", "--out", "o", "--igrf", "-33.9,151.2,0,2024-01-01"], "igrf_spec", "-33.9,151.2,0,2024-01-01"),
    (["fit", "log.csv", "--igrf=-33.9,151.2,0,2024-01-01"], "igrf_spec", "-33.9,151.2,0,2024-01-01"),
])
def test_a_number_with_a_leading_minus_is_the_options_value(argv: list[str], dest: str, value: object) -> None:
    args = build_parser().parse_args(argv)
    assert getattr(args, dest) == value


def test_a_flag_after_a_flag_is_still_a_missing_value(capsys: pytest.CaptureFixture[str]) -> None:
    """Only a number is taken as a value: ``--igrf --units nT`` still says --igrf lacks its argument."""
    with pytest.raises(SystemExit) as stop:
        main(["fit", "log.csv", "--igrf", "--units", "nT"])
    assert stop.value.code == 2
    assert "--igrf" in capsys.readouterr().err


def test_a_southern_site_fits_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``trimag fit LOG --igrf -33.9,151.2,0,2024-01-01`` (Sydney) fits against that site's field."""
    path = tmp_path / "log.csv"
    np.savetxt(path, simulate_ellipsoid(800, noise=20.0, seed=3, F=57000.0), delimiter=",", header="x,y,z",
               comments="", fmt="%.3f")
    assert main(["fit", str(path), "--units", "nT", "--igrf", "-33.9,151.2,0,2024-01-01", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert "-33.9" in summary["reference"]["source"]
    assert 50000 < summary["reference"]["value"] < 65000
