"""No page on the web can drive the local server of ``trimag live`` (issue 33, item 2).

Every request must name the server itself as its Host (127.0.0.1 or localhost with the port: a DNS-rebinding page
names its own host); a state-changing request must come from the page's own origin and carry the per-session
token the page holds. A client that drops its connection leaves nothing on the terminal.
"""

from __future__ import annotations

import http.client
import json
import socket
import struct

import pytest
from _live_helpers import chrome, page_token, sensor

from trimag.live import LiveServer, LiveSession
from trimag.live.sources import Batch
from trimag.simulate import uniform_directions


@pytest.fixture
def served(tmp_path):
    """A live server (a free port) of a session holding a full sphere; POST /save writes into tmp_path."""
    session = LiveSession(units="counts")
    session.add(Batch(sensor(uniform_directions(600, seed=21))))
    server = LiveServer(session, 0, save=lambda: session.save(tmp_path / "cal.json")).start()
    yield server
    server.shutdown()


def _request(server: LiveServer, method: str, path: str, headers: dict[str, str]) -> tuple[int, dict, bytes]:
    """``method path`` with exactly ``headers`` (no Host added unless given); status, headers, body."""
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=30)
    try:
        conn.putrequest(method, path, skip_host=True, skip_accept_encoding=True)
        for key, value in headers.items():
            conn.putheader(key, value)
        conn.endheaders(b"" if method == "POST" else None)
        r = conn.getresponse()
        return r.status, {k.lower(): v for k, v in r.getheaders()}, r.read()
    finally:
        conn.close()


def _own(server: LiveServer, host: str = "127.0.0.1") -> dict[str, str]:
    return {"Host": f"{host}:{server.port}", "Origin": f"http://{host}:{server.port}",
            "X-Trimag-Token": page_token(server.url), "Content-Length": "0"}


def test_the_page_own_origin_and_token_can_save_and_nothing_else_can(served, tmp_path):
    own = _own(served)
    refused = {
        "no token": {k: v for k, v in own.items() if k != "X-Trimag-Token"},
        "a wrong token": {**own, "X-Trimag-Token": "0" * len(own["X-Trimag-Token"])},
        "another origin (a page on the web)": {**own, "Origin": "http://evil.example"},
        "another port's origin": {**own, "Origin": f"http://127.0.0.1:{served.port + 1}"},
        "an opaque origin (a sandboxed frame)": {**own, "Origin": "null"},
        "no origin (curl)": {k: v for k, v in own.items() if k != "Origin"},
        "a cross-site fetch": {**own, "Sec-Fetch-Site": "cross-site"},
        "a rebound host name": {**own, "Host": f"evil.example:{served.port}"},
        "another port in the Host": {**own, "Host": f"127.0.0.1:{served.port + 1}"},
        "no Host": {k: v for k, v in own.items() if k != "Host"},
    }
    for why, headers in refused.items():
        status, _, body = _request(served, "POST", "/save", headers)
        assert status in (400, 403, 421), (why, status, body)
        assert "error" in json.loads(body), why
        assert not list(tmp_path.iterdir()), f"{why}: files written"
    assert len(own["X-Trimag-Token"]) >= 32
    for host in ("127.0.0.1", "localhost"):
        status, _, body = _request(served, "POST", "/save", _own(served, host))
        assert status == 200, body
        assert set(json.loads(body)["written"]) == {"samples", "calibration"}


def test_a_rebound_host_name_cannot_read_the_status(served):
    """DNS rebinding: a page of evil.example whose name now resolves to 127.0.0.1 sends Host: evil.example:PORT."""
    for host in (f"evil.example:{served.port}", f"127.0.0.1.evil.example:{served.port}", "127.0.0.1",
                 f"localhost:{served.port + 1}"):
        for path in ("/status", "/", "/live.js"):
            status, _, body = _request(served, "GET", path, {"Host": host})
            assert status in (400, 403, 421), (host, path, status)
            assert b"n_samples" not in body and b"trimag-token" not in body
    status, _, body = _request(served, "GET", "/status?points=0", {"Host": f"localhost:{served.port}"})
    assert status == 200 and json.loads(body)["n_samples"] == 600


