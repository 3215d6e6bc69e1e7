"""What a user sees with an early PX4 ULog whose only magnetometer is ``sensor_combined.magnetometer_ga`` (issue 30:
every real log gives parameters or a refusal naming what to record, never "no magnetometer"). The log
(``tests/data/logs/pyulog_sample_head.ulg``, the first 5.9 s of pyulog's ``test/sample.ulg``) has attitudes, no GPS
fix, and turned little (roll +-22 deg, pitch +-9, yaw -48..-20)."""

from __future__ import annotations

from pathlib import Path

from _helpers import TESTS_DIR, refusal_text, run_trimag

HEAD = TESTS_DIR / "data" / "logs" / "pyulog_sample_head.ulg"
#: somewhere the user says they flew (the log has no fix): Zurich, the log's year
IGRF = "47.4,8.5,500,2016-06-01"


def _error_lines(stderr: str) -> list[str]:
    """The refusal in stderr, if any: its verdict line and the indented detail lines under it, as one text
    (docs/cli.md, "Errors"); warnings left out."""
    assert "Traceback" not in stderr
    assert "no sensor_mag or vehicle_magnetometer" not in stderr and "no magnetometer" not in stderr, stderr
    if not any(line.startswith("trimag: ") and not line.startswith("trimag: warning") for line in stderr.splitlines()):
        return []
    return [refusal_text(stderr, max_verdict=None)]


def test_fit_refuses_with_what_to_record_and_names_the_compass(tmp_path: Path) -> None:
    out = tmp_path / "cal.json"
    r = run_trimag("fit", HEAD, "-o", out)
    assert r.returncode == 3, r.stderr
    (line,) = _error_lines(r.stderr)
    assert "1 (sensor_combined)" in line, line
    assert any(w in line for w in ("rotate the vehicle", "turn the vehicle", "pitched")), line
    assert not out.exists()


def test_target_px4_without_a_gps_fix_asks_for_the_field() -> None:
    r = run_trimag("fit", HEAD, "--target", "px4")
    assert r.returncode == 2, r.stderr
    (line,) = _error_lines(r.stderr)
    assert "GPS fix" in line and "--igrf" in line and "--reference" in line, line


def test_target_px4_with_igrf_says_the_readings_are_rotated_and_export_refuses(tmp_path: Path) -> None:
    """The readings are PX4's calibrated, rotated output (before v1.12): the fit flags them, as for an sdlog2 log,
    and export will not write their orientation and offsets as the firmware's parameters."""
    cal = tmp_path / "px4.json"
    r = run_trimag("fit", HEAD, "--target", "px4", "--igrf", IGRF, "-o", cal)
    assert r.returncode == 0, r.stderr
    assert not _error_lines(r.stderr)
    warning = next(line for line in r.stderr.splitlines() if line.startswith("trimag: warning") and "v1.12" in line)
    assert "SENS_BOARD_ROT" in warning and "rotated" in warning, warning
    # 2016's sensors.cpp rotated the driver's calibrated report: after its offsets and scales (sdlog2's drivers: before)
    assert "after their offsets and scales" in warning, warning
    out = tmp_path / "px4.params"
    e = run_trimag("export", cal, "--to", "px4", "-o", out)
    assert e.returncode == 2, e.stderr
    assert len(e.stderr.strip().splitlines()) == 1 and "v1.12" in e.stderr, e.stderr
    assert not out.exists()


def test_a_refused_target_fit_does_not_ask_for_the_options_it_was_given() -> None:
    """The whole sample.ulg (and these 100 readings) with --target px4 --igrf: the log's calibration fits better than
    any level, exit 3, "record the vehicle turning ..." (since issue 38: the 100 readings never turned, so the
    offsets are not excited: "record a calibration turn through all headings"). The refusal went on "From an
    ordinary flight, --target px4 fits ... (this log has no GPS fix: add --igrf ...)": both were given."""
    r = run_trimag("fit", HEAD, "--target", "px4", "--igrf", IGRF, "--rows", "0:100")
    assert r.returncode == 3, r.stderr
    (line,) = _error_lines(r.stderr)
    assert "1 (sensor_combined)" in line and "turn through all headings" in line, line  # issue 38: not excited
    assert "--target px4 fits" not in line and "add --igrf" not in line, line


def test_a_refusal_with_igrf_given_offers_target_without_asking_for_igrf() -> None:
    r = run_trimag("fit", HEAD, "--igrf", IGRF)
    assert r.returncode == 3, r.stderr
    (line,) = _error_lines(r.stderr)
    assert "--target px4 fits" in line and "add --igrf" not in line, line


def test_target_px4_with_the_right_magnitude_is_not_called_a_wrong_unit() -> None:
    """Following the no-fix refusal's advice with the right magnitude (`--reference 0.48`, the log's own |B| under its
    calibration) gave exit 2 "the data's field is 0.332x the reference field (0.1594 against 0.48 G) ... the reference
    or the data's unit is wrong": the sphere through readings that span a 25 deg cap has no defined radius. The
    log's calibration puts them at 0.48 G: the reference is not contradicted."""
    r = run_trimag("fit", HEAD, "--target", "px4", "--reference", "0.48")
    assert "unit is wrong" not in r.stderr, r.stderr
    assert r.returncode in (0, 3), r.stderr
    if r.returncode == 3:
        (line,) = _error_lines(r.stderr)
        assert "record" in line, line
