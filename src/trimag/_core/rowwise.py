"""Row-wise arithmetic on (N, 3) sample arrays (not public API).

numpy subtracts a (3,) vector from an (N, 3) array, or multiplies it by a 3 x 3 matrix, with an inner loop of
length 3, which costs 5-10x the same work on the transposed (3, N) layout, where each component is one
contiguous pass (measured: ``(B - b) @ W.T`` on 65 536 rows 2.0 ms, the blocked transposed form 0.25 ms). The
helpers here transpose chunks of :func:`~trimag._core.chunks.chunk_rows` rows (65 536 at the default setting, a
size that stays in cache) and work component by component.

Block buffers come from :func:`scratch`, a per-thread pool of reused arrays. A fresh array of more than 128 KiB is
mapped by the allocator and costs a page fault per 4 KiB on first touch, and glibc returns freed memory to the
system, so a fit that allocates its block buffers anew pays those faults on every call (measured: ~2 us each,
1600 per ``ellipsoid-fit`` at N = 1e5, a third of its time).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import numpy as np
from numpy.typing import NDArray

from .chunks import chunk_rows

__all__ = ["affine", "column_means", "count_duplicate_rows", "row_dot", "scratch", "sum_squares", "transposed_blocks"]

#: Buffers of :func:`scratch` up to this many doubles (4 MiB) are kept for reuse; larger ones are freed.
SCRATCH_KEEP = 1 << 19
#: Buffers kept per thread (the smallest is dropped beyond this).
SCRATCH_POOL = 8
_pool = threading.local()


@contextmanager
def scratch(*shape: int) -> Iterator[NDArray[np.float64]]:
    """A C-contiguous float64 array of ``shape`` with undefined contents, lent from this thread's pool of reused
    buffers for the duration of the ``with`` block (nested uses get distinct buffers). Never return it or a view
    of it to a caller."""
    free: list[NDArray[np.float64]] = _pool.__dict__.setdefault("free", [])
    need = math.prod(shape)
    fits = [i for i, b in enumerate(free) if b.size >= need]
    buf = free.pop(min(fits, key=lambda i: free[i].size)) if fits else np.empty(max(need, 1))
    try:
        yield buf[:need].reshape(shape)
    finally:
        if buf.size <= SCRATCH_KEEP:
            free.append(buf)
            if len(free) > SCRATCH_POOL:
                del free[min(range(len(free)), key=lambda i: free[i].size)]  # by index: arrays have no ==


def row_dot(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Row-wise dot products ``sum_k a_ik b_ik`` of two (N, 3) arrays -> (N,).

    Three column products: about 5x faster than ``np.einsum("ij,ij->i", a, b)``, whose inner loop over 3
    elements dominates; other shapes fall back to ``einsum``.
    """
    if a.ndim == 2 and a.shape[1] == 3 and b.shape == a.shape:
        out = a[:, 0] * b[:, 0]
        out += a[:, 1] * b[:, 1]
        out += a[:, 2] * b[:, 2]
        return out
    return np.asarray(np.einsum("...i,...i->...", a, b), dtype=np.float64)


def transposed_blocks(
    B: NDArray[np.float64], offset: NDArray[np.float64] | None = None, *, block: int | None = None
) -> Iterator[tuple[int, NDArray[np.float64]]]:
    """Yield ``(start, T)`` for consecutive blocks of ``B`` (N, 3): ``T`` (3, m) is ``(B[start:start+m] - offset).T``,
    C-contiguous. ``T`` is a reused buffer: use it before the next block is requested. ``block``: rows per block
    (default :func:`~trimag._core.chunks.chunk_rows`)."""
    n = len(B)
    block = block or chunk_rows()
    with scratch(3, min(max(n, 1), block)) as buf:
        for start in range(0, n, block):
            rows = B[start : start + block]
            t = buf[:, : len(rows)]
            np.copyto(t, rows.T)
            if offset is not None:
                t -= np.asarray(offset, dtype=np.float64)[:, None]
            yield start, t


def sum_squares(
    t: NDArray[np.float64], *, out: NDArray[np.float64], tmp: NDArray[np.float64]
) -> NDArray[np.float64]:
    """``t[0]^2 + t[1]^2 + t[2]^2`` of a component-major block ``t`` (3, m), in that order, into ``out`` (m,);
    ``tmp`` (m,) is scratch. Returns ``out``."""
    np.multiply(t[0], t[0], out=out)
    out += np.multiply(t[1], t[1], out=tmp)
    out += np.multiply(t[2], t[2], out=tmp)
    return out


