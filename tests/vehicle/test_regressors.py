"""Regressor terms of the offset (issue 20, item 1; docs/vehicle.md): ``b(t) = b0 + sum_j k_j (u_j(t) - mean_j)``.

Simulated sensors with known truth (fixed seeds, small sizes): a hard/soft-iron magnetometer (or paper C's vehicle
model) whose offset moves with a motor current (k = (30, -20, 50) nT/A, 0-20 A) and a temperature ramp
(k = (2, 1, -3) nT/degC, 20-35 degC), 20 nT white noise per axis on a 50 000 nT field.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import trimag
from trimag import Calibration
from trimag.errors import IdentifiabilityError, TrimagInputError
from trimag.simulate import body_field, current_profile, random_attitudes, temperature_ramp, uniform_directions
from trimag.vehicle.regressors import check_regressors, fit_regressors, ranking_table

from _helpers import run_trimag

F = 50_000.0
NOISE = 20.0
K_CURRENT = np.array([30.0, -20.0, 50.0])  # nT per A
K_TEMPERATURE = np.array([2.0, 1.0, -3.0])  # nT per degC
SOFT = np.array([[1.05, 0.02, -0.01], [0.0, 0.97, 0.03], [0.0, 0.0, 1.02]])  # W, the correction
HARD = np.array([300.0, -200.0, 150.0])
H_N = np.array([18_000.0, 1_200.0, 46_000.0])
K_VEHICLE = np.array([[1.02, 0.01, -0.02], [0.015, 0.98, 0.01], [-0.01, 0.02, 1.01]])
C_VEHICLE = np.array([250.0, -120.0, 80.0])


def _log(seed: int, n: int = 2000, *, temperature: bool = True) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Raw samples (n, 3) and the channels: current (A), temperature (degC), a pure-noise channel."""
    rng = np.random.default_rng(seed)
    current = current_profile(n, rng, cycles=3 + seed % 3)
    temp = temperature_ramp(n, rng)
    shift = np.outer(current, K_CURRENT) + (np.outer(temp, K_TEMPERATURE) if temperature else 0.0)
    raw = (F * uniform_directions(n, rng)) @ np.linalg.inv(SOFT).T + HARD + shift + rng.normal(0, NOISE, (n, 3))
    return raw, {"current": current, "temperature": temp, "noise": rng.normal(size=n)}


def _vehicle(seed: int, n: int = 2000):
    rng = np.random.default_rng(seed)
    R = random_attitudes(n, rng)
    current = current_profile(n, rng, cycles=3 + seed % 3)
    temp = temperature_ramp(n, rng)
    H_m = (body_field(R, H_N) @ K_VEHICLE.T + C_VEHICLE + np.outer(current, K_CURRENT)
           + np.outer(temp, K_TEMPERATURE) + rng.normal(0, NOISE, (n, 3)))
    return H_m, R, {"current": current, "temperature": temp, "noise": rng.normal(size=n)}


def _rms_magnitude(cal: Calibration, raw: np.ndarray, regressors=None) -> float:
    return float(np.sqrt(np.mean((np.linalg.norm(cal.apply(raw, regressors=regressors), axis=1) - F) ** 2)))


@pytest.fixture(scope="module")
def fitted() -> tuple[Calibration, Calibration, np.ndarray, dict[str, np.ndarray]]:
    raw, channels = _log(1)
    cal = trimag.fit(raw, reference=F, units="nT", regressors=channels)
    base = trimag.fit(raw, reference=F, units="nT")
    return cal, base, raw, channels


# ------------------------------------------------------------------ estimation (ellipsoid, ml)
def test_coefficients_recovered_within_three_sigma(fitted) -> None:
    cal, _, _, _ = fitted
    std = cal.uncertainty["param_std"]
    names = cal.regressors["names"]
    K = np.asarray(cal.regressors["coefficients"])
    for name, truth in (("current", K_CURRENT), ("temperature", K_TEMPERATURE)):
        k = K[names.index(name)]
        sigma = np.array([std[f"k_{name}_{a}"] for a in "xyz"])
        assert np.all(np.abs(k - truth) < 3 * sigma), (name, k, sigma)
    assert np.all(np.abs(K[names.index("noise")]) < 3 * np.array([std[f"k_noise_{a}"] for a in "xyz"]))
    # b0 is the offset at the mean regressor values
    expected_b0 = HARD + np.mean(_log(1)[1]["current"]) * K_CURRENT + np.mean(_log(1)[1]["temperature"]) * K_TEMPERATURE
    assert np.all(np.abs(cal.offset - expected_b0) < 3 * np.array([std[f"hard_iron_{a}"] for a in "xyz"]))
    assert cal.uncertainty["covariance_order"][9:12] == ["k_current_x", "k_current_y", "k_current_z"]
    assert np.allclose(cal.regressors["means"], [np.mean(v) for v in _log(1)[1].values()])


