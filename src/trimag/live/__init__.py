"""``trimag live``: watch the sphere of field directions fill while recording, and know when to stop; a front end
like the CLI, on top of the application layer.

A source (:mod:`trimag.live.sources`) feeds a :class:`~trimag.live.session.LiveSession`, which refits on a
background thread; a local web page (:mod:`trimag.live.server`, 127.0.0.1 only) shows the clouds, the coverage, the
RMS, the identifiability verdict, the next orientations to record and a "good enough" state, and ``GET /status``
returns the same as JSON. The save button, SIGINT and (optionally) the end of the source write the calibration and
the recorded samples, atomically. docs/recording.md shows the page.
"""

from __future__ import annotations

import time
import webbrowser
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

from ..app.requests import LiveRequest
from ..errors import TrimagInputError
from .server import LiveServer
from .session import LiveSession
from .sources import Batch, line_source, mavlink_source, replay_source, serial_source

__all__ = ["LiveResult", "LiveServer", "LiveSession", "open_source", "run_live"]


@dataclass
class LiveResult:
    """What a live session ended with: the page's address, the files written, the final state (``/status``
    without the points) and why it stopped (``"interrupted"``, ``"source ended"``)."""

    url: str
    written: dict[str, str] = field(default_factory=dict)
    status: dict[str, Any] = field(default_factory=dict)
    reason: str = ""


def open_source(request: LiveRequest) -> tuple[Iterator[Batch], str]:
    """The batches of the request's source and a short description of it."""
    kind = request.source
    columns = None if request.columns is None else [c.strip() for c in request.columns.split(",")]
    if kind == "replay":
        assert request.replay is not None
        rate = request.rate
        return (replay_source(request.replay, rate=rate, fmt=request.fmt, columns=request.columns,
                              sensor=request.sensor),
                f"replay of {request.replay} at {rate:g} samples/s" if rate else f"replay of {request.replay}")
    if kind == "stdin":
        import sys

        return line_source(sys.stdin, columns=columns), "standard input"
    if kind == "serial":
        assert request.serial is not None
        if request.baud <= 0:
            raise TrimagInputError(f"`baud` must be positive; got {request.baud}")
        return serial_source(request.serial, request.baud, columns=columns), f"serial {request.serial}"
    assert request.mavlink is not None
    return mavlink_source(request.mavlink), f"MAVLink {request.mavlink}"


def run_live(request: LiveRequest, say: Callable[[str], None] = print, *,
             ready: Callable[[LiveServer], None] | None = None) -> LiveResult:
    """Run a live recording until SIGINT (Ctrl-C), or until the source ends with ``request.exit_at_end``; then save
    the calibration and the samples (as the page's save button does at any time).

    Parameters
    ----------
    request : LiveRequest
    say : callable
        Where progress lines go (the page's address, the files written).
    ready : callable, optional
        Called with the running server (tests use it to learn the port).

    Returns
    -------
    LiveResult
    """
    from ..estimators import make_estimator

    make_estimator(request.model, request.method, dict(request.options))  # an unknown model fails before serving
    if request.reference is not None and not request.reference > 0:
        raise TrimagInputError(f"`reference` must be a positive field magnitude; got {request.reference}")
    batches, description = open_source(request)
    session = LiveSession(model=request.model, method=request.method, units=request.units,
                          reference=request.reference, options=request.options, interval=request.interval,
                          source=description)

    def save() -> dict[str, str]:
        written = session.save(request.out, request.samples_out)
        say("saved " + ", ".join(f"{what} {path}" for what, path in written.items()))
        return written

    server = LiveServer(session, request.port, save=save).start()
    result = LiveResult(server.url)
    try:
        session.start(batches)
        say(f"trimag live: {description}; the page is at {server.url} (Ctrl-C saves and stops)")
        if request.open_browser:
            webbrowser.open(server.url)
        if ready is not None:
            ready(server)
        announced = False
        while True:
            time.sleep(0.1)
            if session.ended and not announced:
                announced = True
                say(f"{session.status(points=False)['source_message']}: {session.status(points=False)['n_samples']} "
                    "samples")
                if request.exit_at_end:
                    result.reason = "source ended"
                    break
    except KeyboardInterrupt:
        result.reason = "interrupted"
    finally:
        session.stop()
        try:
            result.written = save()
        finally:
            server.shutdown()
    result.status = session.status(points=False)
    return result
