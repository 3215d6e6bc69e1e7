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


def test_a_table_is_not_a_flight(tmp_path: Path) -> None:
    table = tmp_path / "t.csv"
    table.write_text("x,y,z\n1,2,3\n")
    with pytest.raises(TrimagInputError, match="autopilot log"):
        FlightReview(table)


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
