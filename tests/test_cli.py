"""End to end: the installed ``trimag`` command run as a subprocess, as a user would."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from _helpers import run_trimag, simulate_ellipsoid

REQUIRED_KEYS = {
    "model", "method", "units", "n_samples", "n_used", "reference", "rms_before", "rms_after",
    "max_abs_before", "max_abs_after", "converged", "iterations", "params", "matrix", "offset",
}


def _one_line_error(proc, code: int, pattern: str) -> None:
    assert proc.returncode == code, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert "Traceback" not in proc.stderr
    assert any(pattern in ln for ln in lines), proc.stderr


def test_version() -> None:
    proc = run_trimag("--version")
    assert proc.returncode == 0 and proc.stdout.startswith("trimag ")


def test_demo_writes_outputs(tmp_path: Path) -> None:
    proc = run_trimag("demo", "--out", tmp_path / "demo")
    assert proc.returncode == 0, proc.stderr
    cal = json.loads((tmp_path / "demo" / "trimag-demo-calibration.json").read_text())
    png = (tmp_path / "demo" / "trimag-demo-report.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 50_000
    assert cal["units"] == "counts" and cal["model"] == "ellipsoid"
    # real QMC5883L log: hard iron dominates the raw magnitude; after correction the spread is ~1/9 of before
    assert cal["stats"]["rms_after"] < 0.02 * cal["stats"]["rms_before"]
    assert cal["stats"]["std_norm_after"] < 0.15 * cal["stats"]["std_norm_before"]
    for word in ("before", "after", "RMS", "wrote calibration", "wrote report"):
        assert word in proc.stdout


def test_fit_json_contract(ellipsoid_log: Path, tmp_path: Path) -> None:
    out = tmp_path / "cal.json"
    proc = run_trimag("fit", ellipsoid_log, "--units", "nT", "--reference", "48000", "-o", out,
                      "--report", tmp_path / "r.png", "--json")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)  # exactly one JSON object on stdout
    assert REQUIRED_KEYS <= set(summary)
    assert summary["units"] == "nT" and summary["n_used"] == 600
    assert summary["reference"]["value"] == 48000 and summary["reference"]["source"] == "given"
    assert summary["rms_after"] < 10 < summary["rms_before"]
    assert np.array(summary["matrix"]).shape == (3, 3) and len(summary["offset"]) == 3
    assert json.loads(out.read_text())["units"] == "nT"
    assert (tmp_path / "r.png").stat().st_size > 10_000
    assert "bx, by, bz" in proc.stderr  # the column choice is reported


def test_fit_igrf_reference(ellipsoid_log: Path) -> None:
    # NOAA's calculator (IGRF-14) at 20 N, 50 E, sea level, 2020-01-01: F = 41232.3 nT (tests/fields/test_reference.py)
    proc = run_trimag("fit", ellipsoid_log, "--units", "nT", "--igrf", "20,50,0,2020-01-01", "--json")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    ref = summary["reference"]
    assert ref["source"].startswith("igrf") and abs(ref["value"] - 41232.3) < 5.0
    # the calibration scales the log (|B| = 48000) to that reference
    assert summary["rms_after"] < 20.0


def test_apply_keeps_rows_and_columns(ellipsoid_log: Path, tmp_path: Path) -> None:
    cal = tmp_path / "cal.json"
    assert run_trimag("fit", ellipsoid_log, "--units", "nT", "-o", cal, "-q").returncode == 0
    text = ellipsoid_log.read_text().splitlines()
    text[5] = "0.08,nan,oops,1"  # a bad row must be kept, with empty corrected cells
    bad_log = tmp_path / "in.csv"
    bad_log.write_text("\n".join(text) + "\n")
    out = tmp_path / "out.csv"
    proc = run_trimag("apply", cal, bad_log, "-o", out, "--chunk-rows", "100")
    assert proc.returncode == 0, proc.stderr
    assert "1 of 600 rows" in proc.stderr
    df_in = pd.read_csv(bad_log, dtype=str, keep_default_na=False)
    df_out = pd.read_csv(out, dtype=str, keep_default_na=False)
    assert list(df_out.columns) == ["t", "bx", "by", "bz", "bx_cal", "by_cal", "bz_cal"]
    pd.testing.assert_frame_equal(df_out[df_in.columns], df_in)
    assert df_out.loc[4, "bx_cal"] == "" and df_out.loc[5, "bx_cal"] != ""


def test_evaluate(ellipsoid_log: Path, tmp_path: Path) -> None:
    cal = tmp_path / "cal.json"
    run_trimag("fit", ellipsoid_log, "--units", "nT", "--reference", "48000", "-o", cal, "-q")
    proc = run_trimag("evaluate", cal, ellipsoid_log, "--reference", "48000", "--json", "--chunk-rows", "64")
    assert proc.returncode == 0, proc.stderr
    r = json.loads(proc.stdout)
    fit = json.loads(cal.read_text())["stats"]
    assert r["n_used"] == 600
    assert r["rms_after"] == pytest.approx(fit["rms_after"], rel=1e-9)
    assert r["rms_before"] == pytest.approx(fit["rms_before"], rel=1e-9)
    sub = json.loads(run_trimag("evaluate", cal, ellipsoid_log, "--rows", "0:100", "--json").stdout)
    assert sub["n_used"] == 100


def test_simulate_then_fit_recovers_truth(tmp_path: Path) -> None:
    params = {"hard_iron_x": 0.1, "hard_iron_y": -0.05, "hard_iron_z": 0.02, "w11": 1.05, "w12": 0.02,
              "w13": 0.0, "w21": 0.0, "w22": 0.97, "w23": 0.01, "w31": 0.0, "w32": 0.0, "w33": 1.0}
    (tmp_path / "p.json").write_text(json.dumps(params))
    proc = run_trimag("simulate", "--model", "ellipsoid", "--params", tmp_path / "p.json", "--n", "400",
                      "--noise", "0", "-o", tmp_path / "sim.csv", "--truth", tmp_path / "truth.json")
    assert proc.returncode == 0, proc.stderr
    fit = json.loads(run_trimag("fit", tmp_path / "sim.csv", "--reference", "1", "--json").stdout)
    np.testing.assert_allclose(fit["offset"], [0.1, -0.05, 0.02], atol=1e-9)
    assert json.loads((tmp_path / "truth.json").read_text())["params"] == params


# ---- exit codes and messages --------------------------------------------------------------------------
def test_missing_file_exit_2(tmp_path: Path) -> None:
    _one_line_error(run_trimag("fit", tmp_path / "nope.csv"), 2, "no such file")


def test_unknown_unit_exit_2(ellipsoid_log: Path) -> None:
    _one_line_error(run_trimag("fit", ellipsoid_log, "--units", "furlongs"), 2, "unknown unit")


def test_wrong_columns_exit_2(ellipsoid_log: Path) -> None:
    _one_line_error(run_trimag("fit", ellipsoid_log, "--columns", "bx,by,q"), 2, "no column 'q'")


def test_usage_error_exit_2() -> None:
    _one_line_error(run_trimag("fit"), 2, "DATA")


def test_planar_data_exit_3(tmp_path: Path) -> None:
    t = np.linspace(0, 2 * np.pi, 300, endpoint=False)
    p = tmp_path / "plane.csv"
    np.savetxt(p, np.column_stack([np.cos(t), np.sin(t), np.zeros_like(t)]), delimiter=",",
               header="bx,by,bz", comments="")
    out = tmp_path / "cal.json"
    proc = run_trimag("fit", p, "-o", out)
    _one_line_error(proc, 3, "one plane")
    assert not out.exists() and not list(tmp_path.glob(".*tmp"))


def test_single_axis_turn_of_a_noisy_sensor_exit_3(tmp_path: Path) -> None:
    """A turn about one axis with 1 % noise is not an exact plane, but the spread across the plane is noise:
    refused with exit 3 (it used to give a calibration without a warning)."""
    rng = np.random.default_rng(0)
    t = rng.uniform(0, 2 * np.pi, 2000)
    tilt = np.array([[1.0, 0.0, 0.0], [0.0, 0.8, -0.6], [0.0, 0.6, 0.8]])
    raw = np.column_stack([np.cos(t), np.sin(t), np.zeros_like(t)]) @ tilt.T * 480.0 + [30.0, -12.0, 55.0]
    raw += rng.normal(scale=4.8, size=raw.shape)
    p = tmp_path / "one-axis.csv"
    np.savetxt(p, raw, delimiter=",", header="bx,by,bz", comments="")
    out = tmp_path / "cal.json"
    proc = run_trimag("fit", p, "-o", out)
    _one_line_error(proc, 3, "one plane within the noise")
    assert not out.exists()


def test_strict_refuses_nan(tmp_path: Path) -> None:
    raw = simulate_ellipsoid(100, noise=20.0)
    raw[10, 0] = np.nan
    p = tmp_path / "n.csv"
    np.savetxt(p, raw, delimiter=",", header="bx,by,bz", comments="")
    proc = run_trimag("fit", p, "--json")
    assert proc.returncode == 0 and json.loads(proc.stdout)["n_dropped"] == 1
    assert "dropped 1 of 100 rows" in proc.stderr
    _one_line_error(run_trimag("fit", p, "--strict"), 2, "--strict")


def test_calibration_of_other_format_version_exit_2(ellipsoid_log: Path, tmp_path: Path) -> None:
    cal = tmp_path / "cal.json"
    run_trimag("fit", ellipsoid_log, "-o", cal, "-q")
    doc = json.loads(cal.read_text())
    doc["format_version"] = "9.0.0"
    cal.write_text(json.dumps(doc))
    _one_line_error(run_trimag("apply", cal, ellipsoid_log, "-o", tmp_path / "o.csv"), 2, "newer")
    assert not (tmp_path / "o.csv").exists()


def test_fit_and_apply_geosoft_xyz(tmp_path: Path) -> None:
    """`trimag fit data.xyz --columns FLUX_X,FLUX_Y,FLUX_Z --units nT` works; `apply` writes a CSV with the header
    (the names of the `/` record, then the line column) and every row, `*` rows kept with empty corrected cells."""
    sys.path.insert(0, str(Path(__file__).resolve().parent / "io"))  # run alone too, not only after tests/io
    from test_io import _geosoft_xyz

    path, _ = _geosoft_xyz(tmp_path / "survey.xyz")
    cal = tmp_path / "cal.json"
    fit = run_trimag("fit", path, "--columns", "FLUX_X,FLUX_Y,FLUX_Z", "--units", "nT", "-o", cal)
    assert fit.returncode == 0, fit.stderr
    assert "2 line record(s) skipped" in fit.stdout + fit.stderr and "dropped 2 of 400 rows" in fit.stdout + fit.stderr
    out = tmp_path / "survey_cal.csv"
    app = run_trimag("apply", cal, path, "-o", out, "--columns", "FLUX_X,FLUX_Y,FLUX_Z")
    assert app.returncode == 0, app.stderr
    df = pd.read_csv(out, dtype=str, keep_default_na=False)
    assert list(df.columns) == ["X", "Y", "FLUX_X", "FLUX_Y", "FLUX_Z", "MAG", "line",
                                "FLUX_X_cal", "FLUX_Y_cal", "FLUX_Z_cal"]
    assert len(df) == 400 and (df["FLUX_Y"] == "*").sum() == 2 and (df["FLUX_Y_cal"] == "").sum() == 2
    bad = run_trimag("apply", cal, path, "-o", tmp_path / "survey_cal.xyz", "--columns", "FLUX_X,FLUX_Y,FLUX_Z")
    _one_line_error(bad, 2, "cannot write .xyz files")


def test_each_command_builds_its_request_from_its_flags() -> None:
    """cli._request fills each request field (and each field of its input/reference/attitude specs) from the flag
    of the same destination: nothing a user gives is dropped, and a plain field named like a spec (live's
    `reference`, a number) stays a plain field."""
    from trimag.app.requests import ApplyRequest, EvaluateRequest, ExportRequest, LiveRequest, SimulateRequest
    from trimag.cli import _request, build_parser

    parse = build_parser().parse_args
    live = _request(LiveRequest, parse(["live", "--replay", "x.csv", "--reference", "48000", "--port", "0"]))
    assert live.reference == 48000.0 and live.replay == "x.csv" and live.port == 0
    a = parse(["evaluate", "c.json", "d.csv", "--igrf", "1,2,3,2020-01-01", "--quaternion-columns", "a,b,c,d",
               "--time-column", "t", "--rows", "3:9", "--chunk-rows", "7", "--declination", "2"])
    ev = _request(EvaluateRequest, a, a.data)
    assert (ev.calibration, ev.input.path, ev.input.rows, ev.chunk_rows) == ("c.json", "d.csv", "3:9", 7)
    assert ev.reference.igrf_spec == "1,2,3,2020-01-01" and ev.declination == "2"
    assert (ev.attitude.quaternion_columns, ev.attitude.time_column) == ("a,b,c,d", "t")
    a = parse(["apply", "c.json", "d.csv", "-o", "o.csv", "--units", "uT", "--chunk-rows", "5", "--scalar-column", "s"])
    ap = _request(ApplyRequest, a, a.data)
    assert (ap.out, ap.input.units, ap.chunk_rows, ap.scalar_column) == ("o.csv", "uT", 5, "s")
    a = parse(["export", "c.json", "--to", "px4", "--instance", "2", "-o", "p.params"])
    assert _request(ExportRequest, a) == ExportRequest("c.json", "px4", "p.params", instance=2)
    a = parse(["simulate", "--model", "ellipsoid", "--params", "p.json", "--n", "9", "-o", "s.csv", "--seed", "4"])
    assert _request(SimulateRequest, a, params_path=a.params) == SimulateRequest("ellipsoid", "p.json", 9, "s.csv",
                                                                                  seed=4)


def test_one_parser_serves_every_call_of_main_and_keeps_nothing_from_the_last() -> None:
    """main() builds the parser once per process (cli._command_parser): a repeated flag, a sub-command's defaults
    and an unknown flag of one call do not reach the next, and the flags are registered for the messages."""
    from trimag.cli import _FLAGS, _command_parser

    parser = _command_parser()
    assert _command_parser() is parser and _FLAGS.get("units") == "--units"
    first, _ = parser.parse_known_args(["fit", "a.csv", "--option", "k=1", "--option", "j=2", "--units", "uT"])
    again, _ = parser.parse_known_args(["fit", "a.csv", "--option", "m=3"])
    assert first.option == ["k=1", "j=2"] and again.option == ["m=3"] and again.units is None
    other, unknown = parser.parse_known_args(["apply", "c.json", "d.csv", "--nonsense"])
    assert other.command == "apply" and unknown == ["--nonsense"] and not hasattr(other, "option")
    assert parser.parse_known_args(["fit", "b.csv"])[0].option is None


# ------------------------------------------------ flags every reading command honours (found in the app-layer split)
LOG = Path(__file__).parent / "data" / "logs" / "ardusub_small.BIN"
CALIBRATIONS = Path(__file__).parent / "data" / "calibrations"


def _calibration_in(unit: str, tmp_path: Path, model: str = "ellipsoid") -> Path:
    """A reference calibration file relabelled to ``unit`` (the numbers do not matter to these tests)."""
    d = json.loads((CALIBRATIONS / f"{model}.json").read_text())
    d["units"] = d["input_unit"] = d["output_unit"] = unit
    out = tmp_path / f"{model}-{unit}.json"
    out.write_text(json.dumps(d))
    return out


def test_evaluate_reads_the_magnetometer_given_by_sensor(tmp_path: Path) -> None:
    """``evaluate --sensor`` read the log's default magnetometer whatever was asked."""
    from trimag.io import read_samples

    cal = _calibration_in("mG", tmp_path)
    for sensor in ("1", "2"):
        r = run_trimag("evaluate", cal, LOG, "--sensor", sensor, "--json")
        assert r.returncode == 0, r.stderr
        expected = np.linalg.norm(read_samples(LOG, sensor=sensor).field, axis=1).mean()
        assert json.loads(r.stdout)["mean_norm_before"] == pytest.approx(expected, rel=1e-12)


