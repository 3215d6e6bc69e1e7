"""``trimag review LOG``: the flight review page (issue 40; docs/review.md), a front end like ``trimag live`` and the
CLI, on the same local server (:class:`~trimag.live.server.LocalServer`: 127.0.0.1 only, its own ``Host`` only, a
``POST`` from its page's origin with the session's token).

The page (``static/review.html``, ``review.js``, Plotly's ``plotly.min.js`` from the ``review`` extra) asks the
server; the server answers from :class:`trimag.app.review.FlightReview`, which fits with the command line's own
:func:`trimag.app.fit_file` and writes the parameters with ``trimag export``'s writers:

- ``GET /overview``: the log, its compasses, the flight figure, the choices (503 with the progress line while the
  log is read: the page is served at once and says how far the reading is);
- ``POST /fit`` (JSON ``start_s``, ``stop_s``, ``level``, ``motor``, ``yaw_source``): fit every compass on a
  background thread;
- ``GET /state``: busy or not, reading or not, the progress line (and the last ones said), the last choice, an
  error; ``GET /results``: per compass
  the verdict, the tables and the figures;
- ``GET /download?what=ardupilot|px4|qgc|json&compass=N|all``: the file, as an attachment.
"""

from __future__ import annotations

import json
import threading
import time
import webbrowser
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any
from urllib.parse import parse_qs, quote

from ..app.requests import ReviewRequest
from ..app.review import FlightReview, plotly_js
from ..errors import TrimagError, TrimagInputError, full_message
from .server import Answer, LocalServer, _json_answer

__all__ = ["ReviewResult", "ReviewServer", "run_review"]

#: How many of the server's last progress lines ``GET /state`` keeps (``said``).
SAID = 40

_STATIC = {"/": ("review.html", "text/html; charset=utf-8"), "/index.html": ("review.html", "text/html; charset=utf-8"),
           "/review.js": ("review.js", "text/javascript; charset=utf-8")}


class ReviewServer(LocalServer):
    """Serve a :class:`FlightReview` on ``http://127.0.0.1:PORT/`` (module docstring)."""

    name = "trimag review"

    def __init__(self, review: FlightReview | None, port: int = 8765) -> None:
        self._review = review
        self._plotly = plotly_js()
        self._state: dict[str, Any] = {"busy": review is None, "reading": review is None,
                                       "progress": "" if review is not None else "starting to read the log",
                                       "error": None, "fits": 0, "choice": {}, "said": []}
        self._results: bytes = b'{"compasses": []}'
        self._lock = threading.Lock()
        super().__init__(port)

    @property
    def review(self) -> FlightReview:
        """The log under review (read); a request before it is read is answered "reading" (``GET /state``)."""
        if self._review is None:
            raise TrimagInputError("the log is being read: wait for it")
        return self._review

    def read(self, make: Callable[[Callable[[float, str], None]], FlightReview]) -> FlightReview:
        """Read the log with ``make(progress)`` (on the caller's thread; the page, already served, shows how far it
        is: ``GET /state``, ``GET /overview`` answers 503 meanwhile), then serve it."""
        def progress(fraction: float, what: str) -> None:
            self._progress(f"reading the log: {100 * fraction:.0f} % ({what})")

        try:
            review = make(progress)
        except TrimagError as exc:
            with self._lock:
                self._state.update(busy=False, reading=False, progress="", error=str(exc))
            raise
        with self._lock:
            self._review = review
            self._state.update(busy=False, reading=False, progress="")
        return review

    # ------------------------------------------------------------------ the fit on a background thread
    def start_fit(self, choice: dict[str, Any]) -> bool:
        """Fit with ``choice`` on a background thread; False when a fit is already running."""
        with self._lock:
            if self._state["busy"] or self._review is None:
                return False
            self._state.update(busy=True, progress="starting", error=None)
        threading.Thread(target=self._fit, args=(choice,), name="trimag-review-fit", daemon=True).start()
        return True

    def _progress(self, line: str) -> None:
        """What the server is doing: the page's progress line (``GET /state``), and the last lines said."""
        with self._lock:
            self._state["progress"] = line
            self._state["said"] = [*self._state["said"][-(SAID - 1):], line]

    def _fit(self, choice: dict[str, Any]) -> None:
        try:
            self.review.fit(choice.get("start_s"), choice.get("stop_s"), str(choice.get("level") or "auto"),
                            str(choice.get("motor") or "auto"), str(choice.get("yaw_source") or "auto"),
                            progress=self._progress)
            self._progress("drawing")
            compasses = [self.review.compass_result(n) for n in sorted(self.review.results)]
            body = json.dumps({"choice": self.review.choice, "compasses": compasses,
                               "flight": self.review.flight_figure(self.review.choice["start_s"],
                                                                   self.review.choice["stop_s"])},
                              allow_nan=False).encode()
            with self._lock:
                self._results = body
                self._state.update(fits=self._state["fits"] + 1, choice=self.review.choice)
        except TrimagError as exc:
            with self._lock:
                self._state["error"] = full_message(exc)
        except Exception as exc:  # a bug: shown on the page and on the terminal, the server goes on
            with self._lock:
                self._state["error"] = f"internal error (a bug in trimag): {type(exc).__name__}: {exc}"
        finally:
            with self._lock:
                self._state.update(busy=False, progress="")

    def state(self) -> dict[str, Any]:
        """What ``GET /state`` answers."""
        with self._lock:
            return dict(self._state)

    # ------------------------------------------------------------------ the requests
    def get(self, path: str, query: str) -> Answer:
        if path in _STATIC:
            return self.page(*_STATIC[path])
        if path == "/plotly.min.js":
            return 200, self._plotly, "text/javascript; charset=utf-8", {"Cache-Control": "max-age=3600"}
        if path == "/overview":
            if self._review is None:  # the page waits, showing the progress line
                return _json_answer(503, {"error": "the log is being read", "progress": self.state()["progress"]})
            return _json_answer(200, self.review.overview())
        if path == "/state":
            return _json_answer(200, self.state())
        if path == "/results":
            with self._lock:
                return 200, self._results, "application/json", {}
        if path == "/download":
            args = {k: v[-1] for k, v in parse_qs(query).items()}
            if self._review is None:
                return _json_answer(400, {"error": "the log is being read: nothing is fitted yet"})
            try:
                name, text = self.review.download(args.get("what", "ardupilot"), args.get("compass", "all"))
            except TrimagInputError as exc:
                return _json_answer(400, {"error": str(exc)})
            kind = "application/json" if name.endswith(".json") else "text/plain; charset=utf-8"
            return 200, text.encode(), kind, {"Content-Disposition": f"attachment; filename*=UTF-8''{quote(name)}"}
        return _json_answer(404, {"error": f"no page {path}"})

    def post(self, path: str, body: bytes) -> Answer:
        if path != "/fit":
            return _json_answer(404, {"error": f"no action {path}"})
        try:
            choice = json.loads(body or b"{}")
            if not isinstance(choice, dict):
                raise ValueError("not an object")
            start, stop = choice.get("start_s"), choice.get("stop_s")
            for value in (start, stop):
                if value is not None and (isinstance(value, bool) or not isinstance(value, int | float)):
                    raise ValueError("start_s and stop_s are numbers of seconds")
        except ValueError as exc:
            return _json_answer(400, {"error": f"POST /fit takes a JSON object (start_s, stop_s, level, motor): {exc}"})
        if not self.start_fit(choice):
            return _json_answer(409, {"error": "the log is being read or a fit is running; wait for it"})
        return _json_answer(202, {"started": True})