def test_reported_sigmas_match_the_scatter_of_a_small_monte_carlo() -> None:
    """20 logs of 1000 samples, current only: the standardised errors of the 3 current coefficients have a standard
    deviation within sampling error of 1 (60 values: [0.7, 1.35] holds it with probability > 0.99)."""
    z = []
    for seed in range(20):
        raw, channels = _log(100 + seed, 1000, temperature=False)
        cal = trimag.fit(raw, reference=F, units="nT", regressors={"current": channels["current"]})
        sigma = np.array([cal.uncertainty["param_std"][f"k_current_{a}"] for a in "xyz"])
        z.extend((np.asarray(cal.regressors["coefficients"][0]) - K_CURRENT) / sigma)
    assert 0.7 < float(np.std(z)) < 1.35
    assert abs(float(np.mean(z))) < 0.4


def test_held_out_log_reaches_the_noise_floor_only_with_the_terms(fitted) -> None:
    cal, base, _, _ = fitted
    raw2, channels2 = _log(2)  # its own current profile and temperature ramp
    with_terms = _rms_magnitude(cal, raw2, channels2)
    without = _rms_magnitude(base, raw2)
    assert with_terms < 1.15 * NOISE
    assert without > 5 * with_terms


def test_ranking_marks_the_true_channels_significant_and_noise_not(fitted) -> None:
    cal, base, _, _ = fitted
    ranking = cal.diagnostics["regressors"]["ranking"]
    by_name = {e["name"]: e for e in ranking}
    assert ranking[0]["name"] == "current" and [e["rank"] for e in ranking] == [1, 2, 3]
    assert by_name["current"]["significant"] and by_name["temperature"]["significant"]
    assert not by_name["noise"]["significant"] and by_name["noise"]["p_value"] > 0.01
    assert by_name["current"]["rms_without"] > 5 * by_name["current"]["rms_with_all"]
    assert by_name["current"]["variance_explained_fraction"] > 0.9
    assert by_name["noise"]["variance_explained_fraction"] < 0.01
    assert cal.stats["rms_after"] < 1.1 * NOISE < base.stats["rms_after"]
    assert cal.stats["rms_after_without_regressors"] == pytest.approx(base.stats["rms_after"])
    table = ranking_table(ranking, "nT")
    assert "current" in table and "significant" in table and len(table.splitlines()) == 2 + 2 * 3 + 1


def test_unknown_magnitude_recovers_the_coefficients() -> None:
    raw, channels = _log(3, temperature=False)
    cal = trimag.fit(raw, units="nT", regressors={"current": channels["current"]})
    sigma = np.array([cal.uncertainty["param_std"][f"k_current_{a}"] for a in "xyz"])
    assert np.all(np.abs(np.asarray(cal.regressors["coefficients"][0]) - K_CURRENT) < 3 * sigma)


# ------------------------------------------------------------------ interference12 (linear-vector)
def test_vector_model_recovers_the_coefficients_and_generalises() -> None:
    H_m, R, channels = _vehicle(1)
    cal = trimag.fit(H_m, model="interference12", reference=H_N, attitude=R, units="nT", regressors=channels)
    base = trimag.fit(H_m, model="interference12", reference=H_N, attitude=R, units="nT")
    std = cal.uncertainty["param_std"]
    names = cal.regressors["names"]
    for name, truth in (("current", K_CURRENT), ("temperature", K_TEMPERATURE)):
        k = np.asarray(cal.regressors["coefficients"][names.index(name)])
        assert np.all(np.abs(k - truth) < 3 * np.array([std[f"k_{name}_{a}"] for a in "xyz"]))
    assert np.allclose(np.linalg.inv(cal.matrix), K_VEHICLE, atol=3e-3)
    ranking = {e["name"]: e for e in cal.diagnostics["regressors"]["ranking"]}
    assert ranking["current"]["significant"] and not ranking["noise"]["significant"]
    H2, R2, channels2 = _vehicle(2)
    floor = NOISE * np.sqrt(3)  # vector error of white noise per axis
    err = np.sqrt(np.mean(np.sum((cal.apply(H2, regressors=channels2) - body_field(R2, H_N)) ** 2, axis=1)))
    err0 = np.sqrt(np.mean(np.sum((base.apply(H2) - body_field(R2, H_N)) ** 2, axis=1)))
    assert err < 1.15 * floor and err0 > 5 * err