def test_sensor_on_a_file_that_is_not_a_log_is_refused(tmp_path: Path) -> None:
    """``--sensor`` on a table was silently ignored (the table has one magnetometer)."""
    data = tmp_path / "d.csv"
    B = simulate_ellipsoid(300, seed=1)
    pd.DataFrame(B, columns=["x", "y", "z"]).to_csv(data, index=False)
    for args in (("fit", data), ("evaluate", _calibration_in("nT", tmp_path), data),
                 ("apply", _calibration_in("nT", tmp_path), data, "-o", tmp_path / "out.csv")):
        r = run_trimag(*args, "--sensor", "1")
        assert r.returncode == 2, (args[0], r.stderr)
        assert r.stderr.count("\n") == 1 and "autopilot log" in r.stderr
    assert not (tmp_path / "out.csv").exists()


def test_strict_refuses_bad_rows_in_evaluate_and_apply(tmp_path: Path) -> None:
    """``evaluate --strict`` and ``apply --strict`` dropped (or passed through) a row with a NaN field."""
    data = tmp_path / "d.csv"
    B = simulate_ellipsoid(300, seed=2)
    B[17, 1] = np.nan
    pd.DataFrame(B, columns=["x", "y", "z"]).to_csv(data, index=False)
    cal = _calibration_in("nT", tmp_path)
    ok = run_trimag("evaluate", cal, data, "--json")
    assert ok.returncode == 0 and json.loads(ok.stdout)["n_dropped"] == 1
    out = tmp_path / "out.csv"
    for args in (("evaluate", cal, data), ("apply", cal, data, "-o", out)):
        r = run_trimag(*args, "--strict")
        assert r.returncode == 2, (args[0], r.stderr)
        assert r.stderr.count("\n") == 1 and "data row 17" in r.stderr
    assert not out.exists()


