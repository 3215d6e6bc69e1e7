"""Limits on what a text file may make trimag hold in memory, whoever wrote the file (issue 33, item 4).

Reading a log costs memory in proportion to its size (docs/performance.md: 2 to 17 bytes per byte of CSV text, the
shorter the rows the more). Two things break that proportion, and both are bounded here:

- **fields per line**: a 2 MB line of a million fields became a table of a million columns (6.3 GB). A line of
  more than ``max_fields`` fields, or longer than ``max_fields * 100`` bytes (at least 1 MB), among the lines the
  readers sniff the layout from, is refused; a longer line further on is refused by the parser (its row has another
  number of fields) without being split.
- **decompressed size**: a 4.4 MB ``.gz`` of 1 GB of zeros. Compressed input (gzip, bzip2, xz, zip, and the members of
  an ``.npz``) is decompressed in chunks and refused beyond ``max_decompressed_mb`` megabytes (10^6 bytes).

The limits are a context (:func:`input_limits`, a :class:`contextvars.ContextVar` like the chunk setting of
:mod:`trimag._core.chunks`): ``trimag`` sets them from ``--max-fields`` and ``--max-decompressed-mb``, ``trimag
batch`` hands them to its worker processes, and a Python caller writes ``with input_limits(max_fields=50_000):``.
"""

from __future__ import annotations

import contextvars
import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from ..errors import TrimagInputError

__all__ = ["InputLimits", "current_limits", "input_limits", "read_head_lines"]


#: The largest limits that can be set: 10^8 fields per line (a 10 GB line) and 10^9 MB (a petabyte) decompressed;
#: beyond them a limit only overflows the integers it sizes.
MAX_FIELDS_LIMIT = 10**8
MAX_DECOMPRESSED_MB_LIMIT = 1e9


@dataclass(frozen=True)
class InputLimits:
    """What one input file may make trimag hold.

    Attributes
    ----------
    max_fields : int
        Most fields on one line of delimited text (``--max-fields``).
    max_decompressed_mb : float
        Most megabytes (10^6 bytes) a compressed input may expand to (``--max-decompressed-mb``).
    """

    max_fields: int = 10_000
    max_decompressed_mb: float = 1024.0

    def __post_init__(self) -> None:
        if isinstance(self.max_fields, bool) or not isinstance(self.max_fields, int) or \
                not 3 <= self.max_fields <= MAX_FIELDS_LIMIT:
            raise TrimagInputError(f"`max_fields` must be an integer from 3 (x, y, z) to {MAX_FIELDS_LIMIT:.0e}; got "
                                   f"{self.max_fields!r}")
        mb = self.max_decompressed_mb
        if isinstance(mb, bool) or not isinstance(mb, int | float) or not (math.isfinite(mb) and
                                                                          0 < mb <= MAX_DECOMPRESSED_MB_LIMIT):
            raise TrimagInputError(f"`max_decompressed_mb` must be a positive number of megabytes, at most "
                                   f"{MAX_DECOMPRESSED_MB_LIMIT:.0e}; got {mb!r}")

    @property
    def max_line_bytes(self) -> int:
        """Longest line the layout sniffer reads: 100 bytes per field allowed, at least 1 MB."""
        return max(100 * self.max_fields, 1_000_000)

    @property
    def max_decompressed_bytes(self) -> int:
        return int(self.max_decompressed_mb * 1e6)

    def too_many_fields(self, where: str, line_number: int, n_fields: int) -> TrimagInputError:
        """The refusal of a line of ``n_fields`` fields (1-based ``line_number``) in ``where``."""
        return TrimagInputError(
            f"{where}: line {line_number} has {n_fields} fields, more than {self.max_fields} (the limit on fields "
            "per line); if this is a log with that many columns, raise it with `max_fields=N`"
        )

    def too_long(self, where: str, line_number: int) -> TrimagInputError:
        """The refusal of a line longer than :attr:`max_line_bytes`."""
        return TrimagInputError(
            f"{where}: line {line_number} is longer than {self.max_line_bytes / 1e6:.3g} MB without a line break (not "
            f"a text log, or a line of more than {self.max_fields} fields, the limit on fields per line); if it is "
            "a log with that many columns, raise the limit with `max_fields=N`"
        )

    def too_large(self, where: str, what: str = "decompressed") -> TrimagInputError:
        """The refusal of a compressed input that expands past :attr:`max_decompressed_mb`."""
        return TrimagInputError(
            f"{where}: more than {self.max_decompressed_mb:g} MB when {what} (the limit on decompressed input); if "
            "the log is that large, raise it with `max_decompressed_mb=MB`"
        )


_LIMITS: contextvars.ContextVar[InputLimits] = contextvars.ContextVar(
    "trimag_input_limits", default=InputLimits()  # noqa: B039 (frozen: immutable)
)


def current_limits() -> InputLimits:
    """The limits in force (the defaults of :class:`InputLimits` unless :func:`input_limits` set others)."""
    return _LIMITS.get()


@contextmanager
def input_limits(max_fields: int | None = None, max_decompressed_mb: float | None = None) -> Iterator[InputLimits]:
    """Set the input limits inside the ``with`` block (None: keep the one in force); yields them."""
    now = _LIMITS.get()
    limits = InputLimits(now.max_fields if max_fields is None else max_fields,
                         now.max_decompressed_mb if max_decompressed_mb is None else max_decompressed_mb)
    token = _LIMITS.set(limits)
    try:
        yield limits
    finally:
        _LIMITS.reset(token)


def read_head_lines(path: str | Path, n: int, *, where: str | None = None) -> list[str]:
    """The first ``n`` lines of a text file (UTF-8, undecodable bytes replaced, line ends kept), each read with a
    bounded length: a line longer than the limit in force is refused (:meth:`InputLimits.too_long`), never read
    whole. ``where`` names the file in the message (default: ``path``)."""
    limits = current_limits()
    cap = limits.max_line_bytes
    out: list[str] = []
    with Path(path).open("r", encoding="utf-8", errors="replace", newline="") as fh:
        for k in range(n):
            line = fh.readline(cap + 1)
            if not line:
                break
            if len(line) > cap and not line.endswith(("\n", "\r")):
                raise limits.too_long(str(where or path), k + 1)
            out.append(line)
    return out
