"""The one chunk setting of every pass over samples (not public API).

Every sum, product or design built over samples is taken chunk by chunk, so memory does not grow with N and the
chunk's temporaries stay in cache. How many rows a chunk holds follows from ONE setting, the working memory of a
chunk in bytes (like scikit-learn's ``working_memory``): a pass whose rows need ``d`` doubles of temporaries takes
``working_memory // (8 d)`` rows at a time (:func:`chunk_rows`). At the default, a pass over plain (N, 3) samples
takes 65 536 rows (the size measured fastest for the component-major blocks of :mod:`trimag._core.rowwise`), a
residual with ~24 temporaries per row 8192 (:mod:`trimag.estimators.ml`), and a blocked QR panel stays within
1/12 of it, 128 KiB (:mod:`trimag._core.qr`).

Every pass walks its rows with :func:`row_blocks` (a slice per chunk). Tests shrink every chunk at once with
:func:`working_memory_limit` (the ``small_chunks`` fixture), so one test covers the multi-chunk path of every
pass.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar

__all__ = [
    "DEFAULT_CHUNK_ROWS",
    "WORKING_MEMORY_BYTES",
    "chunk_rows",
    "qr_panel_bytes",
    "read_block_bytes",
    "row_blocks",
    "working_memory",
    "working_memory_limit",
]

#: Default working memory of one chunk: 65 536 rows of three float64 components (1.5 MiB).
WORKING_MEMORY_BYTES = 65_536 * 3 * 8
#: Rows per chunk of a file read in a stream (``trimag apply``/``evaluate`` on large files; ``--chunk-rows``).
DEFAULT_CHUNK_ROWS = 200_000

_WORKING_MEMORY: ContextVar[int] = ContextVar("trimag_working_memory", default=WORKING_MEMORY_BYTES)


def working_memory() -> int:
    """The working memory of one chunk, bytes (:data:`WORKING_MEMORY_BYTES` unless limited)."""
    return _WORKING_MEMORY.get()


@contextmanager
def working_memory_limit(nbytes: int) -> Iterator[None]:
    """Use ``nbytes`` of working memory per chunk inside the ``with`` block (tests use a few hundred bytes to
    make every pass take many chunks)."""
    if nbytes < 8:
        raise ValueError(f"working memory must be at least 8 bytes; got {nbytes}")
    token = _WORKING_MEMORY.set(int(nbytes))
    try:
        yield
    finally:
        _WORKING_MEMORY.reset(token)


def chunk_rows(doubles_per_row: float = 3.0) -> int:
    """Rows per chunk of a pass whose rows need ``doubles_per_row`` float64 values of temporaries (at least 1)."""
    return max(1, int(_WORKING_MEMORY.get() // (8.0 * doubles_per_row)))


def row_blocks(n: int, doubles_per_row: float = 3.0, *, rows: int | None = None) -> Iterator[slice]:
    """The one chunked pass over ``n`` samples: consecutive row slices of :func:`chunk_rows` (``doubles_per_row``)
    rows each, or of ``rows`` rows (e.g. a QR panel's, :func:`~trimag._core.qr.panel_rows`); the last is shorter."""
    step = max(1, int(rows)) if rows is not None else chunk_rows(doubles_per_row)
    for start in range(0, n, step):
        yield slice(start, min(start + step, n))


def read_block_bytes(estimate: int) -> int:
    """Bytes per block of a streamed CSV reader for an ``estimate`` of a chunk's bytes, clipped to 1/24 .. 2/3 of
    the working memory (64 KiB .. 1 MiB at the default): pyarrow keeps some tens of blocks' worth of buffers
    alive while streaming (measured: pool peak ~40x the block size), so blocks stay small; 1 MiB blocks read as
    fast as 7 MiB ones (docs/performance.md)."""
    wm = _WORKING_MEMORY.get()
    return int(min(max(estimate, wm // 24), wm * 2 // 3))


def qr_panel_bytes() -> int:
    """Bytes of one panel factored per LAPACK call by :class:`~trimag._core.qr.BlockedQR`: 1/12 of the working
    memory (128 KiB at the default, a panel that stays in the L2 cache; measured 3x faster per row than
    65 536-row panels, docs/performance.md)."""
    return max(64, _WORKING_MEMORY.get() // 12)
