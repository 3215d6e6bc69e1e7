"""Numerical helpers shared by estimators (not public API)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._core.normalise import Normalisation, normalisation_of, normalisation_stats, normalise
from .._core.quadric import TERMS, quadric_scatter, quadric_to_ellipsoid
from ..errors import IdentifiabilityError, TrimagInputError
from ..fields.reference import ScalarReference, as_scalar_reference
from ..quality.diagnostics import check_condition, weak_directions

__all__ = [
    "Normalisation", "algebraic_ellipsoid", "check_ellipsoid_options", "gauge_scale", "iterative_start",
    "normalisation_of", "normalisation_stats", "normalise", "scalar_reference", "unpack",
]


def scalar_reference(reference: Any, n: int, units: str) -> ScalarReference:
    """Shortcut to :func:`trimag.fields.reference.as_scalar_reference`."""
    return as_scalar_reference(reference, n, units=units)


def check_ellipsoid_options(form: str, noise_std: float | None = None) -> None:
    """Validate the options the ellipsoid estimators share (``form``, ``noise_std``)."""
    if form not in ("upper", "symmetric"):
        raise TrimagInputError(f"`form` must be 'upper' or 'symmetric'; got {form!r}")
    if noise_std is not None and not (np.isfinite(noise_std) and noise_std >= 0):
        raise TrimagInputError(f"`noise_std` must be a non-negative number; got {noise_std!r}")


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
    weak = weak_directions(vt[:-1], np.sqrt(s2[:-1]), TERMS, threshold=1e4) if np.isfinite(cond) else []
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


def gauge_scale(
    W: NDArray[np.float64], reference_values: NDArray[np.float64] | None
) -> tuple[NDArray[np.float64], float | None]:
    """Scale a unit-sphere correction ``W`` to the reference (RMS of the per-sample values) or, without one,
    to ``det(W) = 1`` (volume preserved); returns the scaled ``W`` and the implied magnitude when unknown."""
    if reference_values is not None:
        return W * float(np.sqrt(np.mean(reference_values**2))), None
    c = float(np.linalg.det(W)) ** (-1.0 / 3.0)
    return W * c, c


def iterative_start(u: NDArray[np.float64], start: str) -> NDArray[np.float64]:
    """Starting vector (9,) for the scaled problem: ``"nominal"`` (zero offset) or ``"centroid"``."""
    if start == "nominal":
        b0 = np.zeros(3)
    elif start == "centroid":
        b0 = u.mean(axis=0)
    else:
        raise TrimagInputError(f"`start` must be 'nominal' or 'centroid'; got {start!r}")
    k0 = float(np.sqrt(np.mean(np.sum((u - b0) ** 2, axis=1))))
    if not k0 > 0:
        raise IdentifiabilityError("all samples equal the starting offset: the sensor appears stuck")
    M0 = np.eye(3) / k0
    return np.concatenate([M0[_UPPER], b0])


_UPPER = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))


def unpack(p: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``p`` (9,) -> (upper-triangular ``M`` (3, 3), ``b`` (3,))."""
    M = np.zeros((3, 3))
    M[_UPPER] = p[:6]
    return M, p[6:9]
