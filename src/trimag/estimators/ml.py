"""``ml``: least squares on the magnitude residual ``|W (B - b)| - F``, Levenberg-Marquardt, analytic Jacobian.

Start: the algebraic fit (``ellipsoid-fit``). Parameters: the upper-triangular ``W`` (6, the gauge that removes
the rotation a magnitude cannot see) and the offset ``b`` (3). With an unknown magnitude the fit is made on the
unit sphere and then scaled to ``det(W) = 1``. Parameter standard deviations come from the Jacobian at the
solution, ``cov = s^2 (J^T J)^-1`` with ``s^2`` the residual variance (noise estimated from the data).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from ..calibration import Calibration
from ..diagnostics import check_condition, check_not_degenerate, design_condition, weak_directions
from ..models.ellipsoid import Ellipsoid, to_symmetric
from ._common import normalise, scalar_reference
from .base import Estimator, build_calibration
from .ellipsoid_fit import algebraic_ellipsoid, gauge_scale

__all__ = ["MaximumLikelihood", "magnitude_jacobian"]

_UPPER = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))
_NAMES = ("w11", "w12", "w13", "w22", "w23", "w33", "hard_iron_x", "hard_iron_y", "hard_iron_z")


def _unpack(p: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    W = np.zeros((3, 3))
    W[_UPPER] = p[:6]
    return W, p[6:9]


def magnitude_jacobian(
    u: NDArray[np.float64], W: NDArray[np.float64], b: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Magnitudes ``|W (u - b)|`` (N,) and their Jacobian (N, 9) w.r.t. (upper W, b)."""
    e = u - b
    y = e @ W.T
    mag = np.sqrt(np.einsum("ij,ij->i", y, y))
    n = y / mag[:, None]
    J = np.empty((len(u), 9))
    J[:, :6] = n[:, _UPPER[0]] * e[:, _UPPER[1]]
    J[:, 6:] = -(n @ W)
    return mag, J


class MaximumLikelihood(Estimator):
    """Magnitude-residual least squares (the maximum-likelihood fit for small noise).

    Parameters
    ----------
    model : str
        ``"ellipsoid"``.
    form : {"upper", "symmetric"}
        Gauge of the returned soft-iron matrix.
    loss : str
        ``scipy.optimize.least_squares`` loss: ``"linear"`` (default) or a robust one (``"soft_l1"``,
        ``"huber"``, ``"cauchy"``) for logs with disturbed samples.
    max_iter : int
        Iteration limit.
    """

    name = "ml"
    models = ("ellipsoid",)

    def __init__(self, model: str = "ellipsoid", form: str = "upper", loss: str = "linear", max_iter: int = 100):
        self.model = model
        self.form = form
        self.loss = loss
        self.max_iter = max_iter

    def _fit(
        self, B: NDArray[np.float64], reference: Any, *, model: str, units: str, attitude: Any
    ) -> Calibration:
        check_not_degenerate(B)
        ref = scalar_reference(reference, len(B), units)
        u, norm = normalise(B)
        W0, c0, _ = algebraic_ellipsoid(u)
        if ref.values is not None:
            f_scale = float(np.sqrt(np.mean(ref.values**2)))
            target = ref.values / f_scale
        else:
            f_scale, target = 1.0, np.ones(len(B))
        # unit-sphere start; corrected_u = W_u (u - b_u) has magnitude ~ target
        p0 = np.concatenate([W0[_UPPER], c0])

        def fun(p: NDArray[np.float64]) -> NDArray[np.float64]:
            W, b = _unpack(p)
            return np.linalg.norm((u - b) @ W.T, axis=1) - target

        def jac(p: NDArray[np.float64]) -> NDArray[np.float64]:
            W, b = _unpack(p)
            return magnitude_jacobian(u, W, b)[1]

        method = "lm" if self.loss == "linear" else "trf"
        res = least_squares(
            fun, p0, jac=jac, method=method, loss=self.loss, xtol=1e-12, ftol=1e-12, gtol=1e-12,
            max_nfev=self.max_iter * 10,
        )
        W_u, b_u = _unpack(res.x)
        cond, s, vt = design_condition(res.jac)
        check_condition(
            cond, what="the ellipsoid model", hint="record the sensor turning about all three axes",
            weak=weak_directions(vt, s, _NAMES, threshold=1e4) if np.isfinite(cond) else [],
        )
        dof = max(len(u) - 9, 1)
        sigma2 = float(np.sum(res.fun**2) / dof)
        cov_u = sigma2 * np.linalg.pinv(res.jac.T @ res.jac)
        # back to data units: W = W_u * f_scale / scale, b = centre + scale * b_u
        W = W_u * f_scale / norm.scale
        offset = norm.centre + norm.scale * b_u
        jac_scale = np.concatenate([np.full(6, f_scale / norm.scale), np.full(3, norm.scale)])
        cov = cov_u * np.outer(jac_scale, jac_scale)
        F_hat = None
        if ref.values is None:
            W, F_hat = gauge_scale(W, None)
        if self.form == "symmetric":
            W = to_symmetric(W)
        iterations = int(getattr(res, "njev", None) or res.nfev)
        uncertainty = {
            "gauge": "upper-triangular W" + (" (before det(W)=1 scaling)" if F_hat is not None else ""),
            "param_std": dict(zip(_NAMES, np.sqrt(np.diag(cov)).tolist(), strict=True)),
            "covariance": cov.tolist(),
            "covariance_order": list(_NAMES),
            "noise_std": float(np.sqrt(sigma2) * f_scale),
        }
        return build_calibration(
            B, W, offset, model=model, method=self.name, units=units, reference=ref,
            params=Ellipsoid.from_matrix_offset(W, offset).as_dict(), iterations=iterations,
            converged=bool(res.success), fitted_magnitude=F_hat, uncertainty=uncertainty,
            diagnostics={"condition_number": cond, "optimizer": res.message},
        )
