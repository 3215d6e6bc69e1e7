"""``als``: adjusted least squares for the ellipsoid (Markovsky, Kukush & Van Huffel 2004), a consistent
estimator under strong noise (``docs/accuracy.md``).

The quadric ``v^T xi(x) = 0`` with ``xi = (x^2, y^2, z^2, 2yz, 2xz, 2xy, 2x, 2y, 2z, 1)`` is fitted by
minimising ``v^T Psi v`` with ``|v| = 1``. The ordinary scatter ``Psi = sum xi xi^T`` is biased by the noise
(``E[x_noisy^2] = x^2 + sigma^2``), which is what makes algebraic fits shrink. ALS replaces every monomial
``x^p y^q z^r`` of ``xi xi^T`` by the product of Hermite-type polynomials ``t_p(x) t_q(y) t_r(z)`` whose expectation
under ``N(0, sigma^2)`` noise is the noise-free monomial:

    t_0 = 1, t_1 = x, t_2 = x^2 - s, t_3 = x^3 - 3 s x, t_4 = x^4 - 6 s x^2 + 3 s^2     (s = sigma^2)

so ``E[Psi_als(s)] = Psi_noise_free``, a matrix polynomial ``Psi_0 + s Psi_1 + s^2 Psi_2``. The noise-free
scatter is singular (the true quadric is its null vector), so ``sigma^2`` is estimated as the smallest positive
``s`` at which ``Psi_als(s)`` is singular (a quadratic eigenvalue problem, solved by companion linearisation),
and ``v`` is the null vector there. Consistent as N grows, with the noise estimated from the data; unweighted, so
slightly less efficient than ``ml`` when the soft iron is strong.
"""

from __future__ import annotations

from itertools import product
from typing import Any

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from .._core.quadric import (
    power_sums,
    power_sums_from_moments,
    quadric_moments,
    quadric_to_ellipsoid,
    scatter_from_moments,
)
from ..calibration import Calibration
from ..errors import IdentifiabilityError
from ..quality.diagnostics import check_not_degenerate
from ._common import algebraic_ellipsoid, check_ellipsoid_options, gauge_scale, normalisation_stats, scalar_reference
from ._finish import ellipsoid_result
from .base import Estimator

__all__ = ["AdjustedLeastSquares"]

# xi(x) = sum of coef * x^p y^q z^r, one (exponent, coefficient) list per entry
_XI: tuple[tuple[tuple[tuple[int, int, int], float], ...], ...] = (
    (((2, 0, 0), 1.0),), (((0, 2, 0), 1.0),), (((0, 0, 2), 1.0),),
    (((0, 1, 1), 2.0),), (((1, 0, 1), 2.0),), (((1, 1, 0), 2.0),),
    (((1, 0, 0), 2.0),), (((0, 1, 0), 2.0),), (((0, 0, 1), 2.0),), (((0, 0, 0), 1.0),),
)
# t_k(x; s) = sum_j _HERMITE[k][j] s^j x^(k - 2j)
_HERMITE: tuple[dict[int, float], ...] = ({0: 1.0}, {0: 1.0}, {0: 1.0, 1: -1.0}, {0: 1.0, 1: -3.0},
                                          {0: 1.0, 1: -6.0, 2: 3.0})


