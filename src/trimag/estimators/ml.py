"""``ml``: maximum likelihood on the magnitude residual, Gauss-Newton (Levenberg-Marquardt when it does not
descend) with analytic Jacobian, corrected for its second-order noise bias (``docs/method-ml.md``).

Model (``docs/accuracy.md``): raw samples ``x_i = inv(W) y_i + b + e_i`` with ``|y_i| = F`` and white Gaussian
noise ``e_i ~ N(0, sigma^2 I)``. Parameters: the upper-triangular ``W`` (6, the gauge that removes the rotation a
magnitude cannot see) and the offset ``b`` (3).

1. **Start**: the algebraic fit (``ellipsoid-fit``) on normalised data.
2. **Maximum likelihood** (first order): Gauss-Newton from the start (:func:`gauss_newton_solve`;
   Levenberg-Marquardt, :func:`trimag._core.solve.levenberg_marquardt`, when a step raises the cost), analytic
   Jacobian, on
   the geometric residual ``r_i = (|W (x_i - b)| - F_i) / |W^T n_i|`` (``n_i`` the corrected direction): the
   first-order signed distance of the sample from the ellipsoid, of variance ``sigma^2``. This is the ML
   weighting (it attains the Cramér–Rao bound of :func:`trimag.quality.crlb.crlb` to first order); the weight sits
   inside the residual with its exact derivative, which also stops the iteration from shrinking ``W`` towards a
   huge ellipsoid on partial coverage (as a magnitude residual with frozen weights does on one hemisphere).
3. **Bias correction** (the point of this method): the estimate solves ``sum_i psi(x_i, theta) = 0`` with
   ``psi = r grad_theta r``. Under noise ``E[psi(x + e)] = psi(x) + sigma^2/2 Laplacian_x psi + O(sigma^4)``,
   so the estimate carries the bias ``-H^-1 sum_i sigma^2/2 Laplacian_x psi_i`` (``H = J^T J``), of order
   ``(sigma/F)^2`` relative, independent of N (3-7 standard deviations at ``sigma/F = 5e-2``, ``N = 20000``).
   The Laplacian is evaluated on a tetrahedral stencil at the data and the estimate, ``sigma^2`` is estimated
   from the residuals (``sum r^2 / (N - 9)``), and the bias is subtracted. The remaining bias is ``O(sigma^2 / N)``
   and ``O(sigma^4)``.
4. **Uncertainty**: covariance = inverse Fisher information at the estimate
   (:func:`trimag.quality.crlb.fisher_information`, noise from the data), the predicted RMS error of the corrected
   field and magnitude over the sphere, and the identifiability diagnostics (condition number, variance inflation
   per parameter, sphere coverage).
With an unknown magnitude the fit is made on the unit sphere and the result scaled to ``det(W) = 1``; the
covariance is then stated in that gauge with ``F`` as a tenth parameter.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._core.chunks import chunk_rows, row_blocks
from .._core.rowwise import scratch, sum_squares
from .._core.solve import GaussNewtonResult, contraction, gauss_newton, gauss_newton_rule, levenberg_marquardt
from ..calibration import Calibration
from ..errors import IdentifiabilityError, TrimagInputError
from ..quality.crlb import (
    UPPER,
    UPPER_NAMES,
)
from ..quality.diagnostics import (
    CONDITION_WARN,
    DIAGNOSTIC_SAMPLES,
    check_condition,
    check_not_degenerate,
    coverage_advice,
    design_condition,
    diagnostic_subsample,
    gram_condition,
    weak_directions,
)
from ._common import (
    Normalisation,
    algebraic_ellipsoid,
    check_ellipsoid_options,
    gauge_scale,
    normalisation_stats,
    normalise,
    scalar_reference,
)
from ._finish import BALANCE_CHOICES, ellipsoid_result
from .base import Estimator

__all__ = ["MaximumLikelihood"]

_NAMES = UPPER_NAMES


def _unpack(p: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    W = np.zeros((3, 3))
    W[UPPER] = p[:6]
    return W, p[6:9]


#: The magnitude each sample should have: one number (the same for every sample) or an array (N,).
Target = float | NDArray[np.float64]


def _take(target: Target, idx: Any) -> Target:
    """``target`` for the samples ``idx`` (indices or a slice)."""
    return target if np.ndim(target) == 0 else target[idx]  # type: ignore[index]


def geometric_residual(
    u: NDArray[np.float64], p: NDArray[np.float64], target: Target
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Weighted residual ``r_i = (|W (u_i - b)| - t_i) / |W^T n_i|`` (N,) and its exact Jacobian (N, 9).

    ``r_i`` is, to first order, the signed distance of sample ``i`` from the ellipsoid (variance ``sigma^2``),
    invariant to the scale of ``W``; the Jacobian includes the derivative of the weight. Computed in blocks of
    a chunk (:func:`~trimag._core.chunks.chunk_rows`) samples (:func:`_residual_block`).
    """
    W, b = _unpack(p)
    n = len(u)
    r = np.empty(n)
    Jt = np.empty((9, n))
    for rows in row_blocks(n, 24):
        _residual_block(u[rows], W, b, _take(target, rows), r[rows], Jt[:, rows])
    return r, Jt.T


