"""Nonlinear least squares from a close start: Gauss-Newton first, Levenberg-Marquardt when it fails (not public API).

The refinements of ``ml``, ``pairwise`` and ``geometric`` start from a closed-form solution that is exact on noise-free
data, so the problem is nearly linear there and undamped Gauss-Newton converges quadratically in a few steps.
Each step solves the p x p normal equations ``(J^T J) delta = J^T r`` (one BLAS product over the N x p Jacobian),
where MINPACK's Levenberg-Marquardt factors the N x p Jacobian by QR at every iteration and, at the tight
tolerances these fits use, iterates well past the point where the parameters stop changing. When a Gauss-Newton
step raises the cost (far from the minimum), the solver hands over to ``scipy.optimize.least_squares(method="lm")``
from the start, so the result is never worse than MINPACK's.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:  # scipy.optimize is imported only when Levenberg-Marquardt runs (it costs ~0.3 s to import)
    from scipy.optimize import OptimizeResult

__all__ = ["GaussNewtonResult", "contraction", "gauss_newton", "gauss_newton_then_lm"]

#: Relative step (``|delta| <= XTOL (1 + |p|)``) at which Gauss-Newton has converged: about 100 x rounding.
XTOL = 1e-13
#: A relative step below this after which the cost rose (by rounding only) also counts as converged.
ROUNDING_STEP = 1e-8


class GaussNewtonResult(dict[str, Any]):
    """A converged :func:`gauss_newton` run: a dict whose keys are also attributes, as
    ``scipy.optimize.OptimizeResult`` (``x``, ``fun``, ``jac``, ``nfev``, ``njev``, ``success``, ``status``,
    ``method``, ``message``, ``step_norms``), without importing scipy.optimize."""

    def __getattr__(self, name: str) -> Any:
        try:
            return self[name]
        except KeyError:
            raise AttributeError(name) from None


@dataclass
class GaussNewtonRun:
    """Where :func:`gauss_newton_rule` stopped: the point ``p``, the ``state`` and ``model`` evaluated there (what
    the caller's ``evaluate`` and ``linearise`` returned), its ``cost`` (``sum r^2``), the counts and the sizes of the
    accepted steps."""

    p: NDArray[np.float64]
    state: Any
    cost: float
    model: Any
    nfev: int
    njev: int
    steps: int
    step_norms: list[float]


def gauss_newton_rule(
    evaluate: Callable[[NDArray[np.float64]], tuple[Any, float]],
    linearise: Callable[[NDArray[np.float64], Any], Any],
    direction: Callable[[Any, Any], NDArray[np.float64] | None],
    p0: NDArray[np.float64],
    *,
    max_steps: int,
    xtol: float = XTOL,
) -> GaussNewtonRun | None:
    """The one undamped Gauss-Newton rule of trimag, whatever the linear algebra of a step.

    ``evaluate(p) -> (state, sum r^2)`` is called at every trial point (``state`` None: no usable evaluation);
    ``linearise(p, state) -> model`` only at accepted points (the Jacobian, or the state itself when ``evaluate``
    already factored the system); ``direction(state, model) -> delta`` gives the step ``p <- p + delta`` (None when
    the system is singular). Converged when the relative step ``|delta| / (1 + |p|)`` is at most ``xtol``; a step
    that raised the cost by rounding only (relative step below :data:`ROUNDING_STEP`) keeps the point before it.
    Returns None as soon as a step raises ``sum r^2`` (far from the minimum) or after ``max_steps`` steps without
    convergence: the caller then runs Levenberg-Marquardt. Used by :func:`gauss_newton` (normal equations from
    ``r`` and ``J``) and by ``geometric`` (a :class:`~trimag._core.qr.BlockedQR` of ``[J | -r]``).
    """
    p = np.asarray(p0, dtype=np.float64).copy()
    state, cost = evaluate(p)
    model = linearise(p, state) if state is not None else None
    nfev = njev = 1
    step_norms: list[float] = []
    for step_no in range(1, max_steps + 1):
        if state is None or not np.isfinite(cost):
            return None
        delta = direction(state, model)
        if delta is None:
            return None
        p_new = p + delta
        state_new, cost_new = evaluate(p_new)
        nfev += 1
        step_norm = float(np.linalg.norm(delta))
        rel_step = step_norm / (1.0 + float(np.linalg.norm(p_new)))
        if not np.isfinite(cost_new) or cost_new > cost * (1.0 + 1e-12):
            if rel_step <= max(xtol, ROUNDING_STEP):  # the minimum, to rounding: keep the better point
                return GaussNewtonRun(p, state, cost, model, nfev, njev, step_no, step_norms)
            return None
        p, state, cost = p_new, state_new, cost_new
        step_norms.append(step_norm)
        model = linearise(p, state)
        njev += 1
        if rel_step <= xtol:
            return GaussNewtonRun(p, state, cost, model, nfev, njev, step_no, step_norms)
    return None


def gauss_newton(
    fun: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    jac: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    p0: NDArray[np.float64],
    *,
    max_steps: int = 50,
    xtol: float = XTOL,
) -> GaussNewtonResult | None:
    """Undamped Gauss-Newton from ``p0`` by :func:`gauss_newton_rule`, each step from the Jacobi-scaled normal
    equations, or None as soon as a step raises ``sum fun(p)^2`` (far from the minimum) or ``max_steps`` pass
    without convergence; the caller then runs Levenberg-Marquardt.

    ``fun`` is evaluated at every trial point and ``jac`` only at accepted ones (a caller whose ``fun`` and ``jac``
    share one evaluation can cache it). Returns a :class:`GaussNewtonResult` with the fields of
    :func:`gauss_newton_then_lm`'s.
    """

    def evaluate(p: NDArray[np.float64]) -> tuple[NDArray[np.float64], float]:
        r = fun(p)
        return r, float(r @ r)

    def direction(r: NDArray[np.float64], J: NDArray[np.float64]) -> NDArray[np.float64] | None:
        A = J.T @ J
        g = J.T @ r
        d = np.sqrt(np.diag(A))
        if not np.all(np.isfinite(d)) or np.any(d == 0):
            return None
        try:  # Jacobi-scaled normal equations (columns of very different size stay well conditioned)
            return -(np.linalg.solve(A / np.outer(d, d), g / d) / d)
        except np.linalg.LinAlgError:
            return None

    run = gauss_newton_rule(evaluate, lambda p, r: jac(p), direction, p0, max_steps=max_steps, xtol=xtol)
    if run is None:
        return None
    return _result(run.p, run.state, run.model, run.nfev, run.njev, run.steps, xtol, run.step_norms)


def gauss_newton_then_lm(
    fun: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    jac: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    p0: NDArray[np.float64],
    *,
    max_steps: int = 50,
    xtol: float = XTOL,
    lm_options: dict[str, Any] | None = None,
) -> GaussNewtonResult | OptimizeResult:
    """Minimise ``sum fun(p)^2`` from ``p0`` by :func:`gauss_newton`; fall back to Levenberg-Marquardt.

    Parameters
    ----------
    fun : callable
        Residuals ``r(p)``, shape (N,).
    jac : callable
        Jacobian ``dr/dp``, shape (N, P).
    p0 : ndarray, shape (P,)
        Start, close to the minimum (a closed-form fit).
    max_steps : int
        Gauss-Newton steps before handing over to Levenberg-Marquardt.
    xtol : float
        Gauss-Newton has converged when the relative step is at most this.
    lm_options : dict, optional
        Keyword arguments of the fallback ``least_squares(fun, p0, jac=jac, method="lm", ...)`` call.

    Returns
    -------
    scipy.optimize.OptimizeResult
        ``x``, ``fun`` (residuals at ``x``), ``jac`` (at ``x``), ``nfev``, ``njev``, ``success``, ``status``,
        ``message``, ``step_norms`` (Gauss-Newton only: sizes of the accepted steps) and ``method``
        (``"gauss-newton"`` or ``"levenberg-marquardt"``), as ``least_squares``
        returns them.
    """
    gn = gauss_newton(fun, jac, p0, max_steps=max_steps, xtol=xtol)
    if gn is not None:
        return gn
    from scipy.optimize import least_squares

    res = least_squares(fun, np.asarray(p0, dtype=np.float64), jac=jac, method="lm", **(lm_options or {}))
    res.method = "levenberg-marquardt"
    res.message = f"Gauss-Newton did not converge; Levenberg-Marquardt: {res.message}"
    return res


def _result(
    p: NDArray[np.float64], r: NDArray[np.float64], J: NDArray[np.float64], nfev: int, njev: int, steps: int,
    xtol: float, step_norms: list[float],
) -> GaussNewtonResult:
    return GaussNewtonResult(
        x=p, fun=r, jac=J, nfev=nfev, njev=njev, success=True, status=2, method="gauss-newton",
        message=f"Gauss-Newton converged in {steps} steps (relative step <= {xtol:g})",
        step_norms=step_norms,
    )


def contraction(step_norms: list[float]) -> float | None:
    """The factor by which Gauss-Newton shrinks the error per step, from the sizes of its accepted steps.

    Away from a zero-residual minimum Gauss-Newton converges linearly: ``|step_k| ~ rho |step_(k-1)|``. The
    first step leaves the (nonlinear) start, so the estimate is the larger ratio of the last two pairs of
    later steps; None with fewer than three steps. Rounding in the last steps only makes it larger
    (conservative).
    """
    if len(step_norms) < 3 or min(step_norms[-3:-1]) <= 0:
        return None
    ratios = [step_norms[k] / step_norms[k - 1] for k in range(max(2, len(step_norms) - 2), len(step_norms))]
    return float(max(ratios))
