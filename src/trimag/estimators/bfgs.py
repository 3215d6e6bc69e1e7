"""``bfgs``: quasi-Newton (BFGS) on the magnitude residual, the iterative baseline paper D compares against.

Paper D (methods.md) cites an earlier calibration that solves the magnitude-correction formula iteratively
(dual LMS and BFGS) and needs data from all directions. This module is that BFGS baseline, rebuilt:

    minimise  f(p) = 1/2 mean_i ( |M (u_i - b)| - t_i )^2        (scipy.optimize.minimize, method="BFGS")

with ``u = V / F_ref``, ``t_i = F_i / F_ref`` (``F_ref`` the RMS reference magnitude, so the problem is
unit-free), ``p`` = the six entries of the upper-triangular correction ``M`` and the offset ``b`` (the same
coefficients paper D's ``W`` encodes), and the analytic gradient. The start is the nominal sensor (identity
matrix scaled to the mean magnitude, zero offset; ``start="centroid"`` starts from the data's centroid); no
use is made of the linear solution, so that the comparison with ``quadric`` is fair. The result is brought to
the model's gauge (``M = cholesky(M^T M)^T``) and converted to the physical parameters.

Like every paper-D method it needs a known magnitude, and it refuses data whose physical Jacobian is rank
deficient (:func:`trimag.estimators.quadric.identifiability_report`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize

from .._core.chunks import chunk_rows
from ..calibration import Calibration
from ..errors import IdentifiabilityError, TrimagInputError
from ..models.zhang_cheng import ZhangCheng, upper_from_quadric
from .base import Estimator, build_calibration
from .ml import magnitude_jacobian
from .quadric import check_identifiable, diagnostics_entries, identifiability_report, require_magnitude

__all__ = ["BFGS", "finish_iterative", "iterative_start", "unpack"]

_UPPER = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))


def unpack(p: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``p`` (9,) -> (upper-triangular ``M`` (3, 3), ``b`` (3,))."""
    M = np.zeros((3, 3))
    M[_UPPER] = p[:6]
    return M, p[6:9]


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


def finish_iterative(
    estimator: Estimator,
    B: NDArray[np.float64],
    p: NDArray[np.float64],
    f_ref: float,
    *,
    model: str,
    units: str,
    ref: Any,
    report: Any,
    iterations: int,
    converged: bool,
    extra: dict[str, Any],
) -> Calibration:
    """Scaled solution ``p`` -> Calibration in the model's gauge, with the identifiability report."""
    if not np.isfinite(p).all():
        raise TrimagInputError(
            f"method {estimator.name!r} diverged (non-finite coefficients); use a smaller step or a better start"
        )
    M_u, b_u = unpack(p)
    try:
        M = upper_from_quadric(M_u.T @ M_u)  # same magnitudes, the model's (upper-triangular) gauge
        est = ZhangCheng.from_matrix_offset(M, b_u * f_ref)
    except TrimagInputError as exc:
        raise IdentifiabilityError(
            f"method {estimator.name!r} ended outside the zhang-cheng model ({exc}); the data do not constrain "
            "it well enough for an iterative fit from the nominal start"
        ) from None
    M, offset = est.correction()
    diagnostics = diagnostics_entries(report, est)
    diagnostics.update(extra)
    return build_calibration(
        B, M, offset, model=model, method=estimator.name, units=units, reference=ref,
        params=est.as_dict(), iterations=iterations, converged=converged, diagnostics=diagnostics,
    )


class BFGS(Estimator):
    """BFGS on the magnitude residual (paper D's quasi-Newton baseline).

    Parameters
    ----------
    model : str
        ``"zhang-cheng"``.
    gtol : float
        Gradient-norm tolerance of ``scipy.optimize.minimize(method="BFGS")`` (scaled, unit-free problem).
    max_iter : int
        Iteration limit.
    start : {"nominal", "centroid"}
        Starting offset: zero (the nominal sensor) or the centroid of the samples.
    """

    name = "bfgs"
    models = ("zhang-cheng",)
    requires_reference = True

    def __init__(
        self, model: str = "zhang-cheng", gtol: float = 1e-10, max_iter: int = 2000, start: str = "nominal"
    ) -> None:
        self.model = model
        self.gtol = gtol
        self.max_iter = max_iter
        self.start = start

    def _fit(
        self, B: NDArray[np.float64], reference: Any, *, model: str, units: str, attitude: Any
    ) -> Calibration:
        ref = require_magnitude(reference, len(B), units, self.name)
        assert ref.values is not None
        f_ref = float(np.sqrt(np.mean(ref.values**2)))
        report = identifiability_report(B, f_ref**2)
        check_identifiable(report, linear=False)
        u, t = B / f_ref, ref.values / f_ref
        p0 = iterative_start(u, self.start)
        n = len(u)

        def fun(p: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
            M, b = unpack(p)
            cost, grad = 0.0, np.zeros(9)
            chunk = chunk_rows(24)
            for s in range(0, n, chunk):  # the (N, 9) Jacobian is never formed: block by block
                mag, J = magnitude_jacobian(u[s : s + chunk], M, b)
                r = mag - t[s : s + chunk]
                cost += float(r @ r)
                grad += r @ J
            return 0.5 * cost / n, grad / n

        res = minimize(
            fun, p0, jac=True, method="BFGS", options={"gtol": float(self.gtol), "maxiter": int(self.max_iter)}
        )
        extra = {
            "optimizer": str(res.message),
            "optimizer_success": bool(res.success),
            "gradient_norm": float(np.linalg.norm(res.jac)),
            "objective": float(res.fun),
            "start": self.start,
        }
        return finish_iterative(
            self, B, res.x, f_ref, model=model, units=units, ref=ref, report=report,
            iterations=int(res.nit), converged=bool(res.success), extra=extra,
        )
