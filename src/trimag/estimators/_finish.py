"""The finishing step shared by estimators (not public API): uncertainty, identifiability diagnostics and the
:class:`~trimag.calibration.Calibration` of a fitted model (``ellipsoid_result`` for the ellipsoid estimators,
``finish_iterative`` for paper D's iterative fits)."""

from __future__ import annotations

import math
import warnings
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._core.rowwise import column_means
from .._core.sphere import fibonacci_sphere
from ..calibration import UNCERTAINTY_FIELDS, Calibration, Uncertainty, make_uncertainty
from ..errors import IdentifiabilityError, IdentifiabilityWarning, TrimagInputError
from ..fields.reference import ScalarReference
from ..models.ellipsoid import Ellipsoid, to_symmetric, to_upper
from ..models.zhang_cheng import ZhangCheng, upper_from_quadric
from ..quality.crlb import (
    UPPER,
    UPPER_NAMES,
    _constrained_inverse,
    _upper_param,
    ellipsoid_fisher,
    ellipsoid_geometry,
    predicted_errors,
)
from ..quality.diagnostics import (
    CONDITION_ERROR,
    CONDITION_WARN,
    check_not_planar_within_noise,
    data_coverage,
    describe_directions,
    diagnostic_subsample,
)
from ._common import unpack
from ._quadric import diagnostics_entries
from .base import Estimator, build_calibration

__all__ = [
    "BALANCE_CHOICES",
    "COVERAGE_WARN",
    "INFLATION_WARN",
    "UNCERTAINTY_FIELDS",
    "VIF_REPORT",
    "VIF_WARN",
    "Uncertainty",
    "balance_test",
    "chi2_survival",
    "ellipsoid_result",
    "finish_iterative",
    "identifiability",
    "make_uncertainty",
]

_NAMES = UPPER_NAMES

#: Covered fraction of the sphere (cells of :func:`trimag.quality.diagnostics.sphere_coverage`) below which a fit warns.
COVERAGE_WARN = 0.25


#: Variance inflation factor (``C_kk J_kk``: how much the correlation with the other parameters inflates a
#: parameter's variance) above which a parameter is listed as poorly determined (its standard deviation is more
#: than 3x what it would be if the others were known) ...
VIF_REPORT = 10.0


#: ... and above which the fit warns (standard deviation inflated 10x).
VIF_WARN = 100.0


#: Warn when the worst-determined combination of parameters has more than this many times the standard
#: deviation a full-sphere recording of the same length would give (:func:`identifiability`). Measured: 1.0-1.3
#: for full spheres and three great circles, 10-11 for one hemisphere, 1.6-6.5 on five real logs, 120-2400
#: for two great circles at sigma/F <= 1e-2.
INFLATION_WARN = 30.0


