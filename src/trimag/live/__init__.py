"""``trimag live``: watch the sphere of field directions fill while recording, and know when to stop; a front end
like the CLI, on top of the application layer.

A source (:mod:`trimag.live.sources`) feeds a :class:`~trimag.live.session.LiveSession`, which refits on a
background thread; a local web page (:mod:`trimag.live.server`, 127.0.0.1 only) shows the clouds, the coverage, the
RMS, the identifiability verdict, the next orientations to record and a "good enough" state, and ``GET /status``
returns the same as JSON. The save button, SIGINT, SIGTERM and (optionally) the end of the source write the recorded
samples and the calibration of exactly them, atomically; a signal during the save waits for it. What cannot work is
refused before the session starts (:mod:`trimag.live._checks`). docs/recording.md shows the page.
"""

from __future__ import annotations

import os
import signal
import threading
import time
import webbrowser
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any

from ..app.requests import LiveRequest
from ..calibration import SensorRecord
from ..errors import TrimagInputError
from ._checks import check_method, check_request, output_lock, replay_units
from .server import LiveServer
from .session import LiveSession
from .sources import Batch, _play, bounded_lines, line_source, mavlink_source, serial_source

__all__ = ["LiveResult", "LiveServer", "LiveSession", "open_source", "run_live"]


@dataclass
class LiveResult:
    """What a live session ended with: the page's address, the files written, the final state (``/status``
    without the points) and why it stopped (``"interrupted"`` (SIGINT), ``"terminated"`` (SIGTERM),
    ``"source ended"``)."""

    url: str
    written: dict[str, str] = field(default_factory=dict)
    status: dict[str, Any] = field(default_factory=dict)
    reason: str = ""


def open_source(request: LiveRequest) -> tuple[Iterator[Batch], str]:
    """The batches of the request's source and a short description of it."""
    batches, description, _, _, _ = _open(request)
    return batches, description


def _open(request: LiveRequest) -> tuple[Iterator[Batch], str, str | None, list[str], SensorRecord]:
    """The batches, a description, the unit known before the first sample (``request.units``, or a replayed log's
    checked one), the messages of the unit check (a replay's first: the sensor it reads) and the record of the
    sensor (:class:`~trimag.calibration.SensorRecord`, its unit set when the session saves)."""
    kind = request.source
    columns = None if request.columns is None else [c.strip() for c in request.columns.split(",")]
    if kind == "replay":
        from ..io import read_samples

        assert request.replay is not None
        rate = request.rate
        if rate is not None and not rate > 0:
            raise TrimagInputError(f"`rate` must be a positive number of samples per second; got {rate}")
        # read now: a missing file or a contradicting unit fails here, before the session starts
        samples = read_samples(request.replay, fmt=request.fmt, columns=request.columns, var=request.var,
                               sensor=request.sensor)
        units, messages = replay_units(samples, request)
        from ..app._sensor import sensor_record
        from ..app.requests import InputSpec

        record = sensor_record(samples, InputSpec(request.replay, fmt=request.fmt, columns=request.columns,
                                                  var=request.var, sensor=request.sensor), units or "unknown")
        return (_play(samples.field, samples.n_dropped, units, rate, time.sleep),
                f"replay of {request.replay} at {rate:g} samples/s" if rate else f"replay of {request.replay}",
                units, [f"sensor: {record.describe()}", *messages], record)
    if kind == "stdin":
        import sys

        return (line_source(bounded_lines(sys.stdin.buffer.readline), columns=columns), "standard input",
                request.units, [],
                SensorRecord("stream", format="standard input", columns=None if columns is None else tuple(columns)))
    if kind == "serial":
        assert request.serial is not None
        if request.baud <= 0:
            raise TrimagInputError(f"`baud` must be positive; got {request.baud}")
        return (serial_source(request.serial, request.baud, columns=columns), f"serial {request.serial}",
                request.units, [], SensorRecord("stream", format=f"serial {request.serial}",
                                                columns=None if columns is None else tuple(columns)))
    assert request.mavlink is not None
    return (mavlink_source(request.mavlink), f"MAVLink {request.mavlink}", request.units, [],
            SensorRecord("stream", format=f"MAVLink {request.mavlink}"))