def als_scatter(
    u: NDArray[np.float64] | None, *, sums: dict[tuple[int, int, int], float] | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """``(Psi_0, Psi_1, Psi_2)``: the noise-corrected scatter is ``Psi_0 + s Psi_1 + s^2 Psi_2``, ``s = sigma^2``.

    ``u`` : ndarray, shape (N, 3), samples (normalised units); or ``sums``, their power sums
    (:func:`~trimag.estimators.ellipsoid_fit.power_sums`), when the caller has them (``u`` is then not read).
    """
    # the 35 sums of x^p y^q z^r, p + q + r <= 4, in one pass
    mom = sums if sums is not None else power_sums(np.asarray(u, dtype=np.float64))
    P = np.zeros((3, 10, 10))
    for a in range(10):
        for b in range(a, 10):
            for (ea, ca), (eb, cb) in product(_XI[a], _XI[b]):
                e = tuple(i + j for i, j in zip(ea, eb, strict=True))
                for j in product(*(_HERMITE[k].items() for k in e)):
                    power = sum(jj for jj, _ in j)
                    coef = ca * cb * float(np.prod([c for _, c in j]))
                    reduced = tuple(k - 2 * jj for k, (jj, _) in zip(e, j, strict=True))
                    P[power, a, b] += coef * mom[reduced]  # type: ignore[index]
            P[:, b, a] = P[:, a, b]
    return P[0], P[1], P[2]


def als_solve(
    u: NDArray[np.float64] | None, *, sums: dict[tuple[int, int, int], float] | None = None
) -> tuple[NDArray[np.float64], float]:
    """ALS quadric ``v`` (10,) and the estimated noise variance ``s`` (normalised units) for samples ``u`` (or
    their power ``sums``, as :func:`als_scatter`)."""
    P0, P1, P2 = als_scatter(u, sums=sums)
    n = 10
    # companion linearisation of (P0 + s P1 + s^2 P2) v = 0:  A z = s B z with z = (v, s v)
    A = np.block([[np.zeros((n, n)), np.eye(n)], [-P0, -P1]])
    Bm = np.block([[np.eye(n), np.zeros((n, n))], [np.zeros((n, n)), P2]])
    vals = scipy.linalg.eigvals(A, Bm)
    finite = np.isfinite(vals)
    # the root is 0 for noise-free data (computed as +-1e-16): accept a tiny negative value as 0
    real = finite & (np.abs(vals.imag) <= 1e-8 * np.maximum(1.0, np.abs(vals.real))) & (vals.real > -1e-10)
    if not np.any(real):
        raise IdentifiabilityError(
            "adjusted least squares found no noise level that explains the data as an ellipsoid; record the "
            "sensor turning through many more attitudes (or use `method=ml`)"
        )
    s = max(float(np.min(vals.real[real])), 0.0)
    M = P0 + s * P1 + s * s * P2
    _, vecs = np.linalg.eigh(0.5 * (M + M.T))
    return np.asarray(vecs[:, 0], dtype=np.float64), s


class AdjustedLeastSquares(Estimator):
    """Adjusted least squares (consistent under strong noise), noise level estimated from the data.

    Parameters
    ----------
    model : str
        ``"ellipsoid"``.
    form : {"upper", "symmetric"}
        Gauge of the returned soft-iron matrix.
    """

    name = "als"
    models = ("ellipsoid",)

    def __init__(self, model: str = "ellipsoid", form: str = "upper") -> None:
        self.model = model
        self.form = form

    def _fit(
        self, B: NDArray[np.float64], reference: Any, *, model: str, units: str, attitude: Any
    ) -> Calibration:
        check_ellipsoid_options(self.form)
        principal = check_not_degenerate(B)
        ref = scalar_reference(reference, len(B), units)
        # one pass over the raw samples, normalised block by block (no normalised copy: memory independent of N)
        norm = normalisation_stats(B)
        moments = quadric_moments(B, norm)
        _, _, cond = algebraic_ellipsoid(B, scatter=scatter_from_moments(moments))  # identifiability checks
        v, s = als_solve(None, sums=power_sums_from_moments(moments))
        W_u, c_u = quadric_to_ellipsoid(v)
        W = W_u / norm.scale
        offset = norm.centre + norm.scale * c_u
        W, F_hat = gauge_scale(W, ref.values)
        sigma = float(np.sqrt(s) * norm.scale)
        return ellipsoid_result(
            B, W, offset, ref=ref, F_hat=F_hat, sigma=sigma, model=model, method=self.name, units=units,
            form=self.form, diagnostics={"condition_number": cond, "als_noise_std": sigma},
            uncertainty_note="Fisher information at the estimate (a lower bound; ALS is consistent but "
            "unweighted)",
            principal=principal,
        )
