"""Regressor terms: an offset that moves with logged channels (motor current, throttle, temperature, ...).

    b(t) = b0 + sum_j k_j (u_j(t) - mean_j)                              (docs/vehicle.md)

Each ``k_j`` is a 3-vector in data unit per regressor unit. The regressors are centred: ``mean_j`` (the mean of
channel ``j`` over the fitted samples) is stored, and ``b0`` is the offset at the mean regressor values.

* ``ellipsoid`` (any method; ``ml`` by default): the model's own fit, without the terms, is the start of a joint
  Gauss-Newton / Levenberg-Marquardt fit (:func:`trimag._core.solve.gauss_newton_then_lm`) of the upper-triangular
  ``W`` (6), ``b0`` (3) and the ``k_j`` (3 m) to the magnitude residual ``|W (x_i - b0 - sum_j k_j u_ij)| - F_i``.
  With an unknown magnitude ``F`` is held at the mean corrected magnitude of the start (it fixes the scale of
  ``W``, which a magnitude cannot see; the ``k_j`` do not depend on it).
* ``interference12`` (``linear-vector``): the terms are extra design columns of the same linear least squares,
  ``H_m = K H_b + c + sum_j k_j u_j``, solved jointly (per sensor axis, design ``[H_b, 1, u]``). With
  ``estimate_background=true`` the background is held at the value the fit without terms found.

Derived regressors: the eddy-current terms of ``interference12`` (:mod:`trimag.vehicle.eddy`) are the measured
vector's time derivative, each component a regressor; ``free`` holds some coefficients at 0 (the diagonal of ``E``),
each axis then solving its own design. A per-sample background (N, 3) of the base fit is taken from ``reference``.

Uncertainty: ``sigma^2 (J^T J)^-1`` at the estimate (the Fisher information of the Gaussian model), ``sigma^2`` from
the residuals, times the residuals' integrated autocorrelation time (:func:`trimag.quality.honesty.correlation_time`,
magnitude residuals). The ranking (``diagnostics["regressors"]["ranking"]``) refits without each term and reports the
residual variance it explains and an F-test of its three coefficients (the F statistic and its denominator degrees of
freedom divided by the same autocorrelation time).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._core.solve import gauss_newton_then_lm
from ..calibration import Calibration, make_uncertainty
from ..errors import IdentifiabilityError, TrimagInputError
from ..quality.crlb import UPPER, UPPER_NAMES
from ..quality.diagnostics import CONDITION_ERROR, condition_words
from ..quality.honesty import correlation_time

__all__ = ["SIGNIFICANCE_ALPHA", "check_regressors", "fit_regressors", "ranking_table"]

#: Significance level of the ranking: a term is ``significant`` when its F-test p-value is below it.
SIGNIFICANCE_ALPHA = 0.01
#: A regressor whose standard deviation is below this fraction of its mean magnitude counts as constant.
_CONSTANT = 1e-9
#: Models whose fits take regressor terms.
MODELS = ("ellipsoid", "interference12")

_AXES = ("x", "y", "z")


def check_regressors(values: Mapping[str, ArrayLike], n: int) -> tuple[tuple[str, ...], NDArray[np.float64]]:
    """The regressors as names (m) and an (n, m) float array, checked: finite, varying and not collinear.

    Parameters
    ----------
    values : mapping str -> array_like, shape (n,)
        One series per regressor, aligned with the samples, in the regressor's own unit.
    n : int
        Number of samples.

    Raises
    ------
    TrimagInputError
        No regressor, a wrong length, a non-finite value, or a constant regressor (it cannot be told from the
        offset).
    IdentifiabilityError
        Regressors that are (nearly) linear combinations of each other.
    """
    names = tuple(str(k) for k in values)
    if not names:
        raise TrimagInputError("`regressors` is empty; give at least one regressor (name -> values)")
    columns = []
    for name in names:
        u = np.asarray(values[name], dtype=np.float64)
        if u.shape != (n,):
            raise TrimagInputError(f"regressor {name!r} must have shape ({n},) (one value per sample); got {u.shape}")
        if not np.isfinite(u).all():
            raise TrimagInputError(f"regressor {name!r} has {int((~np.isfinite(u)).sum())} non-finite value(s)")
        std, mean = float(np.std(u)), float(np.mean(u))
        if not std > _CONSTANT * abs(mean):
            raise TrimagInputError(
                f"regressor {name!r} does not vary (every value is {mean:.6g}): its term cannot be told from the "
                "offset; drop it from the regressors"
            )
        columns.append(u)
    U = np.stack(columns, axis=1)
    if len(names) > 1:
        Z = (U - U.mean(axis=0)) / U.std(axis=0)
        ev, vec = np.linalg.eigh(Z.T @ Z / n)
        if ev[0] < 1e-8:
            involved = [names[k] for k in np.flatnonzero(np.abs(vec[:, 0]) > 0.2)]
            raise IdentifiabilityError(
                f"the regressors {', '.join(involved)} are (nearly) linear combinations of each other: their terms "
                "cannot be told apart; drop one of them"
            )
    return names, U


# ------------------------------------------------------------------ ellipsoid: joint magnitude least squares
class _Magnitude:
    """Residual ``|W (x - b - u K)| - t`` (N,) and its Jacobian (N, 9 + 3 m) in normalised units.

    ``x`` (N, 3) are the samples minus a centre, over a scale; ``u`` (N, m) the centred regressors over their
    standard deviations; ``t`` the target magnitude (scalar or (N,)) over the same scale. Parameters: the upper
    entries of ``W`` (:data:`trimag.quality.crlb.UPPER` order), ``b`` (3), then ``K`` (m, 3) row by row.
    """

    def __init__(self, x: NDArray[np.float64], u: NDArray[np.float64], t: Any) -> None:
        # component-major (3, N) and (m, N) copies: every step below is a pass over contiguous rows
        # (row-wise arithmetic on (N, 3) arrays is 5-10x slower, docs/architecture.md)
        self.xT, self.uT, self.t = np.ascontiguousarray(x.T), np.ascontiguousarray(u.T), t
        self._key: bytes | None = None
        self._value: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None

    def both(self, p: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        key = np.asarray(p, dtype=np.float64).tobytes()
        if key != self._key or self._value is None:
            self._key, self._value = key, self._evaluate(np.asarray(p, dtype=np.float64))
        return self._value

    def _evaluate(self, p: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        W = np.zeros((3, 3))
        W[UPPER] = p[:6]
        m, n_samples = self.uT.shape
        d = self.xT - p[6:9, None] - p[9:].reshape(m, 3).T @ self.uT  # (3, N)
        y = W @ d
        mag = np.sqrt(y[0] ** 2 + y[1] ** 2 + y[2] ** 2)
        n = y / mag
        q = W.T @ n  # W^T n per sample, (3, N)
        Jt = np.empty((9 + 3 * m, n_samples))
        for k, (a, b) in enumerate(zip(*UPPER, strict=True)):
            np.multiply(n[a], d[b], out=Jt[k])
        np.negative(q, out=Jt[6:9])
        for j in range(m):
            np.multiply(-self.uT[j], q, out=Jt[9 + 3 * j : 12 + 3 * j])
        return mag - self.t, Jt.T


def _solve(
    problem: _Magnitude, p0: NDArray[np.float64], max_iter: int
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], int, bool]:
    """``(p, residuals, Jacobian, evaluations, converged)`` of the magnitude fit from ``p0``."""
    res = gauss_newton_then_lm(
        lambda p: problem.both(p)[0], lambda p: problem.both(p)[1], p0, max_steps=max_iter,
        lm_options={"xtol": 1e-12, "ftol": 1e-12, "gtol": 1e-12, "max_nfev": 20 * max_iter},
    )
    p = np.asarray(res.x, dtype=np.float64)
    r, J = problem.both(p)
    return p, r, J, int(res.nfev), bool(res.success)


def _covariance(J: NDArray[np.float64], sigma2: float, names: Sequence[str]) -> NDArray[np.float64]:
    """``sigma^2 (J^T J)^-1``, column-scaled; refuses an unidentifiable design naming its weakest parameters."""
    d = np.sqrt(np.einsum("ij,ij->j", J, J))
    d[d == 0] = 1.0
    A = (J.T @ J) / np.outer(d, d)
    ev, vec = np.linalg.eigh(A)
    cond = float(ev[-1] / ev[0]) if ev[0] > 0 else float("inf")
    if not np.sqrt(cond) < CONDITION_ERROR:
        weak = [names[int(k)] for k in np.flatnonzero(np.abs(vec[:, 0]) > 0.3)]
        raise IdentifiabilityError(
            f"the data cannot identify the regressor terms together with the calibration "
            f"({condition_words(np.sqrt(cond))}; weakest: {', '.join(weak)}); a regressor that follows the "
            "magnetometer's own reading cannot be told from the calibration: record the vehicle turning while the "
            "regressors vary"
        )
    return np.asarray(sigma2 * np.linalg.inv(A) / np.outer(d, d), dtype=np.float64)


def _ellipsoid_names(names: Sequence[str]) -> list[str]:
    return [*UPPER_NAMES, *(f"k_{name}_{a}" for name in names for a in _AXES)]


def _vector_names(names: Sequence[str]) -> list[str]:
    return [*(f"k{i}{j}" for i in range(1, 4) for j in range(1, 4)), "c1", "c2", "c3",
            *(f"k_{name}_{a}" for name in names for a in _AXES)]


def _fit_ellipsoid(
    base: Calibration, B: NDArray[np.float64], U: NDArray[np.float64], target: Any, names: Sequence[str],
    max_iter: int,
) -> dict[str, Any]:
    """Joint fit of ``W`` (upper), ``b0`` and ``K`` (m, 3) from ``base``, and the fits without each term.

    ``U`` (N, m) are the centred regressors, ``target`` the magnitude (scalar or (N,)), data units.
    """
    _, R = np.linalg.qr(np.asarray(base.matrix))
    W0 = np.sign(np.diag(R))[:, None] * R  # upper, positive diagonal, the same magnitudes as base.matrix
    centre = np.asarray(base.offset, dtype=np.float64)
    scale = float(np.sqrt(np.mean(np.sum((B - centre) ** 2, axis=1)))) or 1.0
    u_scale = U.std(axis=0)
    x, u, t = (B - centre) / scale, U / u_scale, np.asarray(target, dtype=np.float64) / scale
    n, m = U.shape
    p, r, J, nfev, converged = _solve(_Magnitude(x, u, t), np.concatenate([W0[UPPER], np.zeros(3 + 3 * m)]),
                                      max_iter)
    k = 9 + 3 * m
    ss = float(r @ r)
    cov_n = _covariance(J, ss / max(n - k, 1), _ellipsoid_names(names))
    D = np.concatenate([np.ones(6), np.full(3, scale), np.repeat(scale / u_scale, 3)])
    ss_without = []
    for j in range(m):  # each term left out in turn, from the joint solution without it
        keep = [c for c in range(m) if c != j]
        p0 = np.concatenate([p[:9], p[9:].reshape(m, 3)[keep].ravel()])
        _, r_j, _, _, _ = _solve(_Magnitude(x, u[:, keep], t), p0, max_iter)
        ss_without.append(float(r_j @ r_j) * scale**2)
    W = np.zeros((3, 3))
    W[UPPER] = p[:6]
    return {
        "matrix": W, "offset": centre + scale * p[6:9], "K": p[9:].reshape(m, 3) * (scale / u_scale)[:, None],
        "cov": cov_n * np.outer(D, D), "residuals": r * scale, "ss": ss * scale**2, "ss_without": ss_without,
        "n_params": k, "iterations": nfev, "converged": converged, "param_names": _ellipsoid_names(names),
    }


def _vector_solve(
    A: NDArray[np.float64], B: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Least squares ``B ~ A X`` (three right-hand sides) with column scaling: ``(X, residuals, (A^T A)^-1)``."""
    d = np.sqrt(np.einsum("ij,ij->j", A, A))
    As = A / d
    X, *_ = np.linalg.lstsq(As, B, rcond=None)
    X = X / d[:, None]
    return X, B - A @ X, np.linalg.inv(As.T @ As) / np.outer(d, d)