def identifiability(
    fisher: NDArray[np.float64], names: tuple[str, ...], covariance: NDArray[np.float64], coverage: dict[str, Any],
    *, vif_report: float = VIF_REPORT, vif_warn: float = VIF_WARN, coverage_warn: float = COVERAGE_WARN,
    reference_fisher: NDArray[np.float64] | None = None, inflation_warn: float = INFLATION_WARN,
) -> dict[str, Any]:
    """Condition number, per-parameter variance inflation and the verdict, for ``Calibration.diagnostics``.

    Parameters whose variance inflation factor exceeds ``vif_report`` are listed in ``poorly_determined``.
    Warns (:class:`IdentifiabilityWarning`) when the covered fraction of the sphere is below ``coverage_warn``,
    a parameter's variance inflation factor exceeds ``vif_warn`` or the column-normalised condition number of
    the Fisher information exceeds ``CONDITION_WARN``; raises :class:`IdentifiabilityError` above
    ``CONDITION_ERROR``.

    With ``reference_fisher`` (the information a full sphere of the same length carries at the same estimate),
    the generalised eigenvalues of the W, b blocks are the fractions of that information each combination of
    parameters keeps. The smallest, as a ratio of standard deviations ``1 / sqrt(fraction)``, is
    ``std_inflation_vs_full_sphere``; the fit warns above ``inflation_warn`` and names the parameters of that
    combination. This catches two great circles (the pencil of quadrics through both leaves one combination to
    the noise), which the column-normalised condition number and the variance inflation factors do not see:
    the weak combination is nearly a single parameter whose information is small but uncorrelated.
    """
    # the condition number is taken on W and b alone (with an unknown magnitude the scale of W and F
    # trade off exactly, which the det(W) gauge removes; it is not a property of the data)
    fw = fisher[:9, :9]
    d = np.sqrt(np.clip(np.diag(fw), 1e-300, None))
    ev = np.linalg.eigvalsh(fw / np.outer(d, d))
    cond = float(np.sqrt(ev[-1] / ev[0])) if ev[0] > 0 else float("inf")
    k = min(len(names), len(covariance))
    vif = np.diag(covariance)[:k] * np.diag(fisher)[:k]
    poor = [n for n, v in zip(names[:k], vif, strict=True) if v > vif_report]
    bad = [n for n, v in zip(names[:k], vif, strict=True) if v > vif_warn]
    out = {
        "condition_number_fisher": cond,
        "variance_inflation": dict(zip(names[:k], vif.tolist(), strict=True)),
        "poorly_determined": poor,
        "coverage_fraction": coverage.get("fraction"),
        "thresholds": {"vif_report": vif_report, "vif_warn": vif_warn, "coverage": coverage_warn,
                       "condition_warn": CONDITION_WARN, "condition_error": CONDITION_ERROR},
    }
    reasons = []
    if not np.isfinite(cond) or cond > CONDITION_ERROR:
        raise IdentifiabilityError(
            f"the data cannot identify the ellipsoid model (Fisher condition number {cond:.3g}; poorly determined: "
            f"{', '.join(poor) or 'several'}); record the sensor turning about all three axes"
        )
    if cond > CONDITION_WARN:
        reasons.append(f"condition number {cond:.3g}")
    if coverage.get("fraction") is not None and coverage["fraction"] < coverage_warn:
        reasons.append(describe_directions(coverage) if coverage.get("cone_axis") is not None
                       else f"the data cover {100 * coverage['fraction']:.0f}% of the sphere of directions")
    if bad:
        reasons.append(f"poorly determined: {', '.join(bad)} (variance inflated more than {vif_warn:g}x by the "
                       "correlation with the other parameters)")
    if reference_fisher is not None:
        inflation, weakest = _inflation_vs_full_sphere(fw, reference_fisher[:9, :9], names[:9])
        out["std_inflation_vs_full_sphere"] = inflation
        out["weakest_combination"] = weakest
        if inflation > inflation_warn:
            reasons.append(f"the worst-determined parameter combination ({', '.join(weakest)}) has {inflation:.3g}x "
                           "the standard deviation a full sphere of the same length would give")
    out["warning"] = "; ".join(reasons) or None
    if reasons:
        warnings.warn(
            "the calibration is poorly identified: " + "; ".join(reasons)
            + "; record the sensor in more attitudes (turn it about all three axes)",
            IdentifiabilityWarning, stacklevel=4,
        )
    return out


def _inflation_vs_full_sphere(
    fisher: NDArray[np.float64], reference: NDArray[np.float64], names: tuple[str, ...]
) -> tuple[float, list[str]]:
    """``1 / sqrt(smallest generalised eigenvalue)`` of ``(fisher, reference)`` (both (p, p)) and the parameters
    that dominate its eigenvector (in units of their full-sphere standard deviations); ``(nan, [])`` when the
    reference is not positive definite."""
    try:
        L = np.linalg.cholesky(reference)
    except np.linalg.LinAlgError:
        return float("nan"), []
    Linv = np.linalg.inv(L)
    ev, vecs = np.linalg.eigh(Linv @ fisher @ Linv.T)
    inflation = float(1.0 / np.sqrt(ev[0])) if ev[0] > 0 else float("inf")
    v = np.abs((Linv.T @ vecs[:, 0]) * np.sqrt(np.diag(reference)))  # the combination, per reference std
    return inflation, [names[k] for k in np.nonzero(v > 0.3 * v.max())[0]]