def _residual_block(
    u: NDArray[np.float64], W: NDArray[np.float64], b: NDArray[np.float64], target: Target,
    r_out: NDArray[np.float64], Jt_out: NDArray[np.float64], norm: Normalisation | None = None,
) -> None:
    """:func:`geometric_residual` of the samples ``u`` (m, 3): writes ``r`` into ``r_out`` (m,) and ``J^T`` into
    ``Jt_out`` (9, m). With ``norm``, ``u`` are raw samples, normalised here (``(x - centre) / scale``)."""
    # Component-major layout: every quantity is a (3, m) or (m,) array of contiguous rows, so each step below
    # is one pass over m numbers. All temporaries live in one reused (26, m) buffer (trimag._core.rowwise.scratch):
    # fresh ones would be mapped and page-faulted anew at every call.
    with scratch(26, len(u)) as ws:
        e, y, n, q, Wq, P = ws[0:3], ws[3:6], ws[6:9], ws[9:12], ws[12:15], ws[15:18]
        mag, tmp, g, qn2, qn, s, gamma, beta = ws[18:26]
        if norm is None:
            np.subtract(u.T, b[:, None], out=e)  # (``(u - b).T`` broadcasts over rows of 3: slow)
        else:  # (x - centre) / scale - b
            np.multiply(u.T, 1.0 / norm.scale, out=e)
            e -= (norm.centre / norm.scale + b)[:, None]
        np.matmul(W, e, out=y)
        sum_squares(y, out=mag, tmp=tmp)
        np.sqrt(mag, out=mag)
        np.divide(y, mag, out=n)
        np.subtract(mag, target, out=g)
        np.matmul(W.T, n, out=q)  # W^T n
        sum_squares(q, out=qn2, tmp=tmp)
        np.sqrt(qn2, out=qn)
        np.divide(1.0, qn, out=s)
        # Closed-form Jacobian (no (N, 3, 9) tensor): for an upper entry (i, j) dy/dtheta = e_j unit_i, for b_m
        # dy/dtheta = -W[:, m]. Then dg = n . dy, dq = W^T (dy - n dg) / mag (+ n_i at row j for W_ij itself),
        # ds = -(q . dq) / |q|^3; the products q . W^T dy reduce to (W q)_i e_j and -(W^T W q)_m. Collecting
        # terms, J = alpha dg - beta (q . W^T dy) - gamma (q_j n_i for W_ij) with the per-sample factors below:
        #   J[W_ij] = e_j (alpha n_i - beta (W q)_i) - gamma n_i q_j,    J[b_m] = -alpha q_m + beta (W^T W q)_m.
        np.matmul(W, q, out=Wq)
        WtWq = np.matmul(W.T, Wq, out=y)  # y is not needed any more
        np.multiply(qn2, qn, out=gamma)
        np.divide(g, gamma, out=gamma)
        np.divide(gamma, mag, out=beta)
        alpha = np.add(s, np.multiply(beta, qn2, out=tmp), out=qn)  # qn is not needed any more
        np.multiply(alpha, n, out=P)
        P -= np.multiply(beta, Wq, out=Wq)  # P = alpha n - beta W q
        R = np.multiply(gamma, n, out=n)  # R = gamma n
        for k, (i, j) in enumerate(zip(*UPPER, strict=True)):
            np.multiply(e[j], P[i], out=Jt_out[k])
            Jt_out[k] -= np.multiply(R[i], q[j], out=tmp)
        np.multiply(beta, WtWq, out=Jt_out[6:])
        Jt_out[6:] -= np.multiply(alpha, q, out=q)
        np.multiply(s, g, out=r_out)


