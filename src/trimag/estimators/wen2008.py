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
from typing import Any, ClassVar, Self

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from ..calibration import Calibration
from ..diagnostics import check_condition, check_not_degenerate, design_condition
from ..errors import IdentifiabilityError, TrimagInputError
from ..models.base import ErrorModel
from ..models.ortho_gain import OrthoGain, normalised_upper
from ._common import scalar_reference
from ._pairs import PAIRINGS, TERM_INDEX, closed_form_from_factor, pair_factor, pair_normalisation, pair_samples
from .base import Estimator, build_calibration

__all__ = ["Wen2008"]

WEN_PARAMS = ("alpha", "beta", "gamma", "k1", "k2")


@dataclasses.dataclass(frozen=True)
class Wen2008Model(ErrorModel):
    """The reconstructed Wen (2008) family (not in the model registry: it only serves the baseline).

    Attributes
    ----------
    k1, k2 : float
        Gains of X' and Y' (Z gain 1), multiplying: ``B'x = k1 X'.B``.
    alpha : float
        Angle between X' and X [rad].
    beta : float
        Angle between Y' (in XOY) and X [rad], near pi/2.
    gamma : float
        Azimuth of X' about X, measured from the XOY plane [rad].
    """

    k1: float = 1.0
    k2: float = 1.0
    alpha: float = 0.0
    beta: float = np.pi / 2
    gamma: float = 0.0

    name: ClassVar[str] = "wen2008"
    n_identifiable: ClassVar[int] = 4

    def axes(self) -> NDArray[np.float64]:
        """Rows X', Y', Z' (unit vectors in the ideal frame), shape (3, 3)."""
        a, b, g = self.alpha, self.beta, self.gamma
        return np.array(
            [
                [np.cos(a), np.sin(a) * np.cos(g), np.sin(a) * np.sin(g)],
                [np.cos(b), np.sin(b), 0.0],
                [0.0, 0.0, 1.0],
            ]
        )

    def distortion(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        D: NDArray[np.float64] = np.diag([self.k1, self.k2, 1.0]) @ self.axes()
        return D, np.zeros(3)

    def correction(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        C = np.asarray(np.linalg.inv(self.distortion()[0]), dtype=np.float64)
        return C, np.zeros(3)

    def coefficients(self) -> dict[str, float]:
        """Entries of ``D^-1 / (D^-1)[0, 0]``: ``a1 = C12``, ``a2 = C13``, ``a3 = C21``, ``a4 = -C23``
        (``= -k1 cot(beta) sin(alpha) sin(gamma)``, paper A's quoted a4), ``a5 = C22``, ``a6 = C33``."""
        C = self.correction()[0]
        C = C / C[0, 0]
        return {
            "a1": float(C[0, 1]), "a2": float(C[0, 2]), "a3": float(C[1, 0]),
            "a4": float(-C[1, 2]), "a5": float(C[1, 1]), "a6": float(C[2, 2]),
        }

    def gauge_residual(self) -> float:
        """``tan(alpha) cos(gamma) - cot(beta)``: zero in the reconstruction's gauge."""
        return float(np.tan(self.alpha) * np.cos(self.gamma) - 1.0 / np.tan(self.beta))

    @classmethod
    def in_gauge(cls, k1: float, k2: float, alpha: float, gamma: float) -> Self:
        """The member with free parameters ``(k1, k2, alpha, gamma)`` and ``beta`` from the gauge."""
        beta = float(np.arctan2(1.0, np.tan(alpha) * np.cos(gamma)))
        return cls(k1=float(k1), k2=float(k2), alpha=float(alpha), beta=beta, gamma=float(gamma))

    @classmethod
    def from_gram(cls, G: ArrayLike) -> Self:
        """The gauge-fixed member whose ``D D^T`` matches ``G`` (3, 3) at (1,1), (2,2), (1,2) and (1,3).

        With the gauge, ``X' = (cos e cos d, cos e sin d, sin e)`` and ``Y' = (sin d, cos d, 0)``:
        ``k1 = sqrt(G11)``, ``k2 = sqrt(G22)``, ``sin e = G13 / k1``, ``sin 2d = G12 / (k1 k2 cos e)``; then
        ``alpha = arccos(cos e cos d)``, ``gamma = atan2(sin e, cos e sin d)`` (the division by the small
        ``sin d``), ``beta = pi/2 - d``. ``G23`` (Y'.Z', paper A's psi) cannot be represented and is ignored.
        """
        g = np.asarray(G, dtype=np.float64)
        k1, k2 = float(np.sqrt(g[0, 0])), float(np.sqrt(g[1, 1]))
        sin_e = g[0, 2] / k1
        if abs(sin_e) >= 1:
            raise IdentifiabilityError("wen2008: the fitted X' elevation is not a valid angle")
        cos_e = float(np.sqrt(1.0 - sin_e**2))
        s2d = g[0, 1] / (k1 * k2 * cos_e)
        if abs(s2d) >= 1:
            raise IdentifiabilityError(
                "wen2008: the fitted angle between X' and Y' cannot be split in the reconstruction's gauge"
            )
        d = 0.5 * float(np.arcsin(s2d))
        alpha = float(np.arccos(np.clip(cos_e * np.cos(d), -1.0, 1.0)))
        gamma = float(np.arctan2(sin_e, cos_e * np.sin(d)))
        return cls(k1=k1, k2=k2, alpha=alpha, beta=float(np.pi / 2 - d), gamma=gamma)

    @classmethod
    def from_matrix_offset(cls, matrix: ArrayLike, offset: ArrayLike = (0.0, 0.0, 0.0)) -> Self:
        """Parameters of a correction matrix of the family (any gauge), read from ``D = inv(matrix)``."""
        D = np.linalg.inv(np.asarray(matrix, dtype=np.float64))
        scale = float(np.max(np.abs(D)))
        if np.any(np.abs(np.asarray(offset, dtype=np.float64)) > 0):
            raise TrimagInputError("the wen2008 family has no offsets")
        if np.max(np.abs(D[2] - [0.0, 0.0, 1.0])) > 1e-9 * scale or abs(D[1, 2]) > 1e-9 * scale:
            raise TrimagInputError("matrix is not a member of the wen2008 family (Z' = Z, Y' in XOY)")
        k1, k2 = float(np.linalg.norm(D[0])), float(np.linalg.norm(D[1]))
        x, y = D[0] / k1, D[1] / k2
        return cls(
            k1=k1, k2=k2, alpha=float(np.arccos(np.clip(x[0], -1, 1))),
            beta=float(np.arctan2(y[1], y[0])), gamma=float(np.arctan2(x[2], x[1])),
        )


def wen_params_from_matrix(matrix: ArrayLike) -> Wen2008Model:
    """Map any correction matrix to the gauge-fixed Wen parameters through its magnitude invariants
    ``G = inv(M^T M)`` (normalised to ``G33 = 1``). Used to express another estimator's fit in Wen's
    parameters."""
    m = np.asarray(matrix, dtype=np.float64)
    G = np.linalg.inv(m.T @ m)
    return Wen2008Model.from_gram(G / G[2, 2])


@dataclasses.dataclass(frozen=True)
class WenSolution:
    """Result of :func:`solve_wen_pairs`: the fitted ``model``, the closed-form ``start`` model, ``phi`` and
    the optimizer result."""

    model: Wen2008Model
    start: Wen2008Model
    phi: float
    start_cond: float
    result: Any


def _distortion_and_derivatives(p: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``D`` (3, 3) of :meth:`Wen2008Model.in_gauge` at ``p = (k1, k2, alpha, gamma)`` and ``dD/dp`` (4, 3, 3).

    ``D = diag(k1, k2, 1) [X'; Y'; Z']`` with ``X' = (ca, sa cg, sa sg)``, ``Y' = (cb, sb, 0)`` and the gauge
    ``beta = arccot(t)``, ``t = tan(alpha) cos(gamma)``: ``dbeta/dalpha = -cg / (ca^2 (1 + t^2))``,
    ``dbeta/dgamma = tan(alpha) sg / (1 + t^2)``.
    """
    k1, k2, alpha, gamma = (float(v) for v in p)
    ca, sa, cg, sg = np.cos(alpha), np.sin(alpha), np.cos(gamma), np.sin(gamma)
    t = np.tan(alpha) * cg
    beta = float(np.arctan2(1.0, t))
    cb, sb = np.cos(beta), np.sin(beta)
    dbeta_dalpha = -cg / (ca * ca * (1.0 + t * t))
    dbeta_dgamma = np.tan(alpha) * sg / (1.0 + t * t)
    x_axis = np.array([ca, sa * cg, sa * sg])
    y_axis = np.array([cb, sb, 0.0])
    dy_dbeta = np.array([-sb, cb, 0.0])
    D = np.array([k1 * x_axis, k2 * y_axis, [0.0, 0.0, 1.0]])
    dD = np.zeros((4, 3, 3))
    dD[0, 0] = x_axis
    dD[1, 1] = y_axis
    dD[2, 0] = k1 * np.array([-sa, ca * cg, ca * sg])
    dD[2, 1] = k2 * dy_dbeta * dbeta_dalpha
    dD[3, 0] = k1 * np.array([0.0, -sa * sg, sa * cg])
    dD[3, 1] = k2 * dy_dbeta * dbeta_dgamma
    return D, dD


def _gram_entries(p: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The unknowns ``m`` (6,) of the pair design for ``M = C^T C = (D D^T)^-1`` at ``p`` and ``dm/dp`` (6, 4):
    ``dM = -M dG M`` with ``dG = dD D^T + D dD^T``."""
    D, dD = _distortion_and_derivatives(p)
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
    res = least_squares(
        fun, p0, jac=jac, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=max_iter * 10
    )
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
