"""The local web server of ``trimag live``: the page (HTML and JavaScript shipped in the package, nothing fetched
from the internet), ``GET /status`` (the session's state as JSON) and ``POST /save``.

Standard library only (:mod:`http.server` on its own threads); bound to 127.0.0.1, so only this machine sees it.
No page on the web can drive it (docs/recording.md, "Who may drive the server"): every request must name the
server itself as its ``Host`` (``127.0.0.1:PORT`` or ``localhost:PORT``; a DNS-rebinding page names its own
host), and a request that changes anything (``POST``) must also come from the page's own ``Origin`` and carry the
per-session token the page holds (header ``X-Trimag-Token``), which no other origin can read. The page may not be
framed by another.
"""

from __future__ import annotations

import hmac
import json
import secrets
import sys
import threading
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any, TypeVar

from ..errors import TrimagInputError
from .session import LiveSession

__all__ = ["HOST", "LiveServer", "LocalServer"]

#: The only address the server listens on.
HOST = "127.0.0.1"
#: The request header that carries the session's token (the page reads it from its ``trimag-token`` meta tag).
TOKEN_HEADER = "X-Trimag-Token"
#: Seconds a connection may stay silent (a half-sent request, a client that stopped reading) before it is dropped.
IDLE_SECONDS = 5.0
_TOKEN_PLACEHOLDER = b"__TRIMAG_TOKEN__"
#: Sent with every answer: no framing by another page, no sniffing, no reading from another origin.
_SECURITY_HEADERS = {
    "Content-Security-Policy": "default-src 'self'; style-src 'self' 'unsafe-inline'; frame-ancestors 'none'; "
                               "base-uri 'none'; form-action 'none'",
    "X-Frame-Options": "DENY",
    "X-Content-Type-Options": "nosniff",
    "Cross-Origin-Resource-Policy": "same-origin",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-store",
}
_STATIC = {"/": ("index.html", "text/html; charset=utf-8"), "/index.html": ("index.html", "text/html; charset=utf-8"),
           "/live.js": ("live.js", "text/javascript; charset=utf-8")}


_S = TypeVar("_S", bound="LocalServer")
#: An answer: status code, body, content type and any further headers.
Answer = tuple[int, bytes, str, dict[str, str]]


def _static(name: str) -> bytes:
    return (resources.files("trimag.live") / "static" / name).read_bytes()


def _json_answer(code: int, data: Any) -> Answer:
    """``data`` as a JSON answer."""
    return code, json.dumps(data, allow_nan=False).encode(), "application/json", {}


class _Server(ThreadingHTTPServer):
    """A thread per connection; a client that drops its connection is not an error worth a line."""

    daemon_threads = True
    name = "trimag live"

    def handle_error(self, request: Any, client_address: Any) -> None:
        exc = sys.exc_info()[1]
        if isinstance(exc, (ConnectionError, TimeoutError)):  # the client went away: nothing to say
            return
        name = getattr(self, "name", "trimag live")
        sys.stderr.write(f"{name}: internal error while answering a request: {type(exc).__name__}: {exc}\n")