#: Values of the ``balance`` option of ``ml``.
BALANCE_CHOICES = ("auto", "never", "always")


#: Significance level of :func:`balance_test`: the data count as balanced unless the test rejects at this level.
BALANCE_ALPHA = 0.01


def chi2_survival(x: float, dof: int) -> float:
    """``P(X > x)`` for ``X`` chi-square with ``dof`` in (1, 2, 3) degrees of freedom, in closed form
    (``scipy.stats.chi2.sf`` without importing scipy.stats, which takes ~0.3 s): ``erfc(sqrt(x/2))``,
    ``exp(-x/2)`` and ``erfc(sqrt(x/2)) + sqrt(2x/pi) exp(-x/2)``."""
    if dof not in (1, 2, 3):
        raise ValueError(f"dof must be 1, 2 or 3; got {dof}")
    if math.isnan(x):
        return math.nan
    if x <= 0:
        return 1.0
    if math.isinf(x):
        return 0.0
    if dof == 2:
        return math.exp(-0.5 * x)
    tail = math.erfc(math.sqrt(0.5 * x))
    return tail if dof == 1 else tail + math.sqrt(2.0 * x / math.pi) * math.exp(-0.5 * x)


def balance_test(
    B: NDArray[np.float64], offset: NDArray[np.float64], cov_offset: NDArray[np.float64], sigma: float,
    *, alpha: float = BALANCE_ALPHA,
) -> dict[str, Any]:
    """Are the true field directions balanced (``sum_i u_i = 0``), so that the sample mean is the offset?

    With balanced directions (e.g. complete turns sampled evenly in time) ``mean(x) = b + mean(e)``: the sample
    mean estimates the offset with covariance ``sigma^2 I / N``, below the bound for unknown directions (about
    ``3 sigma^2 / N`` per axis on a full sphere). The test compares ``d = mean(x) - b_ml`` with its covariance
    under balance. To first order ``mean(e)`` is uncorrelated with the maximum-likelihood error (its
    Jacobian in ``b`` is minus the unit normals), so ``Cov(d) = Cov(b_ml) - sigma^2 I / N`` (a Hausman test), and
    ``chi2 = d^T Cov(d)^-1 d`` has 3 degrees of freedom under balance.

    Parameters
    ----------
    B : ndarray, shape (N, 3)
        Raw samples.
    offset : ndarray, shape (3,)
        Maximum-likelihood offset.
    cov_offset : ndarray, shape (3, 3)
        Its covariance (data units squared).
    sigma : float
        Noise standard deviation per axis (data units).
    alpha : float
        Significance level; balanced when the p-value exceeds it.

    Returns
    -------
    dict
        ``balanced`` (bool), ``chi2``, ``dof``, ``p_value``, ``alpha``, ``sample_mean`` (list of 3).
    """
    n = len(B)
    mean = column_means(B)
    d = mean - offset
    cov_d = np.asarray(cov_offset, dtype=np.float64) - (sigma**2 / n) * np.eye(3)
    evals, evecs = np.linalg.eigh(0.5 * (cov_d + cov_d.T))
    keep = evals > 1e-6 * max(float(evals.max()), sigma**2 / n)
    dof = int(keep.sum())
    z = evecs.T @ d
    stat = float(np.sum(z[keep] ** 2 / evals[keep])) if dof else float("inf")
    p_value = chi2_survival(stat, dof) if dof else 0.0
    return {
        "balanced": bool(dof == 3 and p_value > alpha),
        "chi2": stat,
        "dof": dof,
        "p_value": p_value,
        "alpha": alpha,
        "sample_mean": mean.tolist(),
    }


