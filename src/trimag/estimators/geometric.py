"""``geometric``: paper A's model fitted on all samples at once, the field magnitude a free nuisance.

Beyond the paper. Instead of differences of squared magnitudes over pairs, minimise the geometric residual of
every sample (methods.md, paper A, model; trimag extension)

    sum_i ( |Gamma^-1 (B'_i - b)| - h )^2     over (q1..q5, [b], h)

with ``Gamma^-1 = [[q1, q2, q3], [0, q4, q5], [0, 0, 1]]`` and ``h`` the unknown field magnitude in the Z
axis's unit. For white isotropic noise that is small against ``h`` this is the maximum-likelihood fit; each
noise sample enters once, through one residual, where the pairwise objective mixes two samples' noise in each
squared-magnitude difference. Start: a linear least-squares fit of the quadric ``B'^T A B' + 2 g^T B' = 1``
(``g = 0`` for ``ortho-gain``), reduced to ``Gamma^-1`` by the upper Cholesky factor scaled to ``C[2, 2] ==
1``. Then Gauss-Newton with the analytic Jacobian (a few 6 x 6 or 9 x 9 solves), Levenberg-Marquardt when a
step raises the cost (:mod:`trimag.estimators._solve`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..diagnostics import check_condition, check_not_degenerate, design_condition, weak_directions
from ..errors import IdentifiabilityError
from ..models import get_model
from ._common import scalar_reference
from ._solve import gauss_newton_then_lm
from .base import Estimator, build_calibration
from .pairwise import params_covariance, q_to_matrix

__all__ = ["Geometric", "GeometricSolution", "solve_geometric"]

_Q_IDX = (np.array([0, 0, 0, 1, 1]), np.array([0, 1, 2, 1, 2]))
_NAMES = ("q1", "q2", "q3", "q4", "q5")
_B_NAMES = ("bx", "by", "bz")


@dataclass(frozen=True)
class GeometricSolution:
    """Result of :func:`solve_geometric`: ``C`` = Gamma^-1 (3, 3), offset ``b`` (3,), field magnitude ``h``
    (Z-axis unit), ``q`` (5,), the start's condition number and the optimizer result."""

    C: NDArray[np.float64]
    b: NDArray[np.float64]
    h: float
    q: NDArray[np.float64]
    start_cond: float
    result: Any


