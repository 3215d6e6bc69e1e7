"""``pairwise``: paper A's reference-free objective over paired samples (Wu et al. 2013).

Take 2N samples of a constant field in varied attitudes, split them into two groups of N, pair sample i of
group 1 with sample i of group 2 and minimise (methods.md, paper A)

    Phi(q) = sum_i ( |Gamma^-1 B'1[i]|^2 - |Gamma^-1 B'2[i]|^2 )^2,
    Gamma^-1 = [[q1, q2, q3], [0, q4, q5], [0, 0, 1]].

The squared corrected magnitude expands to

    |Gamma^-1 B'|^2 = W1 q1^2 + W2 (q2^2 + q4^2) + W3 (1 + q3^2 + q5^2) + W4 q1 q2 + W5 (q2 q3 + q4 q5)
                      + W6 q1 q3
    W1 = X1^2 - X2^2,  W2 = Y1^2 - Y2^2,  W3 = Z1^2 - Z2^2,
    W4 = 2 (X1 Y1 - X2 Y2),  W5 = 2 (Y1 Z1 - Y2 Z2),  W6 = 2 (X1 Z1 - X2 Z2)

(for a pair's difference), so each pair's residual is linear in the six entries of ``M = Gamma^-T Gamma^-1``.
The closed-form start is the null vector of that N x 6 design ``W``; the upper Cholesky factor of ``M``,
scaled so that its (3, 3) entry is 1, is ``Gamma^-1``. Gauss-Newton (Levenberg-Marquardt when a step raises
the cost: :mod:`trimag._core.solve`) on the five ``q`` (analytic
Jacobian) then minimises ``Phi`` exactly (the paper solves ``grad Phi = 0``).

With offsets (``ortho-gain-bias``) each residual ``|C (B1 - b)|^2 - |C (B2 - b)|^2`` is linear in
``(M, M b)``; the design gains three columns ``-2 (B1 - B2)`` and ``b = M^-1 (M b)``.

The field magnitude never enters: the method needs no reference. Corrected fields are in the unit of the Z
axis (whose gain is the unit, ``Gamma[2, 2] == 1``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._core.chunks import chunk_rows
from .._core.qr import BlockedQR
from .._core.rowwise import column_means
from .._core.solve import gauss_newton_then_lm
from ..calibration import Calibration
from ..diagnostics import check_condition, check_not_degenerate, design_condition, weak_directions
from ..errors import IdentifiabilityError, TrimagInputError
from ..models import get_model
from ..models.ortho_gain import params_from_q
from ._common import scalar_reference
from .base import Estimator, build_calibration

__all__ = [
    "PAIRINGS",
    "TERM_INDEX",
    "Pairwise",
    "PairwiseSolution",
    "closed_form_from_factor",
    "closed_form_pairs",
    "pair_factor",
    "pair_normalisation",
    "pair_samples",
    "pairwise_design",
    "params_covariance",
    "q_to_matrix",
    "quadric_entries",
    "solve_pairs",
]

#: Pairing rules: ``"halves"`` (sample i of the first half with sample i of the second half, as in the paper)
#: and ``"random"`` (a seeded random permutation, then halves).
PAIRINGS = ("halves", "random")

_Q_IDX = (np.array([0, 0, 0, 1, 1]), np.array([0, 1, 2, 1, 2]))
_TERMS6 = ("M11", "M22", "M33", "M12", "M23", "M13")
#: ``(rows, cols)`` of ``M`` in the order of :data:`_TERMS6` (the columns of :func:`pairwise_design`).
TERM_INDEX = (np.array([0, 1, 2, 0, 1, 0]), np.array([0, 1, 2, 1, 2, 2]))
_TERMS9 = (*_TERMS6, "(Mb)x", "(Mb)y", "(Mb)z")
_Q_NAMES = ("q1", "q2", "q3", "q4", "q5")
_B_NAMES = ("bx", "by", "bz")


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


def q_to_matrix(q: NDArray[np.float64]) -> NDArray[np.float64]:
    """``Gamma^-1 = [[q1, q2, q3], [0, q4, q5], [0, 0, 1]]`` from ``q`` (5,)."""
    C = np.eye(3)
    C[_Q_IDX] = q
    return C


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
    chunk = chunk_rows()
    for start in range(0, len(B1), chunk):
        u1 = (B1[start : start + chunk] - c) / scale
        u2 = (B2[start : start + chunk] - c) / scale
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
        Derivatives with respect to ``q1..q5`` (the entries ``_Q_IDX`` of ``C``): ``dM/dC_rc = E_rc^T C +
        C^T E_rc``.
    """
    M = C.T @ C
    rows, cols = TERM_INDEX
    dM = np.zeros((5, 3, 3))
    for k, (r, c) in enumerate(zip(*_Q_IDX, strict=True)):
        dM[k, c, :] += C[r, :]
        dM[k, :, c] += C[r, :]
    m = M[rows, cols]
    dm = dM[:, rows, cols].T
    if b is None:
        return m, dm
    return np.concatenate([m, M @ b]), np.vstack([dm, (dM @ b).T])