@dataclass
class ReviewResult:
    """How a review ended: the page's address and why it stopped."""

    url: str
    reason: str = ""


def run_review(request: ReviewRequest, say: Callable[[str], None] = print, *,
               ready: Callable[[ReviewServer], None] | None = None) -> ReviewResult:
    """Read the log, serve the review page until SIGINT (Ctrl-C) or SIGTERM; the whole flight is fitted at once
    (the page refits on the user's choice). The page is served first and says how far the reading is
    (:meth:`ReviewServer.read`); a missing file, a busy port or no plotly is refused before anything is served, a log
    that cannot be read once the reading fails (the server stops; the command says it in one line)."""
    from pathlib import Path

    from . import _StopSignals

    plotly_js()  # a missing review extra is said before the log is read
    if not Path(request.log).is_file():
        raise TrimagInputError(f"{request.log}: no such file")
    server = ReviewServer(None, request.port)  # served at once: the page says how far the reading is
    server.start()
    result = ReviewResult(server.url)
    with _StopSignals() as stop:
        try:
            say(f"trimag review: {request.log}; the page is at {server.url} (reading the log; Ctrl-C stops)")
            if request.open_browser:
                webbrowser.open(server.url)
            def reading(progress: Callable[[float, str], None]) -> FlightReview:
                def said(fraction: float, what: str) -> None:  # Ctrl-C stops the reading at its next report
                    if stop.reason:
                        raise KeyboardInterrupt
                    progress(fraction, what)

                return FlightReview(request.log, fmt=request.fmt, target=request.target, igrf_spec=request.igrf_spec,
                                    units=request.units, columns=request.columns,
                                    attitude_columns=request.attitude_columns, time_column=request.time_column,
                                    progress=said)

            review = server.read(reading)
            server.start_fit({})
            names = ", ".join(f"{m.number} ({m.name})" for m in review.log.magnetometers)
            say(f"trimag review: read {review.log.format}; compasses {names}; fitting the whole flight")
            for line in review.unavailable():
                say(f"trimag review: {line}")
            if ready is not None:
                ready(server)
            while not stop.reason:
                time.sleep(0.1)
            result.reason = stop.reason
        except KeyboardInterrupt:
            result.reason = stop.reason or "interrupted"
        finally:
            server.shutdown()
    return result
