"""Translation and scale normalisation of samples (not public API): fits run on ``u = (x - centre) / scale``, a
centred cloud of radius about 1, so they are well conditioned in any unit."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .chunks import chunk_rows
from .rowwise import column_means, scratch, sum_squares, transposed_blocks

__all__ = ["NORMALISATION_SAMPLES", "Normalisation", "normalisation_of", "normalisation_stats", "normalise"]


#: Rows :func:`normalisation_of` uses (evenly spread).
NORMALISATION_SAMPLES = 2048


class Normalisation:
    """Affine normalisation ``u = (x - centre) / scale`` that keeps fits well conditioned in any unit."""

    def __init__(self, centre: NDArray[np.float64], scale: float) -> None:
        self.centre = centre
        self.scale = scale

    def forward(self, B: NDArray[np.float64]) -> NDArray[np.float64]:
        return (B - self.centre) / self.scale


def normalise(B: NDArray[np.float64]) -> tuple[NDArray[np.float64], Normalisation]:
    """Centre ``B`` (N, 3) on its mean and scale it to unit RMS radius: returns ``(u, norm)``,
    ``u = norm.forward(B)`` (the centre by :func:`trimag._core.rowwise.column_means`)."""
    centre = column_means(B)
    u = B - centre
    flat = u.ravel()
    scale = float(np.sqrt(np.dot(flat, flat) / len(B))) or 1.0
    u *= 1.0 / scale
    return u, Normalisation(centre, scale)


def normalisation_stats(B: NDArray[np.float64], centre: NDArray[np.float64] | None = None) -> Normalisation:
    """The centre and scale of :func:`normalise` without the normalised copy of ``B`` (N, 3): two passes block by
    block, memory independent of N. The same values to rounding (the sums are taken in another order). With
    ``centre`` given (e.g. zeros for a model without offsets), the scale is the RMS distance from it."""
    centre = column_means(B) if centre is None else np.asarray(centre, dtype=np.float64)
    total = 0.0
    rows = min(max(len(B), 1), chunk_rows())
    with scratch(rows) as out, scratch(rows) as tmp:
        for _, t in transposed_blocks(B, centre):
            m = t.shape[1]
            total += float(np.sum(sum_squares(t, out=out[:m], tmp=tmp[:m])))
    return Normalisation(centre, float(np.sqrt(total / len(B))) or 1.0)


def normalisation_of(B: NDArray[np.float64]) -> Normalisation:
    """The :func:`normalise` centre and scale of at most :data:`NORMALISATION_SAMPLES` evenly spread rows of ``B``
    (N, 3), without a copy of ``B``.

    For fits that are invariant to translation and scale (the algebraic ellipsoid fit) the normalisation only
    conditions the arithmetic (it brings the samples to a centred cloud of radius about 1), so a small subsample
    does as well as the whole log: the fitted ellipsoid is the same to rounding (tested).
    """
    _, norm = normalise(np.ascontiguousarray(B[:: max(1, len(B) // NORMALISATION_SAMPLES)]))
    return norm
