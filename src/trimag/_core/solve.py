"""Nonlinear least squares from a close start: Gauss-Newton first, Levenberg-Marquardt when it fails (not public API).

The refinements of ``ml``, ``pairwise`` and ``geometric`` start from a closed-form solution that is exact on noise-free
data, so the problem is nearly linear there and undamped Gauss-Newton converges quadratically in a few steps.
Each step solves the p x p normal equations ``(J^T J) delta = J^T r`` (one BLAS product over the N x p Jacobian),
where MINPACK's Levenberg-Marquardt factors the N x p Jacobian by QR at every iteration and, at the tight
tolerances these fits use, iterates well past the point where the parameters stop changing. When a Gauss-Newton
step raises the cost (far from the minimum), the solver hands over to Levenberg-Marquardt (:func:`levenberg_marquardt`,
MINPACK through ``scipy.optimize.least_squares(method="lm")``) from the start, so the result is never worse than
MINPACK's.

This module is trimag's one Gauss-Newton / Levenberg-Marquardt driver: :func:`gauss_newton_rule` is the only
Gauss-Newton loop (every estimator's steps run through it, whatever their linear algebra) and
:func:`levenberg_marquardt` the only ``least_squares`` call (scipy.optimize is imported there, lazily).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "GaussNewtonResult", "GaussNewtonRun", "contraction", "gauss_newton", "gauss_newton_rule", "gauss_newton_then_lm",
    "levenberg_marquardt",
]

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

    def __setattr__(self, name: str, value: Any) -> None:
        self[name] = value


@dataclass
class GaussNewtonRun:
    """Where :func:`gauss_newton_rule` stopped: the point ``p``, the ``state`` and ``model`` evaluated there (what
    the caller's ``evaluate`` and ``linearise`` returned; with ``final``, those of the point before the last
    step), its ``cost`` (``sum r^2``), the counts, the sizes, fractions and costs of the accepted steps, whether it
    ``converged``, and whether it ``stalled`` (a step that raised the cost, a singular system or a non-finite cost;
    otherwise unconverged runs stopped after ``max_steps``)."""

    p: NDArray[np.float64]
    state: Any
    cost: float
    model: Any
    nfev: int
    njev: int
    steps: int
    step_norms: list[float]
    converged: bool = True
    stalled: bool = False
    fractions: list[float] = field(default_factory=list)
    costs: list[float] = field(default_factory=list)


def _relative_step(p_new: NDArray[np.float64], step_norm: float) -> float:
    return step_norm / (1.0 + float(np.linalg.norm(p_new)))


def _rises(cost_new: float, cost: float) -> bool:
    return cost_new > cost * (1.0 + 1e-12)


@dataclass
class _Trial:
    """The last point tried from ``p`` along ``delta`` (``fraction`` of it), and whether its cost was accepted."""

    p: NDArray[np.float64]
    state: Any
    cost: float
    step_norm: float
    fraction: float
    accepted: bool
    evaluations: int


def _trial(
    evaluate: Callable[[NDArray[np.float64]], tuple[Any, float]], rises: Callable[[float, float], bool],
    p: NDArray[np.float64], cost: float, delta: NDArray[np.float64], halvings: int,
) -> _Trial:
    """``p + delta``, halved up to ``halvings`` times while its cost is not finite or ``rises``."""
    fraction = 1.0
    for k in range(halvings + 1):
        step = delta if fraction == 1.0 else fraction * delta
        p_new = p + step
        state_new, cost_new = evaluate(p_new)
        step_norm = float(np.linalg.norm(step))
        if np.isfinite(cost_new) and not rises(cost_new, cost):
            return _Trial(p_new, state_new, cost_new, step_norm, fraction, True, k + 1)
        fraction *= 0.5
    return _Trial(p_new, state_new, cost_new, step_norm, 2.0 * fraction, False, halvings + 1)


def gauss_newton_rule(
    evaluate: Callable[[NDArray[np.float64]], tuple[Any, float]],
    linearise: Callable[[NDArray[np.float64], Any], Any],
    direction: Callable[[Any, Any], NDArray[np.float64] | None],
    p0: NDArray[np.float64],
    *,
    max_steps: int,
    xtol: float = XTOL,
    converged: Callable[[NDArray[np.float64], float, float, float, float], bool] | None = None,
    rises: Callable[[float, float], bool] = _rises,
    rounding_step: float | None = ROUNDING_STEP,
    halvings: int = 0,
    final: Callable[[NDArray[np.float64], NDArray[np.float64], Any, Any], bool] | None = None,
) -> GaussNewtonRun:
    """The one Gauss-Newton rule of trimag, whatever the linear algebra of a step.

    ``evaluate(p) -> (state, cost)`` is called at every trial point (``state`` None: no usable evaluation);
    ``linearise(p, state) -> model`` only at accepted points (the Jacobian, or the state itself when ``evaluate``
    already factored the system); ``direction(state, model) -> delta`` gives the step ``p <- p + delta`` (None when
    the system is singular).

    * Acceptance: a trial whose cost is not finite or ``rises(cost_new, cost)`` (default: above
      ``cost (1 + 1e-12)``) is rejected. With ``halvings`` > 0 the step is halved and tried again, up to
      ``halvings`` times (paper B's step control). A rejected (last) trial that is converged, or whose relative
      step is at most ``rounding_step`` (the cost rose by rounding only), keeps the point before it as
      converged (``rounding_step`` None: never); any other rejected step stalls the run (far from the minimum).
    * Convergence: ``converged(p_new, |step|, cost, cost_new, fraction)`` after an accepted step (``fraction``:
      1, 1/2, 1/4, ... of the Gauss-Newton step); default the relative step ``|step| / (1 + |p_new|) <= xtol``.
    * ``final(p_new, delta, state, model)``: a test before the trial is evaluated; True ends the run at
      ``p_new`` unevaluated (``state``, ``cost`` and ``model`` of the point before; ``ml``'s polish, whose
      evaluations each pass over every sample).

    Always returns a :class:`GaussNewtonRun`: ``converged`` False after ``max_steps`` steps, or ``stalled`` (the
    caller then runs Levenberg-Marquardt, :func:`levenberg_marquardt`). Used by :func:`gauss_newton` (normal
    equations from ``r`` and ``J``), ``geometric`` (a :class:`~trimag._core.qr.BlockedQR` of ``[J | -r]``),
    ``gauss-newton`` (the same with step halving), ``twostep`` (9 x 9 sufficient statistics) and ``ml``'s polish.
    """
    test = converged or (lambda p_new, step_norm, *_: _relative_step(p_new, step_norm) <= xtol)
    p = np.asarray(p0, dtype=np.float64).copy()
    state, cost = evaluate(p)
    model = linearise(p, state) if state is not None else None
    nfev = njev = 1
    step_norms: list[float] = []
    fractions: list[float] = []
    costs: list[float] = [cost]

    def stop(steps: int, ok: bool, stalled: bool = False, at: NDArray[np.float64] | None = None) -> GaussNewtonRun:
        return GaussNewtonRun(p if at is None else at, state, cost, model, nfev, njev, steps, step_norms, ok,
                              stalled, fractions, costs)

    for step_no in range(1, max_steps + 1):
        delta = direction(state, model) if state is not None and np.isfinite(cost) else None
        if delta is None:
            return stop(step_no, False, True)
        if final is not None and final(p + delta, delta, state, model):
            return stop(step_no, True, at=p + delta)
        t = _trial(evaluate, rises, p, cost, delta, halvings)
        nfev += t.evaluations
        if not t.accepted:  # the minimum to rounding (keep the better point), or far from it (stalled)
            keep = rounding_step is not None and (
                test(t.p, t.step_norm, cost, t.cost, t.fraction) or _relative_step(t.p, t.step_norm) <= rounding_step
            )
            return stop(step_no, keep, not keep)
        done = test(t.p, t.step_norm, cost, t.cost, t.fraction)
        p, state, cost = t.p, t.state, t.cost
        step_norms.append(t.step_norm)
        fractions.append(t.fraction)
        costs.append(cost)
        model = linearise(p, state)
        njev += 1
        if done:
            return stop(step_no, True)
    return stop(max_steps, False)


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
    if not run.converged:
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
) -> GaussNewtonResult:
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
    GaussNewtonResult
        ``x``, ``fun`` (residuals at ``x``), ``jac`` (at ``x``), ``nfev``, ``njev``, ``success``, ``status``,
        ``message``, ``step_norms`` (Gauss-Newton only: sizes of the accepted steps) and ``method``
        (``"gauss-newton"`` or ``"levenberg-marquardt"``), as ``least_squares``
        returns them.
    """
    gn = gauss_newton(fun, jac, p0, max_steps=max_steps, xtol=xtol)
    if gn is not None:
        return gn
    res = levenberg_marquardt(fun, p0, jac=jac, **(lm_options or {}))
    res.message = f"Gauss-Newton did not converge; Levenberg-Marquardt: {res.message}"
    return res


def levenberg_marquardt(
    fun: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    p0: NDArray[np.float64],
    *,
    jac: Callable[[NDArray[np.float64]], NDArray[np.float64]] | str = "2-point",
    method: str = "lm",
    **options: Any,
) -> GaussNewtonResult:
    """The one entry to ``scipy.optimize.least_squares`` in trimag: Levenberg-Marquardt (MINPACK) by default.

    scipy.optimize is imported here, on first use (~0.3 s), so that trimag imports fast and fits that converge by
    Gauss-Newton never load it.

    Parameters
    ----------
    fun : callable
        Residuals ``r(p)``, shape (N,).
    p0 : ndarray, shape (P,)
        Start.
    jac : callable or str
        Jacobian ``dr/dp`` (N, P), or a finite-difference scheme (``"2-point"``).
    method : {"lm", "trf"}
        ``"lm"`` (Levenberg-Marquardt, the default), or ``"trf"`` where a robust ``loss`` is given or
        MINPACK's ``N >= P`` cannot be promised.
    **options
        Other keyword arguments of ``least_squares`` (``xtol``, ``ftol``, ``gtol``, ``max_nfev``, ``loss``);
        scipy's defaults where not given.

    Returns
    -------
    GaussNewtonResult
        ``least_squares``' fields (``x``, ``fun``, ``jac``, ``cost``, ``nfev``, ``njev``, ``success``,
        ``status``, ``message``, ...) and ``method`` (``"levenberg-marquardt"`` or ``"trust-region"``), in the
        result type of :func:`gauss_newton`.
    """
    from scipy.optimize import least_squares

    res = least_squares(fun, np.asarray(p0, dtype=np.float64), jac=jac, method=method, **options)
    out = GaussNewtonResult(res)
    out["method"] = "levenberg-marquardt" if method == "lm" else "trust-region"
    return out


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
