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
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

from ..errors import TrimagInputError

__all__ = ["atomic_path", "atomic_write_text", "check_distinct_outputs", "check_output_path", "same_file"]

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


def _file_key(path: str | os.PathLike[str]) -> tuple[object, ...]:
    """What identifies the file ``path`` names: its device and inode when it exists (through symbolic and hard
    links), else its absolute path with links, ``.`` and ``..`` resolved."""
    try:
        resolved = str(Path(path).resolve())  # ("a/missing/../b" names a/b, which os.stat does not see)
    except (OSError, RuntimeError):  # unreachable, or a symbolic link loop
        resolved = os.path.abspath(path)
    for name in (path, resolved):
        try:
            st = os.stat(name)
            return ("inode", st.st_dev, st.st_ino)
        except (OSError, ValueError):
            pass
    return ("path", resolved)


def same_file(a: str | os.PathLike[str], b: str | os.PathLike[str]) -> bool:
    """Whether two paths name the same file: through symbolic and hard links, ``.``, ``..`` and relative paths."""
    return _file_key(a) == _file_key(b)


PathMap = Mapping[str, "str | os.PathLike[str] | None"]


def check_distinct_outputs(inputs: PathMap, outputs: PathMap) -> None:
    """Refuse (:class:`TrimagInputError`, exit 2, before anything is written) an output that is one of the inputs or
    the same file as another output. ``inputs`` map how the message names each input (``"the input"``, ``"the
    `prior`"``) to its path, ``outputs`` each output's option (``"out"``) to its path; None and ``"-"`` (standard
    input or output) are left out. One ``stat`` per path (a batch of many files is checked in linear time)."""
    def named(paths: PathMap) -> list[tuple[str, str | os.PathLike[str]]]:
        return [(k, p) for k, p in paths.items() if p is not None and str(p) not in ("", "-")]

    read = {_file_key(given): (source, given) for source, given in reversed(named(inputs))}
    seen: dict[tuple[object, ...], tuple[str, str | os.PathLike[str]]] = {}
    for what, path in named(outputs):
        key = _file_key(path)
        if key in read:
            source, given = read[key]
            raise TrimagInputError(f"`{what}` {os.fspath(path)} would replace {source} {os.fspath(given)}; give the "
                                   "output another name")
        if key in seen:
            raise TrimagInputError(f"`{seen[key][0]}` and `{what}` are the same file ({os.fspath(path)}); give two "
                                   "names")
        seen[key] = (what, path)


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