def affine(
    B: NDArray[np.float64], matrix: NDArray[np.float64], offset: NDArray[np.float64]
) -> NDArray[np.float64]:
    """``(B - offset) @ matrix.T`` for ``B`` (N, 3), ``matrix`` (3, 3), ``offset`` (3,): a new (N, 3) array."""
    out = np.empty((len(B), 3))
    matrix = np.ascontiguousarray(matrix, dtype=np.float64)
    with scratch(3, min(max(len(B), 1), chunk_rows())) as y:  # the same block size as transposed_blocks
        for start, t in transposed_blocks(B, offset):
            m = t.shape[1]
            np.matmul(matrix, t, out=y[:, :m])
            out[start : start + m] = y[:, :m].T
    return out


def column_means(B: NDArray[np.float64]) -> NDArray[np.float64]:
    """The mean of the rows of ``B`` (N, 3), shape (3,): ``ones @ B`` block by block (a matrix-vector product per
    chunk of rows: ``B.mean(axis=0)`` reduces a strided axis, about 10x slower, and one ``ones(N)``
    would take 8 bytes per row)."""
    n = len(B)
    total = np.zeros(B.shape[1] if B.ndim == 2 else 3)
    block = chunk_rows()
    with scratch(min(max(n, 1), block)) as ones:
        ones.fill(1.0)
        for start in range(0, n, block):
            rows = B[start : start + block]
            total += ones[: len(rows)] @ rows
    return total / max(n, 1)


def count_duplicate_rows(
    field: NDArray[np.float64], prepare: Callable[[NDArray[np.float64]], NDArray[np.float64]] | None = None
) -> int:
    """Rows of ``field`` (N, 3) equal to an earlier row (``pd.DataFrame(field).duplicated().sum()``, exact).

    One 64-bit hash per row finds the candidates (a hash table of N integers instead of one of N rows: about
    10x faster on 1e7 rows); only rows whose hash repeats are compared exactly, so a hash collision never
    counts as a duplicate. ``-0.0`` and ``0.0`` count as equal, as in pandas. ``prepare`` (rows (m, 3) ->
    rows (m, 3), e.g. rounding) is applied block by block before the rows are hashed or compared: the rows of
    ``prepare(field)`` are counted without a prepared copy of the whole ``field``.
    """
    if len(field) < 2:
        return 0
    import pandas as pd  # (here: the fit path of an array needs no pandas otherwise)

    def rows_of(start: int, stop: int) -> NDArray[np.float64]:
        rows = field[start:stop]
        return rows if prepare is None else prepare(rows)

    def rows_of_index(index: NDArray[np.intp]) -> NDArray[np.float64]:
        rows = field[index]
        return rows if prepare is None else prepare(rows)

    h = np.empty(len(field), dtype=np.uint64)
    block = chunk_rows()
    for start in range(0, len(field), block):  # chunks: temporaries of the chunk's size, not N
        rows = rows_of(start, start + block)
        hb = pd.util.hash_array(rows[:, 0] + 0.0)  # contiguous column; + 0.0: -0.0 -> 0.0
        for j in range(1, field.shape[1]):
            hb = hb * np.uint64(0x9E3779B97F4A7C15) ^ pd.util.hash_array(rows[:, j] + 0.0)
        h[start : start + len(rows)] = hb
    # each row's hash with its row number in the low bits, sorted in place (8 bytes per row, no other array of N:
    # issue 41, item 10; the hashes and their argsort took 16): rows of equal (high) hash bits are next to each other
    # in file order, and each row whose hash repeats is compared exactly with the first row of its hash, block by
    # block (pandas' hash tables of every repeated row took ~150 bytes per row, 860 MB for 30 MB of `1,2,3` lines)
    n = len(h)
    shift = np.uint64(max((n - 1).bit_length(), 1))
    for start in range(0, n, block):
        keys = h[start : start + block]
        keys >>= shift
        keys <<= shift
        keys |= np.arange(start, start + len(keys), dtype=np.uint64)
    h.sort()
    low = np.uint64((1 << int(shift)) - 1)
    duplicates = 0
    collided: list[NDArray[np.float64]] = []  # rows of a repeated hash unlike its first row (a hash collision)
    group_start = 0  # the first sorted position of the hash that runs into the next block
    for b0 in range(1, n, block):
        b1 = min(n, b0 + block)
        hashes = h[b0 - 1 : b1] >> shift
        same = hashes[1:] == hashes[:-1]
        new_hashes = np.flatnonzero(~same) + b0
        positions = np.flatnonzero(same) + b0
        if len(positions):
            starts = np.concatenate([[group_start], new_hashes])
            first = starts[np.searchsorted(starts, positions, side="right") - 1]
            rows = rows_of_index((h[positions] & low).astype(np.intp)) + 0.0
            same_rows = (rows == rows_of_index((h[first] & low).astype(np.intp)) + 0.0).all(axis=1)
            duplicates += int(same_rows.sum())
            if not same_rows.all():
                collided.append(rows[~same_rows])
        if len(new_hashes):
            group_start = int(new_hashes[-1])
    if collided:  # rarer than a one in a billion: compared exactly among themselves
        duplicates += int(pd.DataFrame(np.concatenate(collided)).duplicated().sum())
    return duplicates
