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

from ..calibration import Calibration
from ..diagnostics import check_condition, check_not_degenerate, weak_directions
from ..errors import IdentifiabilityError
from ._common import Normalisation, normalisation_of, scalar_reference
from .base import Estimator

__all__ = ["EllipsoidFit", "algebraic_ellipsoid", "gauge_scale", "quadric_scatter", "quadric_to_ellipsoid"]

_TERMS = ("xx", "yy", "zz", "yz", "xz", "xy", "x", "y", "z", "1")
_CHUNK = 65_536
_FACTORS = np.array([1.0, 1.0, 1.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0])


def quadric_scatter(u: NDArray[np.float64], norm: Normalisation | None = None) -> NDArray[np.float64]:
    """The 10x10 scatter ``D^T D`` of the quadric design, accumulated in chunks. ``u``: (N, 3).

    With ``norm``, ``u`` holds raw samples and the design is built from ``norm.forward(u)``, one chunk at a time
    (no normalised copy of the samples). The design is built transposed, (10, chunk), so that every term is one
    contiguous elementwise product and the scatter one matrix product (memory: 10 x 65 536 doubles whatever N).
    """
    S = np.zeros((10, 10))
    D = np.empty((10, min(len(u), _CHUNK)))
    buf = np.empty((min(len(u), _CHUNK), 3)) if norm is not None else None
    for start in range(0, len(u), _CHUNK):
        block = u[start : start + _CHUNK]
        if norm is not None and buf is not None:
            block = np.subtract(block, norm.centre, out=buf[: len(block)])
            block *= 1.0 / norm.scale
        x, y, z = block.T
        m = len(x)
        d = D[:, :m]
        np.multiply(x, x, out=d[0])
        np.multiply(y, y, out=d[1])
        np.multiply(z, z, out=d[2])
        np.multiply(y, z, out=d[3])
        np.multiply(x, z, out=d[4])
        np.multiply(x, y, out=d[5])
        d[6], d[7], d[8] = x, y, z
        d[9] = 0.5
        S += d @ d.T
    # the design's terms are (x^2, y^2, z^2, 2yz, 2xz, 2xy, 2x, 2y, 2z, 1): restore the factors of 2
    return S * np.outer(_FACTORS, _FACTORS)


def algebraic_ellipsoid(
    u: NDArray[np.float64], norm: Normalisation | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """Fit an ellipsoid to normalised points ``u`` (N, 3), or to raw samples ``u`` normalised by ``norm``.

    The results are in the normalised frame either way.

    Returns
    -------
    W : ndarray (3, 3)
        Upper-triangular map with ``|W (u - c)| = 1`` on the fitted ellipsoid.
    c : ndarray (3,)
        Centre.
    cond : float
        Column-normalised condition number of the design.
    """
    S = quadric_scatter(u, norm)
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
        check_not_degenerate(B)
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