def test_vector_evaluate_checks_the_unit_given(tmp_path: Path) -> None:
    """The vector evaluation ignored ``--units``: a uT log evaluated with a nT calibration gave numbers."""
    cal = CALIBRATIONS / "interference12.json"
    data = tmp_path / "att.csv"
    rng = np.random.default_rng(3)
    table = pd.DataFrame(rng.normal(size=(50, 3)) * 30_000, columns=["x", "y", "z"])
    table["yaw"], table["pitch"], table["roll"] = rng.uniform(0, 360, 50), rng.uniform(-30, 30, 50), 0.0
    table.to_csv(data, index=False)
    args = ("evaluate", cal, data, "--columns", "x,y,z", "--attitude-columns", "yaw,pitch,roll",
            "--background-ned", "20000,0,45000")
    assert run_trimag(*args).returncode == 0
    r = run_trimag(*args, "--units", "uT")
    assert r.returncode == 2, r.stderr
    assert r.stderr.count("\n") == 1 and "uT" in r.stderr


def test_units_given_with_a_regressor_calibration_are_checked_not_refused(tmp_path: Path) -> None:
    """``apply``/``evaluate --units`` checked the unit by applying the calibration to a zero vector, which a
    calibration with regressor terms refuses (no regressor values): exit 2 for a correct unit."""
    cal = CALIBRATIONS / "ellipsoid-regressors.json"
    data = CALIBRATIONS / "ellipsoid-regressors.in.csv"
    out = tmp_path / "out.csv"
    r = run_trimag("apply", cal, data, "--units", "nT", "-o", out)
    assert r.returncode == 0, r.stderr
    assert run_trimag("evaluate", cal, data, "--units", "nT").returncode == 0
    wrong = run_trimag("evaluate", cal, data, "--units", "uT")
    assert wrong.returncode == 2 and "for data in 'nT'" in wrong.stderr


