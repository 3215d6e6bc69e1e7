"""``trimag review`` (issue 40) in a real browser: headless Chromium (the distribution's package) driven by Selenium
loads the page of a flight log, drags a range across the flight, changes the level, refits and downloads the
parameter file and the calibration JSON; the downloads are compared byte for byte with ``trimag export`` of the same
fit, and the parameters with those of the command line the page shows. The HTML report of ``fit --report
report.html`` is opened with every host unresolvable and holds every figure.

The flight is a simulated ArduCopter flight written as a DataFlash log (tests/app/test_firmware_fit.py: two
compasses, a current term, a wrong orientation in the log's parameters) and the same kind of flight written as a
PX4 ULog; the real logs of ``tests/data/logs`` (copies of the shared ardusub_small.BIN and pyulog's sample) barely
moved: their pages show the compasses and the refusal, and offer no parameters.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from _live_helpers import chrome

from _helpers import TESTS_DIR, restore_sigint, run_trimag

pytest.importorskip("plotly", reason="plotly (the review extra) is not installed")
pytest.importorskip("pymavlink", reason="pymavlink (the logs extra) is not installed")

pytestmark = pytest.mark.slow
LOGS = TESTS_DIR / "data" / "logs"


@pytest.fixture(scope="module")
def flight_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The simulated two-compass DataFlash flight, written once for the module (its AHR2 and BARO too)."""
    sys.path.insert(0, str(TESTS_DIR / "app"))
    from test_firmware_fit import _write_log

    return _write_log(tmp_path_factory.mktemp("flight") / "flight.bin", n=800, seed=4, second=True, dcm=True)