@dataclass(frozen=True)
class PairwiseSolution:
    """Result of :func:`solve_pairs`: ``C`` = Gamma^-1 (3, 3), offset ``b`` (3,), ``q`` (5,), the final
    ``phi`` (the objective, data unit^4), the closed-form ``start_cond``, the optimizer result (on the
    reduced residuals ``R m``: :func:`solve_pairs`), the number of pairs and the internal data scale."""

    C: NDArray[np.float64]
    b: NDArray[np.float64]
    q: NDArray[np.float64]
    phi: float
    start_cond: float
    result: Any
    n_pairs: int = 0
    scale: float = 1.0


def _unpack(p: NDArray[np.float64], bias: bool) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    return q_to_matrix(p[:5]), (p[5:8] if bias else np.zeros(3))


def pair_normalisation(
    B1: NDArray[np.float64], B2: NDArray[np.float64], *, bias: bool = False
) -> tuple[NDArray[np.float64], float]:
    """Centre (the mean of both groups with ``bias``, else 0) and scale (RMS distance from it) of the pairs."""
    n = 2 * len(B1)
    centre = (column_means(B1) + column_means(B2)) / 2 if bias else np.zeros(3)
    total = 0.0
    for group in (B1, B2):
        chunk = chunk_rows()
        for start in range(0, len(group), chunk):
            e = group[start : start + chunk] - centre
            total += float(np.einsum("ij,ij->", e, e))
    return centre, float(np.sqrt(total / n)) or 1.0


def solve_pairs(
    B1: NDArray[np.float64],
    B2: NDArray[np.float64],
    *,
    bias: bool = False,
    max_iter: int = 100,
) -> PairwiseSolution:
    """Minimise ``Phi`` over the pairs ``(B1[i], B2[i])`` (both (N, 3), one unit) without validation.

    The data are scaled (and, with ``bias``, centred) internally; ``C`` is invariant to that, ``b`` is
    mapped back. Start: :func:`closed_form_pairs`; then Gauss-Newton with the analytic Jacobian, falling back to
    Levenberg-Marquardt.

    Every pair's residual is linear in the entries ``m`` of ``M = C^T C`` (and ``M b``): ``r = W m(p)`` with
    the fixed design ``W`` (:func:`pairwise_design`). With ``W = Q R`` the objective ``|W m|^2 = |R m|^2``,
    so the iterations run on the 6 (or 9) residuals ``R m(p)`` with the Jacobian ``R dm/dp``
    (:func:`quadric_entries`): the same minimum, steps, singular values and ``J^T J`` as on the N residuals,
    one pass over the data (:func:`pair_factor`) and memory independent of N. ``result.fun`` and
    ``result.jac`` are those reduced residuals and Jacobian; ``n_pairs`` counts the pairs.
    """
    centre, scale = pair_normalisation(B1, B2, bias=bias)
    R = pair_factor(B1, B2, bias=bias, centre=centre, scale=scale)
    C0, b0, cond = closed_form_from_factor(R, bias=bias)
    p0 = np.concatenate([C0[_Q_IDX], b0]) if bias else C0[_Q_IDX].copy()

    def fun(p: NDArray[np.float64]) -> NDArray[np.float64]:
        C, b = _unpack(p, bias)
        m, _ = quadric_entries(C, b if bias else None)
        return np.asarray(R @ m, dtype=np.float64)

    def jac(p: NDArray[np.float64]) -> NDArray[np.float64]:
        C, b = _unpack(p, bias)
        if not bias:
            return np.asarray(R @ quadric_entries(C)[1], dtype=np.float64)
        _, dm_dq = quadric_entries(C, b)
        dm_db = np.zeros((9, 3))
        dm_db[6:] = C.T @ C  # d(M b)/db = M
        return np.asarray(R @ np.hstack([dm_dq, dm_db]), dtype=np.float64)

    res = gauss_newton_then_lm(
        fun, jac, p0, max_steps=max_iter,
        lm_options={"xtol": 1e-15, "ftol": 1e-15, "gtol": 1e-15, "max_nfev": max_iter * 10},
    )
    C, b_u = _unpack(res.x, bias)
    phi = float(np.sum(res.fun**2)) * scale**4
    return PairwiseSolution(C, centre + scale * b_u, res.x[:5].copy(), phi, cond, res, len(B1), scale)