def test_evaluate_reference_column_with_a_missing_cell_drops_and_counts_the_row(tmp_path: Path) -> None:
    """A blank cell in ``--reference-column`` was an internal error (exit 1), a ``nan`` cell printed RMS nan (and
    ``--json`` exited 1): such a row is now dropped and counted like a bad field row, and ``--strict`` refuses it."""
    B = simulate_ellipsoid(200, seed=4)
    table = pd.DataFrame(B, columns=["x", "y", "z"])
    table["F"] = "48000"
    table.loc[5, "F"] = ""
    table.loc[9, "F"] = "nan"
    data = tmp_path / "d.csv"
    table.to_csv(data, index=False)
    cal = _calibration_in("nT", tmp_path)
    r = run_trimag("evaluate", cal, data, "--reference-column", "F", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["n_dropped"] == 2 and out["n_used"] == 198 and np.isfinite(out["rms_after"])
    strict = run_trimag("evaluate", cal, data, "--reference-column", "F", "--strict")
    assert strict.returncode == 2 and "data row 5" in strict.stderr and strict.stderr.count("\n") == 1


def test_vector_evaluate_counts_each_dropped_row_once(tmp_path: Path) -> None:
    """Rows without an attitude were counted twice in the vector evaluation's ``n_dropped`` (6 for 3 rows)."""
    rng = np.random.default_rng(5)
    table = pd.DataFrame(rng.normal(size=(60, 3)) * 30_000, columns=["x", "y", "z"])
    table["yaw"], table["pitch"], table["roll"] = rng.uniform(0, 360, 60), rng.uniform(-30, 30, 60), 0.0
    table["yaw"] = table["yaw"].astype(object)
    table.loc[[3, 7, 11], "yaw"] = ""
    data = tmp_path / "att.csv"
    table.to_csv(data, index=False)
    r = run_trimag("evaluate", CALIBRATIONS / "interference12.json", data, "--columns", "x,y,z",
                   "--attitude-columns", "yaw,pitch,roll", "--background-ned", "20000,0,45000", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert (out["n_samples"], out["n_used"], out["n_dropped"]) == (60, 57, 3)


@pytest.mark.parametrize("flag", [("--igrf-columns", "lat,lon,alt,2021-01-01"), ("--background-ned", "20000,0,45000"),
                                  ("--background-columns", "x,y,z")])
def test_a_background_vector_for_a_magnitude_model_is_refused(tmp_path: Path, flag: tuple[str, str]) -> None:
    """``--igrf-columns`` (and the other background vectors) were silently ignored by a magnitude fit or
    evaluation: the reference used was the mean magnitude."""
    B = simulate_ellipsoid(300, seed=6)
    table = pd.DataFrame(B, columns=["x", "y", "z"])
    table["lat"], table["lon"], table["alt"] = 52.5, 13.3, 40.0
    data = tmp_path / "d.csv"
    table.to_csv(data, index=False)
    fit = run_trimag("fit", data, "--columns", "x,y,z", "--units", "nT", *flag)
    ev = run_trimag("evaluate", _calibration_in("nT", tmp_path), data, "--columns", "x,y,z", *flag)
    for r in (fit, ev):
        assert r.returncode == 2, r.stderr
        assert r.stderr.count("\n") == 1 and flag[0] in r.stderr and "--igrf " in r.stderr


def test_flags_a_tolles_lawson_file_does_not_use_are_refused(tmp_path: Path) -> None:
    """``apply``/``evaluate`` of a Tolles-Lawson compensation accepted ``--strict``, ``--sensor``, ``--rows``,
    ``--where``, ``--reference`` ... and ignored them (the same output with or without)."""
    comp, data = CALIBRATIONS / "tolles-lawson.json", CALIBRATIONS / "tolles-lawson.in.csv"
    out = tmp_path / "o.csv"
    assert run_trimag("apply", comp, data, "-o", out).returncode == 0
    out.unlink()
    for args in (("apply", comp, data, "-o", out, "--strict"), ("apply", comp, data, "-o", out, "--sensor", "1"),
                 ("evaluate", comp, data, "--rows", "0:300"), ("evaluate", comp, data, "--reference", "50500"),
                 ("evaluate", comp, data, "--chunk-rows", "1000")):
        r = run_trimag(*args)
        assert r.returncode == 2, (args, r.stderr)
        assert r.stderr.count("\n") == 1 and "is not used with a Tolles-Lawson compensation file" in r.stderr
        assert "`" not in r.stderr  # the flag is named as a flag
    assert not out.exists()


def test_strict_covers_attitude_and_heading_cells(tmp_path: Path) -> None:
    """``--strict`` refused bad field cells only: a blank yaw (vector fit and evaluation) or a blank reference
    heading was still skipped and counted."""
    rng = np.random.default_rng(8)
    table = pd.DataFrame(rng.normal(size=(80, 3)) * 30_000, columns=["x", "y", "z"])
    table["yaw"], table["pitch"], table["roll"] = rng.uniform(0, 360, 80), rng.uniform(-30, 30, 80), 0.0
    table["ax"], table["ay"], table["az"] = 0.0, 0.0, -9.81
    table["heading"] = table["yaw"]
    table["yaw"], table["heading"] = table["yaw"].astype(object), table["heading"].astype(object)
    table.loc[4, "yaw"] = ""
    table.loc[6, "heading"] = ""
    data = tmp_path / "att.csv"
    table.to_csv(data, index=False)
    vector = ("--columns", "x,y,z", "--attitude-columns", "yaw,pitch,roll", "--background-ned", "20000,0,45000")
    cal = CALIBRATIONS / "interference12.json"
    runs = [run_trimag("evaluate", cal, data, *vector, "--strict"),
            run_trimag("fit", data, "--model", "interference12", *vector, "--units", "nT", "--strict"),
            run_trimag("evaluate", _calibration_in("nT", tmp_path), data, "--columns", "x,y,z", "--accel-columns",
                       "ax,ay,az", "--heading-column", "heading", "--strict")]
    for r in runs:
        assert r.returncode == 2, r.stderr
        assert r.stderr.count("\n") == 1 and "drop --strict" in r.stderr
    assert run_trimag("evaluate", cal, data, *vector).returncode == 0  # without it: skipped and counted


def test_messages_name_flags_and_the_numbers_the_user_gave(tmp_path: Path) -> None:
    """Three messages named a Python argument or an internal value: ``export --instance 0`` said "got -1", an
    unknown ``--sensor`` said "choose with sensor", a missing policy file said "use policy 'default'"."""
    r = run_trimag("export", CALIBRATIONS / "ellipsoid.json", "--to", "json", "--instance", "0", "-o", tmp_path / "x")
    assert r.returncode == 2 and "--instance must be 1..8" in r.stderr and "got 0" in r.stderr
    r = run_trimag("fit", LOG, "--sensor", "7")
    assert r.returncode == 2 and "choose with --sensor" in r.stderr
    r = run_trimag("fit", CALIBRATIONS / "ellipsoid.in.csv", "--policy", tmp_path / "nope.toml")
    assert r.returncode == 2 and "--policy default" in r.stderr


def test_simulate_refuses_a_bad_unit_before_writing_anything(tmp_path: Path) -> None:
    """``simulate --units bogus`` exited 2 but left the simulated log on disk (it was written before the unit was
    read)."""
    params = tmp_path / "p.json"
    params.write_text(json.dumps({"hard_iron_x": 10.0, "hard_iron_y": 0.0, "hard_iron_z": 0.0, "w11": 1.0, "w12": 0.0,
                                  "w13": 0.0, "w21": 0.0, "w22": 1.0, "w23": 0.0, "w31": 0.0, "w32": 0.0, "w33": 1.0}))
    out, truth = tmp_path / "s.csv", tmp_path / "t.json"
    assert run_trimag("simulate", "--model", "ellipsoid", "--params", params, "--n", "50", "-o", out).returncode == 0
    out.unlink()
    r = run_trimag("simulate", "--model", "ellipsoid", "--params", params, "--n", "50", "-o", out, "--truth", truth,
                   "--units", "bogus")
    assert r.returncode == 2 and r.stderr.count("\n") == 1
    assert not out.exists() and not truth.exists()
    folder = tmp_path / "a-file"
    folder.write_text("")
    r = run_trimag("simulate", "--model", "ellipsoid", "--params", params, "--n", "50", "-o", out, "--truth",
                   folder / "t.json")
    assert r.returncode == 2 and not out.exists()


def test_apply_and_export_without_o_write_beside_the_input_under_a_stated_name(tmp_path, ellipsoid_log):
    """`apply`/`export` without `-o` exited 2 (issue 42, item 6): the output goes beside the input, named from it and
    said on stderr; a file of that name is never replaced, and the input never."""
    cal = tmp_path / "cal.json"
    assert run_trimag("fit", ellipsoid_log, "--units", "nT", "-o", cal).returncode == 0
    before = cal.read_bytes(), ellipsoid_log.read_bytes()
    r = run_trimag("apply", cal, ellipsoid_log)
    corrected = tmp_path / "log-corrected.csv"
    assert r.returncode == 0 and corrected.is_file() and "log-corrected.csv" in r.stderr, r.stderr
    assert "bx_cal" in corrected.read_text().splitlines()[0]
    again = run_trimag("apply", cal, ellipsoid_log)
    assert again.returncode == 2 and "already exists" in again.stderr and "-o" in again.stderr, again.stderr
    assert len(again.stderr.strip().splitlines()) == 1
    for target, name in (("ardupilot", "cal.param"), ("px4", "cal.params"), ("json", "cal-export.json")):
        r = run_trimag("export", cal, "--to", target)
        assert r.returncode == 0 and (tmp_path / name).is_file() and name in r.stderr, (target, r.stderr)
    assert (cal.read_bytes(), ellipsoid_log.read_bytes()) == before
