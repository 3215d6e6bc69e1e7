"""Tolles–Lawson model, fit, compensation file and CLI (issue 21)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from trimag.aircraft.compensation import ScalarCompensation
from trimag.aircraft.filtering import BandPass, finite_runs, split_segments
from trimag.errors import CalibrationFormatError, IdentifiabilityError, TrimagInputError
from trimag.estimators.tolles_lawson import fit_tolles_lawson
from trimag.models.tolles_lawson import derivative, design, parse_terms, term_names
from trimag.simulate import simulate_aircraft

from _helpers import SHARED_DATA, run_trimag

MAGNAV = SHARED_DATA / "magnav-tl" / "test_data_TL.mat"
requires_magnav = pytest.mark.skipif(
    not MAGNAV.exists(), reason="../shared/data/magnav-tl absent (SGL data may not be copied into the repository)"
)


def _magnav():
    import scipy.io

    return scipy.io.loadmat(MAGNAV, squeeze_me=True, struct_as_record=False)["TL_data"]


# ----------------------------------------------------------------- model
def test_term_names_follow_magnav_order():
    names = term_names()
    assert names[:3] == ["perm_x", "perm_y", "perm_z"]
    assert names[3:9] == ["ind_xx", "ind_xy", "ind_xz", "ind_yy", "ind_yz", "ind_zz"]
    assert names[9:] == [f"eddy_{a}{b}" for a in "xyz" for b in "xyz"]
    assert len(term_names("p,i5,e8")) == 16
    assert term_names("permanent,bias")[-1] == "bias"


@pytest.mark.parametrize("bad", ["induced,i5", "nonsense", ""])
def test_bad_terms_are_refused(bad):
    with pytest.raises(TrimagInputError):
        parse_terms(bad)


def test_derivative_is_magnav_central_difference():
    x = np.array([0.0, 1.0, 4.0, 9.0, 16.0])
    assert derivative(x).tolist() == [1.0, 2.0, 4.0, 6.0, 7.0]
    assert derivative(x, "backward").tolist() == [1.0, 1.0, 3.0, 5.0, 7.0]


def test_induced_diagonal_sums_to_field_over_scale():
    rng = np.random.default_rng(0)
    B = rng.normal(size=(50, 3)) * 30_000
    A = design(B, "induced3")
    np.testing.assert_allclose(A.sum(axis=1), np.linalg.norm(B, axis=1) / 50_000, rtol=1e-12)


@requires_magnav
def test_design_equals_magnav_A_a():
    d = _magnav()
    A = design(np.column_stack([d.flux_a_x, d.flux_a_y, d.flux_a_z]))
    assert np.abs(A - d.A_a).max() <= 1e-12


@requires_magnav
def test_coefficients_from_magnav_filtered_inputs_equal_TL_a_1():
    from trimag.estimators.tolles_lawson import _solve_gram

    d = _magnav()
    c = _solve_gram(d.A_a_f_t.T @ d.A_a_f_t, d.A_a_f_t.T @ d.mag_1_uc_f_t, 1e-3)
    assert np.abs(c - d.TL_a_1).max() <= 1e-9 * np.abs(d.TL_a_1).max()


@requires_magnav
def test_end_to_end_matches_magnav_compensation():
    d = _magnav()
    B = np.column_stack([d.flux_a_x, d.flux_a_y, d.flux_a_z])
    comp = fit_tolles_lawson(B, d.mag_1_uc, rate_hz=10.0, ridge=1e-3, bootstrap=20)
    compensated = comp.apply(B, d.mag_1_uc)
    assert np.std(compensated - d.mag_1_c) < 0.1  # MagNav.jl's own test threshold
    assert comp.stats["improvement_ratio"] > 2.5


# ----------------------------------------------------------------- filter
def test_finite_runs_and_segments_split_at_gaps_and_ranges():
    ok = np.array([True, True, False, True, True, True, False, False, True])
    assert finite_runs(ok) == [(0, 2), (3, 6), (8, 9)]
    t = np.arange(9.0)
    assert split_segments(ok, t, [(0.0, 4.0), (5.0, 8.0)]) == [(0, 2), (3, 5), (5, 6), (8, 9)]
    t_gap = np.array([0, 1, 2, 3, 10, 11, 12, 13, 14.0])
    assert split_segments(np.ones(9, bool), t_gap, max_gap_s=1.5) == [(0, 4), (4, 9)]


def test_bandpass_removes_out_of_band_and_keeps_in_band():
    t = np.arange(2000) / 10.0
    slow, mid = np.sin(2 * np.pi * 0.01 * t), np.sin(2 * np.pi * 0.4 * t)
    bp = BandPass(rate_hz=10.0)
    assert np.std(bp.apply(slow)) < 0.01
    assert abs(np.std(bp.apply(mid)) - np.std(mid)) < 0.02
    with pytest.raises(TrimagInputError):
        bp.apply(np.zeros(bp.min_length - 1))
    with pytest.raises(TrimagInputError):
        BandPass(0.1, 6.0, rate_hz=10.0)


# ----------------------------------------------------------------- synthetic aircraft
def test_synthetic_aircraft_coefficients_within_reported_uncertainty():
    terms = "permanent,induced5,eddy8"  # without the exactly redundant terms
    z = []
    for seed in range(3):
        sim = simulate_aircraft(60.0, seed=seed, terms=terms)
        comp = fit_tolles_lawson(sim.vector_nT, sim.scalar_nT, rate_hz=sim.rate_hz, segments=sim.segments,
                                 terms=terms, bootstrap=100)
        std = np.array([comp.uncertainty["std"][n] for n in comp.names])
        z.append((comp.coefficients - sim.coefficients) / std)
        assert comp.stats["improvement_ratio"] > 50
    z_arr = np.array(z)
    assert np.sqrt(np.mean(z_arr**2)) < 2.0
    assert np.abs(z_arr).max() < 5.0


def test_formal_sigmas_understate_and_bootstrap_is_reported():
    sim = simulate_aircraft(60.0, seed=4, terms="p,i5,e8")
    comp = fit_tolles_lawson(sim.vector_nT, sim.scalar_nT, rate_hz=10.0, segments=sim.segments, terms="p,i5,e8",
                             bootstrap=100)
    formal = np.array(list(comp.uncertainty["formal_std"].values()))
    boot = np.array(list(comp.uncertainty["bootstrap_std"].values()))
    assert np.median(boot / formal) > 1.3  # band-passed residuals are correlated: formal sigmas are too small


def test_redundant_induced_terms_are_named_as_collinear():
    sim = simulate_aircraft(60.0, seed=2)
    comp = fit_tolles_lawson(sim.vector_nT, sim.scalar_nT, rate_hz=10.0, segments=sim.segments, bootstrap=0)
    groups = [set(g["terms"]) for g in comp.diagnostics["collinear_groups"]]
    assert any({"ind_xx", "ind_yy", "ind_zz"} <= g for g in groups)
    assert any("near-collinear" in w for w in comp.diagnostics["warnings"])


def test_manoeuvre_content_per_segment():
    sim = simulate_aircraft(60.0, seed=3, amplitude_deg=(2.0, 8.0, 15.0))
    comp = fit_tolles_lawson(sim.vector_nT, sim.scalar_nT, rate_hz=10.0, segments=sim.segments, bootstrap=0,
                             attitude_deg=sim.attitude_deg)
    seg = comp.stats["segments"][0]
    assert seg["roll_p2p_deg"] > seg["pitch_p2p_deg"] > seg["yaw_p2p_deg"] > 0


def test_ridge_cross_validation_chooses_a_lambda():
    sim = simulate_aircraft(60.0, seed=5)
    comp = fit_tolles_lawson(sim.vector_nT, sim.scalar_nT, rate_hz=10.0, segments=sim.segments, ridge="cv",
                             bootstrap=0)
    cv = comp.diagnostics["ridge_cv"]
    assert comp.ridge == cv["chosen"] and min(cv["grid"]) <= comp.ridge <= max(cv["grid"])
    assert comp.stats["improvement_ratio"] > 50


def test_too_short_or_bad_inputs_are_refused():
    sim = simulate_aircraft(60.0, seed=0)
    with pytest.raises(IdentifiabilityError, match="long enough"):
        fit_tolles_lawson(sim.vector_nT[:80], sim.scalar_nT[:80], rate_hz=10.0)
    with pytest.raises(TrimagInputError):
        fit_tolles_lawson(sim.vector_nT, sim.scalar_nT[:-1], rate_hz=10.0)
    with pytest.raises(TrimagInputError):
        fit_tolles_lawson(sim.vector_nT, sim.scalar_nT, rate_hz=10.0, ridge="lots")


def test_nan_rows_split_segments_and_are_counted():
    sim = simulate_aircraft(60.0, seed=6)
    scalar = sim.scalar_nT.copy()
    scalar[300:305] = np.nan
    comp = fit_tolles_lawson(sim.vector_nT, scalar, rate_hz=10.0, bootstrap=0)
    assert comp.stats["n_dropped_rows"] == 5
    assert len(comp.stats["segments"]) == 2
    out = comp.apply(sim.vector_nT, scalar)
    assert np.isnan(out[300:305]).all() and np.isfinite(out[:300]).all()


# ----------------------------------------------------------------- file
def test_compensation_file_round_trip_is_exact(tmp_path: Path):
    sim = simulate_aircraft(30.0, seed=1)
    comp = fit_tolles_lawson(sim.vector_nT, sim.scalar_nT, rate_hz=10.0, segments=sim.segments, bootstrap=10)
    back = ScalarCompensation.from_file(comp.to_file(tmp_path / "c.json"))
    assert back == comp
    np.testing.assert_array_equal(back.apply(sim.vector_nT, sim.scalar_nT), comp.apply(sim.vector_nT, sim.scalar_nT))
    data = json.loads((tmp_path / "c.json").read_text())
    assert data["format"] == "trimag-compensation" and data["Bt_scale"] == 50_000
    assert data["filter"]["order"] == 8 and data["derivative_scheme"] == "central"
    data["coefficients"].pop("perm_x")
    with pytest.raises(CalibrationFormatError):
        ScalarCompensation.from_dict(data)


# ----------------------------------------------------------------- CLI
def _write_sim_csv(path: Path, seed: int = 0, seconds: float = 60.0) -> None:
    sim = simulate_aircraft(seconds, seed=seed, terms="p,i5,e8")
    cols = np.column_stack([sim.time_s, sim.vector_nT, sim.scalar_nT])
    np.savetxt(path, cols, delimiter=",", header="time,fx,fy,fz,mag", comments="", fmt="%.6f")


def test_cli_fit_apply_evaluate(tmp_path: Path):
    data = tmp_path / "box.csv"
    _write_sim_csv(data)
    comp = tmp_path / "tl.json"
    r = run_trimag("fit", data, "--model", "tolles-lawson", "--columns", "fx,fy,fz", "--scalar-column", "mag",
                   "--time-column", "time", "--option", "ridge=cv", "--option", "terms=p,i5,e8", "-o", comp)
    assert r.returncode == 0, r.stderr
    assert "ratio" in r.stdout and comp.exists()
    out = tmp_path / "out.csv"
    r = run_trimag("apply", comp, data, "-o", out)
    assert r.returncode == 0, r.stderr
    lines_in = data.read_text().splitlines()
    lines_out = out.read_text().splitlines()
    assert len(lines_in) == len(lines_out)
    assert lines_out[0] == lines_in[0] + ",mag_compensated"
    assert all(o.startswith(i + ",") for i, o in zip(lines_in[1:50], lines_out[1:50], strict=True))
    r = run_trimag("evaluate", comp, data, "--json", "--segments", "0:29,30:59")
    assert r.returncode == 0, r.stderr
    ev = json.loads(r.stdout)
    assert ev["n_segments"] == 2 and all(s["improvement_ratio"] > 20 for s in ev["segments"])


def test_cli_refuses_missing_scalar_column_and_rate(tmp_path: Path):
    data = tmp_path / "box.csv"
    _write_sim_csv(data, seconds=20.0)
    r = run_trimag("fit", data, "--model", "tolles-lawson", "--columns", "fx,fy,fz")
    assert r.returncode == 2 and "--scalar-column" in r.stderr and "Traceback" not in r.stderr
    r = run_trimag("fit", data, "--model", "tolles-lawson", "--columns", "fx,fy,fz", "--scalar-column", "mag")
    assert r.returncode == 2 and "rate" in r.stderr
    r = run_trimag("fit", data, "--model", "tolles-lawson", "--columns", "fx,fy,nope", "--scalar-column", "mag",
                   "--rate", "10")
    assert r.returncode == 2 and "nope" in r.stderr and len(r.stderr.strip().splitlines()) == 1


@requires_magnav
def test_cli_on_magnav_mat_struct(tmp_path: Path):
    comp = tmp_path / "tl.json"
    r = run_trimag("fit", MAGNAV, "--model", "tolles-lawson", "--columns",
                   "TL_data.flux_a_x,TL_data.flux_a_y,TL_data.flux_a_z", "--scalar-column", "TL_data.mag_1_uc",
                   "--rate", "10", "--option", "ridge=1e-3", "-o", comp, "--json")
    assert r.returncode == 0, r.stderr
    out = tmp_path / "out.csv"
    assert run_trimag("apply", comp, MAGNAV, "-o", out).returncode == 0
    import pandas as pd

    df = pd.read_csv(out)
    d = _magnav()
    assert np.std(df["TL_data.mag_1_uc_compensated"].to_numpy() - d.mag_1_c) < 0.1


def test_apply_in_blocks_equals_whole_segment_design(small_chunks):

    sim = simulate_aircraft(30.0, seed=7)
    comp = fit_tolles_lawson(sim.vector_nT, sim.scalar_nT, rate_hz=10.0, segments=sim.segments, bootstrap=0)
    whole = sim.scalar_nT - design(sim.vector_nT) @ comp.coefficients
    small_chunks(97)
    np.testing.assert_allclose(comp.apply(sim.vector_nT, sim.scalar_nT), whole, rtol=0, atol=1e-9)


def test_segment_consistency_shows_formal_sigmas_too_small_and_reported_ones_holding():
    sim = simulate_aircraft(120.0, seed=1, terms="p,i5,e8")
    comp = fit_tolles_lawson(sim.vector_nT, sim.scalar_nT, rate_hz=10.0, segments=sim.segments, terms="p,i5,e8",
                             bootstrap=100)
    sc = comp.diagnostics["segment_consistency"]
    assert len(sc["pairs"]) == 3
    assert sc["rms_z_formal"] > 1.8  # white-noise sigmas understate the spread between segments
    assert 0.5 < sc["rms_z_reported"] < 1.8


# ----------------------------------------------------------------- segments and gaps (issue 33, item 6)
def _box_csv(path: Path, *, drop: slice | None = None, terms: str | None = None, scalar_scale: float = 1.0) -> Path:
    sim = simulate_aircraft(60.0, seed=0, terms=terms)
    cols = np.column_stack([sim.time_s, sim.vector_nT, sim.scalar_nT * scalar_scale])
    if drop is not None:
        cols = np.delete(cols, np.arange(len(cols))[drop], axis=0)
    np.savetxt(path, cols, delimiter=",", header="time,fx,fy,fz,mag", comments="", fmt="%.6f")
    return path


def test_each_segment_reports_its_own_band_passed_spread(tmp_path: Path):
    """--segments 0:100,100:300 with the default (near-collinear) terms: segment 0's std after compensation was
    reported as 5.3 nT (4x worse than before) where the compensated, band-passed signal has 0.01 nT: the sums
    behind the statistics cancelled catastrophically on coefficients of 4e9."""
    from trimag.app.tolles_lawson import TollesLawsonFitRequest, fit_compensation_file, parse_segments

    data = _box_csv(tmp_path / "box.csv")
    comp, _ = fit_compensation_file(TollesLawsonFitRequest(
        data=data, vector_columns=["fx", "fy", "fz"], scalar_column="mag", time_column="time",
        segments=parse_segments("0:100,100:300"), bootstrap=0))
    table = np.loadtxt(data, delimiter=",", skiprows=1)
    assert len(comp.stats["segments"]) == 2
    for seg in comp.stats["segments"]:
        a, b = seg["rows"]
        direct = float(np.std(comp.bandpass.apply(comp.apply(table[a:b, 1:4], table[a:b, 4]))))
        assert seg["std_after_nT"] == pytest.approx(direct, rel=1e-6)
        assert seg["std_after_nT"] < seg["std_before_nT"] / 50
    assert np.abs(comp.coefficients).max() < 1e4  # the unidentified combinations are not fitted to noise


def test_evaluate_and_apply_cut_the_compensation_at_time_gaps_as_the_fit_does(tmp_path: Path):
    """A 0.5 s gap in the time column (5 rows lost in a turn): the fit cut its segments there, the evaluation and
    apply differentiated across it and reported a 9x improvement where the fit had 170x."""
    data = _box_csv(tmp_path / "gap.csv", drop=slice(700, 705), terms="p,i5,e8")
    comp = tmp_path / "tl.json"
    r = run_trimag("fit", data, "--model", "tolles-lawson", "--columns", "fx,fy,fz", "--scalar-column", "mag",
                   "--time-column", "time", "--option", "terms=p,i5,e8", "-o", comp, "--json")
    assert r.returncode == 0, r.stderr
    fitted = json.loads(r.stdout)["stats"]["segments"]
    assert [s["rows"] for s in fitted] == [[0, 700], [700, 2995]]
    r = run_trimag("evaluate", comp, data, "--json")
    assert r.returncode == 0, r.stderr
    ev = json.loads(r.stdout)
    assert ev["n_segments"] == 2
    for seg, fit_seg in zip(ev["segments"], fitted, strict=True):
        assert seg["improvement_ratio"] > 100
        assert seg["std_after_nT"] == pytest.approx(fit_seg["std_after_nT"], rel=0.05)
    out = tmp_path / "out.csv"
    assert run_trimag("apply", comp, data, "-o", out).returncode == 0
    import pandas as pd

    table = np.loadtxt(data, delimiter=",", skiprows=1)
    expected = ScalarCompensation.from_file(comp).apply(table[:, 1:4], table[:, 4], [(0, 700), (700, 2995)])
    np.testing.assert_allclose(pd.read_csv(out)["mag_compensated"].to_numpy(), expected, rtol=0, atol=1e-6)


def test_a_rate_the_band_cannot_be_filtered_at_is_refused(tmp_path: Path):
    data = _box_csv(tmp_path / "box.csv", terms="p,i5,e8")
    base = ["fit", data, "--model", "tolles-lawson", "--columns", "fx,fy,fz", "--scalar-column", "mag"]
    r = run_trimag(*base, "--rate", "1e10")  # was a LinAlgError, exit 1
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "rate" in r.stderr and "Traceback" not in r.stderr and "internal error" not in r.stderr
    r = run_trimag(*base, "--rate", "1e4")  # 3000 rows = 0.3 s: no segment holds one period of 0.1 Hz
    assert r.returncode == 3 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "0.1 Hz" in r.stderr


def test_a_scalar_in_another_unit_than_the_vector_is_refused(tmp_path: Path):
    data = _box_csv(tmp_path / "box.csv", terms="p,i5,e8", scalar_scale=1e-3)  # scalar in uT, vector in nT
    r = run_trimag("fit", data, "--model", "tolles-lawson", "--columns", "fx,fy,fz", "--scalar-column", "mag",
                   "--time-column", "time")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "mag" in r.stderr and "unit" in r.stderr