class LocalServer:
    """A page and its requests on ``http://127.0.0.1:PORT/`` (``port`` 0: a free one) from a background thread, with
    the checks of every request (:meth:`refusal`); what each path answers is the subclass's (:meth:`get`,
    :meth:`post`). ``name`` says which command serves (the internal-error line, the thread's name)."""

    name = "trimag live"
    #: The largest request body a POST may carry (bytes).
    max_body = 64 * 1024

    def __init__(self, port: int = 8765) -> None:
        #: The per-session token a state-changing request must carry (in the page; never in a URL).
        self.token = secrets.token_urlsafe(32)
        check_port(port)
        handler = self._handler()
        try:
            self.httpd = _Server((HOST, port), handler)
        except OSError as exc:
            raise TrimagInputError(f"cannot listen on {HOST}:{port} ({exc.strerror or exc}); give another `port` "
                                   "(0 picks a free one)") from None
        self.httpd.name = self.name
        self._thread: threading.Thread | None = None

    @property
    def port(self) -> int:
        """The port listened on."""
        return int(self.httpd.server_address[1])

    @property
    def url(self) -> str:
        """The page's address."""
        return f"http://{HOST}:{self.port}/"

    @property
    def origins(self) -> tuple[str, ...]:
        """The page's own origins: the only ``Origin`` a state-changing request may come from."""
        return f"http://{HOST}:{self.port}", f"http://localhost:{self.port}"

    def refusal(self, method: str, headers: Any) -> str | None:
        """Why a request with these ``headers`` is refused (None when it is the page's own): a ``Host`` other than
        the server itself (DNS rebinding); for ``POST``, a cross-site fetch, an ``Origin`` other than the page's,
        a missing or wrong token."""
        host = headers.get("Host")
        if host is None or host.strip().lower() not in {o.removeprefix("http://") for o in self.origins}:
            return (f"this server answers as {HOST}:{self.port} or localhost:{self.port} only (Host {host!r}); open "
                    f"{self.url}")
        if method in ("GET", "HEAD"):
            return None
        if headers.get("Sec-Fetch-Site", "same-origin") not in ("same-origin", "none"):
            return "a request from another site cannot change anything here"
        origin = headers.get("Origin")
        if origin not in self.origins:
            return (f"only the page itself ({self.url}) can {method} here (Origin: {origin or 'none'}); a script "
                    f"sends the header Origin: {self.origins[0]}")
        token = str(headers.get(TOKEN_HEADER) or "").encode("utf-8", "replace")
        if not hmac.compare_digest(token, self.token.encode()):
            return (f"the session's token is missing or wrong (header {TOKEN_HEADER}; the page holds it in its "
                    "trimag-token meta tag)")
        return None

    def start(self: _S) -> _S:
        """Serve on a daemon thread; returns self."""
        self._thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.1},
                                        name=f"{self.name.replace(' ', '-')}-http", daemon=True)
        self._thread.start()
        return self

    def shutdown(self) -> None:
        """Stop serving and close the socket."""
        if self._thread is not None:
            self.httpd.shutdown()
            self._thread.join(timeout=5)
        self.httpd.server_close()

    def page(self, name: str, kind: str) -> Answer:
        """A static file of the page, with the session's token put in."""
        return 200, _static(name).replace(_TOKEN_PLACEHOLDER, self.token.encode()), kind, {}

    def get(self, path: str, query: str) -> Answer:
        """The answer to ``GET path?query``."""
        return _json_answer(404, {"error": f"no page {path}"})

    def post(self, path: str, body: bytes) -> Answer:
        """The answer to ``POST path`` with ``body`` (the checks of :meth:`refusal` passed)."""
        return _json_answer(404, {"error": f"no action {path}"})

    def _handler(self) -> type[BaseHTTPRequestHandler]:
        server = self

        class Handler(BaseHTTPRequestHandler):
            timeout = IDLE_SECONDS

            def log_message(self, format: str, *args: Any) -> None:  # quiet: the terminal shows the session
                return

            def end_headers(self) -> None:  # every answer, the errors of http.server included
                for key, value in _SECURITY_HEADERS.items():
                    self.send_header(key, value)
                super().end_headers()

            def _send(self, answer: Answer) -> None:
                code, body, kind, headers = answer
                self.send_response(code)
                self.send_header("Content-Type", kind)
                self.send_header("Content-Length", str(len(body)))
                for key, value in headers.items():
                    self.send_header(key, value)
                self.end_headers()
                self.wfile.write(body)

            def _refused(self) -> bool:
                why = server.refusal(self.command, self.headers)
                if why is not None:
                    self.close_connection = True
                    self._send(_json_answer(403, {"error": why}))
                return why is not None

            def do_GET(self) -> None:
                if self._refused():
                    return
                path, _, query = self.path.partition("?")
                self._send(server.get(path, query))

            def do_POST(self) -> None:
                if self._refused():
                    return
                try:
                    length = int(self.headers.get("Content-Length") or 0)
                except ValueError:
                    length = -1
                if not 0 <= length <= server.max_body:
                    self.close_connection = True
                    self._send(_json_answer(413, {"error": f"a request body of at most {server.max_body} bytes"}))
                    return
                body = self.rfile.read(length) if length else b""
                self._send(server.post(self.path.split("?", 1)[0], body))

        return Handler


class LiveServer(LocalServer):
    """Serve ``session`` on ``http://127.0.0.1:PORT/`` (``port`` 0: a free port) from a background thread.

    Parameters
    ----------
    session : LiveSession
    port : int
        TCP port (0 picks a free one: see :attr:`port`).
    save : callable, optional
        What ``POST /save`` runs; returns the written files ({what: path}).
    """

    def __init__(self, session: LiveSession, port: int = 8765,
                 save: Callable[[], dict[str, str]] | None = None) -> None:
        self.session = session
        self._save = save
        super().__init__(port)

    def get(self, path: str, query: str) -> Answer:
        if path == "/status":
            return _json_answer(200, self.session.status(points="points=0" not in query))
        if path in _STATIC:
            return self.page(*_STATIC[path])
        return _json_answer(404, {"error": f"no page {path}"})

    def post(self, path: str, body: bytes) -> Answer:
        if path != "/save":
            return _json_answer(404, {"error": f"no action {path}"})
        if self._save is None:
            return _json_answer(403, {"error": "saving is not enabled"})
        try:
            written = self._save()
        except Exception as exc:  # a full disk, a folder removed: shown on the page, not fatal
            return _json_answer(500, {"error": f"{type(exc).__name__}: {exc}"})
        return _json_answer(200, {"written": written})


def check_port(port: int) -> None:
    """Refuse a TCP port outside 0-65535 (0: a free one)."""
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise TrimagInputError(f"`port` must be a TCP port, 0-65535 (0 picks a free one); got {port!r}")
