"""``geometric``: paper A's model fitted on all samples at once, the field magnitude a free nuisance.

Beyond the paper. Instead of differences of squared magnitudes over pairs, minimise the geometric residual of
every sample (methods.md, paper A, model; trimag extension)

    sum_i ( |Gamma^-1 (B'_i - b)| - h )^2     over (q1..q5, [b], h)

with ``Gamma^-1 = [[q1, q2, q3], [0, q4, q5], [0, 0, 1]]`` and ``h`` the unknown field magnitude in the Z
axis's unit. For white isotropic noise that is small against ``h`` this is the maximum-likelihood fit; each
noise sample enters once, through one residual, where the pairwise objective mixes two samples' noise in each
squared-magnitude difference. Start: a linear least-squares fit of the quadric ``B'^T A B' + 2 g^T B' = 1``
(``g = 0`` for ``ortho-gain``), reduced to ``Gamma^-1`` by the upper Cholesky factor scaled to ``C[2, 2] ==
1``. Then Gauss-Newton with the analytic Jacobian, Levenberg-Marquardt when a step raises the cost (the rule of
:func:`trimag._core.solve.gauss_newton_then_lm`).

Every sum over samples (the normalisation, the start's design, the residuals, the Jacobian and the cost) is taken
in chunks of samples (:func:`~trimag._core.chunks.chunk_rows`): the start's design and each Gauss-Newton system ``[J
| -r]`` are factored
block by block (:class:`._qr.BlockedQR`), so memory does not grow with N. Only the rare Levenberg-Marquardt
fallback holds the whole (N, p) Jacobian (MINPACK needs it).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._core.chunks import chunk_rows, row_blocks
from .._core.qr import BlockedQR
from .._core.quadric import quadratic_terms
from .._core.rowwise import scratch, sum_squares, transposed_blocks
from .._core.solve import XTOL, GaussNewtonResult, gauss_newton_rule, levenberg_marquardt
from .._core.threads import one_blas_thread
from ..calibration import Calibration
from ..errors import IdentifiabilityError
from ..models import get_model
from ..models.ortho_gain import Q_INDEX, params_covariance, q_to_matrix
from ..quality.diagnostics import check_condition, check_not_degenerate, design_condition, weak_directions
from ._common import normalisation_stats, scalar_reference
from ._finish import make_uncertainty
from .base import Estimator, build_calibration

__all__ = ["Geometric"]

_NAMES = ("q1", "q2", "q3", "q4", "q5")
_B_NAMES = ("bx", "by", "bz")

#: The Gauss-Newton system at a point: its :class:`._qr.BlockedQR` of ``[J | -r]`` (None when a residual is not
#: finite) and ``sum r^2``.
_System = tuple[BlockedQR | None, float]


@dataclass(frozen=True)
class GeometricSolution:
    """Result of :func:`solve_geometric`.

    Attributes
    ----------
    C : ndarray, shape (3, 3)
        ``Gamma^-1``.
    b : ndarray, shape (3,)
        Offset (data unit; zeros without bias).
    h : float
        Field magnitude (Z-axis unit).
    q : ndarray, shape (5,)
        ``(q1..q5)``.
    start_cond : float
        Column-normalised condition number of the linear start's design.
    result : dict
        The optimizer's summary, as ``scipy.optimize.OptimizeResult``: ``x`` (normalised parameters), ``nfev``,
        ``njev``, ``success``, ``status``, ``method``, ``message``. The (N,) residuals and (N, p) Jacobian are
        not kept: see ``R``, ``rss`` and ``n``.
    R : ndarray, shape (p, p)
        Upper-triangular factor of the Jacobian ``J`` (N, p) at the solution, in the normalised parameters
        ``(q1..q5, [b / scale], h / scale)``: the same singular values, right singular vectors and column norms
        as ``J``, and ``R^T R = J^T J``.
    rss : float
        ``sum r_i^2`` at the solution (normalised units: data unit / ``scale``, squared).
    n : int
        Number of samples (residuals).
    centre, scale : ndarray (3,), float
        The normalisation ``u = (B - centre) / scale`` of the fit (``centre`` = the mean with bias, else zeros;
        ``scale`` = the RMS of ``|B - centre|``).
    """

    C: NDArray[np.float64]
    b: NDArray[np.float64]
    h: float
    q: NDArray[np.float64]
    start_cond: float
    result: Any
    R: NDArray[np.float64]
    rss: float
    n: int
    centre: NDArray[np.float64]
    scale: float


def _normalisation(B: NDArray[np.float64], bias: bool) -> tuple[NDArray[np.float64], float]:
    """``centre`` (the mean of ``B`` with bias, else zeros) and ``scale`` = RMS ``|B - centre|`` (1 if zero), block
    by block (:func:`._common.normalisation_stats`)."""
    norm = normalisation_stats(B, centre=None if bias else np.zeros(3))
    return norm.centre, norm.scale


def _unit_blocks(
    B: NDArray[np.float64], centre: NDArray[np.float64], scale: float
) -> Iterator[NDArray[np.float64]]:
    """Consecutive blocks ``((B - centre) / scale).T`` (3, m) of a chunk of samples, component-major, in a
    reused buffer (use each before asking for the next)."""
    for _, t in transposed_blocks(B, centre, block=chunk_rows()):
        np.divide(t, scale, out=t)
        yield t


def _start(
    B: NDArray[np.float64], centre: NDArray[np.float64], scale: float, bias: bool
) -> tuple[NDArray[np.float64], NDArray[np.float64], float, float]:
    """Linear start on ``u = (B - centre) / scale``.

    Fits ``u^T A u + 2 g^T u = 1`` (``g = 0`` without bias) by least squares, then ``c = -A^-1 g``,
    ``M = A / (1 + c^T A c)``, ``Gamma^-1 = R / R[2, 2]`` with ``M = R^T R``. The design is accumulated block by
    block into a QR factorisation (:class:`._qr.BlockedQR`): its ``R`` has the singular values and column norms
    of the design, so the column-normalised solution (with ``numpy.linalg.lstsq``'s cut-off for N rows) and
    condition number are those of the whole design.

    Returns
    -------
    C : ndarray, shape (3, 3)
    c : ndarray, shape (3,)
        Centre of the ellipsoid in ``u``.
    h : float
        Field magnitude in ``u``'s unit.
    cond : float
        Column-normalised condition number of the design.

    Raises
    ------
    IdentifiabilityError
        When the design is ill-conditioned or the quadric is not an ellipsoid.
    """
    n = len(B)
    p = 9 if bias else 6
    qr = BlockedQR(p)
    m0 = min(max(n, 1), chunk_rows())
    with scratch(p, m0) as design, scratch(m0) as ones:
        ones.fill(1.0)
        for t in _unit_blocks(B, centre, scale):
            m = t.shape[1]
            d = design[:, :m]
            quadratic_terms(t, d)  # x^2, y^2, z^2, yz, xz, xy
            d[3:6] *= 2.0
            if bias:
                np.multiply(t, 2.0, out=d[6:9])
            qr.add(d.T, ones[:m])
    R = qr.R
    cond, _, _ = design_condition(R)  # R has the singular values and column norms of the design
    model = "ortho-gain-bias" if bias else "ortho-gain"
    check_condition(
        cond, what=f"the {model} model from field magnitudes",
        hint="record full turns about all three sensor axes",
    )
    d_norm = np.linalg.norm(R, axis=0)
    d_norm[d_norm == 0] = 1.0
    # the cut-off numpy.linalg.lstsq(rcond=None) applies to the whole (N, p) design
    rcond = float(np.finfo(np.float64).eps) * max(n, p)
    sol = np.linalg.lstsq(R / d_norm, qr.qtb, rcond=rcond)[0]
    m = sol / d_norm
    A = np.array([[m[0], m[5], m[4]], [m[5], m[1], m[3]], [m[4], m[3], m[2]]])
    c = -np.linalg.solve(A, m[6:9]) if bias else np.zeros(3)
    k = 1.0 + float(c @ A @ c)
    try:
        if k <= 0:
            raise np.linalg.LinAlgError
        U = np.linalg.cholesky(A / k).T
    except np.linalg.LinAlgError:
        raise IdentifiabilityError(
            "the samples do not describe an ellipsoid (the fitted quadric is not positive definite); "
            "record full turns about all three sensor axes"
        ) from None
    return U / U[2, 2], c, 1.0 / U[2, 2], cond


def _unpack(p: NDArray[np.float64], bias: bool) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """``(Gamma^-1, b, h)`` from the parameters ``(q1..q5, [b], h)``."""
    return q_to_matrix(p[:5]), (p[5:8] if bias else np.zeros(3)), float(p[-1])


def _system_block(
    e: NDArray[np.float64], C: NDArray[np.float64], h: float, bias: bool,
    out: NDArray[np.float64], y: NDArray[np.float64],
) -> None:
    """Rows of ``[J | -r]^T`` for one block into ``out`` (p + 1, m): the Jacobian ``J^T`` (p, m) then ``-r``.

    ``e = u - b`` (3, m); ``y`` (3, m) is scratch. With ``y = C e`` and ``n = y / |y|``, the residual is
    ``r = |y| - h`` and ``dr/dq_k = n_row e_col`` for ``q_k = C[row, col]``, ``dr/db = -C^T n``, ``dr/dh = -1``.
    """
    p = len(out) - 1
    np.matmul(C, e, out=y)
    neg_r = out[p]
    sum_squares(y, out=neg_r, tmp=out[0])
    np.sqrt(neg_r, out=neg_r)  # |y|
    y /= neg_r  # n
    for k, (row, col) in enumerate(zip(*Q_INDEX, strict=True)):
        np.multiply(y[row], e[col], out=out[k])
    if bias:
        np.matmul(C.T, y, out=out[5:8])
        np.negative(out[5:8], out=out[5:8])
    out[p - 1] = -1.0
    np.subtract(h, neg_r, out=neg_r)  # -r = h - |y|


def _linearise(
    B: NDArray[np.float64], centre: NDArray[np.float64], scale: float, bias: bool, p: NDArray[np.float64]
) -> _System:
    """The Gauss-Newton system ``min |J delta + r|`` at ``p``: a :class:`._qr.BlockedQR` of ``[J | -r]`` accumulated
    block by block (``J`` is never held whole) and ``sum r_i^2``; ``(None, inf)`` as soon as a residual is not
    finite."""
    C, b, h = _unpack(p, bias)
    npar = len(p)
    n = len(B)
    m0 = min(max(n, 1), chunk_rows())
    qr = BlockedQR(npar)
    rss = 0.0
    with scratch(npar + 1, m0) as system, scratch(3, m0) as y:
        for t in _unit_blocks(B, centre, scale):
            m = t.shape[1]
            t -= b[:, None]
            out = system[:, :m]
            _system_block(t, C, h, bias, out, y[:, :m])
            part = float(out[npar] @ out[npar])
            if not np.isfinite(part):
                return None, float("inf")
            rss += part
            qr.add(out[:npar].T, out[npar])
    return qr, rss


def _gauss_newton(
    system: Callable[[NDArray[np.float64]], _System], p0: NDArray[np.float64], *, max_steps: int, xtol: float = XTOL
) -> tuple[GaussNewtonResult, BlockedQR, float] | None:
    """Undamped Gauss-Newton from ``p0`` by :func:`trimag._core.solve.gauss_newton_rule`, each step from the QR
    factorisation of ``[J | -r]`` (``system(p)``) instead of the normal equations; None when a step raises
    ``sum r^2`` (far from the minimum) or ``max_steps`` pass without convergence. The system is linearised at every
    trial point (a rejected trial ends the run). Returns the result (fields of ``scipy.optimize.OptimizeResult``
    without ``fun`` and ``jac``), the system at the solution and its ``sum r^2``.
    """

    def direction(qr: BlockedQR, _: Any) -> NDArray[np.float64] | None:
        R = qr.R
        d = np.linalg.norm(R, axis=0)  # the column norms of J
        if not np.all(np.isfinite(d)) or np.any(d == 0):
            return None
        try:  # Jacobi-scaled (columns of very different size stay well conditioned)
            return np.asarray(np.linalg.solve(R / d, qr.qtb) / d, dtype=np.float64)
        except np.linalg.LinAlgError:
            return None

    run = gauss_newton_rule(system, lambda p, qr: None, direction, p0, max_steps=max_steps, xtol=xtol)
    if not run.converged:
        return None
    result = GaussNewtonResult(
        x=run.p, nfev=run.nfev, njev=run.njev, success=True, status=2, method="gauss-newton",
        message=f"Gauss-Newton converged in {run.steps} steps (relative step <= {xtol:g})", step_norms=run.step_norms,
    )
    return result, run.state, run.cost


def _levenberg_marquardt(
    B: NDArray[np.float64], centre: NDArray[np.float64], scale: float, bias: bool, p0: NDArray[np.float64],
    max_iter: int,
) -> tuple[Any, BlockedQR, float]:
    """Levenberg-Marquardt (:func:`trimag._core.solve.levenberg_marquardt`) from ``p0`` on all samples at once
    (the fallback: MINPACK
    holds the (N, p) Jacobian). Returns the result without ``fun`` and ``jac``, the QR factorisation of
    ``[J | -r]`` at the solution and ``sum r^2``."""
    n, npar = len(B), len(p0)
    ut = np.empty((3, n))  # component-major (3, N): contiguous passes (trimag._core.rowwise)
    for start, t in transposed_blocks(B, centre, block=chunk_rows()):
        np.divide(t, scale, out=ut[:, start : start + t.shape[1]])

    def fun(p: NDArray[np.float64]) -> NDArray[np.float64]:
        C, b, h = _unpack(p, bias)
        y = C @ (ut - b[:, None])
        return np.asarray(np.sqrt(y[0] * y[0] + y[1] * y[1] + y[2] * y[2]) - h, dtype=np.float64)

    def jac(p: NDArray[np.float64]) -> NDArray[np.float64]:
        C, b, h = _unpack(p, bias)
        out = np.empty((npar + 1, n))
        _system_block(ut - b[:, None], C, h, bias, out, np.empty((3, n)))
        return out[:npar].T

    res = levenberg_marquardt(fun, p0, jac=jac, xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=max_iter * 10)
    res.message = f"Gauss-Newton did not converge; Levenberg-Marquardt: {res.message}"
    J, r = res.pop("jac"), res.pop("fun")
    qr = BlockedQR(npar)
    for rows in row_blocks(n):
        qr.add(J[rows], -r[rows])
    return res, qr, float(r @ r)


def solve_geometric(B: NDArray[np.float64], *, bias: bool = False, max_iter: int = 100) -> GeometricSolution:
    """Fit ``|Gamma^-1 (B - b)| = h`` on all samples ``B`` (N, 3) without validation.

    Parameters
    ----------
    B : ndarray, shape (N, 3)
        Raw samples.
    bias : bool
        Fit the offset ``b`` too (``ortho-gain-bias``).
    max_iter : int
        Gauss-Newton steps before Levenberg-Marquardt takes over (with ``10 max_iter`` function evaluations).

    Returns
    -------
    GeometricSolution

    Notes
    -----
    The fit runs on ``u = (B - centre) / scale`` block by block: memory does not grow with N, except in the
    Levenberg-Marquardt fallback (taken when a Gauss-Newton step raises the cost), which holds the whole (N, p)
    Jacobian. Called from the main thread it runs with one BLAS thread (:func:`trimag._core.threads.one_blas_thread`).
    """
    def system(p: NDArray[np.float64]) -> _System:
        return _linearise(B, centre, scale, bias, p)

    # small QR factorisations per block: a second BLAS thread would only spin-wait (trimag._core.threads)
    with one_blas_thread():
        centre, scale = _normalisation(B, bias)
        C0, b0, h0, cond = _start(B, centre, scale, bias)
        nb = 3 if bias else 0
        p0 = np.concatenate([C0[Q_INDEX], b0[:nb], [h0]])
        gn = _gauss_newton(system, p0, max_steps=max_iter)
        if gn is not None:
            res, qr, rss = gn
        else:
            res, qr, rss = _levenberg_marquardt(B, centre, scale, bias, p0, max_iter)
    x = np.asarray(res.x, dtype=np.float64)
    C, b_u, h = _unpack(x, bias)
    return GeometricSolution(
        C, centre + scale * b_u, h * scale, x[:5].copy(), cond, res, qr.R, rss, len(B), centre, scale
    )


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
        # R (p, p) stands for the Jacobian (N, p) at the solution: the same singular values, right singular vectors
        # and column norms, and R^T R = J^T J
        R = sol.R
        cond, s, vt = design_condition(R)
        check_condition(
            cond,
            what=f"the {model} model from field magnitudes",
            hint="record full turns about all three sensor axes",
            weak=weak_directions(vt, s, names, threshold=1e4) if np.isfinite(cond) else [],
        )
        instance = get_model(model).from_matrix_offset(sol.C, sol.b)
        npar = R.shape[1]
        dof = max(sol.n - npar, 1)
        s2 = sol.rss / dof
        cov = params_covariance(sol.q, s2 * np.linalg.pinv(R.T @ R), np.full(npar - 5, sol.scale))
        out_names = [*get_model(model).param_names(), "h"]
        uncertainty = make_uncertainty(
            out_names, covariance=cov, noise_std=float(np.sqrt(s2) * sol.scale),
            basis="s^2 (J^T J)^-1 at the solution, s^2 = RSS / (N - p), propagated to the model's parameters",
            gauge="Z gain 1 (the corrected field is in the unit of the Z axis)",
        )
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