# ------------------------------------------------------------------ the Calibration: apply, JSON
def test_json_round_trip_and_format_versions(fitted) -> None:
    cal, base, raw, channels = fitted
    data = json.loads(cal.to_json())
    assert data["format_version"] == "2.0.0" and data["regressors"]["names"] == ["current", "temperature", "noise"]
    back = Calibration.from_json(cal.to_json())
    assert back == cal and back.approx_equal(cal, atol=0)
    assert np.array_equal(back.apply(raw, regressors=channels), cal.apply(raw, regressors=channels))
    plain = json.loads(base.to_json())
    assert plain["format_version"] == "1.0.0" and "regressors" not in plain  # as before regressors existed
    assert not base.approx_equal(cal, atol=1e9)


def test_apply_forms_inverse_and_refusals(fitted) -> None:
    cal, base, raw, channels = fitted
    U = np.column_stack([channels[n] for n in cal.regressors["names"]])
    corrected = cal.apply(raw, regressors=channels)
    assert np.array_equal(cal.apply(raw, regressors=U), corrected)
    assert np.allclose(cal.apply(raw[0], regressors=U[0]), corrected[0])
    assert np.allclose(cal.apply(raw[0], regressors={k: v[0] for k, v in channels.items()}), corrected[0])
    assert np.allclose(cal.apply(corrected, inverse=True, regressors=U), raw, atol=1e-8)
    with pytest.raises(TrimagInputError, match=r"has regressor terms \(current, temperature, noise\)"):
        cal.apply(raw)
    with pytest.raises(TrimagInputError, match="lacks 'noise'"):
        cal.apply(raw, regressors={"current": channels["current"], "temperature": channels["temperature"]})
    with pytest.raises(TrimagInputError, match=r"shape \(2000, 3\)"):
        cal.apply(raw, regressors=U[:, :2])
    with pytest.raises(TrimagInputError, match="has no regressor terms"):
        base.apply(raw, regressors=U)
    with pytest.raises(TrimagInputError, match="inverse of a calibration with regressor terms"):
        cal.inv()
    with pytest.raises(TrimagInputError, match="composition"):
        _ = base * cal


def test_constant_and_collinear_regressors_are_refused() -> None:
    raw, channels = _log(4, 500, temperature=False)
    with pytest.raises(TrimagInputError, match="'battery' does not vary"):
        trimag.fit(raw, reference=F, regressors={"current": channels["current"], "battery": np.full(500, 12.6)})
    with pytest.raises(IdentifiabilityError, match="linear combinations"):
        trimag.fit(raw, reference=F, regressors={"current": channels["current"], "power": 12 * channels["current"]})
    with pytest.raises(TrimagInputError, match="non-finite"):
        check_regressors({"current": np.r_[np.nan, channels["current"][1:]]}, 500)
    base = trimag.fit(raw, reference=F)
    with pytest.raises(TrimagInputError, match="models ellipsoid, interference12"):
        fit_regressors(trimag.fit(raw, model="ortho-gain", reference=F), raw, {"current": channels["current"]})
    with pytest.raises(TrimagInputError, match=r"shape \(500,\)"):
        fit_regressors(base, raw, {"current": channels["current"][:10]})


def test_fit_file_takes_the_typed_request(tmp_path: Path) -> None:
    from trimag.app import fit_file
    from trimag.app.requests import FitRequest, InputSpec

    raw, channels = _log(5, 1000, temperature=False)
    path = tmp_path / "log.csv"
    pd.DataFrame({"x": raw[:, 0], "y": raw[:, 1], "z": raw[:, 2], "current": channels["current"]}).to_csv(path,
                                                                                                        index=False)
    result = fit_file(FitRequest(InputSpec(path, units="nT"), reference=trimag.app.requests.ReferenceSpec(reference=F),
                                 regressors=("current",)))
    assert result.calibration.regressors["names"] == ["current"]
    assert result.summary["regressors"]["ranking"][0]["significant"]
    same = fit_file(path, units="nT", reference=F, regressors="current")  # FitRequest.of, a comma-separated string
    assert same.calibration.approx_equal(result.calibration, atol=1e-9)


