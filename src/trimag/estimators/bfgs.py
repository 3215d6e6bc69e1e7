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

from .._core.chunks import row_blocks
from ..calibration import Calibration
from ..models.ellipsoid import magnitude_jacobian
from ._common import iterative_start, unpack
from ._finish import finish_iterative
from ._quadric import check_identifiable, identifiability_report, require_magnitude
from .base import Estimator

__all__ = ["BFGS"]


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
            for rows in row_blocks(n, 24):  # the (N, 9) Jacobian is never formed: block by block
                mag, J = magnitude_jacobian(u[rows], M, b)
                r = mag - t[rows]
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
