"""Paper A's pair design, shared by ``pairwise`` and ``wen2008`` (not public API; Wu et al. 2013, methods.md
paper A): samples split into pairs, the W design of squared-magnitude differences built and factored chunk by
chunk, and its closed-form null-vector solution."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .._core.chunks import row_blocks
from .._core.qr import BlockedQR
from .._core.rowwise import column_means
from ..errors import IdentifiabilityError, TrimagInputError
from ..models.ortho_gain import Q_INDEX

__all__ = [
    "PAIRINGS", "TERM_INDEX", "closed_form_from_factor", "closed_form_pairs", "pair_factor", "pair_normalisation",
    "pair_samples", "pairwise_design", "quadric_entries",
]


#: Pairing rules: ``"halves"`` (sample i of the first half with sample i of the second half, as in the paper)
#: and ``"random"`` (a seeded random permutation, then halves).
PAIRINGS = ("halves", "random")




#: ``(rows, cols)`` of ``M`` in the order of :data:`_TERMS6` (the columns of :func:`pairwise_design`).
TERM_INDEX = (np.array([0, 1, 2, 0, 1, 0]), np.array([0, 1, 2, 1, 2, 2]))


def pair_samples(
    B: NDArray[np.float64], pairing: str = "halves", seed: int | None = 0
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.intp]]:
    """Split ``B`` (2N, 3) into paired groups ``B1, B2`` (N, 3).

    Returns ``(B1, B2, index)`` where ``index`` (2N',) lists the rows used (group 1 then group 2); with an odd
    count the last sample (``"halves"``) or one random sample (``"random"``) is left out.
    """
    if pairing not in PAIRINGS:
        raise TrimagInputError(f"`pairing` must be one of {PAIRINGS}; got {pairing!r}")
    n = len(B) // 2
    if pairing == "halves":  # views of B, no copy
        return B[:n], B[n : 2 * n], np.arange(2 * n)
    idx = np.random.default_rng(seed).permutation(len(B))[: 2 * n]
    return B[idx[:n]], B[idx[n:]], idx


def pairwise_design(B1: NDArray[np.float64], B2: NDArray[np.float64], *, bias: bool = False) -> NDArray:
    """The paper's W design, shape (N, 6) (``bias=False``) or (N, 9) with the offset columns ``-2 (B1 - B2)``.

    Columns: ``W1..W6`` (methods.md, paper A), multiplying ``(M11, M22, M33, M12, M23, M13)``, then
    ``(M b)``.
    """
    x1, y1, z1 = B1.T
    x2, y2, z2 = B2.T
    cols = [
        x1 * x1 - x2 * x2,
        y1 * y1 - y2 * y2,
        z1 * z1 - z2 * z2,
        2.0 * (x1 * y1 - x2 * y2),
        2.0 * (y1 * z1 - y2 * z2),
        2.0 * (x1 * z1 - x2 * z2),
    ]
    if bias:
        cols += list(-2.0 * (B1 - B2).T)
    return np.column_stack(cols)


def pair_factor(
    B1: NDArray[np.float64], B2: NDArray[np.float64], *, bias: bool = False,
    centre: NDArray[np.float64] | None = None, scale: float = 1.0,
) -> NDArray[np.float64]:
    """Triangular factor ``R`` of the W design of the pairs ``((B1 - centre) / scale, (B2 - centre) / scale)``.

    The design (:func:`pairwise_design`, (N, 6) or (N, 9)) is built and factored block by block
    (:class:`~trimag._core.qr.BlockedQR`, a chunk of pairs at a time), so memory does not grow with N.
    ``W^T W = R^T R``, and ``R`` has the same singular values, right singular vectors and column norms as
    ``W``; every pair's residual is ``W_i . m`` with ``m`` the entries of ``M`` (and ``M b``), so
    ``sum_i (W_i . m)^2 = |R m|^2`` for every ``m``: the whole objective lives in ``R``.

    Returns
    -------
    ndarray, shape (6, 6) or (9, 9)
    """
    c = np.zeros(3) if centre is None else np.asarray(centre, dtype=np.float64)
    qr = BlockedQR(9 if bias else 6)
    for rows in row_blocks(len(B1)):
        u1 = (B1[rows] - c) / scale
        u2 = (B2[rows] - c) / scale
        qr.add(pairwise_design(u1, u2, bias=bias))
    return qr.R


def closed_form_from_factor(
    R: NDArray[np.float64], *, bias: bool = False
) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """:func:`closed_form_pairs` from the design's factor ``R`` (:func:`pair_factor`)."""
    d = np.linalg.norm(R, axis=0)
    d[d == 0] = 1.0
    _, s, vt = np.linalg.svd(R / d)
    cond = float(s[0] / s[-2]) if s[-2] > 0 else float("inf")
    x = vt[-1] / d
    M = np.array([[x[0], x[3], x[5]], [x[3], x[1], x[4]], [x[5], x[4], x[2]]])
    if np.trace(M) < 0:
        M, x = -M, -x
    try:
        L = np.linalg.cholesky(M)
    except np.linalg.LinAlgError:
        raise IdentifiabilityError(
            "the paired samples do not determine a positive-definite field quadric (the closed-form "
            "start failed); record full turns about all three sensor axes"
        ) from None
    U = L.T
    C = U / U[2, 2]
    b = np.linalg.solve(M, x[6:9]) if bias else np.zeros(3)
    return C, b, cond


def closed_form_pairs(
    B1: NDArray[np.float64], B2: NDArray[np.float64], *, bias: bool = False
) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """Closed-form solution: the null vector of the W design (column-normalised SVD).

    Returns
    -------
    C : ndarray (3, 3)
        ``Gamma^-1`` (upper triangular, ``C[2, 2] == 1``).
    b : ndarray (3,)
        Offset (zeros when ``bias`` is False).
    cond : float
        ``s_max / s_second_smallest`` of the column-normalised design: the conditioning of the null space
        (``inf`` when the data leave more than one solution).

    Raises
    ------
    IdentifiabilityError
        When the null vector is not a positive-definite quadratic form (no ellipsoid in the data).
    """
    return closed_form_from_factor(pair_factor(B1, B2, bias=bias), bias=bias)


def quadric_entries(
    C: NDArray[np.float64], b: NDArray[np.float64] | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The unknowns ``m`` of the W design for ``M = C^T C`` (and ``M b``), and ``dM / dq`` for the upper ``q``.

    Returns
    -------
    m : ndarray, shape (6,) or (9,)
        ``(M11, M22, M33, M12, M23, M13)`` then ``M b`` when ``b`` is given.
    dm_dq : ndarray, shape (6, 5) or (9, 5)
        Derivatives with respect to ``q1..q5`` (the entries ``Q_INDEX`` of ``C``): ``dM/dC_rc = E_rc^T C +
        C^T E_rc``.
    """
    M = C.T @ C
    rows, cols = TERM_INDEX
    dM = np.zeros((5, 3, 3))
    for k, (r, c) in enumerate(zip(*Q_INDEX, strict=True)):
        dM[k, c, :] += C[r, :]
        dM[k, :, c] += C[r, :]
    m = M[rows, cols]
    dm = dM[:, rows, cols].T
    if b is None:
        return m, dm
    return np.concatenate([m, M @ b]), np.vstack([dm, (dM @ b).T])


def pair_normalisation(
    B1: NDArray[np.float64], B2: NDArray[np.float64], *, bias: bool = False
) -> tuple[NDArray[np.float64], float]:
    """Centre (the mean of both groups with ``bias``, else 0) and scale (RMS distance from it) of the pairs."""
    n = 2 * len(B1)
    centre = (column_means(B1) + column_means(B2)) / 2 if bias else np.zeros(3)
    total = 0.0
    for group in (B1, B2):
        for rows in row_blocks(len(group)):
            e = group[rows] - centre
            total += float(np.einsum("ij,ij->", e, e))
    return centre, float(np.sqrt(total / n)) or 1.0
