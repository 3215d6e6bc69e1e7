"""``wen2008``: a documented RECONSTRUCTION of the older method of Wen, Song, Huang et al. (2008).

The 2008 paper is not public; paper A (Wu et al. 2013) only says that its estimated vector contains ``a4 = -k1
cot(beta) sin(alpha) sin(gamma)`` with ``beta -> pi/2`` and ``alpha, gamma -> 0``, so that ``gamma`` must be
recovered by division by small quantities and its noise is amplified. This module builds a baseline with
exactly that property (methods.md, paper A, "The older method"); it is not Wen et al.'s code, and the
derivation is in ``docs/method-pairwise.md``.

Model (:class:`Wen2008Model`): ``Z' = Z``; ``Y' = (cos beta, sin beta, 0)`` in the XOY plane; ``X' = (cos
alpha, sin alpha cos gamma, sin alpha sin gamma)``; ``B' = D B`` with ``D = diag(k1, k2, 1) [X'; Y'; Z']``.
Normalised by its (1, 1) entry the correction ``D^-1`` is

    [[1,         -k1 sa cg / (k2 sb),   -k1 sa sg         ],
     [-cot(b),    k1 ca / (k2 sb),       k1 sa sg cot(b)  ],      (sa = sin(alpha), ... ; a4 = -entry (2, 3))
     [0,          0,                     k1 (ca - sa cg cot(b))]]

Gauge. A rotation of the reference frame about Z maps the family onto itself and leaves every magnitude
unchanged, so as written it is not identifiable. The reconstruction fixes the gauge with one constraint: the
non-orthogonality in the XOY plane is split evenly, the projection of X' lies as far from X as Y' lies from Y,
``tan(alpha) cos(gamma) = cot(beta)``. The free parameters are then ``(k1, k2, alpha, gamma)`` and ``beta =
arccot(tan(alpha) cos(gamma))``. The family keeps Y' perpendicular to Z', so it cannot represent paper A's
``psi`` (it is paper A's model with ``psi = 0``, differently parametrised).

Identification (same data, same objective as ``pairwise``): pair the samples, take the closed-form W null
vector, read the magnitude invariants ``G = D D^T`` (``k1^2``, ``k2^2``, ``k1 k2 X'.Y'`` and ``k1 sin(alpha)
sin(gamma)``), recover the angles with the gauge (the division step), then minimise the paired ``Phi`` over
``(k1, k2, alpha, gamma)`` with Levenberg-Marquardt.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._core.solve import levenberg_marquardt
from ..calibration import Calibration
from ..errors import TrimagInputError
from ..models.ortho_gain import OrthoGain, normalised_upper
from ..models.wen2008 import WEN_PARAMS, Wen2008Model, distortion_and_derivatives, wen_params_from_matrix
from ..quality.diagnostics import check_condition, check_not_degenerate, design_condition
from ._common import scalar_reference
from ._pairs import PAIRINGS, TERM_INDEX, closed_form_from_factor, pair_factor, pair_normalisation, pair_samples
from .base import Estimator, build_calibration

__all__ = ["Wen2008"]


@dataclasses.dataclass(frozen=True)
class WenSolution:
    """Result of :func:`solve_wen_pairs`: the fitted ``model``, the closed-form ``start`` model, ``phi`` and
    the optimizer result."""

    model: Wen2008Model
    start: Wen2008Model
    phi: float
    start_cond: float
    result: Any


def _gram_entries(p: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The unknowns ``m`` (6,) of the pair design for ``M = C^T C = (D D^T)^-1`` at ``p`` and ``dm/dp`` (6, 4):
    ``dM = -M dG M`` with ``dG = dD D^T + D dD^T``."""
    D, dD = distortion_and_derivatives(p)
    M = np.linalg.inv(D @ D.T)
    dG = dD @ D.T
    dG = dG + dG.transpose(0, 2, 1)
    dM = -M @ dG @ M  # (4, 3, 3)
    rows, cols = TERM_INDEX
    return M[rows, cols], dM[:, rows, cols].T


