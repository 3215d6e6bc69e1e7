"""The flight review's application layer (issue 40, :class:`trimag.app.review.FlightReview`): it fits with the
command line's own fit and says what it cannot fit; the yaw source the user chooses (``fit --yaw-source``)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from test_firmware_fit import _write_log

from trimag.app.review import FlightReview
from trimag.errors import TrimagInputError

from _helpers import run_trimag

pytest.importorskip("pymavlink")


def test_the_yaw_source_is_the_users_choice_where_the_log_has_several(tmp_path: Path) -> None:
    log = _write_log(tmp_path / "gsf.bin", n=900, seed=6, gsf=True)
    review = FlightReview(log)
    assert review.yaw_sources() == ["auto", "attitude", "gsf"]
    auto = review.fit(level="offsets", compasses=[1])[1]
    assert auto.error is None and any("EKF-GSF" in m for m in auto.messages)
    assert auto.calibration is not None and auto.calibration.diagnostics["firmware"]["residual"] == "vector"
    att = review.fit(level="offsets", yaw_source="attitude", compasses=[1])[1]
    assert att.calibration is not None and att.calibration.diagnostics["firmware"]["residual"] == "heading-free"
    assert "--yaw-source attitude" in att.command
    with pytest.raises(TrimagInputError, match="yaw_source"):
        review.fit(yaw_source="gps")
    r = run_trimag("fit", log, "--target", "ardupilot", "--yaw-source", "gps")
    assert r.returncode == 2 and "no GPS heading" in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    r = run_trimag("fit", log, "--yaw-source", "attitude", "--level", "offsets", "--json")  # --target from the log
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["firmware"]["residual"] == "heading-free"


def test_the_range_is_the_command_lines_rows_and_the_rest_is_held_out(tmp_path: Path) -> None:
    log = _write_log(tmp_path / "flight.bin", n=900, seed=7)
    review = FlightReview(log)
    lo, hi = review.span_s
    result = review.fit(lo + 20.0, hi - 20.0, level="offsets", compasses=[1])[1]
    assert result.rows == "200:700" and "--rows 200:700" in result.command  # 10 Hz: 10.0 + 20 s .. 99.9 - 20 s
    stats = review.compass_result(1)["statistics"]
    assert stats["fitted_rows"] == 500 and stats["held_out_rows"] == 400
    assert stats["candidate_held_out_rms"] < stats["logged_held_out_rms"]
    with pytest.raises(TrimagInputError, match="forward in time"):
        review.fit(hi, lo)


def test_a_table_with_attitudes_is_reviewed_as_the_command_line_fits_it(tmp_path: Path) -> None:
    """Issue 40: review takes "any log trimag reads: ... CSV with attitudes". A CSV of a flight (time, the raw
    field, yaw/pitch/roll, current) is one compass: the flight, the expected field, the fit of a dragged range with
    the rest held out, exactly `trimag fit FILE --units mG --attitude-columns yaw,pitch,roll --target ardupilot
    --igrf SITE --rows A:B`. Without --target, --units or --igrf the page shows what it can and says what is not
    available; a table without attitudes is shown too (a magnitude fit)."""
    import numpy as np
    import pandas as pd

    from trimag.io import read_samples
    from trimag.io.logs import read_log

    log = _write_log(tmp_path / "flight.bin", n=900, seed=7)
    s = read_samples(log, sensor="1")
    t = s.table
    csv = tmp_path / "flight.csv"
    pd.DataFrame({"time_s": t["time_s"], "x": s.field[:, 0], "y": s.field[:, 1], "z": s.field[:, 2],
                  "yaw": t["yaw_deg"], "pitch": t["pitch_deg"], "roll": t["roll_deg"],
                  "current": t["current_A"]}).to_csv(csv, index=False)
    gps = read_log(log).gps
    assert gps is not None
    site = f"{gps['lat_deg']:.6f},{gps['lon_deg']:.6f},{gps['alt_m']:.1f},{gps['date']}"
    review = FlightReview(csv, target="ardupilot", units="mG", igrf_spec=site)
    overview = review.overview()
    assert overview["table"] and overview["unavailable"] == [] and len(overview["compasses"]) == 1
    names = [tr["name"] for tr in overview["flight"]["data"]]
    assert any("yaw,pitch,roll" in n for n in names) and any(n.startswith("current_A (current)") for n in names)
    lo, hi = review.span_s
    result = review.fit(lo + 20.0, hi - 20.0, level="offsets")[1]
    assert result.calibration is not None, result.error
    assert result.rows == "200:700" and "--attitude-columns yaw,pitch,roll" in result.command
    assert "--units mG" in result.command and "--target ardupilot" in result.command
    out = review.compass_result(1)
    assert out["statistics"]["held_out_rows"] == 400
    assert out["statistics"]["candidate_held_out_rms"] < out["statistics"]["logged_held_out_rms"]
    assert any("expected" in tr["name"] for tr in out["figures"]["field"]["data"])
    cli = tmp_path / "cli.json"
    r = run_trimag(*result.command.split()[1:-2], "-o", cli)
    assert r.returncode == 0, r.stderr
    assert json.loads(cli.read_text())["diagnostics"]["firmware"]["offsets"] == \
        result.calibration.diagnostics["firmware"]["offsets"]
    report = tmp_path / "table.html"  # the same figures in one file, for a table too
    r = run_trimag(*result.command.split()[1:-2], "--report", report, "-q")
    assert r.returncode == 0, r.stderr
    html = report.read_text()
    assert 'id="compass1-field"' in html.replace("'", '"') and "the readings as recorded" in html
    bare = FlightReview(csv)  # no --target, --units, --igrf: shown, and said
    said = " ".join(bare.unavailable())
    assert "--target" in said and "--units" in said and "--igrf" in said, said
    refused = bare.fit()[1]
    assert refused.calibration is None and refused.exit_code == 2 and "--target" in str(refused.error)
    assert bare.compass_result(1)["verdict"].startswith("not fitted: ")  # not the data's refusal
    assert bare.compass_result(1)["figures"]["field"]["data"]  # the readings, drawn
    plain = tmp_path / "plain.csv"
    plain.write_text("x,y,z\n" + "".join(f"{np.cos(k / 9):.4f},{np.sin(k / 9):.4f},0.3\n" for k in range(40)))
    no_attitude = FlightReview(plain, target="px4", units="G", igrf_spec=site)
    assert any("no attitude" in line and "row number" not in line for line in no_attitude.unavailable())
    assert any("row number" in line for line in no_attitude.unavailable())
    with pytest.raises(TrimagInputError, match="no column 'hdg'"):
        FlightReview(csv, attitude_columns="hdg,pitch,roll")


def test_a_flights_png_report_draws_the_field_against_time(tmp_path: Path) -> None:
    """The lab report draws |B| against the sample number; a flight's, against the log's time (s)."""
    from trimag.io import read_samples
    from trimag.quality.report import fit_report

    log = _write_log(tmp_path / "flight.bin", n=300, seed=8)
    samples = read_samples(log, sensor="1")
    cal = FlightReview(log).fit(level="offsets", compasses=[1])[1].calibration
    assert cal is not None
    plain = cal.__class__.from_json(cal.to_json())
    shifted = samples.field - plain.regressor_shift({"current_A": samples.table["current_A"].to_numpy()},
                                                    samples.field.shape) if plain.regressors else samples.field
    import dataclasses

    shown = dataclasses.replace(plain, regressors=None)
    t = samples.table["time_s"].to_numpy()
    axis = fit_report(shifted, shown, time_s=t).axes[0]
    assert axis.get_xlabel() == "time (s)" and axis.get_xlim()[1] > 30.0  # seconds from the log's start (10 s)
    assert fit_report(shifted, shown).axes[0].get_xlabel() == "sample"
    with pytest.raises(TrimagInputError, match="time stamp per sample"):
        fit_report(shifted, shown, time_s=t[:-1])


def test_each_levels_candidate_is_drawn_beside_the_chosen_one(tmp_path: Path) -> None:
    """Issue 40: expected against measured "for the log's calibration and each candidate calibration": every row of
    the level table is drawn (the ones not chosen in the legend, a click away), the chosen one marked; the chosen
    row's candidate is exactly the calibration's own field."""
    import numpy as np

    from trimag.app.review import report_html
    from trimag.vehicle.firmware import candidate_field

    log = _write_log(tmp_path / "flight.bin", n=900, seed=7)
    review = FlightReview(log)
    result = review.fit(compasses=[1])[1]
    cal = result.calibration
    assert cal is not None
    rows = cal.diagnostics["firmware"]["levels"]
    assert len(rows) >= 3 and sum(r["chosen"] for r in rows) == 1
    judged = review.judged(1)
    assert [lv["label"] for lv in judged["levels"]] == [r["level"] + (f" + {r['motor']}" if r["motor"] else "")
                                                         for r in rows]
    chosen = next(lv for lv in judged["levels"] if lv["chosen"])
    assert np.allclose(chosen["field"], judged["candidate"], atol=1e-9 * np.abs(judged["candidate"]).max())
    others = [lv for lv in judged["levels"] if not lv["chosen"]]
    assert any(not np.allclose(lv["field"], judged["candidate"]) for lv in others)
    out = review.compass_result(1)
    for name in ("field", "magnitude", "heading"):
        traces = out["figures"][name]["data"]
        drawn = [t["name"] for t in traces if t.get("showlegend", True)]
        assert sum("(chosen)" in n for n in drawn) <= 1
        for lv in others:
            assert any(lv["label"] in n and t.get("visible") == "legendonly" for t in traces
                       for n in [t["name"]]), (name, lv["label"], drawn)
    assert any("(chosen)" in t["name"] for t in out["figures"]["field"]["data"])
    assert len(out["statistics"]["levels"]) == len(rows)
    html = report_html(review, [1])
    assert all(f"candidate: {lv['label']}" in html for lv in others)
    vector = [f"{v['fitted_rms']:.4g}" for v in out["statistics"]["levels"]]  # the whole flight: none held out
    assert len(set(vector)) > 1 and all(f"<td>{v}</td>" in html for v in vector)  # in the levels table
    with pytest.raises(TrimagInputError, match="motor channel"):
        spec = next(r["compass"] for r in rows if r["compass"]["motor_type"])
        candidate_field(spec, np.zeros((2, 3)), "mG")



def test_the_dcm_attitude_and_the_altitude_are_shown_and_the_dcm_is_a_choice_the_cli_fits_too(tmp_path: Path) -> None:
    """Issue 40: "choose the attitude source where the log has several (EKF, DCM/AHR2, GSF yaw)" and the flight's
    altitude. A DataFlash log with AHR2 and BARO: the flight draws both; `dcm` is offered, and the page's fit with it
    is the command line's `fit --yaw-source dcm` (roll, pitch and yaw from AHR2, heading-free: DCM's yaw fuses the
    compass). A log without AHR2 refuses `--yaw-source dcm` in one line."""
    from trimag.io.logs import read_log

    log = _write_log(tmp_path / "dcm.bin", n=900, seed=6, dcm=True)
    vehicle = read_log(log)
    assert "AHR2" in vehicle.attitudes and vehicle.altitude is not None
    assert vehicle.altitude.source.startswith("BARO.Alt") and 9.0 < float(vehicle.altitude.values.max()) - 20.0 <= 10.0
    review = FlightReview(log)
    assert review.yaw_sources() == ["auto", "attitude", "dcm"]
    overview = review.overview()
    names = [t["name"] for t in overview["flight"]["data"]]
    assert any("AHR2" in n for n in names) and any(n.startswith("altitude (BARO.Alt") for n in names), names
    titles = [v["title"]["text"] for k, v in overview["flight"]["layout"].items() if k.startswith("yaxis")]
    assert "altitude (m)" in titles, titles
    dcm = review.fit(level="offsets", yaw_source="dcm", compasses=[1])[1]
    assert dcm.calibration is not None, dcm.error
    assert any("AHR2" in m and "yaw_source=dcm" in m for m in dcm.messages), dcm.messages
    assert any("DCM's, which fuses" in m for m in dcm.messages)
    assert dcm.calibration.diagnostics["firmware"]["residual"] == "heading-free"
    assert "--yaw-source dcm" in dcm.command
    assert "AHR2" in review.compass_result(1)["figures"]["heading"]["layout"]["title"]["text"]
    out = tmp_path / "cli.json"
    words = dcm.command.split()
    r = run_trimag(*words[1:-2], "-o", out)
    assert r.returncode == 0, r.stderr
    cli = json.loads(out.read_text())["diagnostics"]["firmware"]
    page = dcm.calibration.diagnostics["firmware"]
    assert cli["offsets"] == page["offsets"] and cli["residual"] == "heading-free"
    ekf = review.fit(level="offsets", yaw_source="attitude", compasses=[1])[1].calibration
    assert ekf is not None and ekf.diagnostics["firmware"]["offsets"] != page["offsets"]  # another attitude
    plain = _write_log(tmp_path / "plain.bin", n=300, seed=6)
    r = run_trimag("fit", plain, "--target", "ardupilot", "--yaw-source", "dcm")
    assert r.returncode == 2 and "no DCM attitude" in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "dcm" not in FlightReview(plain).yaw_sources()


def test_the_figures_use_the_attitude_the_fit_used(tmp_path: Path) -> None:
    """Issue 40: "expected (IGRF rotated by the attitude, with the board trim) against measured" and "choose the
    attitude source where the log has several". A log with an EKF-GSF yaw (XKY0) and a GPS heading (GPS.Yaw) and a
    board trim: whichever yaw the fit takes (gsf as asked; auto, which takes the GPS heading here), the figures'
    expected field is the IGRF field rotated by that yaw with the logged roll and pitch and the trim, not by the
    EKF's attitude; the vector RMS is measured against it, and the page and the HTML report (`fit --report`) say
    which attitude the figures use."""
    import numpy as np

    from trimag.app import fit_file
    from trimag.fields.attitude import body_field, from_euler
    from trimag.fields.reference import igrf
    from trimag.io import read_samples
    from trimag.io.logs import read_log

    trim = {"AHRS_TRIM_X": 0.02, "AHRS_TRIM_Y": -0.015, "AHRS_TRIM_Z": 0.0}
    log = _write_log(tmp_path / "yaws.bin", n=600, seed=6, gsf=True, gps_yaw=True, parameters=trim)
    table = read_samples(log, sensor="1").table
    gps = read_log(log).gps
    assert gps is not None
    ned = np.asarray(igrf(gps["lat_deg"], gps["lon_deg"], gps["alt_m"], gps["date"]).ned_nT) / 100.0  # mG

    def rotated_by(yaw_column: str) -> np.ndarray:
        rotation = from_euler(table[yaw_column].to_numpy() + np.degrees(trim["AHRS_TRIM_Z"]),
                              table["pitch_deg"].to_numpy() + np.degrees(trim["AHRS_TRIM_Y"]),
                              table["roll_deg"].to_numpy() + np.degrees(trim["AHRS_TRIM_X"]))
        return np.asarray(body_field(rotation, ned))

    review = FlightReview(log)
    assert review.yaw_sources() == ["auto", "attitude", "gsf", "gps"]
    ekf = rotated_by("yaw_deg")
    for choice, column, name in (("gsf", "yaw_gsf_deg", "XKY0.YC"), ("auto", "yaw_gps_deg", "GPS.Yaw")):
        result = review.fit(level="offsets", yaw_source=choice, compasses=[1])[1]
        assert result.calibration is not None, result.error
        judged = review.judged(1)
        shown = np.isfinite(judged["expected"]).all(axis=1)
        assert shown.mean() > 0.95, (choice, shown.mean())
        want = rotated_by(column)
        assert np.allclose(judged["expected"][shown], want[shown], atol=1e-6), choice
        assert np.abs(judged["expected"][shown] - ekf[shown]).max() > 5.0, choice  # not the EKF's attitude
        candidate = judged["candidate"]
        err = np.linalg.norm(candidate - want, axis=1)[shown]
        stats = review.compass_result(1)["statistics"]
        assert stats["candidate_fitted_rms"] == pytest.approx(np.sqrt(np.mean(err ** 2)), rel=1e-9), choice
        page = review.compass_result(1)
        title = page["figures"]["field"]["layout"]["title"]["text"]
        assert name in page["attitude"] and name in title, (page["attitude"], title)
    report = tmp_path / "gsf.html"
    lo, hi = review.span_s
    fit_file(review.request(1, lo, hi, "offsets", "auto", "gsf", report=report))
    html = report.read_text()
    figures = json.loads(html.split('<script id="figures" type="application/json">')[1].split("</script>")[0])
    expected = [tr for tr in figures["compass1-field"]["data"] if tr["legendgroup"] == "expected"]
    x = np.array([[np.nan if v is None else v for v in tr["y"]] for tr in expected]).T  # all 600 rows are drawn
    shown = np.isfinite(x).all(axis=1)
    assert shown.mean() > 0.95 and np.allclose(x[shown], rotated_by("yaw_gsf_deg")[shown], atol=1e-4)
    assert "XKY0.YC" in html.split("<h2>compass 1</h2>")[1].split("<pre>")[0]  # said beside the verdict