class Pairwise(Estimator):
    """Paper A's reference-free pairwise estimator (Wu et al. 2013).

    Parameters
    ----------
    model : {"ortho-gain", "ortho-gain-bias"}
        Paper A's 5-parameter model, or the same with three offsets (for real sensors).
    pairing : {"halves", "random"}
        ``"halves"`` pairs sample i of the first half with sample i of the second half (the paper);
        ``"random"`` pairs a seeded random permutation.
    seed : int
        Seed of the random pairing.
    max_iter : int
        Gauss-Newton step limit; the Levenberg-Marquardt fallback gets x10 function evaluations.

    Notes
    -----
    A numeric ``reference`` is accepted but only used for the before/after statistics: the model fixes the Z
    gain to 1, so the corrected magnitude is in the Z axis's unit, whatever the true field.
    """

    name = "pairwise"
    models = ("ortho-gain", "ortho-gain-bias")
    reference_kind = "none"

    def __init__(
        self, model: str = "ortho-gain", pairing: str = "halves", seed: int = 0, max_iter: int = 100
    ) -> None:
        self.model = model
        self.pairing = pairing
        self.seed = seed
        self.max_iter = max_iter

    def _min_samples(self, model: str) -> int:
        # every pair gives one equation: n_identifiable pairs at least
        return 2 * int(get_model(model).n_identifiable)

    def _fit(
        self, B: NDArray[np.float64], reference: Any, *, model: str, units: str, attitude: Any
    ) -> Calibration:
        if self.pairing not in PAIRINGS:
            raise TrimagInputError(f"option `pairing` must be one of {PAIRINGS}; got {self.pairing!r}")
        check_not_degenerate(B)
        ref = scalar_reference(reference, len(B), units)
        bias = model == "ortho-gain-bias"
        B1, B2, idx = pair_samples(B, self.pairing, self.seed)
        sol = solve_pairs(B1, B2, bias=bias, max_iter=int(self.max_iter))
        names = (*_Q_NAMES, *_B_NAMES) if bias else _Q_NAMES
        check_condition(
            sol.start_cond,
            what=f"the {model} model from paired samples",
            hint="record full turns about all three sensor axes (the pairs must differ in every component)",
        )
        cond, s, vt = design_condition(sol.result.jac)
        check_condition(
            cond,
            what=f"the {model} model from paired samples",
            hint="record full turns about all three sensor axes",
            weak=weak_directions(vt, s, names, threshold=1e4) if np.isfinite(cond) else [],
        )
        model_cls = get_model(model)
        instance = model_cls.from_matrix_offset(sol.C, sol.b)
        uncertainty = _uncertainty(sol, bias)
        return build_calibration(
            B, sol.C, sol.b, model=model, method=self.name, units=units, reference=ref,
            params=instance.as_dict(), iterations=int(sol.result.nfev), converged=bool(sol.result.success),
            uncertainty=uncertainty,
            diagnostics={
                "condition_number": cond,
                "closed_form_condition": sol.start_cond,
                "optimizer": str(sol.result.message),
            },
            extra_stats={"n_pairs": len(B1), "n_used": len(idx), "pairing": self.pairing, "phi": sol.phi},
        )


def params_covariance(q: NDArray[np.float64], cov_u: NDArray[np.float64], extra_scales: NDArray) -> NDArray:
    """Propagate a covariance of ``(q1..q5, extras)`` (internal, scaled units) to ``(theta, phi, psi, kxz, kyz,
    extras)``: finite-difference Jacobian of :func:`params_from_q` at ``q``; each extra is multiplied by its
    entry of ``extra_scales`` (e.g. the data scale for offsets)."""
    p = 5 + len(extra_scales)
    A = np.zeros((p, p))
    base = params_from_q(q)
    for j in range(5):
        h = 1e-7 * max(abs(q[j]), 1.0)
        dq = q.copy()
        dq[j] += h
        A[:5, j] = (params_from_q(dq) - base) / h
    A[5:, 5:] = np.diag(extra_scales)
    return A @ cov_u @ A.T


def _uncertainty(sol: PairwiseSolution, bias: bool) -> dict[str, Any]:
    """Parameter standard deviations from the Jacobian at the solution (``cov = s^2 (J^T J)^-1``, the residual
    variance ``s^2 = Phi / (n_pairs - p)`` estimated from the pairs), propagated to the physical parameters.
    ``J^T J`` and ``Phi`` are those of the N pair residuals (the reduced ones of :func:`solve_pairs` have both)."""
    J = sol.result.jac
    p = J.shape[1]
    s2 = float(np.sum(sol.result.fun**2)) / max(sol.n_pairs - p, 1)
    cov_u = s2 * np.linalg.pinv(J.T @ J)
    cov = params_covariance(sol.q, cov_u, np.full(3 if bias else 0, sol.scale))
    names = ["theta", "phi", "psi", "kxz", "kyz", *(_B_NAMES if bias else ())]
    return {
        "param_std": dict(zip(names, np.sqrt(np.clip(np.diag(cov), 0, None)).tolist(), strict=True)),
        "covariance": cov.tolist(),
        "covariance_order": names,
    }