def weighted_ml(
    u: NDArray[np.float64], p0: NDArray[np.float64], target: Target, *, loss: str = "linear",
    max_iter: int = 100, xtol: float = 1e-12,
) -> tuple[NDArray[np.float64], Any, int]:
    """Magnitude-residual ML (geometric residual, exact Jacobian) from ``p0`` (upper W, b) on normalised ``u``.

    Returns ``(p, least_squares result, function evaluations)``.
    """

    fun, jac = _cached_residual(u, target)
    if loss == "linear":
        gn = gauss_newton(fun, jac, p0, max_steps=max_iter, xtol=xtol)
        if gn is not None:
            return np.asarray(gn.x, dtype=np.float64), gn, int(gn.nfev)
    res = levenberg_marquardt(
        fun, p0, jac=jac, method="lm" if loss == "linear" else "trf", loss=loss, xtol=1e-12, ftol=1e-12,
        gtol=1e-12, max_nfev=max_iter * 10,
    )
    return np.asarray(res.x, dtype=np.float64), res, int(res.nfev)


def gauss_newton_solve(
    u: NDArray[np.float64], p0: NDArray[np.float64], target: Target, *, max_steps: int = 100,
    xtol: float = 1e-12,
) -> GaussNewtonResult | None:
    """Undamped Gauss-Newton on the geometric residual from ``p0``, or None as soon as a step does not lower
    the sum of squares (the caller then runs Levenberg-Marquardt from ``p0``): :func:`trimag._core.solve.gauss_newton`.

    From the algebraic start the problem is nearly linear, so Gauss-Newton converges quadratically (4-6 steps),
    each a 9 x 9 solve, where MINPACK's Levenberg-Marquardt factors the (N, 9) Jacobian at every step. It stops
    on the same criterion as the ``least_squares`` call it replaces (relative step <= ``xtol``), so both
    reach the same minimum to rounding.
    """
    fun, jac = _cached_residual(u, target)
    return gauss_newton(fun, jac, p0, max_steps=max_steps, xtol=xtol)


