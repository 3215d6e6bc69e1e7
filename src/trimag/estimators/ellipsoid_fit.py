"""``ellipsoid-fit``: the algebraic ellipsoid fit of Li & Griffiths (2004), one pass over the data.

The quadric ``a x^2 + b y^2 + c z^2 + 2f yz + 2g xz + 2h xy + 2p x + 2q y + 2r z + d = 0`` is fitted by
minimising ``v^T S v`` (``S = D^T D``, the 10x10 scatter of the design ``D``) under the constraint
``4J - I^2 = 1`` (``k = 4``), which guarantees an ellipsoid: Q. Li, J. G. Griffiths, "Least squares ellipsoid
specific fitting", Proc. Geometric Modeling and Processing, 2004. The scatter matrix is accumulated in chunks,
so memory does not grow with N.

The centre of the quadric is the hard-iron offset; the upper Cholesky factor of its normalised shape matrix is
the soft-iron correction ``W`` (upper triangular). This fit is fast and needs no start, but it is biased under
noise (the scale shrinks by about (sigma/F)^2); ``ml`` refines it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._core.chunks import chunk_rows
from .._core.rowwise import scratch, transposed_blocks
from ..calibration import Calibration
from ..diagnostics import check_condition, check_not_degenerate, weak_directions
from ..errors import IdentifiabilityError
from ._common import Normalisation, normalisation_of, scalar_reference
from .base import Estimator

__all__ = [
    "EllipsoidFit", "algebraic_ellipsoid", "gauge_scale", "power_sums", "power_sums_from_moments", "quadratic_terms",
    "quadric_moments", "quadric_scatter", "quadric_to_ellipsoid", "scatter_from_moments",
]

_TERMS = ("xx", "yy", "zz", "yz", "xz", "xy", "x", "y", "z", "1")
_FACTORS = np.array([1.0, 1.0, 1.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0, 1.0])


#: Exponents (of x, y, z) of the design's terms (x^2, y^2, z^2, yz, xz, xy, x, y, z, 1), factors of 2 aside.
_EXPONENTS = np.array(
    [[2, 0, 0], [0, 2, 0], [0, 0, 2], [0, 1, 1], [1, 0, 1], [1, 1, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 0]]
)


def _moment_plan() -> tuple[list[tuple[int, int]], NDArray[np.int64]]:
    """The 35 distinct monomials of degree <= 4 among the scatter's 55 entries: for each, one pair of design
    terms whose product it is (term 9 is the constant), and for every entry (a, b) the index of its monomial."""
    keys: dict[tuple[int, ...], int] = {}
    pairs: list[tuple[int, int]] = []
    index = np.empty((10, 10), dtype=np.int64)
    for a_ in range(10):
        for b_ in range(a_, 10):
            key = tuple(int(k) for k in _EXPONENTS[a_] + _EXPONENTS[b_])
            if key not in keys:
                keys[key] = len(pairs)
                pairs.append((a_, b_))
            index[a_, b_] = index[b_, a_] = keys[key]
    return pairs, index


_PAIRS, _MOMENT_INDEX = _moment_plan()


def quadratic_terms(t: NDArray[np.float64], out: NDArray[np.float64]) -> NDArray[np.float64]:
    """The quadratic terms ``x^2, y^2, z^2, yz, xz, xy`` of a component-major block ``t`` (3, m) into the rows of
    ``out`` (>= 6, m), in that order (the design's first six terms, factors of 2 aside). Returns ``out``."""
    x, y, z = t
    np.multiply(x, x, out=out[0])
    np.multiply(y, y, out=out[1])
    np.multiply(z, z, out=out[2])
    np.multiply(y, z, out=out[3])
    np.multiply(x, z, out=out[4])
    np.multiply(x, y, out=out[5])
    return out


def _pair_moments(u: NDArray[np.float64], norm: Normalisation | None = None) -> NDArray[np.float64]:
    """The 35 power sums of :data:`_PAIRS` (in that order) of ``u`` (N, 3), or of ``norm.forward(u)``, in chunks.

    Each is one dot product of two contiguous term vectors per chunk (0.43 ms per 65 536 rows against 0.71 ms
    for the full ``D D^T``). Memory: 6 x 65 536 doubles whatever N.
    """
    moments = np.zeros(len(_PAIRS))
    centre = norm.centre if norm is not None else None
    with scratch(6, min(max(len(u), 1), chunk_rows())) as Q:  # a reused buffer (trimag._core.rowwise.scratch)
        for _, t in transposed_blocks(u, centre, block=chunk_rows()):  # component-major blocks: contiguous x, y, z
            if norm is not None:
                t *= 1.0 / norm.scale
            x, y, z = t
            q = quadratic_terms(t, Q[:, : len(x)])
            terms = (*q, x, y, z)
            for k, (a_, b_) in enumerate(_PAIRS):
                if b_ == 9:  # times the constant term
                    moments[k] += float(np.sum(terms[a_])) if a_ < 9 else len(x)
                else:
                    moments[k] += float(np.dot(terms[a_], terms[b_]))
    return moments


def quadric_moments(u: NDArray[np.float64], norm: Normalisation | None = None) -> NDArray[np.float64]:
    """The 35 power sums of degree <= 4 of ``u`` (N, 3), or of ``norm.forward(u)``, in one chunked pass: what
    both :func:`quadric_scatter` and :func:`power_sums` are made of (:func:`scatter_from_moments`,
    :func:`power_sums_from_moments`), for a caller that needs both from one pass over the data."""
    return _pair_moments(u, norm)


def scatter_from_moments(moments: NDArray[np.float64]) -> NDArray[np.float64]:
    """The quadric scatter (10, 10) of :func:`quadric_scatter` from :func:`quadric_moments`."""
    # the design's terms are (x^2, y^2, z^2, 2yz, 2xz, 2xy, 2x, 2y, 2z, 1): the factors of 2
    return np.asarray(moments[_MOMENT_INDEX] * np.outer(_FACTORS, _FACTORS), dtype=np.float64)


def power_sums_from_moments(moments: NDArray[np.float64]) -> dict[tuple[int, int, int], float]:
    """The power sums of :func:`power_sums` (keyed by exponents) from :func:`quadric_moments`."""
    return {
        tuple(int(e) for e in _EXPONENTS[a_] + _EXPONENTS[b_]): float(m)  # type: ignore[misc]
        for (a_, b_), m in zip(_PAIRS, moments, strict=True)
    }


def power_sums(u: NDArray[np.float64], norm: Normalisation | None = None) -> dict[tuple[int, int, int], float]:
    """``sum_i x_i^p y_i^q z_i^r`` for every ``p + q + r <= 4`` (35 sums) of ``u`` (N, 3), or of
    ``norm.forward(u)`` (no normalised copy), in one chunked component-major pass."""
    return power_sums_from_moments(_pair_moments(u, norm))


def quadric_scatter(u: NDArray[np.float64], norm: Normalisation | None = None) -> NDArray[np.float64]:
    """The 10x10 scatter ``D^T D`` of the quadric design, accumulated in chunks. ``u``: (N, 3).

    With ``norm``, ``u`` holds raw samples and the design is built from ``norm.forward(u)``, one chunk at a time
    (no normalised copy of the samples). The 55 entries of the scatter are sums of only 35 distinct monomials
    of degree <= 4 (``sum x^2 y^2`` is both ``(x^2, y^2)`` and ``(xy, xy)``): :func:`_pair_moments`.
    """
    return scatter_from_moments(_pair_moments(u, norm))


def algebraic_ellipsoid(
    u: NDArray[np.float64], norm: Normalisation | None = None, *, scatter: NDArray[np.float64] | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """Fit an ellipsoid to normalised points ``u`` (N, 3), or to raw samples ``u`` normalised by ``norm``.

    The results are in the normalised frame either way. ``scatter``: the quadric scatter of those samples when
    the caller has it already (:func:`scatter_from_moments`); ``u`` is then not read.

    Returns
    -------
    W : ndarray (3, 3)
        Upper-triangular map with ``|W (u - c)| = 1`` on the fitted ellipsoid.
    c : ndarray (3,)
        Centre.
    cond : float
        Column-normalised condition number of the design.
    """
    S = quadric_scatter(u, norm) if scatter is None else scatter
    d = np.sqrt(np.diag(S))
    d[d == 0] = 1.0
    # The solution itself is the (near-)null vector of the design, so identifiability is decided by the
    # second-smallest singular value: a second small one means a family of quadrics fits equally well.
    _, s2, vt = np.linalg.svd(S / np.outer(d, d))
    cond = float(np.sqrt(s2[0] / s2[-2])) if s2[-2] > 0 else float("inf")
    weak = weak_directions(vt[:-1], np.sqrt(s2[:-1]), _TERMS, threshold=1e4) if np.isfinite(cond) else []
    check_condition(
        cond,
        what="an ellipsoid (hard + soft iron)",
        hint="record the sensor in more attitudes, turning it about all three axes",
        weak=weak,
    )
    k = 4.0
    C1 = np.full((3, 3), k / 2 - 1) - (k / 2) * np.eye(3)
    C = np.zeros((6, 6))
    C[:3, :3] = C1
    C[3:, 3:] = -k * np.eye(3)
    S11, S12, S22 = S[:6, :6], S[:6, 6:], S[6:, 6:]
    T = np.linalg.solve(S22, S12.T)
    Mred = S11 - S12 @ T
    _, vecs = np.linalg.eig(np.linalg.solve(C, Mred))
    vecs = np.real(vecs)
    # admissible solutions satisfy v^T C v > 0 (4J - I^2 > 0: an ellipsoid); their eigenvalue
    # lambda = v^T Mred v / v^T C v >= 0 is the algebraic cost, so take the smallest (0 for exact data;
    # Li & Griffiths' "only positive eigenvalue" when the data are noisy).
    q = np.einsum("ij,ik,kj->j", vecs, C, vecs)
    cost = np.einsum("ij,ik,kj->j", vecs, Mred, vecs)
    ok = q > 1e-12 * np.abs(q).max()
    if not np.any(ok):
        raise IdentifiabilityError(
            "the samples do not describe an ellipsoid (no valid algebraic solution); record the sensor "
            "turning through many more attitudes"
        )
    candidates = np.nonzero(ok)[0]
    v1 = vecs[:, candidates[int(np.argmin(cost[ok] / q[ok]))]]
    v = np.concatenate([v1, -T @ v1])
    W, centre = quadric_to_ellipsoid(v)
    return W, centre, cond


def quadric_to_ellipsoid(v: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Upper-triangular ``W`` (3, 3) and centre ``c`` (3,) with ``|W (u - c)| = 1`` on the quadric ``v``.

    ``v`` (10,) holds the coefficients of ``(x^2, y^2, z^2, 2yz, 2xz, 2xy, 2x, 2y, 2z, 1)`` (any scale and sign).

    Raises
    ------
    IdentifiabilityError
        When the quadric is not an ellipsoid.
    """
    a, b, c_, f, g, h, p, q, r, dd = v
    M = np.array([[a, h, g], [h, b, f], [g, f, c_]])
    if np.trace(M) < 0:
        M, p, q, r, dd = -M, -p, -q, -r, -dd
    try:
        centre = -np.linalg.solve(M, np.array([p, q, r]))
    except np.linalg.LinAlgError:
        raise IdentifiabilityError(
            "the samples do not describe an ellipsoid (degenerate quadric); record the sensor turning "
            "through many more attitudes"
        ) from None
    scale = float(centre @ M @ centre - dd)
    try:
        if scale <= 0:
            raise np.linalg.LinAlgError
        L = np.linalg.cholesky(M / scale)
    except np.linalg.LinAlgError:
        raise IdentifiabilityError(
            "the samples do not describe an ellipsoid (the fitted quadric is not closed); record the "
            "sensor turning through many more attitudes"
        ) from None
    return np.asarray(L.T, dtype=np.float64), np.asarray(centre, dtype=np.float64)


class EllipsoidFit(Estimator):
    """Algebraic ellipsoid fit (Li & Griffiths 2004), no iterations.

    Parameters
    ----------
    model : str
        ``"ellipsoid"``.
    form : {"upper", "symmetric"}
        Gauge of the returned soft-iron matrix.
    """

    name = "ellipsoid-fit"
    models = ("ellipsoid",)

    def __init__(self, model: str = "ellipsoid", form: str = "upper") -> None:
        self.model = model
        self.form = form

    def _fit(
        self, B: NDArray[np.float64], reference: Any, *, model: str, units: str, attitude: Any
    ) -> Calibration:
        principal = check_not_degenerate(B)
        ref = scalar_reference(reference, len(B), units)
        # the fit is invariant to translation and scale: normalise chunk by chunk, no copy of B
        norm = normalisation_of(B)
        W_u, c_u, cond = algebraic_ellipsoid(B, norm)
        W = W_u / norm.scale
        offset = norm.centre + norm.scale * c_u
        W, F_hat = gauge_scale(W, ref.values)
        from .ml import ellipsoid_result  # ml builds on this module

        return ellipsoid_result(
            B, W, offset, ref=ref, F_hat=F_hat, sigma=None, model=model, method=self.name, units=units,
            form=self.form, diagnostics={"condition_number": cond},
            uncertainty_note="Fisher information at the estimate: a lower bound; this algebraic fit is biased "
            "under strong noise (use ml)",
            principal=principal,
        )


def gauge_scale(
    W: NDArray[np.float64], reference_values: NDArray[np.float64] | None
) -> tuple[NDArray[np.float64], float | None]:
    """Scale a unit-sphere correction ``W`` to the reference (RMS of the per-sample values) or, without one,
    to ``det(W) = 1`` (volume preserved); returns the scaled ``W`` and the implied magnitude when unknown."""
    if reference_values is not None:
        return W * float(np.sqrt(np.mean(reference_values**2))), None
    c = float(np.linalg.det(W)) ** (-1.0 / 3.0)
    return W * c, c
