"""Figures of merit: magnitude errors, RMS, amplitude (and the papers' indices, added per paper).

All functions are pure and vectorised; inputs are in one unit, outputs in that unit unless stated.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._core import rowwise as _rowwise
from .._core.chunks import chunk_rows, row_blocks
from .._core.rowwise import row_dot
from .._core.stats import StreamingMoments as _Moments
from .crlb import crlb

__all__ = ["before_after_stats", "magnitude_error", "magnitude_stats", "norm_stats", "rms", "row_dot", "row_norms"]


def rms(x: ArrayLike) -> float:
    """Root mean square of ``x``."""
    a = np.asarray(x, dtype=np.float64)
    return float(np.sqrt(np.mean(a * a)))


def row_norms(B: ArrayLike) -> NDArray[np.float64]:
    """Magnitudes ``|B_i|`` of field samples ``B`` (N, 3) -> (N,)."""
    a = np.asarray(B, dtype=np.float64)
    if a.ndim != 2:
        return np.sqrt(row_dot(a, a))
    out = np.empty(len(a))  # block by block: one array of N, no temporaries of N (issue 41, item 10)
    for rows in row_blocks(len(a)):
        np.sqrt(row_dot(a[rows], a[rows]), out=out[rows])
    return out


def magnitude_error(B: ArrayLike, reference: ArrayLike) -> NDArray[np.float64]:
    """``|B_i| - F_i`` for fields ``B`` (N, 3) and reference magnitudes ``F`` (scalar or (N,))."""
    return row_norms(B) - np.asarray(reference, dtype=np.float64)


def magnitude_stats(B: ArrayLike, reference: ArrayLike) -> dict[str, Any]:
    """Summary of ``|B| - F``: ``mean_norm``, ``std_norm``, ``rms``, ``max_abs``, ``peak_to_peak``, ``bias``.

    ``rms`` is the paper B metric ``sqrt(mean((|B_i| - F)^2))``; ``max_abs`` is its error amplitude.
    """
    return norm_stats(row_norms(B), reference)


def norm_stats(norms: ArrayLike, reference: ArrayLike) -> dict[str, Any]:
    """:func:`magnitude_stats` from magnitudes already computed, ``norms`` (N,)."""
    norms = np.asarray(norms, dtype=np.float64)
    err = norms - np.asarray(reference, dtype=np.float64)
    lo, hi = float(err.min()), float(err.max())
    mean_norm = float(norms.mean())
    dev = norms - mean_norm
    return {
        "mean_norm": mean_norm,
        "std_norm": float(np.sqrt(np.dot(dev, dev) / len(dev))),
        "rms": float(np.sqrt(np.dot(err, err) / len(err))),
        "max_abs": max(-lo, hi),
        "peak_to_peak": hi - lo,
        "bias": float(err.mean()),
    }


def _stats_from(norms: _Moments, err: _Moments | None, F: float) -> dict[str, Any]:
    """:func:`norm_stats` from moments; ``err`` holds ``|B_i| - F_i`` (per-sample reference) or None (``F``)."""
    n = norms.n
    std_norm = float(np.sqrt(max(norms.m2, 0.0) / n))
    if err is None:
        bias = norms.mean - F
        rms_ = float(np.sqrt(max(norms.m2, 0.0) / n + bias * bias))
        lo, hi = norms.lo - F, norms.hi - F
    else:
        bias = err.mean
        rms_ = float(np.sqrt(max(err.m2, 0.0) / n + bias * bias))
        lo, hi = err.lo, err.hi
    return {
        "mean_norm": float(norms.mean),
        "std_norm": std_norm,
        "rms": rms_,
        "max_abs": max(-lo, hi),
        "peak_to_peak": hi - lo,
        "bias": float(bias),
    }


def before_after_stats(
    B: NDArray[np.float64],
    matrix: NDArray[np.float64],
    offset: NDArray[np.float64],
    reference: NDArray[np.float64] | None = None,
) -> tuple[dict[str, Any], dict[str, Any], float]:
    """:func:`norm_stats` of the raw samples and of the corrected ``matrix @ (B_i - offset)``, in one pass.

    Parameters
    ----------
    B : ndarray, shape (N, 3)
        Raw samples.
    matrix : ndarray, shape (3, 3)
    offset : ndarray, shape (3,)
    reference : ndarray, shape (N,), optional
        Reference magnitude per sample. Without it ``F`` is the mean corrected magnitude.

    Returns
    -------
    before, after : dict
        As :func:`norm_stats` (``mean_norm``, ``std_norm``, ``rms``, ``max_abs``, ``peak_to_peak``, ``bias``).
    F : float
        The magnitude the statistics refer to: the mean corrected magnitude, or the mean reference.

    Notes
    -----
    The samples are processed in blocks of 65 536 rows (:mod:`trimag._core.rowwise`), so no (N, 3) or (N,) temporary
    is formed; the result
    equals ``norm_stats(row_norms(B), F)`` and ``norm_stats(row_norms(corrected), F)`` to rounding.
    """
    matrix = np.ascontiguousarray(matrix, dtype=np.float64)
    offset = np.asarray(offset, dtype=np.float64)
    raw, cor = _Moments(), _Moments()
    raw_err, cor_err = (_Moments(), _Moments()) if reference is not None else (None, None)
    ref_sum = 0.0
    size = min(max(len(B), 1), chunk_rows())

    def norms(t: NDArray[np.float64], out: NDArray[np.float64], scratch: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.sqrt(_rowwise.sum_squares(t, out=out, tmp=scratch), out=out)

    with _rowwise.scratch(7, size) as work:  # reused block buffers (trimag._core.rowwise.scratch)
        y_buf = work[:3]
        tmp, n_raw_buf, n_cor_buf, err_buf = work[3:]
        for start, t in _rowwise.transposed_blocks(B):  # component-major blocks (trimag._core.rowwise)
            m = t.shape[1]
            n_raw = norms(t, n_raw_buf[:m], tmp[:m])
            t -= offset[:, None]
            y = np.matmul(matrix, t, out=y_buf[:, :m])
            n_cor = norms(y, n_cor_buf[:m], tmp[:m])
            raw.add(n_raw, tmp)
            cor.add(n_cor, tmp)
            if reference is not None:
                assert raw_err is not None and cor_err is not None
                ref = reference[start : start + m]
                ref_sum += float(np.sum(ref))
                raw_err.add(np.subtract(n_raw, ref, out=err_buf[:m]), tmp)
                cor_err.add(np.subtract(n_cor, ref, out=err_buf[:m]), tmp)
    F = ref_sum / len(B) if reference is not None else cor.mean
    return _stats_from(raw, raw_err, F), _stats_from(cor, cor_err, F), float(F)


# ---- paper C: compensation rate and precision (methods.md, paper C) -------------------------------------
__all__ += ["compensation_precision", "compensation_rate"]


def compensation_rate(error_before: ArrayLike, error_after: ArrayLike) -> NDArray[np.float64]:
    """Paper C's compensation rate per attitude: ``(|e_before| - |e_after|) / |e_before|`` (dimensionless).

    ``e_before`` and ``e_after`` are total-field errors (``|H| - F_true``) before and after compensation,
    same unit, shape (N,). 1 means the error was removed, 0 that nothing changed, < 0 that it grew.
    """
    before = np.abs(np.asarray(error_before, dtype=np.float64))
    after = np.abs(np.asarray(error_after, dtype=np.float64))
    if np.any(before == 0):
        raise ValueError("compensation rate is undefined where the error before compensation is 0")
    return (before - after) / before


def compensation_precision(error_after: ArrayLike, true_total: ArrayLike) -> NDArray[np.float64]:
    """Paper C's compensation precision per attitude: ``|e_after| / F_true`` (smaller is better).

    ``error_after`` (N,) is the total-field error after compensation, ``true_total`` (scalar or (N,)) the true
    total field, same unit.
    """
    after = np.abs(np.asarray(error_after, dtype=np.float64))
    return after / np.asarray(true_total, dtype=np.float64)


# ---- paper A: the J index (methods.md, paper A, "Index J") ----------------------------------------------
__all__ += ["j_index"]

#: Paper A's parameters, in the order J sums them.
J_PARAMS = ("theta", "phi", "psi", "kxz", "kyz")


def j_index(true: Any, estimated: Any, *, keys: tuple[str, ...] | None = None) -> Any:
    """Paper A's index ``J = sqrt(sum_p ((p - p_hat) / p)^2)`` over the parameters (dimensionless).

    Parameters
    ----------
    true, estimated : mapping, model, or array_like, shape (..., P)
        True and estimated parameters: ``{name: value}`` mappings or error models (``as_dict()``) read at
        ``keys`` (default ``("theta", "phi", "psi", "kxz", "kyz")``), or arrays whose last axis holds the
        parameters in one order. Arrays broadcast (e.g. one truth (P,) against K trials (K, P)).
    keys : tuple of str, optional
        Parameter names to use with mappings and models.

    Returns
    -------
    float or ndarray, shape (...)
        J per estimate.

    Raises
    ------
    TrimagInputError
        A true parameter is 0 (the relative error is undefined there) or the shapes do not match.
    """
    from ..errors import TrimagInputError

    def as_array(x: Any) -> NDArray[np.float64]:
        if hasattr(x, "as_dict"):
            x = x.as_dict()
        if isinstance(x, dict) or hasattr(x, "keys"):
            return np.array([float(x[k]) for k in (keys or J_PARAMS)], dtype=np.float64)
        return np.asarray(x, dtype=np.float64)

    t, e = as_array(true), as_array(estimated)
    if t.shape[-1:] != e.shape[-1:]:
        raise TrimagInputError(f"true and estimated parameter counts differ: {t.shape} and {e.shape}")
    if np.any(t == 0):
        raise TrimagInputError("J is undefined when a true parameter is 0 (relative error)")
    j = np.sqrt(np.sum(((t - e) / t) ** 2, axis=-1))
    return float(j) if np.ndim(j) == 0 else j


__all__ += ["crlb"]  # the Cramér–Rao bound of the scalar calibration problem, implemented in trimag.quality.crlb