def _cached_residual(
    u: NDArray[np.float64], target: Target
) -> tuple[Callable[[NDArray[np.float64]], NDArray[np.float64]], Callable[[NDArray[np.float64]], NDArray[np.float64]]]:
    """``fun`` and ``jac`` of the geometric residual that share one evaluation per point."""
    cache: dict[bytes, tuple[NDArray[np.float64], NDArray[np.float64]]] = {}

    def both(q: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        key = np.asarray(q, dtype=np.float64).tobytes()
        if key not in cache:
            cache.clear()
            cache[key] = geometric_residual(u, q, target)
        return cache[key]

    return (lambda q: both(q)[0]), (lambda q: both(q)[1])


def _positive_diagonal(W: NDArray[np.float64]) -> NDArray[np.float64]:
    """``W`` with its rows' signs flipped so that the diagonal is positive: ``|W e|`` does not change (a row sign
    is part of the rotation the magnitude cannot see), and ``det W > 0``, which the scale gauge needs."""
    d = np.diag(W)
    if not np.all(np.isfinite(W)) or np.any(d == 0):
        raise IdentifiabilityError(
            "the fit did not converge to an ellipsoid (a zero or undefined axis); the data cannot identify the "
            "ellipsoid model: record the sensor turning about all three axes"
        )
    return np.sign(d)[:, None] * W


#: A condition number the Gram matrix ``J^T J`` gives to about 1e-6 relative (squaring the design loses
#: ``cond^2`` x rounding); above it ``ml`` takes the condition of ``J`` itself (QR), as the checks need it exact.
GRAM_CONDITION_EXACT = 1e5
#: Above this many samples, ``ml`` solves on an evenly spread subsample first, then polishes on all samples
#: with Gauss-Newton steps on the normal equations (9 x 9), so time and memory stay linear in N.
LARGE_N = 10_000


def _normal_equations(
    u: NDArray[np.float64], p: NDArray[np.float64], target: Target, *, hessian: bool = True,
    norm: Normalisation | None = None,
) -> tuple[NDArray[np.float64] | None, NDArray[np.float64], float]:
    """``J^T J`` (9, 9; None when ``hessian`` is False), ``J^T r`` (9,) and ``sum r^2`` of the geometric residual,
    accumulated over chunks of samples (:func:`~trimag._core.chunks.chunk_rows`) (cache-sized temporaries; memory
    independent of
    N). With ``norm``, ``u`` are the raw samples, normalised block by block (no normalised copy of the log)."""
    W, b = _unpack(p)
    JtJ = np.zeros((9, 9)) if hessian else None
    Jtr = np.zeros(9)
    ss = 0.0
    with scratch(10, min(len(u), chunk_rows(24))) as work:  # reused buffers (trimag._core.rowwise.scratch)
        for rows in row_blocks(len(u), 24):
            m = rows.stop - rows.start
            r, Jt = work[0, :m], work[1:, :m]
            _residual_block(u[rows], W, b, _take(target, rows), r, Jt, norm)
            if JtJ is not None:
                JtJ += Jt @ Jt.T
            Jtr += Jt @ r
            ss += float(r @ r)
    return JtJ, Jtr, ss


_SINGULAR = (
    "the data cannot identify the ellipsoid model (its normal equations are singular); record the sensor turning "
    "about all three axes"
)
#: The polish stops when the error left after its last step, predicted from the contraction of the last two
#: steps, is below this many standard deviations of the estimate (per parameter). An error of 0.01 standard
#: deviations adds 1e-4 to the estimate's variance, and is of the size of the sampling error of the bias
#: correction on its subsample (0.003 standard deviations at N = 2e5, more above).
POLISH_TOLERANCE = 1e-2


def gauss_newton_polish(
    u: NDArray[np.float64], p: NDArray[np.float64], target: Target, *, max_steps: int = 8,
    tolerance: float = POLISH_TOLERANCE, contraction: float | None = None, norm: Normalisation | None = None,
) -> tuple[NDArray[np.float64], float, NDArray[np.float64], int]:
    """Gauss-Newton steps on the geometric residual over all samples from a nearby start ``p``.

    Gauss-Newton converges linearly here (the residuals are not zero): each step shrinks the error by a factor
    ``rho``, small on well-covered data (~0.02 at sigma/F = 5e-2 on a full sphere) and larger on poorly
    conditioned data (~0.1 on a hemisphere at sigma/F = 5e-2). With the step size ``s_k`` in standard deviations
    of the estimate (from ``J^T J`` and the residuals), the error left after step ``k`` is about
    ``(s_k / s_{k-1}) s_k``; the polish stops when that is below ``tolerance``, when the relative step is below
    1e-10 (noise-free data), or after ``max_steps`` evaluations. ``contraction``, the factor measured while
    Gauss-Newton converged on the subsample (:func:`trimag._core.solve.contraction`; the same data geometry, so the same
    ``rho`` up to sampling noise), predicts the error left after the first step as ``contraction * s_1``: when
    that is below ``tolerance`` the polish stops after one evaluation. One step on well-covered logs up to a few
    1e5 samples, two above; 3-5 on poorly covered data.

    With ``norm``, ``u`` are the raw samples, normalised block by block (:func:`_normal_equations`). The steps
    are :func:`trimag._core.solve.gauss_newton_rule`'s, every one taken (no cost check between them), the stop
    tested before the next evaluation (``final``).

    Returns ``(p, sum of squared residuals, JtJ, evaluations)``, the last two from the last evaluation (at the
    point before the final step).
    """
    dof = max(len(u) - 9, 1)
    sizes: list[float] = []  # the steps' sizes in standard deviations of the estimate

    def evaluate(q: NDArray[np.float64]) -> tuple[tuple[NDArray[np.float64], NDArray[np.float64], float], float]:
        JtJ, Jtr, ss = _normal_equations(u, q, target, norm=norm)
        assert JtJ is not None
        return (JtJ, Jtr, ss), ss

    def direction(state: tuple[NDArray[np.float64], NDArray[np.float64], float], _: Any) -> NDArray[np.float64]:
        JtJ, Jtr, ss = state
        try:
            step = np.linalg.solve(JtJ, Jtr)
            std = np.sqrt(np.clip(np.diag(np.linalg.inv(JtJ)), 0.0, None) * (ss / dof))
        except np.linalg.LinAlgError as exc:
            raise IdentifiabilityError(_SINGULAR) from exc
        sizes.append(float(np.max(np.abs(step) / std)) if np.all(std > 0) else np.inf)
        return np.asarray(-step, dtype=np.float64)

    def final(p_new: NDArray[np.float64], delta: NDArray[np.float64], state: Any, model: Any) -> bool:
        rho = contraction if len(sizes) == 1 else sizes[-1] / sizes[-2]
        return bool(
            np.linalg.norm(delta) <= 1e-10 * (1.0 + np.linalg.norm(p_new))
            or (rho is not None and rho * sizes[-1] <= tolerance)
            or len(sizes) >= max_steps
        )

    # every step is taken (the start is close and the steps contract: no cost check between them)
    run = gauss_newton_rule(
        evaluate, lambda q, state: None, direction, p, max_steps=max_steps, converged=lambda *_: False,
        rises=lambda *_: False, rounding_step=None, final=final,
    )
    JtJ, _, ss = run.state
    return run.p, ss, JtJ, run.nfev


#: Unit vectors to the vertices of a regular tetrahedron: ``sum v = 0`` and ``sum v v^T = 4/3 I``, so
#: ``sum_v f(x + h v) - 4 f(x) = 2 h^2 / 3 Laplacian f(x) + O(h^3)``.
_TETRAHEDRON = np.array([[1.0, 1.0, 1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]]) / np.sqrt(3.0)
#: Step of the Laplacian stencil (normalised units, data of radius ~1): the truncation error is O(h) relative
#: (measured: the correction moves by <= 1.3e-5 standard deviations from central differences at h = 1e-3).
_LAPLACIAN_STEP = 1e-4


def bias_correction(
    u: NDArray[np.float64], p: NDArray[np.float64], target: Target, sigma2: float,
    *, normal_equations: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
) -> NDArray[np.float64]:
    """Second-order noise bias of the ML estimate ``p`` (to subtract), normalised units.

    ``bias = -H^-1 sum_i sigma^2/2 Laplacian_x psi_i`` (module docstring, step 3), ``H = J^T J``. The Laplacian
    is taken on a regular tetrahedron of radius ``h`` (:data:`_TETRAHEDRON`, :data:`_LAPLACIAN_STEP`): five
    evaluations of ``sum_i psi_i = J^T r`` where central differences need seven. The residual depends on a
    sample only through ``x - b``, so shifting every sample by ``+h v`` is shifting the offset by ``-h v``: no
    shifted copies of the samples are made, and each sum is accumulated block by block (:func:`_normal_equations`).

    ``normal_equations``: ``(J^T J, J^T r)`` of these samples at ``p`` when the caller has them (the last
    Gauss-Newton evaluation); the first of the five evaluations is then skipped.
    """
    h = _LAPLACIAN_STEP
    if normal_equations is None:
        H, base, _ = _normal_equations(u, p, target)  # psi at the data, and H = J^T J: one evaluation
    else:
        H, base = normal_equations
    assert H is not None
    lap = -4.0 * base
    for v in _TETRAHEDRON:
        shifted = p.copy()
        shifted[6:] -= h * v  # samples + h v  ==  offset - h v
        lap += _normal_equations(u, shifted, target, hessian=False)[1]
    lap *= 1.5 / h**2
    try:
        return np.asarray(-np.linalg.solve(H, 0.5 * sigma2 * lap), dtype=np.float64)
    except np.linalg.LinAlgError as exc:
        raise IdentifiabilityError(_SINGULAR) from exc


def _scaled_target(values: NDArray[np.float64] | None) -> tuple[float, Target]:
    """The reference's RMS ``f_scale`` and the magnitudes the fit targets (reference / ``f_scale``; 1 when
    unknown)."""
    if values is None:
        return 1.0, 1.0
    f_scale = float(np.sqrt(np.mean(values**2)))
    return f_scale, values / f_scale


def _solve_samples(B: NDArray[np.float64], large: bool) -> tuple[NDArray[np.float64], Normalisation, Any]:
    """The normalised samples the ML solve runs on, the normalisation and their indices in ``B``: all of them,
    or on large logs an evenly spread subsample of :data:`LARGE_N` (the polish on all samples then normalises
    block by block, so no normalised copy of the log is made: memory independent of N)."""
    if not large:
        u, norm = normalise(B)
        return u, norm, slice(None)
    norm = normalisation_stats(B)
    idx = np.linspace(0, len(B) - 1, LARGE_N).astype(np.int64)
    return norm.forward(B[idx]), norm, idx


def _jacobian_condition(
    res: Any,
) -> tuple[float, NDArray[np.float64], NDArray[np.float64], tuple[NDArray[np.float64], NDArray[np.float64]] | None]:
    """Condition number, singular values and right singular vectors of the solve's Jacobian, and its ``(J^T J,
    J^T r)`` when Gauss-Newton converged (the bias correction's first sums at the estimate)."""
    J = res.jac
    JtJ = J.T @ J
    cond, s, vt = gram_condition(JtJ)  # (N, 9) -> (9, 9): no QR of the Jacobian ...
    if not cond <= GRAM_CONDITION_EXACT:  # ... unless squaring it would cost digits the checks need
        cond, s, vt = design_condition(J)
    at_p = (JtJ, J.T @ res.fun) if getattr(res, "method", "") == "gauss-newton" else None
    return cond, s, vt, at_p


def _sample_bias(
    B: NDArray[np.float64], u_sub: NDArray[np.float64], p: NDArray[np.float64], target: Target, sigma2_u: float,
    norm: Normalisation, large: bool, at_p: tuple[NDArray[np.float64], NDArray[np.float64]] | None,
) -> NDArray[np.float64]:
    """:func:`bias_correction` of the estimate ``p``: the bias is a ratio of two sums over samples, so an evenly
    spread subsample estimates it as well (measured at N = 2e5: 20 000 samples change it by 0.3 % of itself,
    0.003 standard deviations)."""
    n_samples = len(B)
    bias_idx: Any = diagnostic_subsample(n_samples) if n_samples > DIAGNOSTIC_SAMPLES else slice(None)
    u_bias = norm.forward(B[bias_idx]) if large else u_sub[bias_idx]
    return bias_correction(
        u_bias, p, _take(target, bias_idx), sigma2_u,
        normal_equations=at_p if u_bias.shape == u_sub.shape else None,
    )


class MaximumLikelihood(Estimator):
    """Magnitude-residual maximum likelihood with second-order bias correction (trimag's default for
    ``ellipsoid``).

    Parameters
    ----------
    model : str
        ``"ellipsoid"``.
    form : {"upper", "symmetric"}
        Gauge of the returned soft-iron matrix.
    loss : str
        ``scipy.optimize.least_squares`` loss: ``"linear"`` (default) or a robust one (``"soft_l1"``,
        ``"huber"``, ``"cauchy"``) for logs with disturbed samples (no bias correction then).
    max_iter : int
        Iteration limit of each Gauss-Newton / Levenberg-Marquardt run.
    bias_correction : bool
        Subtract the second-order noise bias (default True). False gives the plain weighted ML.
    noise_std : float, optional
        Noise standard deviation per axis in the data's unit; estimated from the residuals when None.
    balance : {"auto", "never", "always"}
        Offset from the sample mean when the field directions are balanced (``sum u_i = 0``, e.g. complete
        turns sampled evenly): ``"auto"`` (default) when :func:`balance_test` accepts it, ``"never"``, or
        ``"always"``. Recorded in ``diagnostics["balanced_offset"]``.
    """

    name = "ml"
    models = ("ellipsoid",)

    def __init__(
        self, model: str = "ellipsoid", form: str = "upper", loss: str = "linear", max_iter: int = 100,
        bias_correction: bool = True, noise_std: float | None = None, balance: str = "auto",
    ) -> None:
        self.model = model
        self.form = form
        self.loss = loss
        self.max_iter = max_iter
        self.bias_correction = bias_correction
        self.noise_std = noise_std
        self.balance = balance

    def _fit(
        self, B: NDArray[np.float64], reference: Any, *, model: str, units: str, attitude: Any
    ) -> Calibration:
        check_ellipsoid_options(self.form, self.noise_std)
        if self.balance not in BALANCE_CHOICES:
            raise TrimagInputError(f"`balance` must be one of {', '.join(BALANCE_CHOICES)}; got {self.balance!r}")
        principal = check_not_degenerate(B)
        ref = scalar_reference(reference, len(B), units)
        f_scale, target = _scaled_target(ref.values)
        n_samples = len(B)
        large = n_samples > LARGE_N and self.loss == "linear"
        u_sub, norm, sub_idx = _solve_samples(B, large)
        # the start only has to lie in the basin of the subsample's minimum: the algebraic fit of that subsample
        W0, c0, _ = algebraic_ellipsoid(u_sub)
        p0 = np.concatenate([W0[UPPER], c0])
        # (on the subsample a relative step of 1e-9 is close enough: the polish on all samples takes it from there)
        p, res, nfev = weighted_ml(u_sub, p0, _take(target, sub_idx), loss=self.loss, max_iter=self.max_iter,
                                   xtol=1e-9 if large else 1e-12)
        if large:
            p, sum_sq, JtJ, n_polish = gauss_newton_polish(
                B, p, target, contraction=contraction(getattr(res, "step_norms", None) or []), norm=norm
            )
            nfev += n_polish
            cond, s, vt = gram_condition(JtJ)  # the condition of J from J^T J (never fails when singular)
            at_p = None
        else:
            sum_sq = float(np.sum(res.fun**2))
            cond, s, vt, at_p = _jacobian_condition(res)
        # an ill-conditioned fit is described by what the samples saw (the same words as the other refusals of a
        # single-axis turn: a log and its parts are refused alike, issue 32); computed only when it is said
        hint = "record the sensor turning about all three axes"
        if not np.isfinite(cond) or cond > CONDITION_WARN:
            hint = coverage_advice(B, float(np.mean(ref.values)) if ref.values is not None else None,
                                   what="the ellipsoid model")
        check_condition(
            cond, what="the ellipsoid model", hint=hint,
            weak=weak_directions(vt, s, _NAMES, threshold=1e4) if np.isfinite(cond) else [],
        )
        sigma2_u = sum_sq / max(n_samples - 9, 1)
        if self.noise_std is not None:
            sigma2_u = (float(self.noise_std) / norm.scale) ** 2
        correction = np.zeros(9)
        if self.bias_correction and self.loss == "linear" and sigma2_u > 0:
            correction = _sample_bias(B, u_sub, p, target, sigma2_u, norm, large, at_p)
            p = p - correction
        W_u, b_u = _unpack(p)
        W = _positive_diagonal(W_u) * f_scale / norm.scale
        offset = norm.centre + norm.scale * b_u
        F_hat = None
        if ref.values is None:
            W, F_hat = gauge_scale(W, None)
        return ellipsoid_result(
            B, W, offset, ref=ref, F_hat=F_hat, sigma=float(np.sqrt(sigma2_u) * norm.scale), model=model,
            method=self.name, units=units, form=self.form, iterations=nfev, converged=bool(res.success),
            balance=self.balance if self.loss == "linear" else "never",
            diagnostics={
                "condition_number": cond,
                "optimizer": str(res.message),
                "bias_correction": {
                    "applied": bool(np.any(correction != 0)),
                    "relative_size": float(np.linalg.norm(correction) / max(float(np.linalg.norm(p)), 1e-300)),
                },
            },
            principal=principal,
        )
