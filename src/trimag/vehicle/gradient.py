"""A background that changes across the room (issue 31, item 4): paper C's vector model with the background's
gradient, fitted from the sensor's positions (motion capture gives them with the attitudes; docs/vehicle.md).

    H_m,i = K C_i^T (H_0 + G (p_i - p_0)) + c

``p_i`` the sensor's position (m, in the attitude source's frame, N, E, D axes as the attitudes'), ``p_0`` the mean
position of the fitted samples (``H_0`` is the background there), ``G`` the background's gradient (data unit per
metre). Indoors, away from currents and the iron itself, the background is a potential field: ``curl H = 0`` makes
``G`` symmetric and ``div H = 0`` traceless, so it has 5 terms (Blakely 1996, "Potential theory in gravity and
magnetic applications", ch. 10; the gradient tensor of magnetic gradiometry):

    G = [[g_xx, g_xy, g_xz], [g_xy, g_yy, g_yz], [g_xz, g_yz, -g_xx - g_yy]]

It is fitted jointly with ``K``, ``c`` and (when the calibration fitted it) the background's direction by
Gauss-Newton (:func:`trimag._core.solve.gauss_newton_rule`; normal equations accumulated block by block,
:func:`trimag._core.chunks.row_blocks`), from the calibration without the gradient and ``G = 0``. ``K`` and the
background share one scale: ``|H_0|`` is held at the calibration's. Uncertainty: ``sigma^2 (J^T J)^-1`` with
``sigma^2`` the residuals' variance per axis, times their integrated autocorrelation time
(:func:`trimag.quality.honesty.correlation_time`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from .._core.chunks import row_blocks
from .._core.solve import gauss_newton_rule
from ..calibration import Calibration, make_uncertainty
from ..errors import IdentifiabilityError, TrimagInputError
from ..quality.diagnostics import CONDITION_ERROR, gram_condition
from ..quality.honesty import correlation_time

__all__ = ["GRADIENT_TERMS", "background_at", "fit_background_gradient", "gradient_tensor"]

#: The five independent terms of a symmetric, traceless gradient.
GRADIENT_TERMS = ("g_xx", "g_xy", "g_xz", "g_yy", "g_yz")
#: ``G = sum_k g_k _BASIS[k]``.
_BASIS = np.zeros((5, 3, 3))
_BASIS[0][0, 0], _BASIS[0][2, 2] = 1.0, -1.0
_BASIS[1][0, 1] = _BASIS[1][1, 0] = 1.0
_BASIS[2][0, 2] = _BASIS[2][2, 0] = 1.0
_BASIS[3][1, 1], _BASIS[3][2, 2] = 1.0, -1.0
_BASIS[4][1, 2] = _BASIS[4][2, 1] = 1.0


def gradient_tensor(terms: ArrayLike) -> NDArray[np.float64]:
    """The symmetric, traceless gradient (3, 3) of its five terms ``(g_xx, g_xy, g_xz, g_yy, g_yz)``."""
    return np.asarray(np.einsum("k,kij->ij", np.asarray(terms, dtype=np.float64), _BASIS), dtype=np.float64)


def background_at(cal: Calibration, positions: ArrayLike) -> NDArray[np.float64]:
    """The background (N, E, D) a calibration with a fitted gradient predicts at ``positions`` (N, 3), m: ``H_0 + G
    (p - p_0)`` (``diagnostics["background_gradient"]``)."""
    grad = cal.diagnostics.get("background_gradient")
    if grad is None:
        raise TrimagInputError("the calibration has no background gradient (fit it with `position_columns`)")
    p = np.asarray(positions, dtype=np.float64)
    G = np.asarray(grad["tensor"], dtype=np.float64)
    H0 = np.asarray(cal.diagnostics["background_ned"], dtype=np.float64)
    return np.asarray(H0 + (p - np.asarray(grad["reference_position_m"])) @ G.T, dtype=np.float64)


def _tangent(h: NDArray[np.float64]) -> NDArray[np.float64]:
    a = np.eye(3)[int(np.argmin(np.abs(h)))]
    e1 = np.cross(h, a) / np.linalg.norm(np.cross(h, a))
    return np.column_stack([e1, np.cross(h / np.linalg.norm(h), e1)])


class _Problem:
    """The samples, attitudes (``C^T``, N x 3 x 3), centred positions and the background's parametrisation."""

    def __init__(self, B: NDArray[np.float64], attitude: Rotation, d: NDArray[np.float64], H0: NDArray[np.float64],
                 fit_direction: bool) -> None:
        self.B, self.Ct, self.d = B, attitude.inv().as_matrix(), d
        self.H0, self.magnitude, self.fit_direction = H0, float(np.linalg.norm(H0)), fit_direction
        self.E = _tangent(H0 / self.magnitude)
        self.p = 12 + 5 + 2 * fit_direction

    def background(self, q: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``H_0`` and its derivative (3, 2) in the direction's two unknowns."""
        if not self.fit_direction:
            return self.H0, np.zeros((3, 2))
        v = self.H0 / self.magnitude + self.E @ q
        nv = float(np.linalg.norm(v))
        u = v / nv
        return self.magnitude * u, self.magnitude * (self.E - np.outer(u, u @ self.E)) / nv

    def unpack(self, p: NDArray[np.float64]) -> tuple[Any, ...]:
        K, c, g = p[:9].reshape(3, 3), p[9:12], p[12:17]
        H0, dH = self.background(p[17:19] if self.fit_direction else np.zeros(2))
        return K, c, g, H0, dH

    def residuals(self, p: NDArray[np.float64], rows: slice = slice(None)) -> NDArray[np.float64]:
        K, c, g, H0, _ = self.unpack(p)
        Hn = H0 + self.d[rows] @ gradient_tensor(g).T  # background at each sample (navigation frame)
        Hb = np.einsum("nij,nj->ni", self.Ct[rows], Hn)
        return np.asarray(self.B[rows] - Hb @ K.T - c, dtype=np.float64)

    def normal_equations(self, p: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
        """``J^T J``, ``J^T r`` and ``r^T r``, over blocks of samples."""
        K, c, g, H0, dH = self.unpack(p)
        G = gradient_tensor(g)
        JtJ, Jtr, ss = np.zeros((self.p, self.p)), np.zeros(self.p), 0.0
        for rows in row_blocks(len(self.B), 3.0 * self.p + 30):
            Ct, d = self.Ct[rows], self.d[rows]
            Hb = np.einsum("nij,nj->ni", Ct, H0 + d @ G.T)
            r = self.B[rows] - Hb @ K.T - c
            J = np.zeros((len(r), 3, self.p))
            for a in range(3):
                J[:, a, 3 * a:3 * a + 3] = -Hb
            J[:, :, 9:12] = -np.eye(3)
            KCt = np.einsum("ab,nbj->naj", K, Ct)
            J[:, :, 12:17] = -np.einsum("naj,kjl,nl->nak", KCt, _BASIS, d)
            if self.fit_direction:
                J[:, :, 17:19] = -KCt @ dH
            JtJ += np.einsum("nap,naq->pq", J, J)
            Jtr += np.einsum("nap,na->p", J, r)
            ss += float(np.sum(r * r))
        return JtJ, Jtr, ss


def _check(cal: Calibration, B: NDArray[np.float64], attitude: Any, positions: NDArray[np.float64]) -> None:
    if cal.model != "interference12":
        raise TrimagInputError(f"a background gradient is fitted with the model interference12; got {cal.model!r}")
    if cal.regressors is not None:
        raise TrimagInputError("fit the background gradient without regressor terms (`regressors`)")
    if cal.diagnostics.get("background_per_sample"):
        raise TrimagInputError("a per-sample background is used as given: a gradient is fitted to one background "
                               "vector (drop `background_columns`)")
    if B.ndim != 2 or B.shape[1] != 3 or positions.shape != B.shape:
        raise TrimagInputError(f"positions must be (N, 3) like the samples; got {positions.shape} for {B.shape}")
    if not np.isfinite(positions).all():
        raise TrimagInputError("the positions contain NaN or inf: drop those rows first")
    if not isinstance(attitude, Rotation) or attitude.single or len(attitude) != len(B):
        raise TrimagInputError("the background gradient needs the attitude of every sample (a Rotation)")


def fit_background_gradient(
    cal: Calibration, B: ArrayLike, attitude: Rotation, positions: ArrayLike, *, max_iter: int = 30,
    position_columns: str | None = None,
) -> Calibration:
    """Refit an ``interference12`` calibration with the background's gradient across the room (module docstring).

    Parameters
    ----------
    cal : Calibration
        The fit of the same samples without the gradient (its ``K``, ``c`` and background are the start; a fitted
        background's direction is refitted, a given one held).
    B : array_like, shape (N, 3)
        Raw samples.
    attitude : Rotation
        The N attitudes (body -> the navigation frame of the background).
    positions : array_like, shape (N, 3)
        The sensor's positions, m, in that frame's axes.

    Returns
    -------
    Calibration
        ``matrix = inv(K)``, ``offset = c``; ``diagnostics["background_ned"]`` the background at the mean position,
        ``diagnostics["background_gradient"]`` (``tensor``, ``terms``, ``terms_std``, ``unit``,
        ``reference_position_m``, ``position_span_m``, ``position_range_m`` (the fitted positions' lowest and
        highest X, Y, Z), the vector RMS with and without it); the terms' sigmas also
        in ``uncertainty``.

    Raises
    ------
    IdentifiabilityError
        Positions that do not move (or move along a line only: fewer terms are seen than fitted).
    """
    X = np.asarray(B, dtype=np.float64)
    P = np.asarray(positions, dtype=np.float64)
    _check(cal, X, attitude, P)
    p0 = P.mean(axis=0)
    span = np.ptp(P, axis=0)
    H0 = np.asarray(cal.diagnostics["background_ned"], dtype=np.float64)
    problem = _Problem(X, attitude, P - p0, H0, bool(cal.diagnostics.get("background_fitted")))
    K0 = np.linalg.inv(np.asarray(cal.matrix))
    start = np.concatenate([K0.ravel(), np.asarray(cal.offset), np.zeros(5), np.zeros(2 * problem.fit_direction)])

    def direction(state: Any, _: Any) -> NDArray[np.float64] | None:
        JtJ, Jtr, _ss = state
        try:
            return np.asarray(-np.linalg.solve(JtJ, Jtr), dtype=np.float64)
        except np.linalg.LinAlgError:
            return None

    def evaluate(p: NDArray[np.float64]) -> tuple[Any, float]:
        state = problem.normal_equations(p)
        return state, state[2]

    run = gauss_newton_rule(evaluate, lambda p, s: None, direction, start, max_steps=max_iter, halvings=5)
    JtJ, _, ss = run.state
    cond, _, _ = gram_condition(JtJ)
    if not np.isfinite(cond) or cond > CONDITION_ERROR or float(np.min(span)) <= 0:
        raise IdentifiabilityError(
            f"the positions (span {np.round(span, 3).tolist()} m) cannot identify the background's gradient "
            f"(condition number {cond:.3g}): move the sensor across the room in all three directions, or drop "
            "`position_columns`")
    return _result(cal, problem, run, JtJ, ss, p0, np.stack([P.min(axis=0), P.max(axis=0)]), position_columns)


def _result(cal: Calibration, problem: _Problem, run: Any, JtJ: NDArray[np.float64], ss: float,
            p0: NDArray[np.float64], box: NDArray[np.float64], position_columns: str | None) -> Calibration:
    from ..models.interference12 import Interference12

    K, c, g, H0, _ = problem.unpack(run.p)
    r = problem.residuals(run.p)
    n = len(r)
    tau = max(max(correlation_time(r[:, a]) for a in range(3)), 1.0)
    sigma2 = ss / max(3 * n - problem.p, 1)
    cov = np.asarray(sigma2 * tau * np.linalg.inv(JtJ), dtype=np.float64)
    names = ([f"k{a + 1}{b + 1}" for a in range(3) for b in range(3)] + ["c1", "c2", "c3"] + list(GRADIENT_TERMS)
             + (["background_direction_1", "background_direction_2"] if problem.fit_direction else []))
    unit = cal.units
    terms_std = np.sqrt(np.clip(np.diag(cov)[12:17], 0.0, None))
    rms_with = float(np.sqrt(np.mean(np.sum(r**2, axis=1))))
    gradient = {
        "tensor": gradient_tensor(g).tolist(), "terms": dict(zip(GRADIENT_TERMS, g.tolist(), strict=True)),
        "terms_std": dict(zip(GRADIENT_TERMS, terms_std.tolist(), strict=True)), "unit": f"{unit}/m",
        "reference_position_m": p0.tolist(), "position_span_m": (box[1] - box[0]).tolist(),
        "position_range_m": box.tolist(), "position_columns": position_columns,
        "vector_rms_without": cal.stats.get("vector_rms_after"), "vector_rms_with": rms_with,
        "correlation_time": tau, "background_direction_fitted": problem.fit_direction,
        "model": "H_m = K C^T (H_0 + G (p - p_0)) + c; G symmetric and traceless (curl-free, divergence-free)",
    }
    diagnostics = {k: v for k, v in cal.diagnostics.items() if k not in ("warnings", "drift")}
    diagnostics.update(background_ned=H0.tolist(), background_gradient=gradient)
    stats = dict(cal.stats)
    stats.update(vector_rms_after=rms_with, vector_rms_after_axis=np.sqrt(np.mean(r**2, axis=0)).tolist(),
                 iterations=int(cal.stats.get("iterations", 0)) + run.nfev,
                 converged=bool(cal.stats.get("converged", True)) and bool(run.converged))
    uncertainty = make_uncertainty(
        names, covariance=cov, noise_std=float(np.sqrt(sigma2)),
        basis="sigma^2 (J^T J)^-1 at the joint estimate with the background gradient, times the residuals' "
              "autocorrelation time",
        gauge="K, c; |H_0| held at the calibration's" + ("; background direction: two tangent unknowns"
                                                         if problem.fit_direction else ""),
        inflation={"total": tau, "correlated_residuals": tau},
    )
    out = Calibration.from_matrix_offset(
        np.linalg.inv(K), c, units=unit, model=cal.model, method=cal.method,
        params=Interference12.from_K_c(K, c).as_dict(), reference=cal.reference, stats=stats,
        uncertainty=uncertainty, diagnostics=diagnostics,
    )
    from dataclasses import replace

    return replace(out, created=cal.created or out.created)
