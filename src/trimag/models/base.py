"""The error-model contract shared by every module in :mod:`trimag.models`.

A model is a frozen dataclass of named physical parameters. It converts to and from the affine form used
everywhere else (``docs/conventions.md``):

    B_raw       = distortion_matrix @ B_true + offset          (``distort``)
    B_corrected = correction_matrix @ (B_raw - offset)         (``correct``)

with ``correction_matrix == inv(distortion_matrix)``. Models know nothing of files or estimators.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, ClassVar, Self

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import TrimagInputError

__all__ = ["PARAM_KINDS", "ErrorModel"]

#: The kinds of parameter a model declares (:attr:`ErrorModel.kinds`): ``offset`` (field unit: bias, hard iron,
#: constant vehicle field), ``gain`` (dimensionless scale factor), ``angle`` (radians), ``matrix`` (a
#: dimensionless entry of a correction or coupling matrix).
PARAM_KINDS = ("offset", "gain", "angle", "matrix")


@dataclasses.dataclass(frozen=True)
class ErrorModel:
    """Base class: subclasses are frozen dataclasses whose fields are the physical parameters (floats)."""

    name: ClassVar[str] = "affine"
    #: Number of parameters a scalar (magnitude-only) fit can identify, for minimum-sample checks.
    n_identifiable: ClassVar[int] = 9
    #: The kind of each parameter (one of :data:`PARAM_KINDS`), declared by each model: reports and checks read
    #: it instead of guessing from names.
    kinds: ClassVar[Mapping[str, str]] = {}

    # ---- to implement in each model
    def correction(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Return ``(matrix (3, 3), offset (3,))`` with ``B_corrected = matrix @ (B_raw - offset)``."""
        raise NotImplementedError

    @classmethod
    def from_matrix_offset(cls, matrix: ArrayLike, offset: ArrayLike = (0.0, 0.0, 0.0)) -> Self:
        """Recover the physical parameters from a correction matrix and offset (exact inverse of
        :meth:`correction` for matrices the model can represent)."""
        raise NotImplementedError

    # ---- shared
    @classmethod
    def kind_of(cls, name: str) -> str:
        """The declared kind of parameter ``name`` (:data:`PARAM_KINDS`)."""
        try:
            return cls.kinds[name]
        except KeyError:
            raise TrimagInputError(f"model {cls.name!r} has no parameter {name!r}") from None

    @classmethod
    def param_names(cls) -> tuple[str, ...]:
        """Names of the physical parameters, in field order."""
        return tuple(f.name for f in dataclasses.fields(cls))

    def as_dict(self) -> dict[str, float]:
        """Parameters as ``{name: float}``."""
        return {k: float(v) for k, v in dataclasses.asdict(self).items()}

    def as_vector(self) -> NDArray[np.float64]:
        """Parameters as a vector in :meth:`param_names` order."""
        return np.array([getattr(self, n) for n in self.param_names()], dtype=np.float64)

    @classmethod
    def from_vector(cls, values: ArrayLike) -> Self:
        """Build from a vector in :meth:`param_names` order."""
        vals = np.asarray(values, dtype=np.float64).ravel()
        names = cls.param_names()
        if vals.shape != (len(names),):
            raise TrimagInputError(f"{cls.name} needs {len(names)} parameters {names}; got {vals.shape[0]}")
        return cls(**{n: float(v) for n, v in zip(names, vals, strict=True)})

    @classmethod
    def from_dict(cls, params: Mapping[str, Any]) -> Self:
        """Build from ``{name: value}``; every parameter must be present, and no others."""
        names = set(cls.param_names())
        given = set(params)
        if given != names:
            missing, extra = sorted(names - given), sorted(given - names)
            raise TrimagInputError(
                f"model {cls.name!r} parameters: missing {missing}, unexpected {extra}; "
                f"expected exactly {list(cls.param_names())}"
            )
        return cls(**{n: float(params[n]) for n in cls.param_names()})

    def distortion(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Return ``(D (3, 3), offset (3,))`` with ``B_raw = D @ B_true + offset``."""
        matrix, offset = self.correction()
        return np.asarray(np.linalg.inv(matrix), dtype=np.float64), offset

    def distort(self, B: ArrayLike) -> NDArray[np.float64]:
        """Map true fields (N, 3) or (3,) to what the sensor reports (same shape, same unit)."""
        D, offset = self.distortion()
        return np.asarray(B, dtype=np.float64) @ D.T + offset

    def correct(self, B_raw: ArrayLike) -> NDArray[np.float64]:
        """Map sensor readings (N, 3) or (3,) to corrected fields (same shape, same unit)."""
        matrix, offset = self.correction()
        return (np.asarray(B_raw, dtype=np.float64) - offset) @ matrix.T