def _fit_vector(
    base: Calibration, B: NDArray[np.float64], U: NDArray[np.float64], H_b: NDArray[np.float64],
    names: Sequence[str], free: NDArray[np.bool_] | None = None,
) -> dict[str, Any]:
    """Joint linear fit of ``H_m = K H_b + c + sum_j k_j u_j`` (design ``[H_b, 1, u]`` per sensor axis), and the
    fits without each term.

    ``free`` (m, 3) bool: which coefficients of each regressor are fitted (the others are held at 0; e.g. the
    diagonal of the eddy-current matrix); None: all.
    """
    n, m = U.shape
    F = np.ones((m, 3), dtype=bool) if free is None else np.asarray(free, dtype=bool)
    param_names = _vector_names(names)
    _covariance(np.column_stack([H_b, np.ones(n), U]), 1.0, [*_vector_names(())[:3], "c", *names])  # identifiable?
    X = np.zeros((4 + m, 3))
    resid = np.empty((n, 3))
    cov = np.zeros((12 + 3 * m, 12 + 3 * m))
    ss_without = np.zeros(m)
    n_free = 12 + int(F.sum())
    for a in range(3):  # the three axes are independent least-squares problems (their designs differ by `free`)
        used = np.flatnonzero(F[:, a])
        A = np.column_stack([H_b, np.ones(n), U[:, used]])
        x_a, r_a, G = _vector_solve(A, B[:, a : a + 1])
        X[[0, 1, 2, 3, *(4 + used)], a] = x_a[:, 0]
        resid[:, a] = r_a[:, 0]
        ss_a = float(r_a[:, 0] @ r_a[:, 0])
        idx = np.array([3 * a, 3 * a + 1, 3 * a + 2, 9 + a, *(12 + 3 * int(j) + a for j in used)])
        cov[np.ix_(idx, idx)] = ss_a / max(n - A.shape[1], 1) * G
        for j in range(m):
            if F[j, a]:
                keep = [c for c in range(A.shape[1]) if c != 4 + int(np.flatnonzero(used == j)[0])]
                ss_without[j] += float(np.sum(_vector_solve(A[:, keep], B[:, a : a + 1])[1] ** 2))
            else:
                ss_without[j] += ss_a
    K = X[:3].T
    return {
        "matrix": np.linalg.inv(K), "offset": X[3], "K": X[4:], "K_interference": K, "cov": cov,
        "residuals": resid, "ss": float(np.sum(resid**2)), "ss_without": ss_without.tolist(), "n_params": n_free,
        "iterations": 1, "converged": True, "param_names": param_names, "free": F,
    }