def ellipsoid_result(
    B: NDArray[np.float64], W: NDArray[np.float64], offset: NDArray[np.float64], *, ref: ScalarReference,
    F_hat: float | None, sigma: float | None, model: str, method: str, units: str, form: str,
    iterations: int = 0, converged: bool = True, diagnostics: dict[str, Any] | None = None,
    uncertainty_note: str = "Fisher information at the estimate (attained by an efficient estimator)",
    balance: str = "never", principal: NDArray[np.float64] | None = None,
) -> Calibration:
    """Finish an ellipsoid fit: uncertainty, identifiability diagnostics and the :class:`Calibration`.

    Parameters
    ----------
    B : ndarray, shape (N, 3)
        Raw samples.
    W, offset : ndarray
        Upper-triangular correction (3, 3) and offset (3,), data units, already in the final scale
        (reference magnitude or ``det W = 1``).
    ref : ScalarReference
    F_hat : float or None
        Fitted magnitude when unknown.
    sigma : float or None
        Noise standard deviation per axis (data units); estimated from the residuals when None.
    balance : {"never", "auto", "always"}
        Whether to replace the offset by the sample mean when the field directions are balanced
        (:func:`balance_test`): never, when the test accepts it, or always.
    principal : ndarray, shape (3,), optional
        Principal standard deviations of ``B``, as :func:`~trimag.quality.diagnostics.check_not_degenerate` returned
        them (computed here when None).
    """
    if form not in ("upper", "symmetric"):
        raise TrimagInputError(f"`form` must be 'upper' or 'symmetric'; got {form!r}")
    if balance not in BALANCE_CHOICES:
        raise TrimagInputError(f"`balance` must be one of {', '.join(BALANCE_CHOICES)}; got {balance!r}")
    known = ref.values is not None
    W = to_upper(W)
    # sums over samples (noise level, information, coverage) use an evenly spread subsample on large logs
    idx = diagnostic_subsample(len(B))
    B_sub = B if len(idx) == len(B) else B[idx]
    geometry = ellipsoid_geometry(B_sub, W, offset)
    target_sub: Any = (
        ref.values[idx] if ref.values is not None
        else float(F_hat if F_hat is not None else geometry.magnitude.mean())
    )
    if sigma is None:
        resid = geometry.magnitude - target_sub
        sigma = float(np.sqrt(np.sum(geometry.weight * resid**2) / max(len(idx) - 9, 1)))
    plane_ratio = check_not_planar_within_noise(B, sigma, std=principal)
    uncertainty: dict[str, Any] | None = None
    diag: dict[str, Any] = dict(diagnostics or {})
    cov: NDArray[np.float64] | None = None
    J: NDArray[np.float64] | None = None
    names: tuple[str, ...] = _NAMES if known else (*_NAMES, "F")
    if sigma > 0:
        # the information is a sum over samples: on large logs, an evenly spread subsample scaled up
        J = ellipsoid_fisher(geometry, sigma, known_magnitude=known) * (len(B) / len(idx))
        cov = _ellipsoid_covariance(J, W, known)
        if balance != "never" and np.isfinite(cov).all():
            offset, cov = _balanced_offset(B, offset, cov, sigma, balance, diag)
    if balance == "always" and "balanced_offset" not in diag:  # no noise estimate or no covariance: no test
        offset = column_means(B)
        diag["balanced_offset"] = {"balanced": None, "applied": True, "sample_mean": offset.tolist(),
                                   "note": "forced by balance='always'; not tested (no noise estimate)"}
    coverage = data_coverage(B_sub)  # a property of the data, not of this fit (issue 32)
    if cov is not None and J is not None:
        Fm = float(np.mean(ref.values)) if ref.values is not None else float(target_sub)
        uncertainty = _ellipsoid_uncertainty(
            J, cov, W, offset, Fm, sigma, known, len(B), names, coverage, plane_ratio, uncertainty_note, diag
        )
    W_out = to_symmetric(W) if form == "symmetric" else W
    return build_calibration(
        B, W_out, offset, model=model, method=method, units=units, reference=ref,
        params=Ellipsoid.from_matrix_offset(W_out, offset).as_dict(), iterations=iterations,
        converged=converged, fitted_magnitude=F_hat, uncertainty=uncertainty, diagnostics=diag, coverage=coverage,
    )