def test_the_page_is_not_framed_shared_or_sniffed(served):
    status, headers, _ = _request(served, "GET", "/", {"Host": f"127.0.0.1:{served.port}"})
    assert status == 200
    assert "frame-ancestors 'none'" in headers["content-security-policy"]
    assert headers["x-frame-options"] == "DENY" and headers["x-content-type-options"] == "nosniff"
    assert headers["cross-origin-resource-policy"] == "same-origin"
    assert "access-control-allow-origin" not in headers
    other = LiveServer(LiveSession(units="counts"), 0).start()
    try:
        assert page_token(other.url) != page_token(served.url), "the token is per session"
    finally:
        other.shutdown()


def _reset_after(data: bytes, port: int, read: int = 0) -> None:
    """Connect, send ``data``, read ``read`` bytes, then reset the connection (SO_LINGER 0: an RST, no FIN)."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=30)
    sock.sendall(data)
    if read:
        sock.recv(read)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    sock.close()


def test_a_client_that_drops_the_connection_prints_nothing(tmp_path, capfd):
    session = LiveSession(units="counts")
    session.add(Batch(sensor(uniform_directions(3000, seed=22))))
    session.refit()
    server = LiveServer(session, 0).start()
    host = f"Host: 127.0.0.1:{server.port}\r\n".encode()
    try:
        _reset_after(b"GET /sta", server.port)  # mid-request
        for _ in range(5):  # mid-reply: the status with its clouds is ~200 kB
            _reset_after(b"GET /status HTTP/1.1\r\n" + host + b"\r\n", server.port, read=64)
        # connections are accepted in order: once this one is answered, the ones above were taken
        status, _, _ = _request(server, "GET", "/status?points=0", {"Host": f"127.0.0.1:{server.port}"})
        assert status == 200
    finally:
        server.shutdown()  # joins the request threads
    out, err = capfd.readouterr()
    assert out == "" and err == ""


_ATTACK = """<!DOCTYPE html><html><body>
<form id="f" method="POST" action="{target}save" enctype="text/plain"><input name="x" value="1"></form>
<script>
  fetch("{target}save", {{method: "POST", mode: "no-cors", body: "x"}})
    .catch(() => null)
    .then(() => fetch("{target}save", {{method: "POST", mode: "no-cors", headers: {{"X-Trimag-Token": "guess"}}}}))
    .catch(() => null)
    .then(() => {{ document.title = "fetched"; setTimeout(() => document.getElementById("f").submit(), 50); }});
</script></body></html>"""


@pytest.mark.slow
def test_no_page_on_the_web_can_drive_the_server_in_a_real_browser(served, tmp_path):
    """Headless Chromium: a page of another origin posts to /save (fetch no-cors, then a form), a rebound host
    name reads /status: all refused, nothing written; then the live page's own Save button saves."""
    import threading
    import time
    from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

    page = _ATTACK.format(target=served.url).encode()

    class Attacker(BaseHTTPRequestHandler):
        def log_message(self, format, *args):  # type: ignore[no-untyped-def]
            return

        def do_GET(self) -> None:
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(page)))
            self.end_headers()
            self.wfile.write(page)

    attacker = ThreadingHTTPServer(("127.0.0.1", 0), Attacker)
    threading.Thread(target=attacker.serve_forever, daemon=True).start()
    rules = "MAP attacker.test 127.0.0.1, MAP rebind.test 127.0.0.1"
    driver = chrome(tmp_path / "profile", f"--host-resolver-rules={rules}", "--disable-features=HttpsUpgrades")
    try:
        driver.get(f"http://attacker.test:{attacker.server_address[1]}/")
        for _ in range(1200):  # the form's answer replaces the attacker's page
            if '"error"' in driver.page_source or "written" in driver.page_source:
                break
            time.sleep(0.05)
        assert '"error"' in driver.page_source and "written" not in driver.page_source, driver.page_source[:500]
        assert not list(tmp_path.glob("cal*")), "a page of another origin saved"
        driver.get(f"http://rebind.test:{served.port}/status")
        assert "n_samples" not in driver.page_source and "answers as" in driver.page_source
        driver.get(served.url)
        driver.find_element("id", "save").click()
        for _ in range(1200):
            if driver.find_element("id", "saved").text.startswith(("saved", "not saved")):
                break
            time.sleep(0.05)
        assert driver.find_element("id", "saved").text.startswith("saved"), driver.find_element("id", "saved").text
    finally:
        driver.quit()
        attacker.shutdown()
        attacker.server_close()
    assert (tmp_path / "cal.json").is_file() and (tmp_path / "cal-samples.csv").is_file()