def _f_survival(f: float, dfn: int, dfd: int) -> float:
    """``P(X > f)`` for ``X ~ F(dfn, dfd)``: the regularised incomplete beta function ``I_x(dfd/2, dfn/2)`` at
    ``x = dfd / (dfd + dfn f)`` (``scipy.stats.f.sf`` without importing scipy.stats, ~0.4 s)."""
    from scipy.special import betainc

    return float(betainc(0.5 * dfd, 0.5 * dfn, dfd / (dfd + dfn * max(f, 0.0))))


def _ranking(
    names: Sequence[str], fit: dict[str, Any], n_rows: int, alpha: float, tau: float = 1.0
) -> list[dict[str, Any]]:
    """One entry per regressor, most variance explained first (module docstring).

    ``tau``: the residuals' integrated autocorrelation time; the F statistic and its denominator degrees of
    freedom are divided by it (``tau`` consecutive samples carry about one sample's information).
    """
    ss, k = fit["ss"], fit["n_params"]
    n_resid = fit["residuals"].size
    dof = max(int((n_resid - k) / tau), 1)
    cov, order = fit["cov"], fit["param_names"]
    out = []
    for j, name in enumerate(names):
        idx = [order.index(f"k_{name}_{a}") for a in _AXES]
        coef = np.asarray(fit["K"][j], dtype=np.float64)
        C = cov[np.ix_(idx, idx)]
        std = np.sqrt(np.clip(np.diag(C), 0.0, None))
        on = np.asarray(fit["free"][j], dtype=bool) if "free" in fit else np.ones(3, dtype=bool)
        dfn = int(on.sum())  # the term's fitted coefficients (3, or fewer when some are held at 0)
        explained = max(fit["ss_without"][j] - ss, 0.0)
        f_stat = (explained / dfn) / (ss / max(n_resid - k, 1)) / tau if ss > 0 else float("inf")
        try:
            wald = float(coef[on] @ np.linalg.solve(C[np.ix_(on, on)], coef[on]))
        except np.linalg.LinAlgError:
            wald = float("inf")
        p_value = _f_survival(f_stat, dfn, dof) if np.isfinite(f_stat) else 0.0
        out.append({
            "name": name,
            "coefficient": coef.tolist(),
            "coefficient_std": std.tolist(),
            "max_abs_z": float(np.max(np.abs(coef) / np.where(std > 0, std, np.inf))),
            "rms_without": float(np.sqrt(fit["ss_without"][j] / n_rows)),
            "rms_with_all": float(np.sqrt(ss / n_rows)),
            "variance_explained": explained / n_rows,
            "variance_explained_fraction": explained / fit["ss_without"][j] if fit["ss_without"][j] > 0 else 0.0,
            "f_statistic": f_stat,
            "p_value": p_value,
            "wald_chi2": wald,
            "significant": bool(p_value < alpha),
        })
    out.sort(key=lambda e: -e["variance_explained"])
    for rank, entry in enumerate(out, start=1):
        entry["rank"] = rank
    return out