def _ellipsoid_covariance(J: NDArray[np.float64], W: NDArray[np.float64], known: bool) -> NDArray[np.float64]:
    """The covariance of ``(W upper, b[, F])`` from the Fisher information ``J``, in the gauge ``det W = 1`` when
    the magnitude is unknown; infinite when ``J`` is singular."""
    grad = None
    if not known:
        Winv = np.linalg.inv(W)
        gW = np.zeros(6)
        for k, (i, j) in enumerate(zip(*UPPER, strict=True)):
            gW[k] = Winv[j, i]
        grad = np.concatenate([gW, np.zeros(3), [0.0]])
    try:
        return _constrained_inverse(J, grad)
    except IdentifiabilityError:
        return np.full_like(J, np.inf)


def _balanced_offset(
    B: NDArray[np.float64], offset: NDArray[np.float64], cov: NDArray[np.float64], sigma: float, balance: str,
    diag: dict[str, Any],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:func:`balance_test` of the samples (recorded in ``diag["balanced_offset"]``); the sample mean and its
    covariance replace the offset and its block of ``cov`` when the test accepts it or ``balance`` is ``"always"``.
    """
    test = balance_test(B, offset, cov[6:9, 6:9], sigma)
    apply_mean = balance == "always" or test["balanced"]
    test["applied"] = bool(apply_mean)
    diag["balanced_offset"] = test
    if not apply_mean:
        return offset, cov
    # the sample mean is the offset; its error (mean noise) is uncorrelated to first order with
    # the ML estimate of W (docs/method-ml.md, "Balanced sampling"), so only the b block changes
    cov = cov.copy()
    cov[6:9, :] = 0.0
    cov[:, 6:9] = 0.0
    cov[6:9, 6:9] = (sigma**2 / len(B)) * np.eye(3)
    return np.asarray(test["sample_mean"], dtype=np.float64), cov


def _ellipsoid_uncertainty(
    J: NDArray[np.float64], cov: NDArray[np.float64], W: NDArray[np.float64], offset: NDArray[np.float64],
    Fm: float, sigma: float, known: bool, n: int, names: tuple[str, ...], coverage: Any, plane_ratio: Any,
    note: str, diag: dict[str, Any],
) -> dict[str, Any]:
    """The uncertainty record (covariance, predicted field and magnitude errors over a sphere of radius ``Fm``)
    and ``diag["identifiability"]`` of an ellipsoid fit on ``n`` samples."""
    theta = np.concatenate([W[UPPER], offset])
    X_test = (Fm * fibonacci_sphere(500)) @ np.linalg.inv(W).T + offset
    field_rms, mag_rms = (
        predicted_errors(cov, _upper_param, theta, X_test) if np.isfinite(cov).all() else (np.inf, np.inf)
    )
    # the information the same number of samples would carry on a full sphere, at the same estimate
    J_ref = ellipsoid_fisher(ellipsoid_geometry(X_test, W, offset), sigma, known_magnitude=known)
    diag["identifiability"] = identifiability(J, names, cov, coverage, reference_fisher=J_ref * (n / 500))
    diag["identifiability"]["plane_noise_ratio"] = plane_ratio  # check_not_planar_within_noise
    return make_uncertainty(
        names, basis=note, covariance=cov, noise_std=sigma,
        gauge="upper-triangular W" + ("" if known else ", det(W) = 1, F estimated"),
        predicted_field_rms=field_rms, predicted_magnitude_rms=mag_rms,
    )


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
