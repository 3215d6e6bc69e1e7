"""The general hard + soft iron model (``ellipsoid``).

    B_raw = inv(W) @ B_true + hard_iron,        B_corrected = W @ (B_raw - hard_iron)

A magnitude-only fit sees ``W`` only up to a rotation on the left (``|Q W e| == |W e|``), so estimators
return ``W`` in a fixed gauge: upper triangular with a positive diagonal (the default) or symmetric positive
definite (``form="symmetric"``, the minimal-rotation correction that MATLAB's ``magcal`` also reports). The
model itself stores all nine entries so that any matrix round-trips exactly.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._core.rowwise import row_dot
from ..errors import TrimagInputError
from .base import ErrorModel

#: Indices (rows, columns) of the six entries of an upper-triangular 3 x 3 matrix, in the order w11 w12 w13 w22
#: w23 w33.
UPPER = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))

__all__ = ["Ellipsoid", "to_symmetric", "to_upper"]


@dataclasses.dataclass(frozen=True)
class Ellipsoid(ErrorModel):
    """Hard iron ``(hard_iron_x, hard_iron_y, hard_iron_z)`` in the data's unit, and the soft-iron correction
    matrix entries ``w11 .. w33`` (row-major, dimensionless)."""

    hard_iron_x: float = 0.0
    hard_iron_y: float = 0.0
    hard_iron_z: float = 0.0
    w11: float = 1.0
    w12: float = 0.0
    w13: float = 0.0
    w21: float = 0.0
    w22: float = 1.0
    w23: float = 0.0
    w31: float = 0.0
    w32: float = 0.0
    w33: float = 1.0

    name: ClassVar[str] = "ellipsoid"
    kinds: ClassVar[Mapping[str, str]] = {
        "hard_iron_x": "offset",
        "hard_iron_y": "offset",
        "hard_iron_z": "offset",
        "w11": "matrix",
        "w12": "matrix",
        "w13": "matrix",
        "w21": "matrix",
        "w22": "matrix",
        "w23": "matrix",
        "w31": "matrix",
        "w32": "matrix",
        "w33": "matrix",
    }
    n_identifiable: ClassVar[int] = 9

    def correction(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        v = self.as_vector()
        return v[3:].reshape(3, 3).copy(), v[:3].copy()

    @classmethod
    def from_matrix_offset(cls, matrix: ArrayLike, offset: ArrayLike = (0.0, 0.0, 0.0)) -> Ellipsoid:
        m = np.asarray(matrix, dtype=np.float64)
        b = np.asarray(offset, dtype=np.float64)
        if m.shape != (3, 3) or b.shape != (3,):
            raise TrimagInputError(f"matrix must be (3, 3) and offset (3,); got {m.shape} and {b.shape}")
        return cls.from_vector(np.concatenate([b, m.ravel()]))


def to_upper(matrix: ArrayLike) -> NDArray[np.float64]:
    """The upper-triangular, positive-diagonal ``R`` with ``R.T @ R == M.T @ M`` (same magnitudes)."""
    m = np.asarray(matrix, dtype=np.float64)
    _, r = np.linalg.qr(m)
    signs = np.sign(np.diag(r))
    signs[signs == 0] = 1.0
    return signs[:, None] * r


def to_symmetric(matrix: ArrayLike) -> NDArray[np.float64]:
    """The symmetric positive-definite ``S`` with ``S @ S == M.T @ M`` (same magnitudes, least rotation)."""
    m = np.asarray(matrix, dtype=np.float64)
    vals, vecs = np.linalg.eigh(m.T @ m)
    return (vecs * np.sqrt(vals)) @ vecs.T


def magnitude_jacobian(
    u: NDArray[np.float64], W: NDArray[np.float64], b: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Magnitudes ``|W (u - b)|`` (N,) and their Jacobian (N, 9) w.r.t. (upper W, b)."""
    e = u - b
    y = e @ W.T
    mag = np.sqrt(row_dot(y, y))
    n = y / mag[:, None]
    J = np.empty((len(u), 9))
    J[:, :6] = n[:, UPPER[0]] * e[:, UPPER[1]]
    J[:, 6:] = -(n @ W)
    return mag, J
