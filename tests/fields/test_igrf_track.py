"""IGRF along the track as the per-sample background of ``interference12`` (issue 21, item 5;
``--igrf-columns LAT,LON,ALT_M,YYYY-MM-DD``): :func:`trimag.fields.reference.igrf_ned`, vectorised, against ppigrf's
point values, and a fit whose background changes by thousands of nT along a simulated track."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from trimag.errors import TrimagInputError
from trimag.fields.reference import igrf, igrf_ned
from trimag.io.background import igrf_along_track, parse_igrf_columns
from trimag.simulate import body_field, random_attitudes

from _helpers import run_trimag

K_TRUE = np.array([[1.02, 0.01, -0.02], [0.015, 0.98, 0.01], [-0.01, 0.02, 1.01]])
C_TRUE = np.array([250.0, -120.0, 80.0])


def test_vectorised_igrf_equals_the_point_values() -> None:
    lat = np.array([52.51, -33.9, 78.2, 0.0, 45.5])
    lon = np.array([13.33, 18.4, 15.6, -160.0, -75.6])
    alt = np.array([40.0, 0.0, 12_000.0, 300.0, 3000.0])
    H = igrf_ned(lat, lon, alt, "2020-06-29")
    for k in range(len(lat)):
        np.testing.assert_allclose(H[k], igrf(lat[k], lon[k], alt[k], "2020-06-29").ned_nT, rtol=0, atol=1e-6)
    uT, _ = igrf_along_track(lat, lon, alt, "2020-06-29", units="uT")
    np.testing.assert_allclose(uT, H / 1000.0)


def test_igrf_along_the_track_in_blocks_equals_one_call(small_chunks) -> None:
    """Positions are evaluated in blocks (ppigrf takes ~10 KB per position: one call on a long flight took
    gigabytes); many small blocks give the same field as the default blocks."""
    rng = np.random.default_rng(3)
    lat, lon, alt = rng.uniform(-70, 70, 60), rng.uniform(-180, 180, 60), rng.uniform(0, 5000, 60)
    whole = igrf_ned(lat, lon, alt, "2021-01-01")
    small_chunks(1)  # a few positions per block
    np.testing.assert_allclose(igrf_ned(lat, lon, alt, "2021-01-01"), whole, rtol=0, atol=1e-9)


def test_bad_positions_and_specs_are_refused() -> None:
    with pytest.raises(TrimagInputError, match="latitude must be within"):
        igrf_ned([95.0], [0.0], [0.0], "2020-01-01")
    with pytest.raises(TrimagInputError, match="finite"):
        igrf_ned([np.nan], [0.0], [0.0], "2020-01-01")
    with pytest.raises(TrimagInputError, match="1900-2029"):
        igrf_ned([10.0], [0.0], [0.0], "2031-01-01")
    with pytest.raises(TrimagInputError, match="LAT,LON,ALT_M,YYYY-MM-DD"):
        parse_igrf_columns("lat,lon,alt")
    assert parse_igrf_columns("lat, lon ,alt,2020-06-29") == (["lat", "lon", "alt"], "2020-06-29")


def _track(path: Path, n: int = 1500) -> Path:
    rng = np.random.default_rng(0)
    lat, lon, alt = np.linspace(40, 60, n), np.linspace(-100, 20, n), np.linspace(0, 8000, n)
    R = random_attitudes(n, rng)
    H_m = body_field(R, igrf_ned(lat, lon, alt, "2020-06-29")) @ K_TRUE.T + C_TRUE + rng.normal(0, 2, (n, 3))
    ypr = R.as_euler("ZYX", degrees=True)
    df = pd.DataFrame({"x": H_m[:, 0], "y": H_m[:, 1], "z": H_m[:, 2], "yaw": ypr[:, 0], "pitch": ypr[:, 1],
                       "roll": ypr[:, 2], "lat": lat, "lon": lon, "alt": alt})
    df.loc[5, "lat"] = np.nan  # a row without a position is dropped, not fitted
    df.to_csv(path, index=False)
    return path


def test_fit_and_evaluate_with_igrf_along_the_track(tmp_path: Path) -> None:
    data = _track(tmp_path / "track.csv")
    args = ("--columns", "x,y,z", "--attitude-columns", "yaw,pitch,roll", "--igrf-columns", "lat,lon,alt,2020-06-29")
    cal = tmp_path / "cal.json"
    proc = run_trimag("fit", data, "--model", "interference12", "--units", "nT", *args, "-o", cal, "--json")
    assert proc.returncode == 0, proc.stderr
    K = np.linalg.inv(np.asarray(json.loads(cal.read_text())["matrix"]))
    np.testing.assert_allclose(K, K_TRUE, atol=2e-4)
    proc = run_trimag("evaluate", cal, data, *args, "--json")
    assert proc.returncode == 0, proc.stderr
    r = json.loads(proc.stdout)
    assert r["after"]["rms_vector"] < 4.0 and r["n_used"] == 1499
    # one constant IGRF vector at the track's middle cannot fit a background that changes by ~5000 nT
    proc = run_trimag("fit", data, "--model", "interference12", "--units", "nT", "--columns", "x,y,z",
                      "--attitude-columns", "yaw,pitch,roll", "--igrf", "50,-40,4000,2020-06-29", "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["rms_after"] > 100.0


def test_cli_refusals(tmp_path: Path) -> None:
    data = _track(tmp_path / "track.csv", n=300)
    base = ("fit", data, "--model", "interference12", "--units", "nT", "--columns", "x,y,z", "--attitude-columns",
            "yaw,pitch,roll")
    proc = run_trimag(*base, "--igrf-columns", "lat,lon,2020-06-29")
    assert proc.returncode == 2 and "LAT,LON,ALT_M,YYYY-MM-DD" in proc.stderr
    proc = run_trimag(*base, "--igrf-columns", "lat,lon,height,2020-06-29")
    assert proc.returncode == 2 and "height" in proc.stderr
    proc = run_trimag(*base, "--igrf-columns", "lat,lon,alt,2020-06-29", "--background-ned", "1,2,3")
    assert proc.returncode == 2 and "exactly one background" in proc.stderr
