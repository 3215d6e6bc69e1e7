"""Least squares on a tall system given block by block: a running QR factorisation (not public API).

For ``min |A x - b|`` with ``A`` (N, p) too large to hold, each block of rows is stacked under the triangular factor
of the rows before and factored again (TSQR): after the last block ``R`` (p, p) and ``c = Q^T b`` (p,) give the
same solution, singular values and residual as a QR of the whole ``A`` (orthogonal transformations only, so no
squaring of the condition number as ``A^T A`` would do), in O(block x p) memory. Each block is factored in panels
of :func:`~trimag._core.chunks.qr_panel_bytes` (128 KiB at the default setting): 3.6 ms per 65 536 rows with
p = 10 (numpy's LAPACK ``dgeqrf``, one thread; 11 ms with whole 65 536-row blocks).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .chunks import qr_panel_bytes

__all__ = ["BlockedQR", "panel_rows"]



def panel_rows(columns: int) -> int:
    """Rows of one panel of ``columns`` float64 columns handed to LAPACK's QR (at least 64): panels that stay in the
    L2 cache (:func:`~trimag._core.chunks.qr_panel_bytes`) were 3x faster per row than 65 536-row blocks on this
    project's 2-core machine (p = 10: 9.9 -> 2.1 ms per 65 536 rows with 2048-row panels; 8 ms with 4096 rows,
    out of cache)."""
    return max(64, qr_panel_bytes() // (8 * columns))


class BlockedQR:
    """Running QR factorisation of ``[A | b]`` (``A``: p columns), fed block by block with :meth:`add`.

    Parameters
    ----------
    p : int
        Columns of ``A``.

    Examples
    --------
    >>> import numpy as np
    >>> A = np.random.default_rng(0).normal(size=(1000, 3)); b = A @ [1.0, 2.0, 3.0]
    >>> qr = BlockedQR(3)
    >>> for s in range(0, 1000, 300):
    ...     qr.add(A[s : s + 300], b[s : s + 300])
    >>> np.allclose(qr.solve(), [1.0, 2.0, 3.0])
    True
    """

    def __init__(self, p: int) -> None:
        self.p = int(p)
        self.rows = 0
        self._R = np.zeros((0, self.p + 1))

    def add(self, A: ArrayLike, b: ArrayLike | None = None) -> None:
        """Append rows ``A`` (m, p) with right-hand side ``b`` (m,); zeros when None (only ``R`` wanted).

        The rows are factored :attr:`rows_per_qr` at a time: LAPACK's Householder QR of a tall panel runs from
        cache when the panel fits in it (:func:`panel_rows`), 3x faster per row than on 65 536-row blocks.
        """
        A = np.asarray(A, dtype=np.float64)
        rhs = None if b is None else np.asarray(b, dtype=np.float64)
        m, step = len(A), self.rows_per_qr
        for start in range(0, m, step):
            part = A[start : start + step]
            k, r = len(self._R), len(part)
            stacked = np.empty((k + r, self.p + 1), order="F")  # LAPACK's layout: no copy inside qr
            stacked[:k] = self._R
            stacked[k:, : self.p] = part
            stacked[k:, self.p] = 0.0 if rhs is None else rhs[start : start + r]
            self._R = np.asarray(np.linalg.qr(stacked, mode="r"), dtype=np.float64)
        self.rows += m

    @property
    def rows_per_qr(self) -> int:
        """Rows factored per LAPACK call: a panel of ``rows x (p + 1)`` doubles (:func:`panel_rows`)."""
        return panel_rows(self.p + 1)

    def _full(self) -> NDArray[np.float64]:
        """The factor of ``[A | b]`` padded to (p + 1, p + 1) (fewer rows while fewer than p + 1 were added)."""
        out = np.zeros((self.p + 1, self.p + 1))
        out[: len(self._R)] = self._R
        return out

    @property
    def R(self) -> NDArray[np.float64]:
        """Upper-triangular factor of ``A``, (p, p): ``A^T A = R^T R``, and ``A`` and ``R`` have the same singular
        values, right singular vectors and column norms."""
        return self._full()[: self.p, : self.p]

    @property
    def qtb(self) -> NDArray[np.float64]:
        """``Q^T b`` (p,)."""
        return self._full()[: self.p, self.p]

    @property
    def residual_sum_squares(self) -> float:
        """``min_x |A x - b|^2``."""
        return float(self._full()[self.p, self.p] ** 2)

    def solve(self) -> NDArray[np.float64]:
        """The least-squares solution ``x`` (p,): the minimum-norm one when ``A`` is rank deficient, as
        ``numpy.linalg.lstsq(A, b)`` gives it."""
        return np.asarray(np.linalg.lstsq(self.R, self.qtb, rcond=None)[0], dtype=np.float64)
