"""A minimal binary DataFlash writer for tests: FMT messages, then the messages of each type (libraries/AP_Logger:
``0xA3 0x95 TYPE PAYLOAD``; FMT = type 128, ``BBnNZ``: Type, Length, Name, Format, Columns)."""

from __future__ import annotations

import struct
from collections.abc import Sequence
from pathlib import Path
from typing import Any

_STRUCT = {"b": "b", "B": "B", "h": "h", "H": "H", "i": "i", "I": "I", "f": "f", "d": "d", "n": "4s", "N": "16s",
           "Z": "64s", "c": "h", "C": "H", "e": "i", "E": "I", "L": "i", "M": "B", "q": "q", "Q": "Q"}
_SCALE = {"c": 100.0, "C": 100.0, "e": 100.0, "E": 100.0, "L": 1e7}


def _pack(fmt: str, values: Sequence[Any]) -> bytes:
    out = []
    for c, v in zip(fmt, values, strict=True):
        if c in "nNZ":
            out.append(v.encode() if isinstance(v, str) else v)
        elif c in _SCALE:
            out.append(round(v * _SCALE[c]))
        else:
            out.append(v)
    return struct.pack("<" + "".join(_STRUCT[c] for c in fmt), *out)


def write_dataflash(path: Path, types: dict[str, tuple[str, str, list[Sequence[Any]]]]) -> Path:
    """``types``: name -> (format, comma-separated columns, rows); values of scaled formats in physical units."""
    body = bytearray()
    ids = {}
    fmt_payload = struct.pack("<BB4s16s64s", 128, 89, b"FMT", b"BBnNZ", b"Type,Length,Name,Format,Columns")
    body += b"\xa3\x95\x80" + fmt_payload
    for k, (name, (fmt, cols, _)) in enumerate(types.items()):
        ids[name] = 130 + k
        length = 3 + struct.calcsize("<" + "".join(_STRUCT[c] for c in fmt))
        body += b"\xa3\x95\x80" + struct.pack("<BB4s16s64s", ids[name], length, name.encode(), fmt.encode(),
                                              cols.encode())
    for name, (fmt, _, rows) in types.items():
        for row in rows:
            body += b"\xa3\x95" + bytes([ids[name]]) + _pack(fmt, row)
    path.write_bytes(bytes(body))
    return path
