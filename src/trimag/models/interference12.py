"""Paper C's 12-coefficient vehicle-interference model (``interference12``).

    H_m = K @ H_b + c,        H_b = C(attitude)^T @ H_n              (methods.md, paper C)

``K`` (3x3: the sensor's own gains and misalignment times the vehicle's induced magnetisation, ``I + D``
for a perfect sensor) and ``c`` (3,: the vehicle's permanent field plus sensor offsets) are constant in the
body frame. In trimag's affine form (``docs/conventions.md``)

    H_b_hat = inv(K) @ (H_m - c),  i.e. correction matrix = inv(K), offset = c.

Coefficients: ``k11 .. k33`` (row-major, dimensionless) and ``c1, c2, c3`` (in the data's unit).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import TrimagInputError
from .base import ErrorModel

__all__ = ["Interference12"]


@dataclasses.dataclass(frozen=True)
class Interference12(ErrorModel):
    """Interference matrix ``K`` entries ``k11 .. k33`` (row-major) and constant field ``c1, c2, c3``.

    ``distort`` maps a body-frame field to what the sensor on the vehicle reports, ``K @ H_b + c``;
    ``correct`` is the compensation ``inv(K) @ (H_m - c)``.
    """

    k11: float = 1.0
    k12: float = 0.0
    k13: float = 0.0
    k21: float = 0.0
    k22: float = 1.0
    k23: float = 0.0
    k31: float = 0.0
    k32: float = 0.0
    k33: float = 1.0
    c1: float = 0.0
    c2: float = 0.0
    c3: float = 0.0

    name: ClassVar[str] = "interference12"
    kinds: ClassVar[Mapping[str, str]] = {
        "k11": "matrix",
        "k12": "matrix",
        "k13": "matrix",
        "k21": "matrix",
        "k22": "matrix",
        "k23": "matrix",
        "k31": "matrix",
        "k32": "matrix",
        "k33": "matrix",
        "c1": "offset",
        "c2": "offset",
        "c3": "offset",
    }
    #: A magnitude-only fit could identify 9 of the 12 (K only up to a rotation); the vector fit of
    #: ``linear-vector`` identifies all 12 from 4 non-coplanar attitudes (its own ``_min_samples``).
    n_identifiable: ClassVar[int] = 9

    @property
    def K(self) -> NDArray[np.float64]:
        """The interference matrix, shape (3, 3)."""
        return self.as_vector()[:9].reshape(3, 3).copy()

    @property
    def c(self) -> NDArray[np.float64]:
        """The constant (permanent) field, shape (3,), in the data's unit."""
        return self.as_vector()[9:].copy()

    @classmethod
    def from_K_c(cls, K: ArrayLike, c: ArrayLike = (0.0, 0.0, 0.0)) -> Interference12:
        """Build from ``K`` (3, 3) and ``c`` (3,)."""
        k = np.asarray(K, dtype=np.float64)
        cc = np.asarray(c, dtype=np.float64)
        if k.shape != (3, 3) or cc.shape != (3,):
            raise TrimagInputError(f"K must be (3, 3) and c (3,); got {k.shape} and {cc.shape}")
        return cls.from_vector(np.concatenate([k.ravel(), cc]))

    def distortion(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        return self.K, self.c

    def correction(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        K = self.K
        if np.linalg.cond(K) > 1e12:
            raise TrimagInputError("the interference matrix K is singular; no compensation exists")
        return np.asarray(np.linalg.inv(K), dtype=np.float64), self.c

    @classmethod
    def from_matrix_offset(cls, matrix: ArrayLike, offset: ArrayLike = (0.0, 0.0, 0.0)) -> Interference12:
        """``K = inv(matrix)``, ``c = offset``."""
        m = np.asarray(matrix, dtype=np.float64)
        b = np.asarray(offset, dtype=np.float64)
        if m.shape != (3, 3) or b.shape != (3,):
            raise TrimagInputError(f"matrix must be (3, 3) and offset (3,); got {m.shape} and {b.shape}")
        return cls.from_K_c(np.linalg.inv(m), b)
