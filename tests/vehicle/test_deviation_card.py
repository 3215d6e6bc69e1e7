"""The deviation card of a boat (issue 30, item 5d; docs/vehicle.md "Deviation card"): heading error against
heading, before and after the calibration, as a table and a figure."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from trimag import Calibration
from trimag.errors import TrimagInputError
from trimag.vehicle.heading import deviation_card, deviation_table

from _helpers import BOAT_SITE, run_trimag, simulate_boat


def test_the_card_bins_the_error_by_heading() -> None:
    """A compass whose error is 5 sin(heading) + 2 deg: each bin's mean error is that function at the bin (to the
    bin's averaging), the whole log's mean is 2; after a perfect calibration, zero."""
    ref = np.linspace(0.0, 360.0, 3600, endpoint=False)
    before = ref + 5.0 * np.sin(np.radians(ref)) + 2.0
    card = deviation_card(ref, before, ref, step_deg=30.0)
    assert card["headings_deg"] == list(np.arange(0.0, 360.0, 30.0)) and sum(card["n"]) == 3600
    expected = 5.0 * np.sin(np.radians(card["headings_deg"])) + 2.0
    np.testing.assert_allclose(card["before_mean_deg"], expected, atol=0.06)
    assert card["before"]["heading_error_mean_deg"] == pytest.approx(2.0, abs=1e-9)
    np.testing.assert_allclose(card["after_mean_deg"], 0.0, atol=1e-12)
    text = deviation_table(card)
    assert len(text.splitlines()) == 2 + 12 and text.splitlines()[-1].split()[0] == "all"
    # wrapping: a heading of 359 against 1 is -2 deg, and a reference of 359.9 falls into the 0 bin
    card = deviation_card([359.9, 0.1], [357.9, 2.1], step_deg=15.0)
    assert card["n"][0] == 2 and card["before_mean_deg"][0] == pytest.approx(0.0, abs=1e-9)
    assert card["after"] is None and card["n"][1] == 0 and card["before_mean_deg"][1] is None
    with pytest.raises(TrimagInputError, match="divide 360"):
        deviation_card(ref, before, step_deg=7.0)


def _csv(path, boat, course: bool = False) -> None:
    cols = {"x": boat["raw"][:, 0], "y": boat["raw"][:, 1], "z": boat["raw"][:, 2]}
    if course:
        cols["course"] = boat["ypr"][:, 0]
    pd.DataFrame(cols).to_csv(path, index=False)


def test_cli_level_turn_prints_and_draws_the_card(tmp_path) -> None:
    boat = simulate_boat(seed=11)
    _csv(tmp_path / "boat.csv", boat)
    card_png = tmp_path / "card.png"
    r = run_trimag("fit", tmp_path / "boat.csv", "--units", "mG", "--igrf", BOAT_SITE, "--level-turn",
                   "--deviation-card", card_png, "-o", tmp_path / "cal.json")
    assert r.returncode == 0, r.stderr
    assert card_png.exists() and card_png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert ("deviation card (true heading; before: raw; reference: the new calibration's heading; the vehicle taken "
            "as level") in r.stdout
    card = Calibration.from_file(tmp_path / "cal.json").diagnostics["deviation_card"]
    # the raw compass is tens of degrees off (120 mG of hard iron on a 187 mG horizontal field), the new calibration
    # predicts a fraction of a degree
    assert max(abs(v) for v in card["before_mean_deg"] if v is not None) > 20.0
    assert max(card["after_sigma_deg"]) < 0.5
    assert sum(card["n"]) == 720


def test_cli_heading_column_card_has_the_after_error_at_the_noise_floor(tmp_path) -> None:
    boat = simulate_boat(seed=12, matrix=np.eye(3))
    _csv(tmp_path / "drive.csv", boat, course=True)
    r = run_trimag("fit", tmp_path / "drive.csv", "--units", "mG", "--igrf", BOAT_SITE, "--heading-column", "course",
                   "--json")
    assert r.returncode == 0, r.stderr
    card = json.loads(r.stdout)["diagnostics"]["deviation_card"]
    assert card["reference"] == "the heading column"
    # 2 mG of noise on a 187 mG horizontal field: 0.6 deg per sample
    assert card["after"]["heading_error_rms_deg"] < 0.8
    assert card["before"]["heading_error_rms_deg"] > 20.0


def test_cli_deviation_card_needs_a_large_vehicle_fit(tmp_path) -> None:
    _csv(tmp_path / "boat.csv", simulate_boat(seed=13))
    r = run_trimag("fit", tmp_path / "boat.csv", "--units", "mG", "--igrf", BOAT_SITE, "--deviation-card",
                   tmp_path / "c.png")
    assert r.returncode == 2 and "--level-turn" in r.stderr and not (tmp_path / "c.png").exists()
