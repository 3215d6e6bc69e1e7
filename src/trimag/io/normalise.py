"""Text inputs people have, turned into what the readers expect: compressed files and decimal commas.

``plain_path(path)`` returns ``path`` itself for an ordinary file, or a normalised copy in a temporary folder of
this process (removed at exit) for:

- gzip, bzip2, xz and zip (one member) compressed text, recognised by their magic bytes;
- ``;``-separated text with decimal commas (``1,25;-0,5;48,1``, as spreadsheets in many locales write it):
  rewritten with ``,`` between fields and ``.`` as the decimal mark.

The copy keeps the file's name without the compression suffix, so the format is still guessed from it.
"""

from __future__ import annotations

import atexit
import bz2
import gzip
import lzma
import re
import shutil
import tempfile
import zipfile
from pathlib import Path
from typing import Any

from ..errors import TrimagInputError

__all__ = ["plain_path"]

_MAGIC = {b"\x1f\x8b": "gzip", b"BZh": "bzip2", b"\xfd7zXZ\x00": "xz", b"PK\x03\x04": "zip"}
_SUFFIXES = {".gz", ".gzip", ".bz2", ".xz", ".zip"}
_DECIMAL_COMMA = re.compile(r"^\s*[-+]?\d+(,\d+)?(\s*;\s*[-+]?\d+(,\d+)?)+\s*$")
_BINARY = {".npz", ".npy", ".mat", ".parquet", ".pq", ".bin", ".ulg", ".tlog", ".px4log", ".bag", ".mcap", ".h5",
           ".hdf5", ".xlsx"}  # formats of their own (an .npz is a zip file): never touched
_tmpdir: Path | None = None


def _workdir() -> Path:
    global _tmpdir
    if _tmpdir is None:
        _tmpdir = Path(tempfile.mkdtemp(prefix="trimag-input-"))
        atexit.register(shutil.rmtree, _tmpdir, True)
    return _tmpdir


def _compression(path: Path) -> str | None:
    try:
        with path.open("rb") as fh:
            head = fh.read(6)
    except OSError:
        return None
    return next((kind for magic, kind in _MAGIC.items() if head.startswith(magic)), None)


def _decompress(path: Path, kind: str) -> Path:
    name = path.name
    for suffix in _SUFFIXES:
        if name.lower().endswith(suffix):
            name = name[: -len(suffix)]
    out = _workdir() / (name or "data.csv")
    try:
        if kind == "zip":
            with zipfile.ZipFile(path) as zf:
                members = [m for m in zf.namelist() if not m.endswith("/")]
                if len(members) != 1:
                    raise TrimagInputError(f"{path}: the zip file holds {len(members)} files; give one log")
                out = _workdir() / Path(members[0]).name
                with zf.open(members[0]) as src, out.open("wb") as dst:
                    shutil.copyfileobj(src, dst)
        else:
            opener: Any = {"gzip": gzip.open, "bzip2": bz2.open, "xz": lzma.open}[kind]
            with opener(path, "rb") as src, out.open("wb") as dst:
                shutil.copyfileobj(src, dst)
    except (OSError, EOFError, zipfile.BadZipFile, lzma.LZMAError) as exc:
        raise TrimagInputError(f"{path}: a damaged {kind} file ({exc})") from None
    return out


def _decimal_comma(path: Path) -> Path | None:
    try:
        with path.open("r", encoding="utf-8", errors="replace") as fh:
            head = [fh.readline() for _ in range(50)]
    except OSError:
        return None
    numeric = [ln for ln in head if ln.strip() and _DECIMAL_COMMA.match(ln)]
    if len(numeric) < 2 or not any("," in ln for ln in numeric):
        return None
    out = _workdir() / path.name
    with path.open("r", encoding="utf-8", errors="strict") as src, out.open("w", encoding="utf-8") as dst:
        for line in src:
            dst.write(line.replace(",", ".").replace(";", ",") if _DECIMAL_COMMA.match(line) else
                      line.replace(",", " ").replace(";", ","))
    return out


def plain_path(path: str | Path) -> Path:
    """``path``, or a normalised copy of it (see the module docstring)."""
    p = Path(path)
    if not p.is_file() or p.suffix.lower() in _BINARY:
        return p
    kind = _compression(p)
    if kind is not None:
        p = _decompress(p, kind)
    if p.suffix.lower() in (".csv", ".txt", ".dat", ".tsv", ""):
        converted = _decimal_comma(p)
        if converted is not None:
            return converted
    return p
