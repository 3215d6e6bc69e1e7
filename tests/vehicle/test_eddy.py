"""Eddy-current terms of ``interference12`` (issue 21, item 5; :mod:`trimag.vehicle.eddy`, docs/vehicle.md):
``H_m = K H_b + c + E dH_m/dt`` with ``dH_m/dt`` the measured vector's own finite difference per segment.

Simulated aircraft (:func:`trimag.simulate.simulate_aircraft` with ``vector_K``, ``vector_c``, ``vector_E``): a
60 s-per-heading calibration box at 10 Hz, 0.5 nT vector noise, known K, c and E (E in seconds, ~0.01-0.05 s).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

import trimag
from trimag.app import apply_to_file
from trimag.errors import TrimagInputError
from trimag.simulate import body_field, current_profile, random_attitudes, simulate_aircraft
from trimag.vehicle.eddy import EDDY_NAMES, eddy_values, free_mask, time_derivative
from trimag.vehicle.regressors import fit_regressors

from _helpers import run_trimag

K_TRUE = np.eye(3) + np.array([[0.02, 0.01, -0.005], [0.0, -0.01, 0.008], [0.004, 0.0, 0.015]])
C_TRUE = np.array([300.0, -150.0, 80.0])
E_TRUE = np.array([[-0.05, 0.01, 0.0], [0.0, -0.03, 0.02], [0.01, 0.0, -0.04]])  # s
EARTH = np.array([18_000.0, 1_000.0, 46_000.0])


def _sim(seed: int = 1, E: np.ndarray = E_TRUE, seconds: float = 60.0):
    return simulate_aircraft(seconds, vector_K=K_TRUE, vector_c=C_TRUE, vector_E=E, vector_noise_nT=0.5,
                             earth_ned_nT=EARTH, seed=seed)


def _fit(sim, terms: int = 9):
    R = Rotation.from_euler("ZYX", sim.attitude_deg, degrees=True)
    base = trimag.fit(sim.vector_nT, model="interference12", reference=EARTH, attitude=R, units="nT")
    values, _, _ = eddy_values(sim.vector_nT, time_s=sim.time_s)
    return fit_regressors(base, sim.vector_nT, values, EARTH, attitude=R, free=free_mask(terms)), values


def _csv(sim, path: Path) -> Path:
    pd.DataFrame({"t": sim.time_s, "x": sim.vector_nT[:, 0], "y": sim.vector_nT[:, 1], "z": sim.vector_nT[:, 2],
                  "yaw": sim.attitude_deg[:, 0], "pitch": sim.attitude_deg[:, 1],
                  "roll": sim.attitude_deg[:, 2]}).to_csv(path, index=False)
    return path


VECTOR_ARGS = ("--columns", "x,y,z", "--attitude-columns", "yaw,pitch,roll", "--background-ned", "18000,1000,46000",
               "--units", "nT")


# ------------------------------------------------------------------ the derivative
def test_derivative_is_central_inside_one_sided_at_segment_ends_and_zero_alone() -> None:
    t = np.array([0.0, 0.1, 0.2, 0.3, 1.0, 1.1, 1.2, 5.0])  # gaps after 0.3 and 1.2: segments of 4, 3, 1 rows
    B = np.column_stack([t**2, 3 * t, -(t**3)])
    dB, isolated = time_derivative(B, t, max_gap_s=0.15)
    assert isolated == 1 and np.all(dB[7] == 0)
    np.testing.assert_allclose(dB[1:3, 0], 2 * t[1:3], atol=1e-12)  # central: exact for a quadratic
    np.testing.assert_allclose(dB[[0, 4], 0], [(B[1, 0] - B[0, 0]) / 0.1, (B[5, 0] - B[4, 0]) / 0.1])  # forward
    np.testing.assert_allclose(dB[[3, 6], 0], [(B[3, 0] - B[2, 0]) / 0.1, (B[6, 0] - B[5, 0]) / 0.1])  # backward
    np.testing.assert_allclose(dB[:7, 1], 3.0, atol=1e-12)
    np.testing.assert_allclose(dB[5, 2], -(t[6] ** 3 - t[4] ** 3) / 0.2)


def test_derivative_from_a_rate_equals_the_one_from_its_time_column() -> None:
    B = np.random.default_rng(0).normal(size=(50, 3))
    by_rate, rate, _ = eddy_values(B, rate_hz=10.0)
    by_time, rate_t, _ = eddy_values(B, time_s=np.arange(50) / 10.0)
    assert rate == pytest.approx(10.0) and rate_t == pytest.approx(10.0)
    for name in EDDY_NAMES:
        np.testing.assert_allclose(by_rate[name], by_time[name])
    with pytest.raises(TrimagInputError, match="sample rate"):
        eddy_values(B)


def test_simulator_obeys_the_model_it_states() -> None:
    sim = _sim(seed=2, seconds=20.0)
    values, _, _ = eddy_values(sim.vector_nT, time_s=sim.time_s)
    dB = np.column_stack([values[n] for n in EDDY_NAMES])
    resid = sim.vector_nT - (sim.body_nT @ K_TRUE.T + C_TRUE + dB @ E_TRUE.T)
    assert np.std(resid) < 0.6  # the 0.5 nT noise (and its small share through the derivative), nothing else


# ------------------------------------------------------------------ recovery (issue 21: "within their uncertainty")
def test_eddy_coefficients_recovered_within_their_reported_uncertainty() -> None:
    sim = _sim()
    cal, _ = _fit(sim)
    std = cal.uncertainty["param_std"]
    coef = np.asarray(cal.regressors["coefficients"])  # row j: column j of E
    sd = np.array([[std[f"k_{n}_{a}"] for a in "xyz"] for n in EDDY_NAMES])
    z = (coef - E_TRUE.T) / sd
    assert np.max(np.abs(z)) < 4.5, z
    K = np.linalg.inv(cal.matrix)
    sd_K = np.array([[std[f"k{i}{j}"] for j in range(1, 4)] for i in range(1, 4)])
    assert np.max(np.abs((K - K_TRUE) / sd_K)) < 4.5
    # the stored offset is c at the mean derivative (centred regressors)
    means = np.asarray(cal.regressors["means"])
    np.testing.assert_allclose(np.asarray(cal.offset) - coef.T @ means, C_TRUE, atol=5 * max(std["c1"], 0.05))
    assert cal.stats["vector_rms_after"] < 1.0 < 50 < cal.stats["vector_rms_after_without_regressors"]


def test_reported_sigmas_of_E_match_the_scatter_of_a_small_monte_carlo() -> None:
    """10 boxes of 20 s per heading: the z-scores of the nine entries of E have a standard deviation near 1 (the
    derivative of the noise makes neighbouring residuals slightly correlated; measured 1.00)."""
    z = []
    for seed in range(10):
        cal, _ = _fit(_sim(seed=20 + seed, seconds=20.0))
        std = cal.uncertainty["param_std"]
        sd = np.array([[std[f"k_{n}_{a}"] for a in "xyz"] for n in EDDY_NAMES])
        z.append(((np.asarray(cal.regressors["coefficients"]) - E_TRUE.T) / sd).ravel())
    spread = float(np.std(z))
    assert 0.75 < spread < 1.3, spread


def test_held_out_box_gains_from_the_terms_only_when_the_aircraft_has_them() -> None:
    train, test = _sim(seed=3), _sim(seed=4)
    cal, _ = _fit(train)
    R = Rotation.from_euler("ZYX", test.attitude_deg, degrees=True)
    expected = body_field(R, EARTH)
    values, _, _ = eddy_values(test.vector_nT, time_s=test.time_s)
    with_terms = np.sqrt(np.mean(np.sum((cal.apply(test.vector_nT, regressors=values) - expected) ** 2, axis=1)))
    base = trimag.fit(train.vector_nT, model="interference12", reference=EARTH,
                      attitude=Rotation.from_euler("ZYX", train.attitude_deg, degrees=True), units="nT")
    without = np.sqrt(np.mean(np.sum((base.apply(test.vector_nT) - expected) ** 2, axis=1)))
    assert with_terms < 1.5 and without > 20 * with_terms


def test_diagonal_terms_hold_the_off_diagonal_at_zero() -> None:
    E = np.diag([-0.04, -0.02, -0.03])
    cal, _ = _fit(_sim(seed=5, E=E), terms=3)
    coef = np.asarray(cal.regressors["coefficients"])
    assert np.all(coef[~np.eye(3, dtype=bool)] == 0.0)
    std = cal.uncertainty["param_std"]
    for j, n in enumerate(EDDY_NAMES):
        assert abs(coef[j, j] - E[j, j]) < 4.5 * std[f"k_{n}_{'xyz'[j]}"]
        assert std[f"k_{n}_{'xyz'[(j + 1) % 3]}"] == 0.0
    ranking = cal.diagnostics["regressors"]["ranking"]
    assert all(e["significant"] for e in ranking)


def test_free_mask_is_refused_outside_interference12_and_for_unknown_names() -> None:
    sim = _sim(seed=6, seconds=20.0)
    R = Rotation.from_euler("ZYX", sim.attitude_deg, degrees=True)
    base = trimag.fit(sim.vector_nT, model="interference12", reference=EARTH, attitude=R, units="nT")
    values, _, _ = eddy_values(sim.vector_nT, time_s=sim.time_s)
    with pytest.raises(TrimagInputError, match="`free` names 'nope'"):
        fit_regressors(base, sim.vector_nT, values, attitude=R, free={"nope": [True, True, True]})


# ------------------------------------------------------------------ per-sample background with regressor terms
def test_regressor_terms_use_the_per_sample_background_not_its_mean() -> None:
    """Finding: with a per-sample background (``background_columns``) the regressor refit used the background's
    mean (the only one in the diagnostics): vector RMS 648 nT instead of the 8.5 nT noise floor, k biased."""
    rng = np.random.default_rng(3)
    n = 2000
    R = random_attitudes(n, rng)
    cur = current_profile(n, rng)
    H_n = EARTH + np.outer(np.linspace(-1, 1, n), [800.0, -500.0, 600.0])
    H_m = body_field(R, H_n) @ K_TRUE.T + C_TRUE + np.outer(cur, [30.0, -20.0, 50.0]) + rng.normal(0, 5, (n, 3))
    cal = trimag.fit(H_m, model="interference12", reference=H_n, attitude=R, units="nT", regressors={"current": cur})
    assert cal.stats["vector_rms_after"] < 10.0
    sd = cal.uncertainty["param_std"]
    for a, k in zip("xyz", [30.0, -20.0, 50.0], strict=True):
        assert abs(np.asarray(cal.regressors["coefficients"])[0, "xyz".index(a)] - k) < 4.5 * sd[f"k_current_{a}"]


# ------------------------------------------------------------------ command line, file format, apply / evaluate
@pytest.fixture(scope="module")
def fitted_file(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    tmp = tmp_path_factory.mktemp("eddy")
    data = _csv(_sim(seed=7), tmp / "box.csv")
    cal = tmp / "cal.json"
    proc = run_trimag("fit", data, "--model", "interference12", *VECTOR_ARGS, "--option", "eddy=9",
                      "--time-column", "t", "-o", cal)
    assert proc.returncode == 0, proc.stderr
    assert "eddy-current terms (9)" in proc.stdout and "dBx/dt" in proc.stdout
    return tmp, data, cal


def test_calibration_file_records_the_terms(fitted_file) -> None:
    _, _, cal_path = fitted_file
    d = json.loads(cal_path.read_text())
    assert d["format_version"].split(".")[0] == "2"  # 2.1.0 with a sensor record (docs/calibration-file.md)
    spec = d["regressors"]["eddy"]
    assert spec["terms"] == 9 and spec["time_column"] == "t" and spec["rate_hz"] == pytest.approx(10.0)
    assert "central" in spec["scheme"] and d["regressors"]["names"] == list(EDDY_NAMES)
    cal = trimag.Calibration.from_file(cal_path)
    assert cal.regressors["eddy"] == spec


def test_apply_streams_across_chunks_like_the_in_memory_correction(fitted_file) -> None:
    tmp, data, cal_path = fitted_file
    cal = trimag.Calibration.from_file(cal_path)
    df = pd.read_csv(data)
    B = df[["x", "y", "z"]].to_numpy()
    values, _, _ = eddy_values(B, time_s=df["t"].to_numpy())
    expected = cal.apply(B, regressors=values)
    apply_to_file(cal_path, data, tmp / "small.csv", columns="x,y,z", chunk_rows=257)
    out = pd.read_csv(tmp / "small.csv")
    np.testing.assert_allclose(out[["x_cal", "y_cal", "z_cal"]].to_numpy(), expected, rtol=0, atol=1e-6)
    proc = run_trimag("apply", cal_path, data, "--columns", "x,y,z", "-o", tmp / "out.csv")
    assert proc.returncode == 0, proc.stderr
    np.testing.assert_allclose(pd.read_csv(tmp / "out.csv")[["x_cal", "y_cal", "z_cal"]].to_numpy(), expected,
                               atol=1e-6)


def test_evaluate_vector_and_magnitude_on_a_held_out_box(fitted_file) -> None:
    tmp, _, cal_path = fitted_file
    other = _csv(_sim(seed=8), tmp / "other.csv")
    proc = run_trimag("evaluate", cal_path, other, *VECTOR_ARGS, "--json")
    assert proc.returncode == 0, proc.stderr
    r = json.loads(proc.stdout)
    assert r["after"]["rms_vector"] < 1.5 < 100 < r["before"]["rms_vector"]
    proc = run_trimag("evaluate", cal_path, other, "--columns", "x,y,z", "--reference",
                      str(float(np.linalg.norm(EARTH))), "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["rms_after"] < 1.0


def test_refusals(fitted_file) -> None:
    tmp, data, cal_path = fitted_file
    df = pd.read_csv(data)
    df["t"] = df["t"] * 2.0  # 5 Hz
    slow = tmp / "slow.csv"
    df.to_csv(slow, index=False)
    proc = run_trimag("evaluate", cal_path, slow, *VECTOR_ARGS)
    assert proc.returncode == 2 and "fitted at 10 Hz" in proc.stderr and "Traceback" not in proc.stderr
    proc = run_trimag("apply", cal_path, slow, "--columns", "x,y,z", "-o", tmp / "x.csv")
    assert proc.returncode == 2 and "fitted at 10 Hz" in proc.stderr
    df.drop(columns="t").to_csv(tmp / "notime.csv", index=False)
    proc = run_trimag("apply", cal_path, tmp / "notime.csv", "--columns", "x,y,z", "-o", tmp / "x.csv")
    assert proc.returncode == 2 and "no column 't'" in proc.stderr
    proc = run_trimag("export", cal_path, "--to", "ardupilot", "-o", tmp / "x.param")
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1 and "dBx/dt" in proc.stderr
    assert "without --option eddy" in proc.stderr  # the fix named, not "without --regressors"
    proc = run_trimag("fit", data, "--model", "interference12", *VECTOR_ARGS, "--option", "eddy=9")
    assert proc.returncode == 2 and "sample rate" in proc.stderr
    proc = run_trimag("fit", data, "--model", "interference12", *VECTOR_ARGS, "--option", "eddy=4", "--rate", "10")
    assert proc.returncode == 2 and "`eddy` takes 9" in proc.stderr
    proc = run_trimag("fit", data, "--columns", "x,y,z", "--option", "eddy=9", "--rate", "10")
    assert proc.returncode == 2 and "for the model interference12" in proc.stderr


def test_rate_instead_of_a_time_column(tmp_path: Path) -> None:
    data = _csv(_sim(seed=9, E=np.diag([-0.04, -0.02, -0.03]), seconds=30.0), tmp_path / "box.csv")
    cal_path = tmp_path / "cal.json"
    proc = run_trimag("fit", data, "--model", "interference12", *VECTOR_ARGS, "--option", "eddy=3", "--rate", "10",
                      "-o", cal_path)
    assert proc.returncode == 0, proc.stderr
    spec = json.loads(cal_path.read_text())["regressors"]["eddy"]
    assert spec["time_column"] is None and spec["terms"] == 3
    proc = run_trimag("evaluate", cal_path, data, *VECTOR_ARGS, "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["after"]["rms_vector"] < 1.5


def test_batch_fits_the_terms_in_every_file(fitted_file, tmp_path: Path) -> None:
    from trimag.app.batch import fit_batch

    _, data, _ = fitted_file
    result = fit_batch([str(data)], tmp_path / "out", model="interference12", options={"eddy": "3"},
                       columns="x,y,z", units="nT", attitude_columns="yaw,pitch,roll",
                       background_ned="18000,1000,46000", time_column="t", progress=False)
    assert result.n_failed == 0, result.table["error"].tolist()
    spec = json.loads((tmp_path / "out" / "box.json").read_text())["regressors"]["eddy"]
    assert spec["terms"] == 3 and spec["time_column"] == "t"


def test_quick_recalibration_keeps_and_recomputes_the_terms(fitted_file, tmp_path: Path) -> None:
    """A prior with eddy terms: its derivative regressors come from the data, not from columns named dBx/dt."""
    _, data, cal_path = fitted_file
    out = tmp_path / "re.json"
    proc = run_trimag("fit", data, "--prior", cal_path, "--columns", "x,y,z", "--attitude-columns",
                      "yaw,pitch,roll", "--reference", str(float(np.linalg.norm(EARTH))), "-o", out)
    assert proc.returncode == 0, proc.stderr
    d = json.loads(out.read_text())
    prior = json.loads(cal_path.read_text())
    assert d["regressors"]["eddy"] == prior["regressors"]["eddy"]
    assert d["regressors"]["coefficients"] == prior["regressors"]["coefficients"]
    assert d["stats"]["rms_after"] < 1.0


# ------------------------------------------------------------------ segments follow the original row numbers
def _seg_csv(seed: int, path: Path, nan_rows: slice | None = None) -> Path:
    """A box with a column ``seg = (row // 500) % 2`` (alternate blocks of 50 s), no time column needed, and the
    x cells of ``nan_rows`` missing."""
    df = pd.read_csv(_csv(_sim(seed=seed), path))
    df["seg"] = (np.arange(len(df)) // 500) % 2
    if nan_rows is not None:
        df.loc[df.index[nan_rows], "x"] = np.nan
    df.to_csv(path, index=False)
    return path


def test_rate_derivative_is_cut_where_rows_are_not_selected(tmp_path: Path) -> None:
    """Without a time column, `--where` keeps rows 0-499, 1000-1499, ...: a jump in row number is a gap (before:
    the derivative bridged the 50 s jumps, fit RMS 250 nT and held-out vector RMS 189 nT, against ~1 nT)."""
    data = _seg_csv(7, tmp_path / "box_seg.csv")
    other = _seg_csv(8, tmp_path / "other_seg.csv")
    cal = tmp_path / "cal.json"
    proc = run_trimag("fit", data, "--model", "interference12", *VECTOR_ARGS, "--option", "eddy=9", "--rate", "10",
                      "--where", "seg==0", "-o", cal)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(cal.read_text())["stats"]["vector_rms_after"] < 2.0
    proc = run_trimag("evaluate", cal, other, *VECTOR_ARGS, "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["after"]["rms_vector"] < 1.5
    # evaluate with `--where` (vector, magnitude): the same cut
    proc = run_trimag("evaluate", cal, other, *VECTOR_ARGS, "--where", "seg==0", "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["after"]["rms_vector"] < 1.5
    proc = run_trimag("evaluate", cal, other, "--columns", "x,y,z", "--reference", str(float(np.linalg.norm(EARTH))),
                      "--where", "seg==0", "--json", "--chunk-rows", "700")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["rms_after"] < 1.0


def test_rate_derivative_is_cut_at_rows_dropped_for_missing_values(tmp_path: Path) -> None:
    """Rows dropped for a missing x are gaps in fit, evaluate and the streamed apply, as a time column would say."""
    from trimag.io import read_samples
    from trimag.vehicle.eddy import fit_values

    data = _seg_csv(7, tmp_path / "box.csv", nan_rows=slice(1000, 1030))
    df = pd.read_csv(data)
    ok = np.isfinite(df[["x", "y", "z"]].to_numpy()).all(axis=1)
    B = df[["x", "y", "z"]].to_numpy()[ok]
    expected, _, _ = eddy_values(B, time_s=df["t"].to_numpy()[ok])  # the time column cuts at the hole
    samples = read_samples(data, columns="x,y,z")
    values, _, _ = fit_values(samples, 9, None, 10.0, data)
    for name in EDDY_NAMES:
        np.testing.assert_allclose(values[name], expected[name], rtol=1e-9, atol=1e-9)
    cal_path = tmp_path / "cal.json"
    proc = run_trimag("fit", data, "--model", "interference12", *VECTOR_ARGS, "--option", "eddy=9", "--rate", "10",
                      "-o", cal_path)
    assert proc.returncode == 0, proc.stderr
    cal = trimag.Calibration.from_file(cal_path)
    apply_to_file(cal_path, data, tmp_path / "out.csv", columns="x,y,z", chunk_rows=257)
    out = pd.read_csv(tmp_path / "out.csv")[["x_cal", "y_cal", "z_cal"]].to_numpy()[ok]
    np.testing.assert_allclose(out, cal.apply(B, regressors=expected), rtol=0, atol=1e-6)
    from trimag.app import evaluate_file

    r = evaluate_file(cal_path, data, columns="x,y,z", reference=float(np.linalg.norm(EARTH)), chunk_rows=311)
    F = np.linalg.norm(cal.apply(B, regressors=expected), axis=1)
    assert r["rms_after"] == pytest.approx(float(np.sqrt(np.mean((F - np.linalg.norm(EARTH)) ** 2))), rel=1e-9)


def test_attitude_file_keeps_the_time_column_for_the_eddy_terms(tmp_path: Path) -> None:
    df = pd.read_csv(_csv(_sim(seed=7), tmp_path / "box.csv"))
    df[["t", "x", "y", "z"]].to_csv(tmp_path / "mag.csv", index=False)
    df[["t", "yaw", "pitch", "roll"]].to_csv(tmp_path / "att.csv", index=False)
    cal = tmp_path / "cal.json"
    proc = run_trimag("fit", tmp_path / "mag.csv", "--model", "interference12", *VECTOR_ARGS, "--attitude-file",
                      tmp_path / "att.csv", "--time-column", "t", "--option", "eddy=9", "-o", cal)
    assert proc.returncode == 0, proc.stderr
    spec = json.loads(cal.read_text())["regressors"]["eddy"]
    assert spec["time_column"] == "t" and spec["rate_hz"] == pytest.approx(10.0)
    proc = run_trimag("fit", tmp_path / "box.csv", "--model", "interference12", *VECTOR_ARGS, "--option", "eddy=9")
    assert proc.returncode == 2 and "--rate" in proc.stderr and "rate_hz" not in proc.stderr


def test_evaluate_and_prior_honour_time_column_and_rate(fitted_file, tmp_path: Path) -> None:
    _, data, cal_path = fitted_file
    other = pd.read_csv(_csv(_sim(seed=8), tmp_path / "other.csv")).rename(columns={"t": "time"})
    renamed = tmp_path / "renamed.csv"
    other.to_csv(renamed, index=False)
    F = str(float(np.linalg.norm(EARTH)))
    proc = run_trimag("evaluate", cal_path, renamed, *VECTOR_ARGS, "--time-column", "time", "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["after"]["rms_vector"] < 1.5
    proc = run_trimag("evaluate", cal_path, renamed, "--columns", "x,y,z", "--reference", F, "--time-column", "time",
                      "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["rms_after"] < 1.0
    proc = run_trimag("fit", renamed, "--prior", cal_path, "--columns", "x,y,z", "--attitude-columns",
                      "yaw,pitch,roll", "--reference", F, "--time-column", "time", "-o", tmp_path / "re.json")
    assert proc.returncode == 0, proc.stderr
    # a rate calibration: the data's `--rate` is checked against the calibration's, in every evaluation
    rate_cal = tmp_path / "rate.json"
    proc = run_trimag("fit", data, "--model", "interference12", *VECTOR_ARGS, "--option", "eddy=9", "--rate", "10",
                      "-o", rate_cal)
    assert proc.returncode == 0, proc.stderr
    for args in (VECTOR_ARGS, ("--columns", "x,y,z", "--reference", F)):
        proc = run_trimag("evaluate", rate_cal, renamed, *args, "--rate", "50")
        assert proc.returncode == 2 and "sampled at 50 Hz" in proc.stderr and "fitted at 10 Hz" in proc.stderr
        proc = run_trimag("evaluate", rate_cal, renamed, *args, "--rate", "10")
        assert proc.returncode == 0, proc.stderr
    proc = run_trimag("fit", renamed, "--prior", rate_cal, "--columns", "x,y,z", "--reference", F, "--rate", "50")
    assert proc.returncode == 2 and "fitted at 10 Hz" in proc.stderr