#: The signals that stop a session (and save it), and the reason each gives.
_STOP_SIGNALS: dict[int, str] = {signal.SIGINT: "interrupted", signal.SIGTERM: "terminated"}


class _StopSignals:
    """SIGINT and SIGTERM, while a session runs, ask it to stop and save (they raise nothing, so no save is cut
    short); one that comes during the save is told to wait. The handler only sets :attr:`reason` (taking a lock
    there could deadlock the thread it interrupts). Only the main thread can set signal handlers: from another
    thread the handlers stay as they are (and Ctrl-C reaches only the main thread)."""

    def __init__(self) -> None:
        self.reason = ""
        self.saving = False
        self._previous: dict[int, Any] = {}

    def _handle(self, signum: int, frame: Any) -> None:
        self.reason = self.reason or _STOP_SIGNALS.get(signum, "stopped")
        if self.saving:  # os.write: a signal handler must not re-enter a buffered stream being written
            os.write(2, b"trimag live: saving the recording; it stops when the files are written\n")

    def __enter__(self) -> _StopSignals:
        if threading.current_thread() is threading.main_thread():
            for signum in _STOP_SIGNALS:
                self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)


def run_live(request: LiveRequest, say: Callable[[str], None] = print, *,
             ready: Callable[[LiveServer], None] | None = None) -> LiveResult:
    """Run a live recording until SIGINT (Ctrl-C) or SIGTERM, or until the source ends with
    ``request.exit_at_end``; then save the samples and their calibration (as the page's save button does at any
    time). A request that cannot work is refused before anything starts.

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
    check_request(request)
    check_method(request)  # an unknown model, or one live cannot feed, fails before serving
    with output_lock(request):  # a second session on the same outputs is refused (exit 2)
        return _run_locked(request, say, ready)


def _run_locked(request: LiveRequest, say: Callable[[str], None],
                ready: Callable[[LiveServer], None] | None) -> LiveResult:
    """:func:`run_live` once the request is checked and its outputs locked."""
    batches, description, units, messages, record = _open(request)
    session = LiveSession(model=request.model, method=request.method, units=units, reference=request.reference,
                          options=request.options, interval=request.interval, source=description, sensor=record)

    def save() -> dict[str, str]:
        written = session.save(request.out, request.samples_out)
        say("saved " + ", ".join(f"{what} {path}" for what, path in written.items()))
        return written

    server = LiveServer(session, request.port, save=save).start()
    result = LiveResult(server.url)
    with _StopSignals() as stop:
        try:
            session.start(batches)
            say(f"trimag live: {description}; the page is at {server.url} (Ctrl-C saves and stops)")
            for message in messages:  # after the address, which a caller reads on the first line
                say(message)
            if request.open_browser:
                webbrowser.open(server.url)
            if ready is not None:
                ready(server)
            result.reason = _wait(session, stop, request.exit_at_end, say)
        except KeyboardInterrupt:  # run from another thread than the main one: no handlers of ours
            result.reason = "interrupted"
        finally:
            stop.saving = True
            session.stop()
            try:
                n = session.status(points=False)["n_samples"]
                say(f"stopping ({result.reason or stop.reason or 'error'}): saving {n} samples and their calibration")
            finally:
                try:
                    result.written = save()
                finally:
                    server.shutdown()
    result.status = session.status(points=False)
    return result


def _wait(session: LiveSession, stop: _StopSignals, exit_at_end: bool, say: Callable[[str], None]) -> str:
    """Wait for a signal (or the end of the source with ``exit_at_end``); returns why the session stops."""
    announced = False
    while not stop.reason:
        time.sleep(0.1)
        if session.ended and not announced:
            announced = True
            st = session.status(points=False)
            say(f"{st['source_message']}: {st['n_samples']} samples")
            if exit_at_end:
                return "source ended"
    return stop.reason
