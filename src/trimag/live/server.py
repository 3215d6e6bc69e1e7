"""The local web server of ``trimag live``: the page (HTML and JavaScript shipped in the package, nothing fetched
from the internet), ``GET /status`` (the session's state as JSON) and ``POST /save``.

Standard library only (:mod:`http.server` on its own threads); bound to 127.0.0.1, so only this machine sees it.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any

from ..errors import TrimagInputError
from .session import LiveSession

__all__ = ["HOST", "LiveServer"]

#: The only address the server listens on.
HOST = "127.0.0.1"
_STATIC = {"/": ("index.html", "text/html; charset=utf-8"), "/index.html": ("index.html", "text/html; charset=utf-8"),
           "/live.js": ("live.js", "text/javascript; charset=utf-8")}


def _static(name: str) -> bytes:
    return (resources.files("trimag.live") / "static" / name).read_bytes()


class LiveServer:
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
        handler = self._handler()
        try:
            self.httpd = ThreadingHTTPServer((HOST, port), handler)
        except OSError as exc:
            raise TrimagInputError(f"cannot listen on {HOST}:{port} ({exc.strerror or exc}); give another `port` "
                                   "(0 picks a free one)") from None
        self.httpd.daemon_threads = True
        self._thread: threading.Thread | None = None

    @property
    def port(self) -> int:
        """The port listened on."""
        return int(self.httpd.server_address[1])

    @property
    def url(self) -> str:
        """The page's address."""
        return f"http://{HOST}:{self.port}/"

    def start(self) -> LiveServer:
        """Serve on a daemon thread; returns self."""
        self._thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.1},
                                        name="trimag-live-http", daemon=True)
        self._thread.start()
        return self

    def shutdown(self) -> None:
        """Stop serving and close the socket."""
        if self._thread is not None:
            self.httpd.shutdown()
            self._thread.join(timeout=5)
        self.httpd.server_close()

    def _handler(self) -> type[BaseHTTPRequestHandler]:
        server = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, format: str, *args: Any) -> None:  # quiet: the terminal shows the session
                return

            def _send(self, code: int, body: bytes, kind: str) -> None:
                self.send_response(code)
                self.send_header("Content-Type", kind)
                self.send_header("Content-Length", str(len(body)))
                self.send_header("Cache-Control", "no-store")
                self.end_headers()
                self.wfile.write(body)

            def _json(self, code: int, data: Any) -> None:
                self._send(code, json.dumps(data, allow_nan=False).encode(), "application/json")

            def do_GET(self) -> None:
                path = self.path.split("?", 1)[0]
                if path == "/status":
                    points = "points=0" not in self.path
                    self._json(200, server.session.status(points=points))
                elif path in _STATIC:
                    name, kind = _STATIC[path]
                    self._send(200, _static(name), kind)
                else:
                    self._json(404, {"error": f"no page {path}"})

            def do_POST(self) -> None:
                if self.path.split("?", 1)[0] != "/save":
                    self._json(404, {"error": f"no action {self.path}"})
                    return
                if server._save is None:
                    self._json(403, {"error": "saving is not enabled"})
                    return
                try:
                    written = server._save()
                except Exception as exc:  # a full disk, a folder removed: shown on the page, not fatal
                    self._json(500, {"error": f"{type(exc).__name__}: {exc}"})
                    return
                self._json(200, {"written": written})

        return Handler
