"""Figures of merit: magnitude errors, RMS, amplitude (and the papers' indices, added per paper).

All functions are pure and vectorised; inputs are in one unit, outputs in that unit unless stated.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["magnitude_error", "magnitude_stats", "norm_stats", "rms", "row_norms"]


def rms(x: ArrayLike) -> float:
    """Root mean square of ``x``."""
    a = np.asarray(x, dtype=np.float64)
    return float(np.sqrt(np.mean(a * a)))


def row_norms(B: ArrayLike) -> NDArray[np.float64]:
    """Magnitudes ``|B_i|`` of field samples ``B`` (N, 3) -> (N,) (one pass, no temporaries of shape (N, 3))."""
    a = np.asarray(B, dtype=np.float64)
    return np.sqrt(np.einsum("...i,...i->...", a, a))


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
    from .errors import TrimagInputError

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


# ---- the Cramér–Rao bound of the scalar calibration problem (issue 7; implemented in trimag.crlb) ------------
from .crlb import crlb  # noqa: E402

__all__ += ["crlb"]
