"""Uncertainty that holds on real data: the corrections every fit's reported sigmas get (issue 22; docs/accuracy.md).

The estimators report the Cramér–Rao covariance at their solution, which assumes one independent, white-noise
residual per sample. Real logs break that in three ways, each corrected here after the fit and recorded in
``Calibration.uncertainty["inflation"]``:

1. **Repeated rows.** A logger that writes each reading twice doubles N but not the information: the covariance is
   multiplied by ``N / N_distinct`` (counted over the first 20 000 rows of a longer log).
2. **Correlated residuals.** Residuals of real logs are mostly slowly varying model error, not white noise:
   consecutive samples carry much less than independent information. The covariance is multiplied by the integrated
   autocorrelation time ``tau = 1 + 2 sum_k rho_k`` of the magnitude residuals in sample order, summed while
   ``rho_k`` is significant (above ``2 / sqrt(m)``), up to lag ``m / 4``, measured (by FFT) on 4 096 consecutive
   samples in the middle of the log, or on 32 768 when the residuals are still correlated at a quarter of that. On white
   noise ``tau`` is 1 (the Cramér–Rao bound and the coverage of simulations are unchanged).
3. **Halves that disagree** (issue 32). The whole calibration (its nine magnitude parameters: the correction in
   upper-triangular form and the offset) is refitted on the first and on the second half of the log (Gauss-Newton
   from the whole fit, up to 5 000 evenly spread samples per half, each with its own noise and correlation time):
   a parameter that moves by more than :data:`DRIFT_Z` of its sigmas is named in a warning (the sensor or its
   surroundings changed during the log), and when the chi-square of the difference over the nine parameters is
   significant (:data:`DRIFT_ALPHA`) the covariance is multiplied by ``chi2 / 9``, so that the reported sigmas cover
   the halves' disagreement. (Before, only the offset was refitted, the matrix fixed: a changed gain went unseen.)
4. **Too few samples.** With ``N_distinct <= p`` nothing is left to estimate the noise: the sigmas are unknown and
   reported as such (None); below ``3 p`` they are flagged as unreliable.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..units import unit_after
from ..validation import ROUNDOFF_FRACTION

__all__ = ["DRIFT_ALPHA", "DRIFT_Z", "chi2_tail", "correlation_time", "count_repeated_rows", "drift_check",
           "honest_uncertainty"]

_SHORT = 4_096
_LONG = 32_768
_EXACT_DUPLICATES_UP_TO = 20_000  # rows checked for repeats (the first ones of a longer log)
_DRIFT_SAMPLES = 1_000  # per half, evenly spread


def _windows(n: int, length: int) -> list[tuple[int, int]]:
    """One window of ``length`` consecutive samples in the middle of the log (the whole log when shorter)."""
    if n <= length:
        return [(0, n)]
    start = (n - length) // 2
    return [(start, start + length)]


def correlation_time(residuals: NDArray[np.float64], *, truncated: list[bool] | None = None) -> float:
    """Integrated autocorrelation time ``1 + 2 sum rho_k`` of a series (1 for white noise), summed while significant.

    Parameters
    ----------
    residuals : ndarray, shape (m,)
        In sample order.
    """
    r = np.asarray(residuals, dtype=np.float64)
    r = r[np.isfinite(r)] - np.mean(r[np.isfinite(r)]) if np.isfinite(r).any() else r
    m = len(r)
    if m < 20 or not np.any(r):
        return 1.0
    size = 1 << int(np.ceil(np.log2(2 * m)))
    spectrum = np.fft.rfft(r, size)
    acf = np.fft.irfft(spectrum * np.conj(spectrum), size)[: m // 4 + 1]
    rho = acf[1:] / acf[0]
    below = np.flatnonzero(rho < 2.0 / np.sqrt(m))  # summed up to the first insignificant lag
    stop = int(below[0]) if len(below) else len(rho)
    if truncated is not None:
        truncated.append(not len(below))
    return float(max(1.0, 1.0 + 2.0 * rho[:stop].sum()))


def count_repeated_rows(X: NDArray[np.float64]) -> int:
    """Rows equal to another row (``N - N_distinct``): rows sorted by a projection, equal neighbours compared."""
    key = X @ np.array([1.0, 1e-3 * np.pi, 1e-6 * np.e])
    sorted_key = np.sort(key)
    if not np.any(sorted_key[1:] == sorted_key[:-1]):  # the usual case, decided by one sort
        return 0
    order = np.argsort(key, kind="stable")
    same = np.flatnonzero(key[order[1:]] == key[order[:-1]])
    if not len(same):
        return 0
    return int(np.all(X[order[same + 1]] == X[order[same]], axis=1).sum())


def _magnitude_residuals(
    cal: Calibration, X: NDArray[np.float64], reference: Any, length: int
) -> list[NDArray[np.float64]]:
    out = []
    ref = getattr(reference, "values", reference)
    for a, b in _windows(len(X), length):
        block = X[a:b]
        fresh = np.ones(len(block), dtype=bool)
        fresh[1:] = np.any(block[1:] != block[:-1], axis=1)  # a row repeating the previous one is counted as such
        mag = np.linalg.norm(cal.apply(block[fresh]), axis=1)
        if isinstance(ref, np.ndarray) and ref.shape == (len(X),):
            out.append(mag - ref[a:b][fresh])
        else:
            out.append(mag - mag.mean())
    return out


def _scale_entries(unc: dict[str, Any], factor: float) -> dict[str, Any]:
    root = float(np.sqrt(factor))
    out = dict(unc)
    for key in ("param_std", "param_std_deg"):
        if isinstance(out.get(key), dict):
            out[key] = {k: (None if v is None else float(v) * root) for k, v in out[key].items()}
    if out.get("covariance") is not None:
        out["covariance"] = (np.asarray(out["covariance"], dtype=np.float64) * factor).tolist()
    for key in ("predicted_field_rms", "predicted_magnitude_rms"):
        if isinstance(out.get(key), (int, float)):
            out[key] = float(out[key]) * root
    return out


#: Upper-triangular entries of the matrix (row, column) refitted on each half by :func:`drift_check`.
_UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
_HALF_NAMES = ("w11", "w12", "w13", "w22", "w23", "w33", "hard_iron_x", "hard_iron_y", "hard_iron_z")
#: A parameter whose halves differ by more than this many of their sigmas is named in the warning: ~1 % of logs
#: whose sigmas hold raise it over nine parameters (Bonferroni: 2 x 9 x P(z > 3.3) = 0.9 %).
DRIFT_Z = 3.3
#: The halves' difference, chi-square over the nine parameters, beyond this tail probability widens the sigmas (and
#: says so): 1 log in 20 whose sigmas hold, by a factor of about 1.4 (chi2 / 9 >= 1.88); a real office log whose
#: halves differ by 1.5 RMS z (p = 0.04) was passed in silence before.
DRIFT_ALPHA = 0.05
#: Samples per half that :func:`drift_check` refits (evenly spread).
_HALF_SAMPLES = 5_000


def _upper_of(matrix: NDArray[np.float64]) -> NDArray[np.float64]:
    """The upper-triangular ``R`` with ``|R v| = |K v|`` for every v (``K = Q R``, positive diagonal)."""
    r = np.linalg.qr(np.asarray(matrix, dtype=np.float64), mode="r")
    return r * np.sign(np.diag(r))[:, None]


def _half_model(X: NDArray[np.float64], F: Any) -> tuple[Any, Any]:
    """Residuals ``|W (x - b)| - F`` (N,) of the nine parameters ``(w11, w12, w13, w22, w23, w33, b)`` on the samples
    ``X`` (N, 3), and their Jacobian (N, 9), as functions of the parameters."""
    rows, cols = np.array(_UPPER).T
    Xt = np.ascontiguousarray(X.T)  # component-major: contiguous x, y, z

    def parts(theta: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        W = np.zeros((3, 3))
        W[rows, cols] = theta[:6]
        d = Xt - theta[6:, None]
        y = W @ d
        return d, y, np.sqrt(np.einsum("ij,ij->j", y, y))

    def fun(theta: NDArray[np.float64]) -> NDArray[np.float64]:
        return parts(theta)[2] - F

    def jac(theta: NDArray[np.float64]) -> NDArray[np.float64]:
        d, y, mag = parts(theta)
        n = y / mag
        J = np.empty((9, len(mag)))
        np.multiply(n[rows], d[cols], out=J[:6])  # d|W d| / d W_rc = n_r d_c
        W = np.zeros((3, 3))
        W[rows, cols] = theta[:6]
        np.matmul(-W.T, n, out=J[6:])  # d|W d| / db = -W^T n
        return J.T

    return fun, jac


def _refit_half(
    W0: NDArray[np.float64], b0: NDArray[np.float64], X: NDArray[np.float64], F: Any
) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """Gauss-Newton (:func:`trimag._core.solve.gauss_newton`) from the whole log's ``(W0 upper, b0)`` on the samples
    ``X`` of one half: the nine parameters of ``|W (x - b)| = F`` (``F`` the whole fit's, a number or per sample)
    and their covariance ``s^2 (J^T J)^-1 tau`` (``tau`` the residuals' correlation time in sample order); None
    when the half does not determine them."""
    from .._core.solve import gauss_newton

    fun, jac = _half_model(X, F)
    start = np.concatenate([W0[tuple(np.array(_UPPER).T)], b0])
    result = gauss_newton(fun, jac, start, max_steps=50, xtol=1e-7)
    if result is None:
        return None
    theta = np.asarray(result.x, dtype=np.float64)
    r, J = fun(theta), jac(theta)
    H = J.T @ J
    if not np.all(np.isfinite(H)) or np.linalg.cond(H) > 1e12:
        return None
    s2 = float(r @ r) / max(len(r) - len(theta), 1)
    return theta, s2 * np.linalg.inv(H) * correlation_time(r)


def chi2_tail(x: float, dof: int) -> float:
    """``P(X > x)`` for ``X`` chi-square with ``dof`` (a positive integer) degrees of freedom, in closed form (the
    regularised upper incomplete gamma function of half-integer order; without importing scipy.stats)."""
    if not x > 0:
        return 1.0
    h = 0.5 * x
    if dof % 2 == 0:  # exp(-h) sum_{k < dof/2} h^k / k!
        term, total = 1.0, 1.0
        for k in range(1, dof // 2):
            term *= h / k
            total += term
        return float(min(1.0, math.exp(-h) * total))
    term, total = math.sqrt(2.0 * x / math.pi), 0.0  # erfc(sqrt(h)) + e^-h sum_k (2x)^(k-1/2) / (sqrt(pi) (2k-1)!!)
    for k in range(1, (dof + 1) // 2):
        total += term
        term *= x / (2 * k + 1)
    return float(min(1.0, math.erfc(math.sqrt(h)) + math.exp(-h) * total))


def drift_check(cal: Calibration, X: NDArray[np.float64], reference: Any = None) -> dict[str, Any] | None:
    """Refit the whole calibration on the first and on the second half of ``X`` and compare (issue 32, item 7).

    The nine parameters of the magnitude fit (the correction brought to upper-triangular form ``W``, and the
    offset ``b``; the field magnitude fixed at the whole fit's) are refitted on each half (Gauss-Newton from the
    whole log's solution, on at most 5 000 evenly spread samples per half; milliseconds), each with its own
    covariance (noise from its residuals, times their correlation time). ``z = (p2 - p1) / sqrt(s1^2 + s2^2)`` per
    parameter; a parameter beyond :data:`DRIFT_Z` is named; ``chi2 = d^T (C1 + C2)^-1 d`` over the nine gives the
    factor by which the whole fit's sigmas understate the halves' disagreement (``chi2 / 9`` when its tail
    probability is below :data:`DRIFT_ALPHA`, else 1).

    Returns
    -------
    dict or None
        ``offset_change`` (second - first, data unit), ``change`` and ``z`` (per parameter), ``moved`` (the
        parameters beyond :data:`DRIFT_Z`), ``drift`` (any moved), ``chi2``, ``dof``, ``p_value``, ``inflation``;
        None for fewer than 100 samples, a vector model or residuals of round-off (at most
        :data:`~trimag.validation.ROUNDOFF_FRACTION` of the field); ``undetermined_halves`` (``"first"``, ``"second"``)
        instead of the comparison when a half does not determine the nine parameters on its own.
    """
    n = len(X)
    if n < 100 or cal.model == "interference12":
        return None
    W0, b0 = _upper_of(np.asarray(cal.matrix)), np.asarray(cal.offset, dtype=np.float64)
    ref = getattr(reference, "values", reference)
    per_sample = isinstance(ref, np.ndarray) and ref.shape == (n,)
    F_whole = float((cal.reference or {}).get("value") or np.mean(np.linalg.norm(cal.apply(X[:: max(1, n // 2000)]),
                                                                                axis=1)))
    rms = cal.stats.get("rms_after")
    if rms is not None and float(rms) <= ROUNDOFF_FRACTION * abs(F_whole):
        return None  # residuals of round-off (noise-free data): the halves' sigmas measure nothing
    fits = []
    for start, stop in ((0, n // 2), (n // 2, n)):  # evenly spread rows of each half, without indexing all of them
        idx = start + np.linspace(0, stop - start - 1, min(stop - start, _HALF_SAMPLES)).astype(np.int64)
        fits.append(_refit_half(W0, b0, X[idx], ref[idx] if per_sample else F_whole))
    if fits[0] is None or fits[1] is None:
        undetermined = [k for k, fit in zip(("first", "second"), fits, strict=True) if fit is None]
        return {"drift": False, "undetermined_halves": undetermined, "inflation": 1.0, "unit": cal.units}
    (p1, C1), (p2, C2) = fits  # type: ignore[misc]
    d, C = p2 - p1, C1 + C2
    var = np.diag(C)
    if not np.all(np.isfinite(var)) or np.any(var <= 0):
        return None
    z = d / np.sqrt(var)
    try:
        chi2 = float(d @ np.linalg.solve(C, d))
    except np.linalg.LinAlgError:
        return None
    p_value = chi2_tail(chi2, len(d))
    moved = [name for name, v in zip(_HALF_NAMES, z, strict=True) if abs(v) > DRIFT_Z]
    return {"rms_z": float(np.sqrt(np.mean(z * z))), "offset_change": d[6:].tolist(),
            "change": dict(zip(_HALF_NAMES, d.tolist(), strict=True)),
            "z": dict(zip(_HALF_NAMES, z.tolist(), strict=True)), "moved": moved,
            "drift": bool(moved) or p_value < DRIFT_ALPHA,
            "chi2": chi2, "dof": len(d), "p_value": p_value,
            "inflation": max(1.0, chi2 / len(d)) if p_value < DRIFT_ALPHA else 1.0, "unit": cal.units}


def _drift_warning(drift: dict[str, Any], unit: str) -> str:
    """The warning of halves that disagree: the parameters that moved, by how much and how many sigmas."""
    z, change = drift["z"], drift["change"]
    unit = unit_after(unit)  # "(unit not given)" for a fit without a unit
    named = sorted(drift["moved"], key=lambda k: -abs(z[k]))
    parts = [f"{k} by {change[k]:.4g}{' ' + unit if k.startswith('hard_iron') else ''} ({abs(z[k]):.1f} sigma)"
             for k in named[:4]]
    moved = (f": {', '.join(parts)}{' ...' if len(named) > 4 else ''} (the offset by "
             f"{np.round(drift['offset_change'], 4).tolist()} {unit})" if parts else "")
    widened = (f"; the reported sigmas are widened {np.sqrt(drift['inflation']):.2g}x to cover it"
               if drift["inflation"] > 1.0 else "")
    return (
        "the sensor or its surroundings changed during the log: refitted on each half, the calibration moves beyond "
        f"its sigmas (RMS z {drift['rms_z']:.2g} over the nine parameters, p = {drift['p_value']:.2g}){moved}"
        f"{widened}; "
        "fit the parts separately, or record again away from moving iron"
    )


def honest_uncertainty(
    cal: Calibration, X: NDArray[np.float64], reference: Any = None, *, n_duplicates: int | None = None
) -> Calibration:
    """``cal`` with its uncertainty corrected for repeated rows, correlated residuals and too few samples.

    Parameters
    ----------
    cal : Calibration
        A fitted calibration whose ``uncertainty["param_std"]`` the estimator filled.
    X : ndarray, shape (N, 3)
        The samples it was fitted on, in their order.
    reference : ScalarReference, float or ndarray, optional
        The magnitude reference of the fit (per-sample values are used for the residuals).
    n_duplicates : int, optional
        Rows repeating an earlier row exactly (counted here when None and N <= 20 000).
    """
    unc = dict(cal.uncertainty or {})
    std = unc.get("param_std")
    if not isinstance(std, dict) or not std:
        return cal
    n = len(X)
    if n_duplicates is None:
        n_duplicates = count_repeated_rows(X[:_EXACT_DUPLICATES_UP_TO])
    factors: dict[str, float] = {}
    if n_duplicates:
        factors["repeated_rows"] = n / max(n - n_duplicates, 1)
    if cal.model != "interference12":
        truncated: list[bool] = []
        tau = max(correlation_time(r, truncated=truncated) for r in _magnitude_residuals(cal, X, reference, _SHORT))
        if any(truncated) and len(X) > _SHORT:  # correlated beyond a quarter of the window: look at a longer one
            tau = max(correlation_time(r) for r in _magnitude_residuals(cal, X, reference, _LONG))
        if tau > 1.0:
            factors["correlated_residuals"] = tau
    total = float(np.prod(list(factors.values()))) if factors else 1.0
    if total > 1.0:
        unc = _scale_entries(unc, total)
    warnings_list = list(cal.diagnostics.get("warnings", []))
    drift = drift_check(cal, X, reference)
    if drift is not None and drift["inflation"] > 1.0:  # the halves disagree beyond the sigmas: they are widened
        factors["halves_disagree"] = drift["inflation"]
        total *= drift["inflation"]
        unc = _scale_entries(unc, drift["inflation"])
    if drift is not None and drift["drift"]:
        warnings_list.append(_drift_warning(drift, cal.units))
    if drift is not None and len(drift.get("undetermined_halves", ())) == 2:
        warnings_list.append(
            "neither half of the log determines the calibration on its own, so its sigmas cannot be checked by "
            "refitting the halves: check the calibration on another log (`trimag evaluate`) before trusting it"
        )
    p = sum(1 for v in std.values() if v is not None)
    n_distinct = n - n_duplicates
    if n_distinct <= p:
        unc["param_std"] = {k: None for k in std}
        unc.pop("param_std_deg", None)
        warnings_list.append(
            f"{n_distinct} distinct samples for {p} parameters: no degree of freedom is left to estimate the noise, "
            "so the uncertainty is unknown; record more samples"
        )
    elif n_distinct < 3 * p:
        warnings_list.append(
            f"only {n_distinct} distinct samples for {p} parameters: the reported uncertainty is unreliable"
        )
    unc["inflation"] = {"total": total, **factors, "n_distinct": n_distinct,
                        "note": "covariance x total (trimag.quality.honesty): repeated rows, correlated residuals"}
    diagnostics = dict(cal.diagnostics)
    if drift is not None:
        diagnostics["drift"] = drift
    if warnings_list:
        diagnostics["warnings"] = warnings_list
    return replace(cal, uncertainty=unc, diagnostics=diagnostics)
