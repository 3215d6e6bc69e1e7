"""Where ``trimag live`` gets its samples: a log played back at a rate, lines of text (standard input or a serial
port), or a MAVLink stream (an autopilot over UDP/TCP/serial, or a telemetry log).

Every source is an iterator of :class:`Batch` (samples, and the count of lines that were not samples); it ends when
its input ends. Sources never raise on bad input: a line that is not three numbers is counted, not fatal.
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._core.extras import require
from ..errors import TrimagInputError
from ..units import header_unit
from ..validation import MAX_READING

__all__ = ["Batch", "LineParser", "line_source", "mavlink_source", "replay_source", "serial_source"]

_SPLIT = re.compile(r"[,;\t ]+")
#: How long a replay sleeps between batches (seconds): at 2 000 samples/s, 40 samples per batch.
REPLAY_TICK = 0.02


@dataclass
class Batch:
    """Samples read in one go (shape (k, 3), the source's unit) and the lines that were not samples."""

    samples: NDArray[np.float64] = field(default_factory=lambda: np.empty((0, 3)))
    n_garbage: int = 0
    #: the unit the source states (a MAVLink message type, a log's header), None when it does not say
    units: str | None = None
    #: who states ``units``, for a message ("the column headers say", "the MAVLink message SCALED_IMU says")
    units_stated_by: str = "the source says"


def _number(token: str) -> float | None:
    try:
        value = float(token)
    except ValueError:
        return None
    return value if np.isfinite(value) and abs(value) <= MAX_READING else None  # 1e308 is not a reading


def _xyz_indices(names: Sequence[str]) -> tuple[int, int, int] | None:
    """Indices of the x, y, z columns in a header: three names that differ only in a trailing (or leading) x, y, z
    (``mx,my,mz``, ``mag_x,mag_y,mag_z``, ``x,y,z``, ``XMag,YMag,ZMag``); None when there are none."""
    low = [n.strip().strip('"').lower() for n in names]
    for i, name in enumerate(low):
        for stem_of, make in ((lambda s: s[:-1] if s.endswith("x") else None, lambda stem, c: stem + c),
                              (lambda s: s[1:] if s.startswith("x") else None, lambda stem, c: c + stem)):
            stem = stem_of(name)
            if stem is None:
                continue
            try:
                return i, low.index(make(stem, "y")), low.index(make(stem, "z"))
            except ValueError:
                continue
    return None


class LineParser:
    """Turns lines of text into samples: ``x,y,z`` (comma, semicolon, tab or space separated), or the columns a CSV
    header names (its x, y, z columns are recognised, or given as ``columns``).

    Parameters
    ----------
    columns : sequence of str, optional
        The header names of the x, y, z columns.
    """

    def __init__(self, columns: Sequence[str] | None = None) -> None:
        self.columns = None if columns is None else [c.strip().lower() for c in columns]
        if self.columns is not None and len(self.columns) != 3:
            raise TrimagInputError(f"`columns` needs three names (x, y, z); got {len(self.columns)}")
        self.indices: tuple[int, int, int] | None = None
        self.header: list[str] | None = None
        #: the unit the header's x, y, z names state (``x_uT``, ``Bx (nT)``), None when they state none
        self.units: str | None = None

    def parse(self, line: str) -> tuple[float, float, float] | bool | None:
        """The sample on ``line``; True when the line was a header (taken), None when it is garbage; blank lines
        and ``#`` comments are True (skipped, not counted)."""
        text = line.strip()
        if not text or text.startswith("#"):
            return True
        tokens = [t for t in _SPLIT.split(text) if t]
        values = [_number(t) for t in tokens]
        if self.indices is None and all(v is None for v in values):
            names = [t.strip().strip('"').lower() for t in tokens]
            found = (_xyz_indices(names) if self.columns is None else
                     tuple(names.index(c) for c in self.columns) if all(c in names for c in self.columns) else None)
            if found is None:
                return None
            self.indices, self.header = (found[0], found[1], found[2]), names
            self.units = header_unit([tokens[k].strip().strip('"') for k in found])
            return True
        if self.indices is not None:
            if len(values) <= max(self.indices):
                return None
            picked = [values[k] for k in self.indices]
        elif len(values) == 3 and self.columns is None:
            picked = values
        else:
            return None
        if any(v is None for v in picked):
            return None
        x, y, z = picked
        assert x is not None and y is not None and z is not None
        return x, y, z


#: The longest line a line source takes (bytes): a line of x, y, z is under 100 bytes and a CSV header a few
#: thousand; a longer line is read in pieces of this size, skipped and counted as a line not understood (issue 41,
#: item 12: one 500 MB line on standard input took 1.58 GB).
MAX_LINE_BYTES = 1 << 16


def bounded_lines(readline: Callable[[int], bytes], limit: int = MAX_LINE_BYTES) -> Iterator[bytes | None]:
    """The lines ``readline(size)`` gives (a binary stream's ``readline``: at most ``size`` bytes, ending at a
    newline), each at most ``limit`` bytes; a longer line is read to its end in pieces and given as None (held in
    memory: ``limit`` bytes at a time). Ends at the end of the stream."""
    while True:
        line = readline(limit + 1)
        if not line:
            return
        if len(line) <= limit or line.endswith(b"\n"):
            yield line
            continue
        while line and not line.endswith(b"\n"):  # the rest of the long line, a piece at a time
            line = readline(limit)
        yield None


def line_source(lines: Iterable[str | bytes | None], *, columns: Sequence[str] | None = None) -> Iterator[Batch]:
    """Samples from lines of text (``x,y,z`` or a CSV header, :class:`LineParser`), one batch per line (a line
    source blocks between lines, so nothing waits in a buffer); undecodable or malformed lines count as garbage, and
    so does a None (a line too long: :func:`bounded_lines`)."""
    parser = LineParser(columns)
    for raw in lines:
        if raw is None:
            yield Batch(n_garbage=1)
            continue
        try:
            line = raw.decode("utf-8") if isinstance(raw, bytes) else raw
        except UnicodeDecodeError:
            yield Batch(n_garbage=1)
            continue
        got = parser.parse(line)
        if got is None:
            yield Batch(n_garbage=1)
        elif got is not True and got is not False:
            yield Batch(np.array([got], dtype=np.float64), units=parser.units, units_stated_by="the column headers say")


def replay_source(path: str | Path, *, rate: float | None = 2000.0, sleep: Callable[[float], Any] = time.sleep,
                  **read_arguments: Any) -> Iterator[Batch]:
    """The samples of a log (any file :func:`trimag.io.read_samples` reads, with its ``read_arguments``: ``fmt``,
    ``columns``, ``sensor``...) played back at ``rate`` samples per second (as fast as they are taken when None).
    The first batch states the log's unit when the log does (a vehicle log, a unit in the column headers)."""
    from ..io import read_samples

    if rate is not None and not rate > 0:
        raise TrimagInputError(f"`rate` must be a positive number of samples per second; got {rate}")
    samples = read_samples(path, **read_arguments)  # read now: a missing file fails here, not in the reader thread
    units = (samples.log_info or {}).get("unit") or header_unit(list(samples.columns)) or samples.stated_unit or None
    return _play(samples.field, samples.n_dropped, units, rate, sleep)


def _play(B: NDArray[np.float64], first_garbage: int, units: str | None, rate: float | None,
          sleep: Callable[[float], Any]) -> Iterator[Batch]:
    start = time.monotonic()
    done = 0
    while done < len(B):
        if rate is None:
            stop = min(len(B), done + 2000)
        else:
            sleep(REPLAY_TICK)
            stop = min(len(B), max(done + 1, int((time.monotonic() - start) * rate)))
        yield Batch(B[done:stop].copy(), first_garbage, units)
        first_garbage, done = 0, stop


def serial_source(port: str, baud: int = 115200, *, columns: Sequence[str] | None = None) -> Iterator[Batch]:
    """Lines of ``x,y,z`` (or a CSV header) from a serial port (needs pyserial: the ``live`` extra)."""
    serial = require("serial", "trimag live --serial")
    try:
        conn = serial.Serial(port, baud, timeout=1.0)
    except (OSError, ValueError, serial.SerialException) as exc:
        raise TrimagInputError(f"cannot open the serial port {port!r} at {baud} baud: {exc}") from None

    def lines() -> Iterator[bytes | None]:
        with conn:
            while True:  # a second without a byte gives an empty read, not the end: read on
                yield from bounded_lines(conn.readline)

    return line_source(lines(), columns=columns)


#: The MAVLink messages that carry a magnetometer reading, and the unit of their ``xmag`` fields.
MAVLINK_MESSAGES: dict[str, str | None] = {"SCALED_IMU": "mG", "SCALED_IMU2": "mG", "SCALED_IMU3": "mG",
                                           "RAW_IMU": None, "HIGHRES_IMU": "G"}


def mavlink_source(url: str, *, message: str | None = None, timeout: float = 5.0) -> Iterator[Batch]:
    """Magnetometer readings from a MAVLink stream (``udpin:0.0.0.0:14550``, ``tcp:host:5760``, a serial device, or
    a ``.tlog`` file; pymavlink, the ``logs`` extra): the first of :data:`MAVLINK_MESSAGES` that arrives (or
    ``message``), in its unit (``RAW_IMU`` in the sensor's own unit). The stream ends after ``timeout`` seconds
    without a reading."""
    mavutil = require("pymavlink.mavutil", "trimag live --mavlink")
    if Path(url).is_file():  # a telemetry log: trimag's linear reader (pymavlink's can stall on damage)
        return _mavlink_batches(_TlogFile(Path(url)), True, message, timeout)
    try:
        conn = mavutil.mavlink_connection(url)
    except Exception as exc:  # pymavlink raises anything from OSError to its own errors
        raise TrimagInputError(f"cannot open the MAVLink stream {url!r}: {exc}") from None
    return _mavlink_batches(conn, Path(url).is_file(), message, timeout)


class _TlogFile:
    """A ``.tlog`` file read by :func:`trimag.io.logs.tlog.read_tlog_messages`, with the one method of a pymavlink
    connection that :func:`_mavlink_readings` calls."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._messages: Iterator[Any] | None = None

    def recv_match(self, type: list[str], blocking: bool = False, timeout: float | None = None) -> Any:
        if self._messages is None:
            from ..io.logs.tlog import read_tlog_messages

            self._messages = iter(read_tlog_messages(self.path, list(MAVLINK_MESSAGES)).messages)
        return next((m for m in self._messages if m.get_type() in type), None)


def _mavlink_batches(conn: Any, from_file: bool, message: str | None, timeout: float) -> Iterator[Batch]:
    try:
        yield from _mavlink_readings(conn, from_file, message, timeout)
    finally:  # the file or socket pymavlink opened
        close = getattr(conn, "close", None)
        if callable(close):
            close()


def _mavlink_readings(conn: Any, from_file: bool, message: str | None, timeout: float) -> Iterator[Batch]:
    wanted = [message] if message else list(MAVLINK_MESSAGES)
    chosen = message
    last = time.monotonic()
    rows: list[tuple[float, float, float]] = []
    while True:
        msg = conn.recv_match(type=wanted, blocking=not from_file, timeout=0.2)
        now = time.monotonic()
        if msg is None:
            if rows:
                yield Batch(np.array(rows, dtype=np.float64), 0, MAVLINK_MESSAGES.get(chosen or ""),
                            f"the MAVLink message {chosen} says")
                rows = []
            if from_file or now - last > timeout:  # a log file has no message left
                return
            continue
        kind = msg.get_type()
        if chosen is None:
            chosen = kind
            wanted = [kind]
        last = now
        rows.append((float(msg.xmag), float(msg.ymag), float(msg.zmag)))
        if len(rows) >= 256:
            yield Batch(np.array(rows, dtype=np.float64), 0, MAVLINK_MESSAGES.get(kind),
                        f"the MAVLink message {kind} says")
            rows = []
