"""MAVLink telemetry logs (``.tlog``) read in one linear pass.

A ``.tlog`` is a stream of records ``[8-byte big-endian receipt time, microseconds][one MAVLink v1 or v2 frame]``.
pymavlink's own log reader (``mavutil.mavmmaplog``) indexes the messages, then, at a record whose time stamp is more
than 3 days from the last good one, re-scans the file byte by byte from that record onward, and seeks back to the
next indexed message afterwards: two damaged bytes made it read a 1.5 MB log for 849 s (issue 41). This reader walks
the records once: a record is taken when its frame is whole (wanted types: pymavlink's ``decode`` checks the
checksum; others: the next record starts where this one says it ends), anything else is skipped one byte at a time,
so every byte is looked at a bounded number of times (at least 1 MB/s on a 1.5 MB log, docs/autopilot.md). Messages
whose receipt time lies more than 3 days from the log's median are dropped and counted (a damaged time stamp).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import TrimagInputError
from .base import require

__all__ = ["TlogRead", "read_tlog_messages"]

_V1, _V2 = 0xFE, 0xFD
_MAGIC = re.compile(rb"[\xfd\xfe]")
#: A receipt time further than this from the log's median is damage, as pymavlink's own re-sync threshold (s).
MAX_TIME_FROM_MEDIAN_S = 3 * 24 * 3600.0


@dataclass
class TlogRead:
    """The messages of a telemetry log and what was skipped: ``skipped_bytes`` (bytes that start no whole frame) and
    ``bad_time`` (messages dropped for a receipt time more than 3 days from the log's median)."""

    messages: list[Any]
    skipped_bytes: int
    bad_time: int

    def notes(self) -> list[str]:
        """One line per kind of damage, for the log's messages (empty for an undamaged log)."""
        out = []
        if self.skipped_bytes:
            out.append(f"telemetry log: {self.skipped_bytes} damaged byte(s) that start no whole MAVLink frame "
                       "were skipped")
        if self.bad_time:
            out.append(f"telemetry log: {self.bad_time} message(s) dropped whose receipt time lies more than 3 days "
                       "from the log's (a damaged time stamp)")
        return out


def _frame_length(raw: Any, at: int, n: int) -> tuple[int, int] | None:
    """``(frame length, message id)`` of the MAVLink frame starting at ``at``, or None when no frame starts there."""
    magic = raw[at]
    if magic == _V1:
        if at + 6 > n:
            return None
        return 6 + raw[at + 1] + 2, raw[at + 5]
    if magic == _V2:
        if at + 10 > n:
            return None
        signed = 13 if raw[at + 2] & 0x01 else 0
        return 10 + raw[at + 1] + 2 + signed, raw[at + 7] | (raw[at + 8] << 8) | (raw[at + 9] << 16)
    return None


def _checksum_ok(raw: Any, at: int, end: int, extra: int, x25crc: Any) -> bool:
    """Whether the frame ``raw[at:end]`` carries the right X.25 checksum (with its type's ``crc_extra``): checked
    before pymavlink decodes it, so that bytes of damage cost a checksum each, not a decoding."""
    signed = raw[at] == _V2 and raw[at + 2] & 0x01
    stop = end - 2 - (13 if signed else 0)
    crc = x25crc(bytes(raw[at + 1:stop]) + bytes([extra])).crc
    return crc == raw[stop] | (raw[stop + 1] << 8)


def read_tlog_messages(path: Path, types: list[str]) -> TlogRead:
    """The messages of ``types`` (MAVLink names, ``"RAW_IMU"``) in ``path``, in file order, each with its receipt
    time as ``_timestamp`` (s since 1970), as pymavlink gives them; see the module docstring for the damage rules."""
    mavlink = require("pymavlink.dialects.v20.ardupilotmega")
    crc_extra = {cls.id: cls.crc_extra for cls in mavlink.mavlink_map.values() if cls.msgname in set(types)}
    wanted = set(crc_extra)
    try:
        raw: Any = Path(path).read_bytes()
    except OSError as exc:
        raise TrimagInputError(f"{path}: cannot read the log ({exc.strerror or exc})") from None
    link = mavlink.MAVLink(None)
    link.robust_parsing = True
    n = len(raw)
    messages: list[Any] = []
    times: list[float] = []
    skipped = 0
    pos = 0
    while pos + 8 + 8 <= n:
        at = pos + 8
        frame = _frame_length(raw, at, n)
        if frame is None or at + frame[0] > n:
            step = 1
            if raw[at] not in (_V1, _V2):  # jump to the next byte that can start a frame
                found = _MAGIC.search(raw, at + 1)
                step = (found.start() - at) if found else n - pos
            pos += step
            skipped += step
            continue
        end = at + frame[0]
        if frame[1] in wanted:
            if not _checksum_ok(raw, at, end, crc_extra[frame[1]], mavlink.x25crc):
                pos += 1
                skipped += 1
                continue
            try:
                msg = link.decode(bytearray(raw[at:end]))
            except Exception:
                pos += 1
                skipped += 1
                continue
            msg._timestamp = int.from_bytes(raw[pos:at], "big") * 1e-6
            messages.append(msg)
            times.append(msg._timestamp)
        elif end + 9 <= n and _frame_length(raw, end + 8, n) is None:
            pos += 1  # an unchecked frame whose end is not the start of the next record: not a frame
            skipped += 1
            continue
        pos = end
    bad_time = 0
    if times:
        t = np.asarray(times)
        bad = np.abs(t - np.median(t)) > MAX_TIME_FROM_MEDIAN_S
        bad_time = int(bad.sum())
        if bad_time:
            messages = [m for m, b in zip(messages, bad.tolist(), strict=True) if not b]
    return TlogRead(messages, skipped + (n - pos), bad_time)  # n - pos: a last record cut short
