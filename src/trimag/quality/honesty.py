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
3. **Drift.** The offset is refitted on the first and on the second half of the log (the matrix fixed, one
   linearised step each, on up to 1 000 evenly spread samples per half); when the two differ by more than 4 of
   their (inflated) sigmas, a warning says that the sensor or its surroundings changed during the log, and by how much.
4. **Too few samples.** With ``N_distinct <= p`` nothing is left to estimate the noise: the sigmas are unknown and
   reported as such (None); below ``3 p`` they are flagged as unreliable.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration

__all__ = ["correlation_time", "count_repeated_rows", "drift_check", "honest_uncertainty"]

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


def _half_offset(cal: Calibration, X: NDArray[np.float64], F: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Offset change ``db`` (3,) that best fits one part of the log with the matrix fixed, and its covariance."""
    W = np.asarray(cal.matrix)
    y = (X - np.asarray(cal.offset)) @ W.T
    mag = np.linalg.norm(y, axis=1)
    n = y / mag[:, None]
    G = -(n @ W)  # d|W (x - b)| / db
    r = mag - F
    G_c = G - G.mean(axis=0)  # the level of |B| is not the offset's business
    r_c = r - r.mean()
    H = G_c.T @ G_c
    try:
        H_inv = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return np.zeros(3), np.full((3, 3), np.inf)
    db = H_inv @ (G_c.T @ -r_c)
    s2 = float(np.sum((r_c + G_c @ db) ** 2)) / max(len(r) - 4, 1)
    return db, s2 * H_inv


def drift_check(cal: Calibration, X: NDArray[np.float64], inflation: float = 1.0) -> dict[str, Any] | None:
    """Compare the offset fitted on the first and on the second half of ``X`` (see the module docstring).

    Returns
    -------
    dict or None
        ``offset_change`` (second - first, data unit), ``z`` (the change over its sigma, per axis), ``drift``
        (True when ``max |z| > 4``); None when a half is too short (< 50 samples) or ill-conditioned.
    """
    n = len(X)
    if n < 100 or cal.model == "interference12":
        return None
    half = n // 2
    step = max(1, half // _DRIFT_SAMPLES)
    parts = (X[:half:step], X[half::step])
    F = float(np.mean(np.linalg.norm(cal.apply(parts[0]), axis=1)))
    (b1, C1), (b2, C2) = (_half_offset(cal, part, F) for part in parts)
    var = (np.diag(C1) * step + np.diag(C2) * step) * inflation
    if not np.all(np.isfinite(var)) or np.any(var <= 0):
        return None
    change = b2 - b1
    z = change / np.sqrt(var)
    return {"offset_change": change.tolist(), "z": z.tolist(), "drift": bool(np.max(np.abs(z)) > 4.0),
            "unit": cal.units}


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
    drift = drift_check(cal, X, factors.get("correlated_residuals", 1.0))
    if drift is not None and drift["drift"]:
        size = float(np.linalg.norm(drift["offset_change"]))
        warnings_list.append(
            f"the sensor or its surroundings changed during the log: the offset fitted on the second half differs "
            f"from the first half's by {np.round(drift['offset_change'], 4).tolist()} {cal.units} "
            f"(|change| {size:.4g}, "
            f"{np.max(np.abs(drift['z'])):.1f} sigma); fit the parts separately, or record again away from "
            "moving iron"
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
