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
the cost: :mod:`trimag.estimators._solve`) on the five ``q`` (analytic
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

from ..calibration import Calibration
from ..diagnostics import check_condition, check_not_degenerate, design_condition, weak_directions
from ..errors import IdentifiabilityError, TrimagInputError
from ..models import get_model
from ..models.ortho_gain import params_from_q
from ._common import scalar_reference
from ._solve import gauss_newton_then_lm
from .base import Estimator, build_calibration

__all__ = [
    "PAIRINGS",
    "Pairwise",
    "PairwiseSolution",
    "closed_form_pairs",
    "pair_samples",
    "pairwise_design",
    "params_covariance",
    "q_to_matrix",
    "solve_pairs",
]

#: Pairing rules: ``"halves"`` (sample i of the first half with sample i of the second half, as in the paper)
#: and ``"random"`` (a seeded random permutation, then halves).
PAIRINGS = ("halves", "random")

_Q_IDX = (np.array([0, 0, 0, 1, 1]), np.array([0, 1, 2, 1, 2]))
_TERMS6 = ("M11", "M22", "M33", "M12", "M23", "M13")
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
    if pairing == "halves":
        idx = np.arange(2 * n)
    else:
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
    W = pairwise_design(B1, B2, bias=bias)
    d = np.linalg.norm(W, axis=0)
    d[d == 0] = 1.0
    _, s, vt = np.linalg.svd(W / d, full_matrices=False)
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
    R = L.T
    C = R / R[2, 2]
    b = np.linalg.solve(M, x[6:9]) if bias else np.zeros(3)
    return C, b, cond


@dataclass(frozen=True)
class PairwiseSolution:
    """Result of :func:`solve_pairs`: ``C`` = Gamma^-1 (3, 3), offset ``b`` (3,), ``q`` (5,), the final
    ``phi`` (the objective, data unit^4), the closed-form ``start_cond``, and the optimizer result."""

    C: NDArray[np.float64]
    b: NDArray[np.float64]
    q: NDArray[np.float64]
    phi: float
    start_cond: float
    result: Any


def _unpack(p: NDArray[np.float64], bias: bool) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    return q_to_matrix(p[:5]), (p[5:8] if bias else np.zeros(3))


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
    """
    both = np.vstack([B1, B2])
    centre = both.mean(axis=0) if bias else np.zeros(3)
    scale = float(np.sqrt(np.mean(np.sum((both - centre) ** 2, axis=1)))) or 1.0
    u1, u2 = (B1 - centre) / scale, (B2 - centre) / scale
    C0, b0, cond = closed_form_pairs(u1, u2, bias=bias)
    p0 = np.concatenate([C0[_Q_IDX], b0]) if bias else C0[_Q_IDX].copy()

    # component-major copies (3, N): every product below is one contiguous pass (trimag._rowwise)
    u1t, u2t = np.ascontiguousarray(u1.T), np.ascontiguousarray(u2.T)

    def fun(p: NDArray[np.float64]) -> NDArray[np.float64]:
        C, b = _unpack(p, bias)
        y1, y2 = C @ (u1t - b[:, None]), C @ (u2t - b[:, None])
        return np.asarray(np.sum(y1 * y1 - y2 * y2, axis=0), dtype=np.float64)

    def jac(p: NDArray[np.float64]) -> NDArray[np.float64]:
        C, b = _unpack(p, bias)
        e1, e2 = u1t - b[:, None], u2t - b[:, None]
        y1, y2 = C @ e1, C @ e2
        Jt = np.empty((8 if bias else 5, e1.shape[1]))
        for k, (r, c) in enumerate(zip(*_Q_IDX, strict=True)):
            np.multiply(y1[r], e1[c], out=Jt[k])
            Jt[k] -= y2[r] * e2[c]
        Jt[:5] *= 2.0
        if bias:
            Jt[5:] = -2.0 * (C.T @ (y1 - y2))
        return Jt.T

    res = gauss_newton_then_lm(
        fun, jac, p0, max_steps=max_iter,
        lm_options={"xtol": 1e-15, "ftol": 1e-15, "gtol": 1e-15, "max_nfev": max_iter * 10},
    )
    C, b_u = _unpack(res.x, bias)
    phi = float(np.sum(res.fun**2)) * scale**4
    return PairwiseSolution(C, centre + scale * b_u, res.x[:5].copy(), phi, cond, res)


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
        uncertainty = _uncertainty(sol, bias, B1, B2)
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


def _uncertainty(sol: PairwiseSolution, bias: bool, B1: NDArray, B2: NDArray) -> dict[str, Any]:
    """Parameter standard deviations from the Jacobian at the solution (``cov = s^2 (J^T J)^-1``, the residual
    variance ``s^2`` estimated from the pairs), propagated to the physical parameters."""
    J = sol.result.jac
    n, p = J.shape
    s2 = float(np.sum(sol.result.fun**2)) / max(n - p, 1)
    cov_u = s2 * np.linalg.pinv(J.T @ J)
    both = np.vstack([B1, B2])
    centre = both.mean(axis=0) if bias else np.zeros(3)
    scale = float(np.sqrt(np.mean(np.sum((both - centre) ** 2, axis=1)))) or 1.0
    cov = params_covariance(sol.q, cov_u, np.full(3 if bias else 0, scale))
    names = ["theta", "phi", "psi", "kxz", "kyz", *(_B_NAMES if bias else ())]
    return {
        "param_std": dict(zip(names, np.sqrt(np.clip(np.diag(cov), 0, None)).tolist(), strict=True)),
        "covariance": cov.tolist(),
        "covariance_order": names,
    }
