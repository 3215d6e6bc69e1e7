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

from .._core.solve import gauss_newton_then_lm
from ..calibration import Calibration
from ..errors import TrimagInputError
from ..models import get_model
from ..models.ortho_gain import Q_INDEX, params_covariance, q_to_matrix
from ..quality.diagnostics import check_condition, check_not_degenerate, design_condition, weak_directions
from ._common import scalar_reference
from ._finish import make_uncertainty
from ._pairs import PAIRINGS, closed_form_from_factor, pair_factor, pair_normalisation, pair_samples, quadric_entries
from .base import Estimator, build_calibration

__all__ = ["Pairwise"]


_TERMS6 = ("M11", "M22", "M33", "M12", "M23", "M13")
_TERMS9 = (*_TERMS6, "(Mb)x", "(Mb)y", "(Mb)z")
_Q_NAMES = ("q1", "q2", "q3", "q4", "q5")
_B_NAMES = ("bx", "by", "bz")


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
    p0 = np.concatenate([C0[Q_INDEX], b0]) if bias else C0[Q_INDEX].copy()

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
    return make_uncertainty(
        names, covariance=cov, noise_std=None, gauge="Z gain 1 (the corrected field is in the unit of the Z axis)",
        basis="s^2 (J^T J)^-1 of the pair residuals at the solution, s^2 = Phi / (n_pairs - p), propagated to the "
        "model's parameters",
    )