@pytest.fixture(scope="module")
def browser(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    """One headless Chromium for the module (a start costs seconds), with no network at all but the loopback: every
    host name is unresolvable, so the page and the report can fetch nothing."""
    driver = chrome(tmp_path_factory.mktemp("profile"), "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1")
    yield driver
    driver.quit()


def start_review(*args: str, cwd: Path) -> tuple[subprocess.Popen, str]:
    """``trimag review ARGS --no-browser --port 0`` in a subprocess; returns it and the page's address."""
    env = {**os.environ, "MPLBACKEND": "Agg"}
    proc = subprocess.Popen([sys.executable, "-m", "trimag", "review", *args, "--no-browser", "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=cwd, env=env,
                            preexec_fn=restore_sigint)
    assert proc.stdout is not None
    first = proc.stdout.readline()
    if "http://127.0.0.1:" not in first:
        proc.kill()
        raise AssertionError(f"no address printed: {first!r} {proc.stderr.read() if proc.stderr else ''}")
    return proc, first.split("the page is at ")[1].split()[0]


def _stop(proc: subprocess.Popen) -> None:
    proc.send_signal(signal.SIGINT)
    _out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert "Traceback" not in err, err


def _wait_fits(driver, n: int, seconds: float = 240.0) -> None:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if driver.execute_script("return document.body.dataset.fits") == str(n):
            return
        time.sleep(0.2)
    raise AssertionError(f"the page did not show fit {n}: {driver.find_element('id', 'progress').text!r} "
                         f"{driver.find_element('id', 'error').text!r}")


def _download(driver, link_id: str, folder: Path, suffix: str) -> Path:  # type: ignore[no-untyped-def]
    before = set(folder.glob(f"*{suffix}"))
    driver.find_element("id", link_id).click()
    for _ in range(300):
        new = [p for p in set(folder.glob(f"*{suffix}")) - before if p.stat().st_size > 0]
        if new:  # Chromium writes NAME.crdownload and renames it when it is complete: NAME is the whole file
            size = new[0].stat().st_size
            time.sleep(0.05)
            if new[0].stat().st_size == size:
                return new[0]
            continue
        time.sleep(0.1)
    raise AssertionError(f"{link_id} downloaded nothing into {folder}")


def _drag_across_flight(driver, start: float, stop: float) -> None:  # type: ignore[no-untyped-def]
    """Press on the flight's top panel at ``start`` of its width, move to ``stop``, release (Plotly zooms)."""
    from selenium.webdriver.common.action_chains import ActionChains

    area = driver.find_elements("css selector", "#flight .nsewdrag")[0]
    width = area.size["width"]
    chain = ActionChains(driver, duration=20)  # Selenium's default is 250 ms per pointer move: 3 s for this drag
    chain.move_to_element_with_offset(area, int(-width / 2 + start * width), 0).click_and_hold()
    for _k in range(1, 11):
        chain.move_by_offset(int((stop - start) * width / 10), 0)
    chain.release().perform()


def _parameter_lines(text: str) -> list[str]:
    return [line for line in text.splitlines() if line and not line.startswith("#")]


def serve_review(log: Path, **options: Any):  # type: ignore[no-untyped-def]
    """The review server of ``log`` (``options``: :class:`~trimag.app.review.FlightReview`'s) in this process, as
    ``run_review`` serves it (read with the page's progress, then the whole flight fitted): no second Python to start
    (the command itself: the static log's test)."""
    from trimag.app.review import FlightReview
    from trimag.live.review import ReviewServer

    server = ReviewServer(None, 0).start()
    server.read(lambda progress: FlightReview(log, progress=progress, **options))
    server.start_fit({})
    return server


def _review_fit_and_download(driver, tmp_path: Path, log: Path, target: str,  # type: ignore[no-untyped-def]
                             kinds: tuple[str, ...]) -> Any:
    """The page of ``log``: drag, level, refit, download ``kinds`` and the JSON; compare with the command line.
    Returns the review the server answered from."""
    downloads = tmp_path / "downloads"
    downloads.mkdir()
    server = serve_review(log)
    url = server.url
    try:
        driver.execute_cdp_cmd("Browser.setDownloadBehavior", {"behavior": "allow", "downloadPath": str(downloads)})
        driver.get(url)
        _wait_fits(driver, 1)  # the whole flight, fitted as the page opens
        span = json.loads(urllib.request.urlopen(url + "overview", timeout=30).read())["span_s"]
        _drag_across_flight(driver, 0.25, 0.8)
        start = float(driver.find_element("id", "start").get_attribute("value"))
        stop = float(driver.find_element("id", "stop").get_attribute("value"))
        assert span[0] + 0.1 * (span[1] - span[0]) < start < stop < span[1] - 0.05 * (span[1] - span[0]), \
            (start, stop, span)
        from selenium.webdriver.support.ui import Select

        Select(driver.find_element("id", "level")).select_by_visible_text("offsets")
        driver.find_element("id", "fit").click()
        _wait_fits(driver, 2)
        results = json.loads(urllib.request.urlopen(url + "results", timeout=30).read())
        assert results["choice"]["level"] == "offsets" and results["choice"]["start_s"] == pytest.approx(start)
        first = results["compasses"][0]
        assert first["error"] is None and first["level"] == "offsets", first["verdict"]
        assert first["statistics"]["held_out_rows"] > 0  # the rows outside the range are judged
        assert "level offsets" in driver.find_element("id", "compass-1").text
        said = driver.find_element("css selector", "#compass-1 .figure-attitude").text  # the figures' attitude
        assert said == f"attitude of the figures (the fit's): {first['attitude']}" and first["attitude"], said
        for name in ("field", "magnitude", "heading"):
            assert driver.execute_script(f"return document.querySelectorAll('#fig-1-{name} .main-svg').length") > 0
        legend = driver.execute_script(
            "return [...document.querySelectorAll('#fig-1-field .legendtext')].map((e) => e.textContent)")
        assert any("(chosen)" in n for n in legend), legend  # the chosen candidate and the others, a click away
        assert any(n.startswith("candidate: ") for n in legend) or len(first["levels"]) == 1, legend
        cal_json = _download(driver, "dl-json-1", downloads, ".json")
        suffixes = {"ardupilot": ".param", "qgc": ".params", "px4": ".txt"}
        files = {kind: _download(driver, f"dl-{kind}-1", downloads, suffixes[kind]) for kind in kinds}
        # byte for byte: `trimag export` of the downloaded calibration writes the downloaded parameter file
        for kind, path in files.items():
            exported = tmp_path / f"exported-{kind}"
            r = run_trimag("export", cal_json, "--to", kind, "-o", exported)
            assert r.returncode == 0, r.stderr
            assert exported.read_bytes() == path.read_bytes(), kind
        # the same fit on the command line (the page's own command): the same parameters
        command = first["command"].split()
        assert command[:2] == ["trimag", "fit"] and "--level" in command and "--rows" in command
        cli_cal = tmp_path / "cli.json"
        r = run_trimag(*command[1:-2], "-o", cli_cal)
        assert r.returncode == 0, r.stderr
        for kind, path in files.items():
            cli_param = tmp_path / f"cli-{kind}"
            assert run_trimag("export", cli_cal, "--to", kind, "-o", cli_param).returncode == 0
            assert _parameter_lines(cli_param.read_text()) == _parameter_lines(path.read_text()), kind
        if os.environ.get("TRIMAG_REVIEW_SCREENSHOTS"):
            driver.set_window_size(1400, 2400)
            driver.save_screenshot(os.environ["TRIMAG_REVIEW_SCREENSHOTS"] + f"/review-{log.stem}.png")
        return server.review
    finally:
        server.shutdown()


def test_the_review_page_of_a_dataflash_flight_in_a_real_browser(browser, flight_log: Path,  # type: ignore[no-untyped-def]
                                                                  tmp_path: Path) -> None:
    _review_fit_and_download(browser, tmp_path, flight_log, "ardupilot", ("ardupilot",))
    from selenium.webdriver.support.ui import Select

    sources = [o.get_attribute("value") for o in Select(browser.find_element("id", "yaw")).options]
    assert sources == ["auto", "attitude", "dcm"], sources  # the DCM (AHR2) beside the EKF
    flight = browser.execute_script(
        "return [...document.querySelectorAll('#flight .legendtext')].map((e) => e.textContent)")
    assert any("AHR2" in n for n in flight) and any(n.startswith("altitude (BARO.Alt") for n in flight), flight


def test_the_review_page_of_a_px4_ulog_flight_in_a_real_browser(browser, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    """A simulated PX4 v1.13 flight written as a ULog on pyulog's sample (tests/live/_ulog_flight.py): the
    QGroundControl file (CAL_MAG0_ID the log's device id) and the param-set script, byte for byte."""
    pytest.importorskip("pyulog", reason="pyulog (the logs extra) is not installed")
    from _ulog_flight import DEVICE_ID, write_px4_flight

    log = write_px4_flight(tmp_path / "px4-flight.ulg")
    review = _review_fit_and_download(browser, tmp_path, log, "px4", ("qgc", "px4"))
    judged = review.judged(1)  # PX4's frame (the rotation after the correction): the chosen candidate's field drawn
    chosen = next(lv for lv in judged["levels"] if lv["chosen"])  # is exactly the calibration's
    assert np.allclose(chosen["field"], judged["candidate"], rtol=0, atol=1e-12)
    qgc = next((tmp_path / "downloads").glob("*.params")).read_text()
    assert f"1\t1\tCAL_MAG0_ID\t{DEVICE_ID}\t6" in qgc.splitlines()


def test_the_review_page_of_a_table_with_attitudes_in_a_real_browser(browser, flight_log: Path,  # type: ignore[no-untyped-def]
                                                                      tmp_path: Path) -> None:
    """Issue 40: "any log trimag reads: ... CSV with attitudes". Compass 1 of the flight as a CSV (time, the field,
    yaw/pitch/roll, current): the page draws the flight of its columns and one compass, fitted as the command line it
    shows fits it, the expected field rotated by the table's attitude."""
    import pandas as pd

    from trimag.io import read_samples
    from trimag.io.logs import read_log

    s = read_samples(flight_log, sensor="1")
    t = s.table
    csv = tmp_path / "flight.csv"
    pd.DataFrame({"time_s": t["time_s"], "x": s.field[:, 0], "y": s.field[:, 1], "z": s.field[:, 2],
                  "yaw": t["yaw_deg"], "pitch": t["pitch_deg"], "roll": t["roll_deg"],
                  "current": t["current_A"]}).iloc[::2].to_csv(csv, index=False)  # 5 Hz: a quicker fit
    gps = read_log(flight_log).gps
    assert gps is not None
    site = f"{gps['lat_deg']:.6f},{gps['lon_deg']:.6f},{gps['alt_m']:.1f},{gps['date']}"
    server = serve_review(csv, target="ardupilot", units="mG", igrf_spec=site)
    try:
        browser.get(server.url)
        _wait_fits(browser, 1)
        flight = browser.execute_script(
            "return [...document.querySelectorAll('#flight .legendtext')].map((e) => e.textContent)")
        assert any("the table's yaw,pitch,roll" in n for n in flight), flight
        assert browser.find_elements("css selector", "#per-compass section") and \
            not browser.find_elements("id", "compass-2")  # one compass
        for name in ("field", "magnitude", "heading"):
            assert browser.execute_script(f"return document.querySelectorAll('#fig-1-{name} .main-svg').length") > 0
        legend = browser.execute_script(
            "return [...document.querySelectorAll('#fig-1-field .legendtext')].map((e) => e.textContent)")
        assert any(n.startswith("expected") for n in legend) and "the readings as recorded" in legend, legend
        said = browser.find_element("css selector", "#compass-1 .figure-attitude").text
        assert "the table's yaw,pitch,roll" in said, said
        page = browser.find_element("id", "compass-1").text
        command = f"trimag fit {csv} --units mG --attitude-columns yaw,pitch,roll --target ardupilot --rows 0:400"
        assert command in page and f"--igrf {site}" in page, page
        assert browser.find_elements("id", "dl-ardupilot-1")  # the parameters offered
    finally:
        server.shutdown()


def test_the_html_report_opens_offline_and_holds_every_figure(browser, flight_log: Path,  # type: ignore[no-untyped-def]
                                                              tmp_path: Path) -> None:
    report = tmp_path / "report.html"
    r = run_trimag("fit", flight_log, "--target", "ardupilot", "--sensor", "2", "--report", report, "-q")
    assert r.returncode == 0, r.stderr
    html = report.read_text()
    assert not re.search(r"<(script|link|img|iframe)\b[^>]*\b(src|href)\s*=", html)  # nothing to fetch
    driver = browser  # no network at all: every host name unresolvable
    driver.get(report.as_uri())
    for _ in range(100):
        if driver.execute_script("return document.body.dataset.drawn"):
            break
        time.sleep(0.1)
    figures = ["flight", "compass2-field", "compass2-magnitude", "compass2-heading"]
    assert driver.execute_script("return document.body.dataset.drawn") == str(len(figures))
    for name in figures:
        assert driver.execute_script(f"return document.querySelectorAll('#{name} .main-svg').length") > 0, name
    assert driver.execute_script("return performance.getEntriesByType('resource').length") == 0
    assert "compass 2" in driver.find_element("tag name", "body").text
    legend = driver.execute_script(
        "return [...document.querySelectorAll('#compass2-field .legendtext')].map((e) => e.textContent)")
    assert any("(chosen)" in n for n in legend) and any(n.startswith("candidate: ") for n in legend), legend


def test_a_real_static_log_shows_both_compasses_refused_and_offers_no_parameters(browser,  # type: ignore[no-untyped-def]
                                                                                tmp_path: Path) -> None:
    """ardusub_small.BIN (MIT, a copy of ../shared/data/flight-logs/ardusub_small.BIN): 24 s, static, no GPS fix.
    Neither compass turned: compass 1's heading-free fit would turn the heading with nothing to support it, and
    compass 2's offsets are not excited by the data (issue 38 item 1: two equations for three offsets). The page
    shows both compasses, says why, and offers no parameter file (the server refuses one too)."""
    driver = browser
    proc, url = start_review(str(LOGS / "ardusub_small.BIN"), "--igrf", "47.6,-122.3,0,2021-06-01", cwd=tmp_path)
    try:
        driver.get(url)
        _wait_fits(driver, 1)
        table = driver.find_element("id", "compasses").text
        assert "MAG[0]" in table and "MAG[1]" in table, table
        assert "--heading" in table or "keep the log's calibration" in table, table
        for n in (1, 2):
            assert driver.find_elements("id", f"dl-ardupilot-{n}") == []  # nothing to download for a refusal
            with pytest.raises(urllib.error.HTTPError) as refused:
                urllib.request.urlopen(url + f"download?what=ardupilot&compass={n}", timeout=30)
            assert refused.value.code == 400
    finally:
        _stop(proc)


def test_review_refuses_what_cannot_work_in_one_line(tmp_path: Path) -> None:
    table = tmp_path / "table.csv"
    table.write_text("x,y,z\n1,2,3\n4,5,6\n")
    for args, words in (((str(tmp_path / "missing.bin"),), "no such file"),
                        ((str(table), "--attitude-columns", "yaw,pitch,roll"), "no column 'yaw'")):
        r = run_trimag("review", *args, "--no-browser", "--port", "0")
        assert r.returncode == 2, r.stderr
        assert len(r.stderr.strip().splitlines()) == 1 and words in r.stderr, r.stderr


def test_the_review_server_takes_orders_only_from_its_own_page() -> None:
    """The live server's checks (LocalServer): its own Host only; POST /fit from its page's origin with the token."""
    import http.client

    from trimag.app.review import FlightReview
    from trimag.live.review import ReviewServer

    server = ReviewServer(FlightReview(LOGS / "ardusub_small.BIN", igrf_spec="47.6,-122.3,0,2021-06-01"), 0).start()
    origin = f"http://127.0.0.1:{server.port}"

    def ask(method: str, path: str, headers: dict[str, str], body: bytes = b"") -> tuple[int, bytes]:
        conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=30)
        conn.putrequest(method, path, skip_host=True)
        for key, value in headers.items():
            conn.putheader(key, value)
        conn.putheader("Content-Length", str(len(body)))
        conn.endheaders(body)
        r = conn.getresponse()
        return r.status, r.read()

    host = {"Host": f"127.0.0.1:{server.port}"}
    try:
        assert ask("GET", "/overview", {"Host": "evil.example:80"})[0] == 403  # DNS rebinding
        status, page = ask("GET", "/", host)
        assert status == 200 and server.token.encode() in page and b"plotly.min.js" in page
        assert ask("GET", "/plotly.min.js", host)[0] == 200
        assert ask("POST", "/fit", host, b"{}")[0] == 403  # no origin, no token
        assert ask("POST", "/fit", {**host, "Origin": origin}, b"{}")[0] == 403  # no token
        good = {**host, "Origin": origin, "X-Trimag-Token": server.token}
        assert ask("POST", "/fit", {**good, "Origin": "http://evil.example"}, b"{}")[0] == 403
        assert ask("POST", "/fit", good, b"[1, 2]")[0] == 400
        assert ask("POST", "/fit", good, b'{"start_s": "ten"}')[0] == 400
        assert ask("GET", "/download?what=ardupilot&compass=all", host)[0] == 400  # nothing fitted yet
        assert ask("POST", "/fit", good, b"x" * (server.max_body + 1))[0] == 413
    finally:
        server.shutdown()
