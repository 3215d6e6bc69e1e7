"""One validator for every field array that enters trimag (style guide: scikit-learn's ``check_array``)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import IdentifiabilityError, TrimagInputError

__all__ = ["check_field", "check_reference_values"]


def check_field(
    B: ArrayLike,
    *,
    name: str = "B",
    min_samples: int = 1,
    allow_single: bool = False,
    model: str | None = None,
) -> NDArray[np.float64]:
    """Validate a field array and return it as float64 of shape (N, 3).

    Parameters
    ----------
    B : array_like, shape (N, 3) (or (3,) when ``allow_single``)
        Field samples, one row per sample, columns x, y, z.
    name : str
        The argument's name, used in messages.
    min_samples : int
        Fewest rows the caller needs (e.g. a model's parameter count).
    allow_single : bool
        Accept a single vector of shape (3,) and return it as (1, 3).
    model : str, optional
        Model name, for the too-few-samples message.

    Returns
    -------
    ndarray, shape (N, 3), float64
        C-ordered and never the caller's writable array: a read-only view when ``B`` is already a C-ordered
        float64 array (no copy), otherwise a new array. The input is never modified.

    Raises
    ------
    TrimagInputError
        Wrong shape, non-numeric or non-finite values.
    IdentifiabilityError
        Fewer than ``min_samples`` rows.
    """
    try:
        if isinstance(B, np.ndarray) and B.dtype == np.float64 and B.flags.c_contiguous:
            # already what trimag needs: a read-only view, no copy (a 1e7-row log is 240 MB); any attempt to
            # write into it raises, so the caller's array can never be modified
            arr = B.view()
            arr.flags.writeable = False
        else:
            arr = np.array(B, dtype=np.float64, copy=True, order="C")  # C order: row blocks are contiguous
    except (TypeError, ValueError) as exc:
        raise TrimagInputError(f"`{name}` must be numeric with shape (N, 3); got {type(B).__name__}") from exc
    if arr.ndim == 1 and allow_single and arr.shape[0] == 3:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise TrimagInputError(
            f"`{name}` must have shape (N, 3) (one row per sample, columns x, y, z); got {arr.shape}"
        )
    if arr.shape[0] == 0:
        raise TrimagInputError(f"`{name}` is empty: no samples to work with")
    # NaN and inf make the sum non-finite (one pass, no (N, 3) mask); only then (or on overflow) look closer
    with np.errstate(over="ignore", invalid="ignore"):
        total = arr.sum()
    if not np.isfinite(total) and not np.isfinite(arr).all():
        bad = ~np.isfinite(arr).all(axis=1)
        raise TrimagInputError(
            f"`{name}` has {int(bad.sum())} row(s) with NaN or inf (first at row {int(np.argmax(bad))}); "
            "drop them first (the file readers do this and report the count)"
        )
    if arr.shape[0] < min_samples:
        what = f" model {model!r}" if model else " this fit"
        raise IdentifiabilityError(
            f"{arr.shape[0]} samples are too few for{what}: at least {min_samples} are needed; "
            "record more samples in more attitudes"
        )
    return arr


def check_reference_values(values: Any, n: int, *, name: str = "reference") -> NDArray[np.float64]:
    """Validate a scalar reference (one value, or one per sample) and return shape (N,) float64."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.full(n, float(arr))
    if arr.shape != (n,):
        raise TrimagInputError(f"`{name}` must be a scalar or have shape ({n},); got {arr.shape}")
    if not np.isfinite(arr).all() or (arr <= 0).any():
        raise TrimagInputError(f"`{name}` must be finite and positive (a field magnitude)")
    return arr
