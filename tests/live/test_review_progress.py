"""The review page says what the server is doing while it reads and fits (issue 40, item 3): the server is served
before the log is read, ``GET /overview`` answers 503 with the progress line meanwhile, ``GET /state`` keeps the
lines said (reading with its percentage, then each compass's fit), and a log that cannot be read is said as the
error. Server level (no browser): the page's script only shows these lines."""

from __future__ import annotations

import json
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from trimag.errors import TrimagInputError

from _helpers import TESTS_DIR

pytest.importorskip("plotly", reason="plotly (the review extra) is not installed")
pytest.importorskip("pymavlink", reason="pymavlink (the logs extra) is not installed")


def _get(url: str) -> tuple[int, dict]:
    try:
        with urllib.request.urlopen(url, timeout=30) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read())


def test_the_page_says_how_far_the_reading_and_the_fit_are(tmp_path: Path) -> None:
    sys.path.insert(0, str(TESTS_DIR / "app"))
    from test_firmware_fit import _write_log

    from trimag.app.review import FlightReview
    from trimag.live.review import ReviewServer

    log = _write_log(tmp_path / "flight.bin", n=600, seed=4, second=True)
    server = ReviewServer(None, 0).start()
    try:
        status, body = _get(server.url + "overview")
        assert status == 503 and body["progress"] == "starting to read the log", body
        state = _get(server.url + "state")[1]
        assert state["busy"] and state["reading"]
        assert not server.start_fit({})  # nothing to fit yet
        assert _get(server.url + "download?what=ardupilot&compass=all")[0] == 400
        seen: list[tuple[int, dict]] = []

        def make(progress):  # type: ignore[no-untyped-def]
            def watched(fraction: float, what: str) -> None:
                progress(fraction, what)
                seen.append(_get(server.url + "overview"))  # what the page is told meanwhile

            return FlightReview(log, progress=watched)

        server.read(make)
        assert seen and all(s == 503 for s, _ in seen)
        assert seen[0][1]["progress"] == "reading the log: 0 % (reading flight.bin)"
        assert seen[-1][1]["progress"].startswith("reading the log: 100 % (read flight.bin: 2 magnetometer(s)")
        assert _get(server.url + "overview")[0] == 200
        assert server.start_fit({"level": "offsets"})
        deadline = time.monotonic() + 120
        while _get(server.url + "state")[1]["fits"] < 1 and time.monotonic() < deadline:
            time.sleep(0.1)
        said = _get(server.url + "state")[1]["said"]
        assert [line for line in said if line.startswith("fitting compass")] == [
            f"fitting compass {n} of 2 (10.0..69.9 s, level offsets, motor auto)" for n in (1, 2)], said
        assert said[-1] == "drawing"
    finally:
        server.shutdown()

    failing = ReviewServer(None, 0).start()
    try:
        def unreadable(progress):  # type: ignore[no-untyped-def]
            progress(0.0, "reading bad.bin")
            raise TrimagInputError("bad.bin: not a readable log")

        with pytest.raises(TrimagInputError):
            failing.read(unreadable)
        state = failing.state()
        assert state["error"] == "bad.bin: not a readable log" and not state["busy"] and not state["reading"]
    finally:
        failing.shutdown()


def test_ctrl_c_while_the_log_is_read_stops_the_reading(tmp_path: Path) -> None:
    """A SIGINT during the reading stops it at its next progress report (it waited for the whole log, minutes for a
    large one, before the command ended); the compasses are then never fitted nor said."""
    import os
    import signal

    sys.path.insert(0, str(TESTS_DIR / "app"))
    from test_firmware_fit import _write_log

    from trimag.app.requests import ReviewRequest
    from trimag.live.review import run_review

    log = _write_log(tmp_path / "flight.bin", n=600, seed=4)
    said: list[str] = []

    def say(line: str) -> None:
        said.append(line)
        if len(said) == 1:  # the page's address: the reading starts next
            os.kill(os.getpid(), signal.SIGINT)

    result = run_review(ReviewRequest(log=str(log), port=0, open_browser=False), say)
    assert result.reason == "interrupted", (result.reason, said)
    assert not any("compasses" in line for line in said), said
