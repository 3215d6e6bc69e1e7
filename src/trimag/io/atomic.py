"""Atomic output files: written under a temporary name in the target's folder, renamed when complete.

A reader never sees a half-written file, an error (or SIGINT) leaves no temporary file and any previous file
untouched. Only a regular file is ever replaced: an output path that is a symbolic link, a FIFO, a device, a socket
or a folder is refused (:func:`check_output_path`), so ``-o /dev/sda`` or a link planted in a shared folder never
redirects a write (issue 33, item 5).
"""

from __future__ import annotations

import os
import stat
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from ..errors import TrimagInputError

__all__ = ["atomic_path", "atomic_write_text", "check_output_path"]

_KINDS = ((stat.S_ISLNK, "a symlink (symbolic link)"), (stat.S_ISDIR, "a folder"),
          (stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def check_output_path(path: str | os.PathLike[str]) -> None:
    """Refuse an output ``path`` that exists and is not a regular file (a symlink, even to a regular file; a FIFO,
    a device, a socket, a folder): :class:`TrimagInputError` naming what it is. A missing path passes."""
    try:
        mode = os.lstat(path).st_mode
    except OSError:  # missing (the usual case), or not reachable: the write itself says why
        return
    if stat.S_ISREG(mode):
        return
    kind = next((name for test, name in _KINDS if test(mode)), "a special file")
    raise TrimagInputError(f"{os.fspath(path)} is {kind}, not a regular file: trimag writes an output as a new regular "
                           "file and replaces nothing else; give another path")


@contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is renamed to ``path``, on error removed. ``path`` must
    be missing or a regular file (:func:`check_output_path`)."""
    check_output_path(path)
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    os.close(fd)
    os.chmod(tmp, 0o644)  # mkstemp creates 0600; outputs are ordinary files
    try:
        yield Path(tmp)
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically (:func:`atomic_path`); returns the path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)