# ------------------------------------------------------------------ the command line
def _write(path: Path, raw: np.ndarray, channels: dict[str, np.ndarray], drop: str | None = None) -> Path:
    table = {"x": raw[:, 0], "y": raw[:, 1], "z": raw[:, 2], **{k: v for k, v in channels.items() if k != drop}}
    pd.DataFrame(table).to_csv(path, index=False)
    return path


def _one_line_error(proc, code: int, pattern: str) -> None:
    assert proc.returncode == code, proc.stderr
    assert "Traceback" not in proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and pattern in lines[0], proc.stderr


def test_cli_fit_apply_evaluate_end_to_end(tmp_path: Path) -> None:
    raw, channels = _log(1)
    raw2, channels2 = _log(2)
    log1, log2 = _write(tmp_path / "log1.csv", raw, channels), _write(tmp_path / "log2.csv", raw2, channels2)
    cal_path = tmp_path / "cal.json"
    proc = run_trimag("fit", log1, "--units", "nT", "--reference", str(F), "--regressors", "current,temperature,noise",
                      "-o", cal_path, "--json")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    ranking = {e["name"]: e for e in summary["regressors"]["ranking"]}
    assert ranking["current"]["significant"] and not ranking["noise"]["significant"]
    assert summary["rms_after"] < 1.1 * NOISE < summary["rms_after_without_regressors"]
    assert "k_current_x" in summary["uncertainty"]["param_std"]
    text = run_trimag("fit", log1, "--units", "nT", "--reference", str(F), "--regressors", "current,noise")
    assert text.returncode == 0 and "regressor terms" in text.stdout and "significant" in text.stdout
    cal = Calibration.from_file(cal_path)
    out = tmp_path / "out.csv"
    proc = run_trimag("apply", cal_path, log2, "-o", out)
    assert proc.returncode == 0, proc.stderr
    written = pd.read_csv(out)[["x_cal", "y_cal", "z_cal"]].to_numpy()
    assert np.allclose(written, cal.apply(raw2, regressors=channels2), rtol=1e-12, atol=1e-9)
    proc = run_trimag("evaluate", cal_path, log2, "--reference", str(F), "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["rms_after"] < 1.15 * NOISE


def test_cli_refusals(tmp_path: Path) -> None:
    raw, channels = _log(6, 600, temperature=False)
    log = _write(tmp_path / "log.csv", raw, channels)
    cal_path = tmp_path / "cal.json"
    assert run_trimag("fit", log, "--reference", str(F), "--regressors", "current", "-o", cal_path).returncode == 0
    no_current = _write(tmp_path / "no_current.csv", raw, channels, drop="current")
    _one_line_error(run_trimag("apply", cal_path, no_current, "-o", tmp_path / "o.csv"), 2, "no column 'current'")
    assert not (tmp_path / "o.csv").exists()
    _one_line_error(run_trimag("evaluate", cal_path, no_current, "--reference", str(F)), 2, "no column 'current'")
    _one_line_error(run_trimag("fit", log, "--reference", str(F), "--regressors", "current,rpm"), 2,
                    "no column 'rpm'")
    constant = _write(tmp_path / "constant.csv", raw, {**channels, "battery": np.full(600, 12.6)})
    _one_line_error(run_trimag("fit", constant, "--reference", str(F), "--regressors", "current,battery"), 2,
                    "'battery' does not vary")
    collinear = _write(tmp_path / "collinear.csv", raw, {**channels, "power": 12 * channels["current"]})
    _one_line_error(run_trimag("fit", collinear, "--reference", str(F), "--regressors", "current,power"), 3,
                    "linear combinations")
    _one_line_error(run_trimag("fit", log, "--model", "ortho-gain", "--reference", str(F), "--regressors", "current"),
                    2, "--regressors works with the models ellipsoid, interference12")


def test_export_refuses_a_calibration_with_regressor_terms(fitted) -> None:
    from trimag.io.export import export_calibration

    cal, base, _, _ = fitted
    assert export_calibration(base, "json").text
    with pytest.raises(TrimagInputError, match=r"regressor terms .* cannot hold .*without `regressors`$"):
        export_calibration(cal, "ardupilot")


def test_cli_vector_model_fit_and_evaluate(tmp_path: Path) -> None:
    paths = []
    for seed in (1, 2):
        H, R, channels = _vehicle(seed, 1000)
        e = R.as_euler("ZYX", degrees=True)
        table = {"x": H[:, 0], "y": H[:, 1], "z": H[:, 2], "yaw": e[:, 0], "pitch": e[:, 1], "roll": e[:, 2],
                 "current": channels["current"]}
        pd.DataFrame(table).to_csv(tmp_path / f"veh{seed}.csv", index=False)
        paths.append(tmp_path / f"veh{seed}.csv")
    cal_path = tmp_path / "cal.json"
    vector = ("--attitude-columns", "yaw,pitch,roll", "--background-ned", ",".join(map(str, H_N)))
    proc = run_trimag("fit", paths[0], "--model", "interference12", "--units", "nT", *vector, "--regressors",
                      "current", "-o", cal_path, "--json")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary["regressors"]["ranking"][0]["significant"]
    proc = run_trimag("evaluate", cal_path, paths[1], *vector, "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["rms_after"] < 1.15 * NOISE * np.sqrt(3)
    pd.read_csv(paths[1]).drop(columns="current").to_csv(tmp_path / "bare.csv", index=False)
    _one_line_error(run_trimag("evaluate", cal_path, tmp_path / "bare.csv", *vector), 2, "no column 'current'")


def test_cli_batch_takes_the_regressors(tmp_path: Path) -> None:
    for seed in (8, 9):
        raw, channels = _log(seed, 800, temperature=False)
        _write(tmp_path / f"log{seed}.csv", raw, channels)
    proc = run_trimag("batch", str(tmp_path / "log*.csv"), "--reference", str(F), "--regressors", "current",
                      "--out", tmp_path / "out", "--json")
    assert proc.returncode == 0, proc.stderr
    for seed in (8, 9):
        cal = Calibration.from_file(tmp_path / "out" / f"log{seed}.json")
        assert cal.regressors["names"] == ["current"]
        assert np.allclose(cal.regressors["coefficients"][0], K_CURRENT, atol=2.0)


def test_repr_rebuilds_the_regressor_terms(fitted) -> None:
    cal, _, raw, channels = fitted
    rebuilt = eval(repr(cal), {"Calibration": Calibration})  # the from_matrix_offset call it shows
    assert rebuilt.approx_equal(cal, atol=0)
    assert np.array_equal(rebuilt.apply(raw, regressors=channels), cal.apply(raw, regressors=channels))


def test_uncertainty_has_the_fields_of_every_estimator(fitted) -> None:
    """A fit with regressor terms wrote its own uncertainty record (no ``gauge`` key for the same schema, no
    predicted RMS): it has the typed fields every estimator's has (``trimag.calibration.UNCERTAINTY_FIELDS``)."""
    from trimag.calibration import UNCERTAINTY_FIELDS

    cal = fitted[0]
    assert set(UNCERTAINTY_FIELDS) <= set(cal.uncertainty)
    assert list(cal.uncertainty["param_std"]) == cal.uncertainty["covariance_order"]


def test_a_regressor_that_is_the_reading_itself_is_explained_not_condition_number_inf(tmp_path, capsys) -> None:
    """Issue 41, item 17: a regressor column equal to the magnetometer's x said "condition number inf"."""
    from trimag.cli import main

    from _helpers import simulate_ellipsoid

    raw = simulate_ellipsoid(400, noise=20.0, seed=8)
    path = tmp_path / "lab.csv"
    np.savetxt(path, np.column_stack([raw, raw[:, 0]]), delimiter=",", header="x,y,z,c1", comments="", fmt="%.3f")
    assert main(["fit", str(path), "--columns", "x,y,z", "--units", "nT", "--regressors", "c1", "-q"]) == 3
    err = capsys.readouterr().err
    assert "inf" not in err.replace("information", "") and "do not determine at all" in err, err
    assert "magnetometer's own reading" in err
