"""The reconstructed Wen (2008) parametrisation of paper A's baseline (not in the model registry: it only serves
the ``wen2008`` estimator and paper A's reproduction; methods.md, paper A)."""

from __future__ import annotations

import dataclasses
from typing import ClassVar, Self

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import IdentifiabilityError, TrimagInputError
from .base import ErrorModel

__all__ = ["WEN_PARAMS", "Wen2008Model", "distortion_and_derivatives", "wen_params_from_matrix"]


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


def distortion_and_derivatives(p: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
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
