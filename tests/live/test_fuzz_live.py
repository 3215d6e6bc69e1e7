"""Property-based fuzzing of ``trimag live`` (issue 33): its server's endpoints and its flags.

The server, for any request (method, path, Host, Origin, token, Sec-Fetch-Site, body, or bytes that are no HTTP at
all): answers or closes, never prints, and writes files only for the page's own ``POST /save`` (its Host, its
Origin, the session's token). The command, for any rate, interval, reference, port and unit: exit 0, 2 or 3, one
line on stderr and no page served when it refuses (2), never a traceback.
"""

from __future__ import annotations

import socket
import string
from pathlib import Path

import numpy as np
import pytest
from _live_helpers import page_token, sensor, write_log
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from trimag.cli import main
from trimag.live import LiveServer, LiveSession
from trimag.live.sources import Batch
from trimag.simulate import uniform_directions

_SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
_VALUE = st.text(alphabet=string.printable.replace("\r", "").replace("\n", "").replace("\x0b", "").replace(
    "\x0c", ""), max_size=40)


@pytest.fixture
def served(tmp_path):
    session = LiveSession(units="counts")
    session.add(Batch(sensor(uniform_directions(300, seed=31))))
    out = tmp_path / "out"
    out.mkdir()
    server = LiveServer(session, 0, save=lambda: session.save(out / "cal.json")).start()
    yield server, out
    server.shutdown()


def _exchange(port: int, data: bytes) -> bytes:
    """Send ``data``, read the answer until the server closes."""
    with socket.create_connection(("127.0.0.1", port), timeout=30) as sock:
        sock.sendall(data)
        sock.shutdown(socket.SHUT_WR)
        chunks = []
        while chunk := sock.recv(65536):
            chunks.append(chunk)
    return b"".join(chunks)


@_SETTINGS
@given(
    method=st.sampled_from(["GET", "POST", "HEAD", "PUT", "DELETE", "OPTIONS", "PATCH", "post"]) | st.text(
        alphabet=string.ascii_letters, min_size=1, max_size=8),
    path=st.sampled_from(["/save", "/status", "/status?points=0", "/", "/live.js", "/index.html"]) | st.text(
        alphabet=string.ascii_letters + string.digits + "/?=&%.-_~", max_size=30).map(lambda p: "/" + p),
    host=st.sampled_from(["own", "localhost", "evil.example:{port}", "127.0.0.1", None]) | _VALUE,
    origin=st.sampled_from(["own", "http://evil.example", "null", None]) | _VALUE,
    token=st.sampled_from(["right", "wrong", None]) | _VALUE,
    site=st.sampled_from([None, "same-origin", "cross-site", "same-site", "none"]),
    body=st.binary(max_size=200),
)
def test_the_server_answers_any_request_and_only_its_page_saves(served, capfd, method, path, host, origin, token,
                                                                site, body):
    server, out = served
    own = f"127.0.0.1:{server.port}"
    headers = {"Host": {"own": own, "localhost": f"localhost:{server.port}"}.get(host or "", host),
               "Origin": "http://" + own if origin == "own" else origin,
               "X-Trimag-Token": {"right": page_token(server.url), "wrong": "x" * 43}.get(token or "", token),
               "Sec-Fetch-Site": site}
    if isinstance(headers["Host"], str):
        headers["Host"] = headers["Host"].replace("{port}", str(server.port))
    lines = [f"{method} {path} HTTP/1.1"] + [f"{k}: {v}" for k, v in headers.items() if v is not None]
    lines.append(f"Content-Length: {len(body)}")
    answer = _exchange(server.port, ("\r\n".join(lines) + "\r\n\r\n").encode("latin-1") + body)
    saved = sorted(p.name for p in out.iterdir())
    for p in out.iterdir():
        p.unlink()
    page_own = (method == "POST" and path.split("?")[0] == "/save" and host in ("own", "localhost")
                and origin == "own" and token == "right" and site in (None, "same-origin", "none"))
    assert saved == (["cal-samples.csv", "cal.json"] if page_own else []), answer[:300]
    if answer.startswith(b"HTTP/1."):  # (a request line without a version gets an HTTP/0.9 answer: no status)
        assert int(answer.split()[1]) != 500, answer[:300]
    if host in ("own", "localhost") and method == "GET" and path.split("?")[0] == "/status":
        assert b'"n_samples": 300' in answer
    if host not in ("own", "localhost"):
        assert b"n_samples" not in answer and b"trimag-token" not in answer
    assert capfd.readouterr() == ("", "")


@_SETTINGS
@given(data=st.binary(max_size=300))
def test_the_server_survives_bytes_that_are_no_http(served, capfd, data):
    server, out = served
    answer = _exchange(server.port, data)
    assert b"n_samples" not in answer and b"trimag-token" not in answer
    assert not list(out.iterdir())
    assert capfd.readouterr() == ("", "")


_number = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.sampled_from(["0", "-1", "1e400", "x", ""]))


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    rate=st.one_of(st.floats(max_value=0.0) | st.sampled_from([float("inf"), float("nan")]),
                   st.floats(1e5, 1e12)).map(repr) | st.sampled_from(["x", ""]),
    interval=_number.map(lambda v: v if isinstance(v, str) else repr(v)),
    reference=st.none() | _number.map(lambda v: v if isinstance(v, str) else repr(v)),
    port=st.integers(-10**6, 10**6).map(str) | st.sampled_from(["0", "x", "65536", "-1"]),
    units=st.none() | st.sampled_from(["counts", "uT", "nT", "furlongs", "", "µT"]),
)
def test_the_command_refuses_what_cannot_work_before_serving(tmp_path: Path, capsys, rate, interval, reference, port,
                                                             units):
    log = tmp_path / "log.csv"
    if not log.exists():
        write_log(log, sensor(uniform_directions(60, seed=32)))
    out = tmp_path / "cal.json"
    for p in tmp_path.glob("cal*"):
        p.unlink()
    argv = ["live", "--replay", str(log), "--no-browser", "--exit-at-end", "-o", str(out), f"--rate={rate}",
            f"--interval={interval}", f"--port={port}"]
    argv += [f"--reference={reference}"] if reference is not None else []
    argv += [f"--units={units}"] if units is not None else []
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's refusal of a value that is not a number
        code = int(exc.code or 0)
    stdout, err = capsys.readouterr()
    assert code in (0, 2, 3), err
    assert "Traceback" not in err and "internal error" not in err
    if code == 2:
        assert len(err.strip().splitlines()) == 1 and "the page is at" not in stdout
        assert not list(tmp_path.glob("cal*"))
    else:
        assert (tmp_path / "cal-samples.csv").is_file()
        assert np.isfinite(float(rate)) and 0 <= float(interval) <= 3600 and 0 <= int(port) <= 65535