def _start(
    u: NDArray[np.float64], bias: bool
) -> tuple[NDArray[np.float64], NDArray[np.float64], float, float]:
    """Linear start: fit ``u^T A u + 2 g^T u = 1`` (``g = 0`` without bias) by least squares, then
    ``c = -A^-1 g``, ``M = A / (1 + c^T A c)``, ``Gamma^-1 = R / R[2, 2]`` with ``M = R^T R``; returns
    ``(C, c, h, cond)``."""
    x, y, z = u.T
    cols = [x * x, y * y, z * z, 2 * x * y, 2 * y * z, 2 * x * z]
    if bias:
        cols += [2 * x, 2 * y, 2 * z]
    D = np.column_stack(cols)
    d = np.linalg.norm(D, axis=0)
    d[d == 0] = 1.0
    sol, *_ = np.linalg.lstsq(D / d, np.ones(len(u)), rcond=None)
    sv = np.linalg.svd(D / d, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
    model = "ortho-gain-bias" if bias else "ortho-gain"
    check_condition(
        cond, what=f"the {model} model from field magnitudes",
        hint="record full turns about all three sensor axes",
    )
    m = sol / d
    A = np.array([[m[0], m[3], m[5]], [m[3], m[1], m[4]], [m[5], m[4], m[2]]])
    c = -np.linalg.solve(A, m[6:9]) if bias else np.zeros(3)
    k = 1.0 + float(c @ A @ c)
    try:
        if k <= 0:
            raise np.linalg.LinAlgError
        R = np.linalg.cholesky(A / k).T
    except np.linalg.LinAlgError:
        raise IdentifiabilityError(
            "the samples do not describe an ellipsoid (the fitted quadric is not positive definite); "
            "record full turns about all three sensor axes"
        ) from None
    return R / R[2, 2], c, 1.0 / R[2, 2], cond


def solve_geometric(B: NDArray[np.float64], *, bias: bool = False, max_iter: int = 100) -> GeometricSolution:
    """Fit ``|Gamma^-1 (B - b)| = h`` on all samples ``B`` (N, 3) without validation."""
    centre = B.mean(axis=0) if bias else np.zeros(3)
    scale = float(np.sqrt(np.mean(np.sum((B - centre) ** 2, axis=1)))) or 1.0
    u = (B - centre) / scale
    C0, b0, h0, cond = _start(u, bias)
    nb = 3 if bias else 0
    p0 = np.concatenate([C0[_Q_IDX], b0[:nb], [h0]])

    def unpack(p: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
        return q_to_matrix(p[:5]), (p[5:8] if bias else np.zeros(3)), float(p[-1])

    ut = np.ascontiguousarray(u.T)  # component-major (3, N): contiguous passes (trimag._rowwise)

    def fun(p: NDArray[np.float64]) -> NDArray[np.float64]:
        C, b, h = unpack(p)
        y = C @ (ut - b[:, None])
        return np.asarray(np.sqrt(y[0] * y[0] + y[1] * y[1] + y[2] * y[2]) - h, dtype=np.float64)

    def jac(p: NDArray[np.float64]) -> NDArray[np.float64]:
        C, b, _ = unpack(p)
        e = ut - b[:, None]
        y = C @ e
        n = y / np.sqrt(y[0] * y[0] + y[1] * y[1] + y[2] * y[2])
        Jt = np.empty((6 + nb, e.shape[1]))
        for k, (r, c) in enumerate(zip(*_Q_IDX, strict=True)):
            np.multiply(n[r], e[c], out=Jt[k])
        if bias:
            Jt[5:8] = -(C.T @ n)
        Jt[-1] = -1.0
        return Jt.T

    res = gauss_newton_then_lm(
        fun, jac, p0, max_steps=max_iter,
        lm_options={"xtol": 1e-15, "ftol": 1e-15, "gtol": 1e-15, "max_nfev": max_iter * 10},
    )
    C, b_u, h = unpack(res.x)
    return GeometricSolution(C, centre + scale * b_u, h * scale, res.x[:5].copy(), cond, res)


class Geometric(Estimator):
    """Paper A's model on all 2N samples, geometric residual ``|Gamma^-1 (B' - b)| - h``, ``h`` free.

    Parameters
    ----------
    model : {"ortho-gain", "ortho-gain-bias"}
        Paper A's 5-parameter model, or the same with three offsets.
    max_iter : int
        Gauss-Newton step limit; the Levenberg-Marquardt fallback gets x10 function evaluations.

    Notes
    -----
    The field magnitude ``h`` is always fitted (in the Z axis's unit, since the model fixes the Z gain to 1);
    a numeric ``reference`` only serves the before/after statistics. ``h`` is reported in
    ``stats["fitted_magnitude"]``.
    """

    name = "geometric"
    models = ("ortho-gain", "ortho-gain-bias")
    reference_kind = "scalar"

    def __init__(self, model: str = "ortho-gain", max_iter: int = 100):
        self.model = model
        self.max_iter = max_iter

    def _min_samples(self, model: str) -> int:
        return int(get_model(model).n_identifiable) + 2  # + the magnitude h, + 1 degree of freedom

    def _fit(
        self, B: NDArray[np.float64], reference: Any, *, model: str, units: str, attitude: Any
    ) -> Calibration:
        check_not_degenerate(B)
        ref = scalar_reference(reference, len(B), units)
        bias = model == "ortho-gain-bias"
        sol = solve_geometric(B, bias=bias, max_iter=int(self.max_iter))
        names = (*_NAMES, *(_B_NAMES if bias else ()), "h")
        cond, s, vt = design_condition(sol.result.jac)
        check_condition(
            cond,
            what=f"the {model} model from field magnitudes",
            hint="record full turns about all three sensor axes",
            weak=weak_directions(vt, s, names, threshold=1e4) if np.isfinite(cond) else [],
        )
        instance = get_model(model).from_matrix_offset(sol.C, sol.b)
        J = sol.result.jac
        dof = max(J.shape[0] - J.shape[1], 1)
        s2 = float(np.sum(sol.result.fun**2)) / dof
        centre = B.mean(axis=0) if bias else np.zeros(3)
        scale = float(np.sqrt(np.mean(np.sum((B - centre) ** 2, axis=1)))) or 1.0
        cov = params_covariance(sol.q, s2 * np.linalg.pinv(J.T @ J), np.full(J.shape[1] - 5, scale))
        out_names = [*get_model(model).param_names(), "h"]
        uncertainty = {
            "param_std": dict(zip(out_names, np.sqrt(np.clip(np.diag(cov), 0, None)).tolist(), strict=True)),
            "covariance": cov.tolist(),
            "covariance_order": out_names,
            "noise_std": float(np.sqrt(s2) * scale),
        }
        return build_calibration(
            B, sol.C, sol.b, model=model, method=self.name, units=units, reference=ref,
            params=instance.as_dict(), iterations=int(sol.result.nfev), converged=bool(sol.result.success),
            fitted_magnitude=sol.h if ref.values is None else None, uncertainty=uncertainty,
            diagnostics={
                "condition_number": cond,
                "start_condition": sol.start_cond,
                "optimizer": str(sol.result.message),
            },
            extra_stats={"fitted_magnitude": sol.h},
        )
