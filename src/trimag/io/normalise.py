"""Text inputs people have, turned into what the readers expect: compressed files and decimal commas.

``plain_path(path)`` returns ``path`` itself for an ordinary file, or a normalised copy in a temporary folder of
this process (removed at exit) for:

- gzip, bzip2, xz and zip (one member) compressed text, recognised by their magic bytes;
- ``;``-separated text with decimal commas (``1,25;-0,5;48,1``, as spreadsheets in many locales write it):
  rewritten with ``,`` between fields and ``.`` as the decimal mark.

The copy keeps the file's name without the compression suffix, so the format is still guessed from it, and
messages about it name the file given (:func:`source_name`). Decompression streams in chunks and stops at the limit
of :mod:`trimag.io.limits` (``--max-decompressed-mb``). Inside :func:`scratch_folder` the copies go to a folder the
caller owns and removes (``trimag batch``: one per file, under a folder of the parent process, so that a worker
killed mid-file leaves nothing behind).
"""

from __future__ import annotations

import atexit
import bz2
import contextvars
import gzip
import lzma
import re
import shutil
import tempfile
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from .._core.chunks import read_block_bytes
from ..errors import TrimagInputError
from .limits import current_limits, read_head_lines

__all__ = ["plain_path", "scratch_folder", "source_name"]

_MAGIC = {b"\x1f\x8b": "gzip", b"BZh": "bzip2", b"\xfd7zXZ\x00": "xz", b"PK\x03\x04": "zip"}
_SUFFIXES = {".gz", ".gzip", ".bz2", ".xz", ".zip"}
_DECIMAL_COMMA = re.compile(r"^\s*[-+]?\d+(,\d+)?(\s*;\s*[-+]?\d+(,\d+)?)+\s*$")
_BINARY = {".npz", ".npy", ".mat", ".parquet", ".pq", ".bin", ".ulg", ".tlog", ".px4log", ".bag", ".mcap", ".h5",
           ".hdf5", ".xlsx"}  # formats of their own (an .npz is a zip file): never touched
_tmpdir: Path | None = None
_SCRATCH: contextvars.ContextVar[Path | None] = contextvars.ContextVar("trimag_scratch", default=None)
#: normalised copy -> the path the user gave (for messages)
_SOURCES: dict[Path, str] = {}


def _workdir() -> Path:
    global _tmpdir
    scratch = _SCRATCH.get()
    if scratch is not None:
        return scratch
    if _tmpdir is None:
        _tmpdir = Path(tempfile.mkdtemp(prefix="trimag-input-"))
        atexit.register(shutil.rmtree, _tmpdir, True)
    return _tmpdir


@contextmanager
def scratch_folder(parent: str | Path | None = None) -> Iterator[Path]:
    """Normalised copies made inside the ``with`` block go to a new folder (under ``parent``, or the system's
    temporary folder), removed at its end."""
    folder = Path(tempfile.mkdtemp(prefix="trimag-input-", dir=parent))
    token = _SCRATCH.set(folder)
    try:
        yield folder
    finally:
        _SCRATCH.reset(token)
        for copy in [c for c in _SOURCES if folder in c.parents]:
            del _SOURCES[copy]
        shutil.rmtree(folder, ignore_errors=True)


def source_name(path: str | Path) -> str:
    """The path the user gave for ``path`` (``path`` itself unless it is a normalised copy)."""
    return _SOURCES.get(Path(path), str(path))


def _copy_bounded(src: Any, dst: Any, where: Path, *, text: bool) -> None:
    """Copy the decompressed stream ``src`` to ``dst`` in chunks, refusing it past the decompressed limit, and, for
    ``text``, as soon as its first line is longer than the line limit (a file of zeros is not written out)."""
    limits = current_limits()
    total = 0
    first_line = text
    step = read_block_bytes(1 << 20)  # bytes per step: the streamed readers' block (1 MiB at the default)
    while chunk := src.read(step):
        total += len(chunk)
        if total > limits.max_decompressed_bytes:
            raise limits.too_large(str(where))
        if first_line:
            first_line = b"\n" not in chunk and b"\r" not in chunk
            if first_line and total > limits.max_line_bytes:
                raise limits.too_long(str(where), 1)
        dst.write(chunk)


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
                members = [m for m in zf.infolist() if not m.is_dir()]
                if len(members) != 1:
                    raise TrimagInputError(f"{path}: the zip file holds {len(members)} files; give one log")
                if members[0].file_size > current_limits().max_decompressed_bytes:
                    raise current_limits().too_large(str(path))
                out = _workdir() / Path(members[0].filename).name
                with zf.open(members[0]) as src, out.open("wb") as dst:
                    _copy_bounded(src, dst, path, text=out.suffix.lower() not in _BINARY)
        else:
            opener: Any = {"gzip": gzip.open, "bzip2": bz2.open, "xz": lzma.open}[kind]
            with opener(path, "rb") as src, out.open("wb") as dst:
                _copy_bounded(src, dst, path, text=out.suffix.lower() not in _BINARY)
    except (OSError, EOFError, zipfile.BadZipFile, lzma.LZMAError) as exc:
        out.unlink(missing_ok=True)
        raise TrimagInputError(f"{path}: a damaged {kind} file ({exc})") from None
    except BaseException:
        out.unlink(missing_ok=True)
        raise
    _SOURCES[out] = str(path)
    return out


def _decimal_comma(path: Path) -> Path | None:
    try:
        head = read_head_lines(path, 50, where=source_name(path))
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
    _SOURCES[out] = source_name(path)
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