def solve_wen_pairs(B1: NDArray[np.float64], B2: NDArray[np.float64], *, max_iter: int = 100) -> WenSolution:
    """Fit the reconstructed Wen (2008) model to pairs ``(B1[i], B2[i])`` (both (N, 3)), no validation.

    As in :func:`~trimag.estimators.pairwise.solve_pairs`, every pair's residual ``|C u1|^2 - |C u2|^2`` is
    ``W_i . m`` with ``m`` the entries of ``M = C^T C``: Levenberg-Marquardt runs on the 6 residuals ``R m(p)``
    (``R`` the triangular factor of the design, one pass over the data) with the analytic Jacobian
    ``R dm/dp`` (:func:`_gram_entries`). The objective, minimum, singular values and ``J^T J`` are those of the
    N pair residuals.
    """
    _, scale = pair_normalisation(B1, B2)
    R = pair_factor(B1, B2, scale=scale)
    C0, _, cond = closed_form_from_factor(R)
    start = wen_params_from_matrix(C0)

    def fun(p: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.asarray(R @ _gram_entries(p)[0], dtype=np.float64)

    def jac(p: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.asarray(R @ _gram_entries(p)[1], dtype=np.float64)

    p0 = np.array([start.k1, start.k2, start.alpha, start.gamma])
    res = levenberg_marquardt(fun, p0, jac=jac, xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=max_iter * 10)
    model = Wen2008Model.in_gauge(*res.x)
    return WenSolution(model, start, float(np.sum(res.fun**2)) * scale**4, cond, res)


class Wen2008(Estimator):
    """Baseline: the reconstructed older method of Wen et al. (2008), fitted by the paired objective.

    Parameters
    ----------
    model : {"ortho-gain"}
        The fitted correction is reported in paper A's form (``psi == 0`` by construction of the family);
        Wen's own parameters are in ``wen_params_`` and ``calibration_.diagnostics["wen2008"]``.
    pairing : {"halves", "random"}
        As for ``pairwise``.
    seed : int
        Seed of the random pairing.
    max_iter : int
        Levenberg-Marquardt iteration limit (x10 function evaluations).
    """

    name = "wen2008"
    models = ("ortho-gain",)
    reference_kind = "none"

    def __init__(
        self, model: str = "ortho-gain", pairing: str = "halves", seed: int = 0, max_iter: int = 100
    ) -> None:
        self.model = model
        self.pairing = pairing
        self.seed = seed
        self.max_iter = max_iter

    def _min_samples(self, model: str) -> int:
        return 2 * Wen2008Model.n_identifiable + 2

    def _fit(
        self, B: NDArray[np.float64], reference: Any, *, model: str, units: str, attitude: Any
    ) -> Calibration:
        if self.pairing not in PAIRINGS:
            raise TrimagInputError(f"option `pairing` must be one of {PAIRINGS}; got {self.pairing!r}")
        check_not_degenerate(B)
        ref = scalar_reference(reference, len(B), units)
        B1, B2, idx = pair_samples(B, self.pairing, self.seed)
        sol = solve_wen_pairs(B1, B2, max_iter=int(self.max_iter))
        check_condition(sol.start_cond, what="the wen2008 model from paired samples",
                        hint="record full turns about all three sensor axes")
        cond, _, _ = design_condition(sol.result.jac)
        check_condition(cond, what="the wen2008 model from paired samples",
                        hint="record full turns about all three sensor axes")
        C, _ = normalised_upper(sol.model.correction()[0])
        self.wen_params_ = {k: float(getattr(sol.model, k)) for k in WEN_PARAMS}
        self.coefficients_ = sol.model.coefficients()
        return build_calibration(
            B, C, np.zeros(3), model=model, method=self.name, units=units, reference=ref,
            params=OrthoGain.from_matrix_offset(C).as_dict(), iterations=int(sol.result.nfev),
            converged=bool(sol.result.success),
            diagnostics={
                "condition_number": cond,
                "closed_form_condition": sol.start_cond,
                "optimizer": str(sol.result.message),
                "wen2008": {
                    "note": "reconstruction of Wen et al. (2008); see docs/method-pairwise.md",
                    "params": dict(self.wen_params_),
                    "coefficients": dict(self.coefficients_),
                    "gauge": "tan(alpha) cos(gamma) = cot(beta)",
                },
            },
            extra_stats={"n_pairs": len(B1), "n_used": len(idx), "pairing": self.pairing, "phi": sol.phi},
        )
