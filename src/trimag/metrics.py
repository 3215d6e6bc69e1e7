"""Figures of merit: magnitude errors, RMS, amplitude (and the papers' indices, added per paper).

All functions are pure and vectorised; inputs are in one unit, outputs in that unit unless stated.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["magnitude_error", "magnitude_stats", "rms"]


def rms(x: ArrayLike) -> float:
    """Root mean square of ``x``."""
    a = np.asarray(x, dtype=np.float64)
    return float(np.sqrt(np.mean(a * a)))


def magnitude_error(B: ArrayLike, reference: ArrayLike) -> NDArray[np.float64]:
    """``|B_i| - F_i`` for fields ``B`` (N, 3) and reference magnitudes ``F`` (scalar or (N,))."""
    return np.linalg.norm(np.asarray(B, dtype=np.float64), axis=-1) - np.asarray(reference, dtype=np.float64)


def magnitude_stats(B: ArrayLike, reference: ArrayLike) -> dict[str, Any]:
    """Summary of ``|B| - F``: ``mean_norm``, ``std_norm``, ``rms``, ``max_abs``, ``peak_to_peak``, ``bias``.

    ``rms`` is the paper B metric ``sqrt(mean((|B_i| - F)^2))``; ``max_abs`` is its error amplitude.
    """
    norms = np.linalg.norm(np.asarray(B, dtype=np.float64), axis=-1)
    err = norms - np.asarray(reference, dtype=np.float64)
    return {
        "mean_norm": float(norms.mean()),
        "std_norm": float(norms.std()),
        "rms": rms(err),
        "max_abs": float(np.max(np.abs(err))),
        "peak_to_peak": float(np.ptp(err)),
        "bias": float(err.mean()),
    }
