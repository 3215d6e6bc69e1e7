"""A result that cannot be right is refused or flagged (issue 32, items 1 and 4): the unit judged on the fitted
field, not on raw magnitudes that include the hard iron; an evaluation that makes the data worse than raw."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from _helpers import run_trimag


def _phone(path: Path, n: int = 2000, seed: int = 0) -> Path:
    """A phone turned through all attitudes: 46 uT field, ~590 uT hard iron (raw |B| ~ 600 uT), soft iron."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    D = np.array([[1.04, 0.03, 0.0], [0.0, 0.97, -0.02], [0.0, 0.0, 1.01]])
    B = 46.0 * u @ D.T + [220.0, 65.0, -540.0] + rng.normal(scale=0.15, size=u.shape)
    np.savetxt(path, B, delimiter=",", header="x,y,z", comments="", fmt="%.4f")
    return path


def test_a_phone_with_a_large_hard_iron_is_not_told_its_unit_is_wrong(tmp_path: Path):
    """Finding: "the data's median |B| = 607 uT is not a plausible Earth field in uT ... looks like mG" for a phone
    whose fitted field is 46 uT; with --igrf the same data were refused (exit 2, "the data are not in uT")."""
    log = _phone(tmp_path / "phone.csv")
    r = run_trimag("fit", log, "--units", "uT", "--json")
    assert r.returncode == 0, r.stderr
    assert "plausible" not in r.stderr and "look like" not in r.stderr, r.stderr
    assert abs(json.loads(r.stdout)["reference"]["value"] - 46.0) < 1.0
    r = run_trimag("fit", log, "--units", "uT", "--igrf", "45.0,9.0,100,2023-06-01")
    assert r.returncode == 0, r.stderr
    assert "look like" not in r.stderr


def test_a_phone_in_the_wrong_unit_is_still_told(tmp_path: Path):
    """The same phone declared in mG: its fitted field (46 "mG") is no Earth field in mG, and is one in uT."""
    log = _phone(tmp_path / "phone.csv")
    r = run_trimag("fit", log, "--units", "mG")
    assert r.returncode == 0 and "F = 46" in r.stderr and "look like uT" in r.stderr, r.stderr
    r = run_trimag("fit", log, "--units", "mG", "--igrf", "45.0,9.0,100,2023-06-01")
    assert r.returncode == 2 and "not in mG" in r.stderr and "uT" in r.stderr, r.stderr


def test_evaluate_says_when_a_calibration_makes_the_data_worse_than_raw(tmp_path: Path):
    """Finding: `evaluate` of a wrong calibration on the other half of the flight doubled the error (139 -> 290 mG
    RMS) and warned nothing. Here the phone's calibration is evaluated on the phone after its hard iron changed."""
    cal = tmp_path / "cal.json"
    assert run_trimag("fit", _phone(tmp_path / "phone.csv"), "--units", "uT", "-o", cal).returncode == 0
    rng = np.random.default_rng(1)
    u = rng.normal(size=(1000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    other = tmp_path / "other.csv"
    np.savetxt(other, 46.0 * u + [20.0, -10.0, 5.0], delimiter=",", header="x,y,z", comments="")
    r = run_trimag("evaluate", cal, other, "--json")
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    assert d["std_norm_after"] > d["std_norm_before"] and d["worse_than_raw"] is True
    assert "worse than the raw data" in r.stderr and d["warnings"]
    r = run_trimag("evaluate", cal, tmp_path / "phone.csv", "--json")
    assert not json.loads(r.stdout)["worse_than_raw"] and "worse" not in r.stderr


def test_evaluate_names_a_corrected_field_far_from_the_one_the_calibration_was_fitted_to(tmp_path: Path):
    """Finding (review 2): a level-turn calibration of the real box_pilot log's first half (fitted to IGRF's
    489.2 mG from the log's GPS), evaluated on the second half without a reference, reported RMS 18.8 mG against the
    corrected data's own mean, 517.5 mG: the 6 % scale error on held-out data was invisible (33.9 mG against 489.2)
    and nothing was said. Now evaluate names the magnitude the calibration was fitted to and the RMS against it when
    the corrected mean is more than 2 % from it. Here: fitted to a known F = 46 uT on one log, held out on a log
    whose sensor's gain changed by 6 % (the same shape, a scale error only the known magnitude can see)."""
    log = _phone(tmp_path / "phone.csv")
    cal = tmp_path / "cal.json"
    r = run_trimag("fit", log, "--units", "uT", "--reference", "46", "-o", cal, "-q")
    assert r.returncode == 0, r.stderr
    B = np.loadtxt(log, delimiter=",", skiprows=1)
    held = tmp_path / "held.csv"
    np.savetxt(held, (B - [220.0, 65.0, -540.0]) * 1.06 + [220.0, 65.0, -540.0], delimiter=",", header="x,y,z",
               comments="", fmt="%.4f")
    r = run_trimag("evaluate", cal, held, "--json")
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    assert d["rms_after"] < 0.5  # against the corrected mean (48.8 uT), the spread alone
    text = " ".join(d["warnings"])
    assert "46" in text and "fitted" in text and "--reference" in r.stderr, r.stderr
    assert d["fitted_reference"]["rms_after"] > 2.0  # against 46 uT: the 6 % shows
    r = run_trimag("evaluate", cal, log, "--json")  # the log it was fitted on: within 2 %, nothing said
    assert r.returncode == 0 and not json.loads(r.stdout)["warnings"], r.stderr


def test_a_reference_in_another_unit_is_named_as_the_reference_s_mistake(tmp_path: Path):
    """Review: data in mG (|B| ~ 500) with `--reference 0.5` (the field given in gauss) was refused with 'the data
    are not in mG; the numbers look like mG; give the right unit': a contradiction that blames the data. When the
    data's field is an Earth field in their unit, the reference is what is wrong, and the refusal says so."""
    from trimag.simulate import uniform_directions

    path = tmp_path / "mG.csv"
    raw = 500.0 * uniform_directions(300, seed=3) + [30.0, -20.0, 10.0]
    np.savetxt(path, raw, delimiter=",", header="x,y,z", comments="")
    r = run_trimag("fit", path, "--units", "mG", "--reference", "0.5", "-o", tmp_path / "cal.json")
    assert r.returncode == 2, r.stderr
    line = r.stderr.strip()
    assert len(line.splitlines()) == 1
    assert "--reference" in line and "the data are not in mG" not in line, line
    assert "G" in line.split("looks like")[-1] if "looks like" in line else True
    # data in G against a reference in mG: the data's field is no Earth field in G's numbers? It is (0.5 G) ->
    # the reference (500 "G") is named, not the data
    np.savetxt(path, raw / 1000.0, delimiter=",", header="x,y,z", comments="")
    r = run_trimag("fit", path, "--units", "G", "--reference", "500", "-o", tmp_path / "cal.json")
    assert r.returncode == 2 and "--reference" in r.stderr and "the data are not in G" not in r.stderr, r.stderr
    # data in the wrong unit (numbers of 500 read as nT) still blame the unit, and name the likely one (issue 38)
    np.savetxt(path, raw, delimiter=",", header="x,y,z", comments="")
    r = run_trimag("fit", path, "--units", "nT", "--reference", "50000", "-o", tmp_path / "cal.json")
    assert r.returncode == 2 and "the data look like mG" in r.stderr and "give --reference in" not in r.stderr, \
        r.stderr