def fit_regressors(
    base: Calibration,
    B: ArrayLike,
    regressors: Mapping[str, ArrayLike],
    reference: Any = None,
    *,
    attitude: Any = None,
    max_iter: int = 100,
    alpha: float = SIGNIFICANCE_ALPHA,
    free: Mapping[str, Sequence[bool]] | None = None,
    record: Mapping[str, Any] | None = None,
    background: ArrayLike | None = None,
) -> Calibration:
    """Refit ``base`` with regressor terms in its offset, jointly with its other parameters (module docstring).

    Parameters
    ----------
    base : Calibration
        The fit of the same samples without regressor terms (model ``ellipsoid`` or ``interference12``): the
        start, and for ``interference12`` the background field (``diagnostics["background_ned"]``).
    B : array_like, shape (N, 3)
        Raw samples, data unit.
    regressors : mapping str -> array_like, shape (N,)
        The channels, aligned with ``B``, in their own units (A, %, degC, ...).
    reference : float, array_like (N,), ScalarReference or None
        The magnitude reference of ``base``'s fit (``ellipsoid``); None: held at the mean corrected magnitude.
        ``interference12``: not used, except a per-sample background (N, 3) of ``base``'s fit, used as it.
    attitude : scipy.spatial.transform.Rotation, optional
        The N attitudes (``interference12``).
    max_iter : int
        Iteration limit of the joint nonlinear fit.
    alpha : float
        Significance level of the ranking.
    free : mapping str -> 3 bool, optional
        ``interference12`` only: which of a regressor's three coefficients are fitted (the others held at 0), e.g.
        the diagonal of the eddy-current matrix (:mod:`trimag.vehicle.eddy`); regressors not named: all three.
    record : mapping, optional
        Extra entries stored with the terms in the calibration (e.g. ``{"eddy": ...}``,
        :func:`trimag.vehicle.eddy.eddy_spec`).
    background : array_like, shape (3,) or (N, 3), optional
        ``interference12``: the background field (NED) of ``base``'s fit; required when it was per sample
        (``base.diagnostics["background_per_sample"]``: the diagnostics hold only its mean; default there:
        ``reference``). Default: the diagnostics' ``background_ned``.

    Returns
    -------
    Calibration
        With :attr:`~Calibration.regressors` (``names``, ``means``, ``coefficients`` (m, 3)), the coefficients'
        standard deviations in ``uncertainty["param_std"]`` (``k_NAME_x`` ...), and
        ``diagnostics["regressors"]["ranking"]``: per regressor the coefficient, the RMS residual without the term
        and with all terms (``rms_without``, ``rms_with_all``, data unit), the residual variance it explains, the
        F-test p-value of its three coefficients and ``significant`` (p < ``alpha``), most explaining first.

    Raises
    ------
    TrimagInputError
        A model without regressor terms, a missing attitude, or a bad regressor (:func:`check_regressors`).
    IdentifiabilityError
        Regressors that are collinear with each other or with the calibration's parameters.
    """
    if base.model not in MODELS:
        raise TrimagInputError(
            f"regressor terms are fitted for the models {', '.join(MODELS)}; got model {base.model!r}"
        )
    if free is not None and base.model != "interference12":
        raise TrimagInputError("`free` (coefficients held at 0) is for the model interference12")
    if base.regressors is not None:
        raise TrimagInputError("`base` already has regressor terms; give the fit without them")
    X = np.asarray(B, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3:
        raise TrimagInputError(f"`B` must have shape (N, 3); got {X.shape}")
    names, U_raw = check_regressors(regressors, len(X))
    means = U_raw.mean(axis=0)
    U = U_raw - means
    if base.model == "ellipsoid":
        from ..fields.reference import as_scalar_reference

        ref = as_scalar_reference(reference, len(X), units=base.units)
        target: Any = ref.values if ref.values is not None else float(np.mean(np.linalg.norm(base.apply(X), axis=1)))
        fit = _fit_ellipsoid(base, X, U, target, names, max_iter)
        magnitude_target = target
    else:
        from scipy.spatial.transform import Rotation

        from ..fields.attitude import body_field

        if not isinstance(attitude, Rotation) or attitude.single or len(attitude) != len(X):
            raise TrimagInputError("interference12 regressor terms need the attitude of every sample (a Rotation)")
        if background is not None:
            H_n = np.asarray(background, dtype=np.float64)
            if H_n.shape not in ((3,), (len(X), 3)):
                raise TrimagInputError(f"`background` must have shape (3,) or ({len(X)}, 3); got {H_n.shape}")
        elif base.diagnostics.get("background_per_sample"):  # the diagnostics hold only its mean
            H_n = np.asarray(reference, dtype=np.float64) if reference is not None else np.empty(0)
            if H_n.shape != (len(X), 3):
                raise TrimagInputError("the fit used a per-sample background: give it as `reference` (N, 3)")
        else:
            H_n = np.asarray(base.diagnostics["background_ned"], dtype=np.float64)
        mask = None
        if free is not None:
            unknown = [k for k in free if k not in names]
            if unknown:
                raise TrimagInputError(f"`free` names {unknown[0]!r}, which is not a regressor")
            mask = np.array([list(free.get(name, (True, True, True))) for name in names], dtype=bool)
            if mask.shape != (len(names), 3) or not mask.any(axis=1).all():
                raise TrimagInputError("`free` needs three booleans per regressor, at least one of them true")
        fit = _fit_vector(base, X, U, body_field(attitude, H_n), names, mask)
        F_n = np.linalg.norm(H_n, axis=-1)
        magnitude_target = float(F_n) if F_n.ndim == 0 else F_n
    return _assemble(base, X, U, names, means, fit, magnitude_target, alpha, record)


def _assemble(
    base: Calibration, X: NDArray[np.float64], U: NDArray[np.float64], names: tuple[str, ...],
    means: NDArray[np.float64], fit: dict[str, Any], target: Any, alpha: float,
    record: Mapping[str, Any] | None = None,
) -> Calibration:
    """The Calibration of a joint fit: parameters, uncertainty, statistics, ranking."""
    from ..models import get_model

    n = len(X)
    matrix, offset, K = fit["matrix"], fit["offset"], fit["K"]
    corrected = (X - U @ K - offset) @ matrix.T
    mag = np.linalg.norm(corrected, axis=1)
    err = mag - target
    cov = fit["cov"]
    factors: dict[str, float] = {}
    if base.model == "ellipsoid":
        mid = max((n - 4096) // 2, 0)
        tau = correlation_time(fit["residuals"][mid : mid + 4096])
        if tau > 1.0:
            factors["correlated_residuals"] = tau
            cov = cov * tau
            fit = {**fit, "cov": cov}
    order = fit["param_names"]
    uncertainty = make_uncertainty(
        order, covariance=cov,
        basis="sigma^2 (J^T J)^-1 at the joint estimate (Gauss-Newton Fisher information; sigma from the "
              "residuals)" + (", per sensor axis" if base.model == "interference12" else ""),
        gauge=("upper-triangular W, |corrected| = F (F held at the reference, or at the mean corrected "
               "magnitude of the fit without regressor terms)") if base.model == "ellipsoid" else "K, c",
        noise_std=float(np.sqrt(fit["ss"] / max(fit["residuals"].size - fit["n_params"], 1))),
        inflation={"total": float(np.prod(list(factors.values()))) if factors else 1.0, **factors,
                   "note": "covariance x total: correlated residuals (trimag.quality.honesty.correlation_time)"},
    )
    ranking = _ranking(names, fit, n, alpha, factors.get("correlated_residuals", 1.0))
    stats = dict(base.stats)
    stats.update({
        "rms_after": float(np.sqrt(np.mean(err**2))), "max_abs_after": float(np.max(np.abs(err))),
        "p2p_after": float(np.ptp(mag)), "mean_norm_after": float(np.mean(mag)), "std_norm_after": float(np.std(mag)),
        "rms_after_without_regressors": base.stats.get("rms_after"),
        "iterations": int(base.stats.get("iterations", 0)) + int(fit["iterations"]),
        "converged": bool(base.stats.get("converged", True)) and bool(fit["converged"]),
    })
    if base.model == "interference12":
        ss_axis = np.sum(fit["residuals"] ** 2, axis=0)
        stats.update({"vector_rms_after_axis": np.sqrt(ss_axis / n).tolist(),
                      "vector_rms_after": float(np.sqrt(np.sum(ss_axis) / n)),
                      "vector_rms_after_without_regressors": base.stats.get("vector_rms_after")})
        params = get_model("interference12").from_matrix_offset(matrix, offset).as_dict()
    else:
        params = get_model("ellipsoid").from_matrix_offset(matrix, offset).as_dict()
    diagnostics = {k: v for k, v in base.diagnostics.items() if k not in ("warnings", "drift")}
    diagnostics["regressors"] = {
        "ranking": ranking,
        "alpha": alpha,
        "model": "b(t) = b0 + sum_j k_j (u_j(t) - mean_j)",
        "without_regressors": {
            "rms_after": base.stats.get("rms_after"),
            **({"warnings": list(base.diagnostics["warnings"])} if base.diagnostics.get("warnings") else {}),
        },
    }
    terms = {"names": list(names), "means": means.tolist(), "coefficients": np.asarray(K).tolist(),
             "note": "offset(u) = offset + sum_j coefficients[j] * (u_j - means[j]); data unit per regressor unit",
             **dict(record or {})}
    cal = Calibration.from_matrix_offset(
        matrix, offset, units=base.units, model=base.model, method=base.method, params=params,
        reference=base.reference, stats=stats, uncertainty=uncertainty, diagnostics=diagnostics, regressors=terms,
    )
    return replace(cal, created=base.created or cal.created)


def ranking_table(ranking: Sequence[Mapping[str, Any]], units: str, *, alpha: float = SIGNIFICANCE_ALPHA) -> str:
    """A text table of :func:`fit_regressors`' ranking (``diagnostics["regressors"]["ranking"]``)."""
    if not ranking:
        return ""
    rms_all = ranking[0]["rms_with_all"]
    lines = [
        f"regressor terms, offset = b0 + sum_j k_j (u_j - mean_j); RMS with all terms {rms_all:.4g} {units}",
        f"{'rank':>4}  {'regressor':<16}{'k_x':>11}{'k_y':>11}{'k_z':>11}{'max|k|/sd':>11}{'RMS without':>13}"
        f"{'explained':>11}{'p-value':>10}  significant (p < {alpha:g})",
    ]
    for e in ranking:
        k, sd = e["coefficient"], e["coefficient_std"]
        coef = "".join(f"{v:11.4g}" for v in k)
        lines.append(
            f"{e['rank']:>4}  {str(e['name'])[:15]:<16}{coef}{e['max_abs_z']:11.3g}{e['rms_without']:13.4g}"
            f"{100 * e['variance_explained_fraction']:10.1f}%{e['p_value']:10.2g}  "
            f"{'yes' if e['significant'] else 'no'}"
        )
        lines.append(f"{'':22}" + "".join(f"{'±' + format(v, '.2g'):>11}" for v in sd))
    lines.append(f"k in {units} per regressor unit (± 1 sigma); 'explained': share of the residual variance without "
                 "the term that it removes")
    return "\n".join(lines)


