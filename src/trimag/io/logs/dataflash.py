"""A fast reader of binary ArduPilot DataFlash logs: only the message types asked for, decoded with numpy.

A DataFlash log is a stream of messages ``0xA3 0x95 TYPE PAYLOAD``; ``FMT`` messages (type 128) give each type's
length, name, field formats and names. pymavlink decodes message by message in Python (about 40 s for a 100 MB
log here); this reader walks the stream once to find where each wanted message starts (a Python loop over
message offsets, no decoding), then decodes all messages of a type at once through a numpy structured dtype
(docs/performance.md, "At a glance"). The file is memory-mapped; memory grows with the messages
wanted, not with the file.

Field formats and scales follow pymavlink's ``DFReader`` (``c``/``C``/``e``/``E`` x 0.01, ``L`` x 1e-7).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ...errors import TrimagInputError

__all__ = ["field_units", "read_dataflash"]

_HEAD = b"\xa3\x95"
_FMT_TYPE = 128
_FMT_LENGTH = 89
_FORMATS: dict[str, tuple[str, float]] = {
    "b": ("i1", 1.0), "B": ("u1", 1.0), "h": ("<i2", 1.0), "H": ("<u2", 1.0), "i": ("<i4", 1.0),
    "I": ("<u4", 1.0), "f": ("<f4", 1.0), "d": ("<f8", 1.0), "n": ("S4", 1.0), "N": ("S16", 1.0),
    "Z": ("S64", 1.0), "c": ("<i2", 0.01), "C": ("<u2", 0.01), "e": ("<i4", 0.01), "E": ("<u4", 0.01),
    "L": ("<i4", 1e-7), "M": ("u1", 1.0), "q": ("<i8", 1.0), "Q": ("<u8", 1.0), "a": ("(32,)<i2", 1.0),
}


def _parse_fmt(payload: bytes) -> tuple[int, int, str, str, list[str]]:
    mtype, length = payload[0], payload[1]
    name = payload[2:6].rstrip(b"\x00").decode("ascii", "replace")
    fmt = payload[6:22].rstrip(b"\x00").decode("ascii", "replace")
    cols = payload[22:86].rstrip(b"\x00").decode("ascii", "replace").split(",")
    return mtype, length, name, fmt, cols


def read_dataflash(
    path: str | Path, types: list[str], formats: dict[str, tuple[int, str, list[str]]] | None = None,
    progress: Callable[[float, str], None] | None = None,
) -> dict[str, dict[str, NDArray[np.generic]]]:
    """Columns of every message of the named ``types`` in a binary DataFlash log.

    ``formats``, when given, receives every message type's ``(type number, format characters, column names)`` from
    the log's FMT messages (what the units of a field depend on: :func:`field_units`). ``progress``, when given,
    is called as ``progress(fraction, what)`` every :data:`PROGRESS_BYTES` of the scan (fraction of the file's
    bytes, 0..1) and once more at the end (1.0).

    Returns
    -------
    dict
        ``{type name: {field name: ndarray (n,)}}``; string fields (``n``, ``N``, ``Z``) are decoded to ``str``
        arrays, scaled formats are float64. Types the log does not have are absent.
    """
    p = Path(path)
    try:
        data = np.memmap(p, dtype=np.uint8, mode="r")
    except (OSError, ValueError) as exc:
        raise TrimagInputError(f"{p}: cannot read the log ({exc})") from None
    lengths, found, starts = _scan(data, set(types), progress)
    if not found:
        raise TrimagInputError(f"{p}: not a binary DataFlash log (no FMT messages)")
    if formats is not None:
        formats.update({name: (mtype, fmt, cols) for mtype, (name, fmt, cols) in found.items()})
    out: dict[str, dict[str, NDArray[np.generic]]] = {}
    for mtype, positions in starts.items():
        if not positions:
            continue
        name, fmt, cols = found[mtype]
        fields = _decode(p, data, name, fmt, cols, positions, lengths[mtype])
        if fields is not None:
            out[name] = fields
    if progress is not None:
        progress(1.0, f"read {len(data) / 1e6:.0f} MB")
    return out


#: How often (bytes of the log scanned) :func:`read_dataflash` reports its progress.
PROGRESS_BYTES = 4 << 20


def _scan(
    data: NDArray[np.uint8], wanted_names: set[str], progress: Callable[[float, str], None] | None = None,
) -> tuple[list[int], dict[int, tuple[str, str, list[str]]], dict[int, list[int]]]:
    """One pass over the log's messages: each type's length and ``(name, format, columns)`` from the FMT messages,
    and the byte offsets of the messages of the wanted types. Bytes that do not start a known message are
    skipped one at a time (a torn write, a log cut short)."""
    raw = data.tobytes() if len(data) < 1 << 20 else data.data  # small files: bytes are faster to index
    n = len(data)
    lengths = [0] * 256
    lengths[_FMT_TYPE] = _FMT_LENGTH
    formats: dict[int, tuple[str, str, list[str]]] = {}
    wanted: set[int] = set()
    starts: dict[int, list[int]] = {}
    pos = 0
    report = PROGRESS_BYTES if progress is not None else n + 1
    while pos + 3 <= n:
        if pos >= report:
            progress(pos / n, f"scanning the log: {pos / 1e6:.0f} of {n / 1e6:.0f} MB")  # type: ignore[misc]
            report += PROGRESS_BYTES
        if raw[pos] != 0xA3 or raw[pos + 1] != 0x95:
            pos += 1
            continue
        mtype = raw[pos + 2]
        length = lengths[mtype]
        if length == 0 or pos + length > n:
            pos += 1
            continue
        if mtype == _FMT_TYPE:
            t, ln, name, fmt, cols = _parse_fmt(bytes(raw[pos + 3 : pos + _FMT_LENGTH]))
            if t != _FMT_TYPE:
                lengths[t] = ln
                formats[t] = (name, fmt, cols)
                if name in wanted_names:
                    wanted.add(t)
                    starts.setdefault(t, [])
        elif mtype in wanted:
            starts[mtype].append(pos)
        pos += length
    return lengths, formats, starts


def _decode(
    p: Path, data: NDArray[np.uint8], name: str, fmt: str, cols: list[str], positions: list[int], length: int
) -> dict[str, NDArray[np.generic]] | None:
    """The columns of one message type from its messages' offsets (None for a format this reader does not size
    like the firmware: the type is skipped rather than misread)."""
    try:
        dtype = np.dtype([(f"f{k}", _FORMATS[c][0]) for k, c in enumerate(fmt)])
    except KeyError as exc:
        raise TrimagInputError(f"{p}: message {name} has an unknown field format {exc.args[0]!r}") from None
    if dtype.itemsize != length - 3:
        return None
    idx = np.asarray(positions, dtype=np.int64)[:, None] + 3 + np.arange(dtype.itemsize)
    records = np.ascontiguousarray(data[idx]).view(dtype).ravel()
    fields: dict[str, NDArray[np.generic]] = {}
    for k, (c, col) in enumerate(zip(fmt, cols, strict=False)):
        values = records[f"f{k}"]
        kind, scale = _FORMATS[c]
        if kind.startswith("S"):
            fields[col] = np.char.decode(np.char.rstrip(values, b"\x00"), "ascii", "replace")
        elif scale != 1.0:
            fields[col] = values.astype(np.float64) * scale
        else:
            fields[col] = values
    return fields


#: Format characters whose values the reader already scales (``c``/``C``/``e``/``E`` x 0.01, ``L`` x 1e-7).
SCALED_FORMATS = frozenset("cCeEL")


def field_units(cols: dict[str, dict[str, NDArray[np.generic]]],
                formats: dict[str, tuple[int, str, list[str]]]) -> dict[str, dict[str, tuple[str, float | None]]]:
    """``{type: {field: (unit label, multiplier)}}`` from a log's ``FMTU``, ``UNIT`` and ``MULT`` messages (ArduPilot
    ``libraries/AP_Logger/LogStructure.h``: the physical value is the logged integer times the multiplier); the
    multiplier is None where the log gives none (``-``), 1 for fields whose format the reader scales itself
    (:data:`SCALED_FORMATS`). Empty for a log without ``FMTU`` (ArduPilot before 3.6 or so)."""
    fmtu, unit, mult = cols.get("FMTU"), cols.get("UNIT"), cols.get("MULT")
    if not fmtu or not mult:
        return {}
    def char(i: object) -> str:  # the Id fields are int8 ('b'): a character code
        return chr(int(i)) if not isinstance(i, str) else i  # type: ignore[call-overload]

    labels = {char(i): str(v) for i, v in zip(unit["Id"], unit["Label"], strict=True)} if unit else {}
    factors = {char(i): float(v) for i, v in zip(mult["Id"], mult["Mult"], strict=True)}
    type_names = {int(t): n for n, (t, _, _) in formats.items()}
    out: dict[str, dict[str, tuple[str, float | None]]] = {}
    for ftype, unit_ids, mult_ids in zip(fmtu["FmtType"], fmtu["UnitIds"], fmtu["MultIds"], strict=True):
        name = type_names.get(int(ftype))
        if name is None:
            continue
        _, fmt, columns = formats[name]
        fields = {}
        for k, col in enumerate(columns):
            u = labels.get(str(unit_ids)[k:k + 1], "")
            m = factors.get(str(mult_ids)[k:k + 1], 0.0)
            scaled = k < len(fmt) and fmt[k] in SCALED_FORMATS
            fields[col] = (u, 1.0 if scaled else (None if m == 0.0 else m))
        out[name] = fields
    return out
