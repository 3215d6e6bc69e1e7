"""Paper B's 9-parameter model (``scalar9``): zero biases, scale factors and non-orthogonality angles.

Convention (methods.md, paper B; the paper's own equation is lost in the OCR):

    B_m = K T B + b,   K = diag(k1, k2, k3),
    T = [[1,          0,                    0                   ],
         [sin(alpha), cos(alpha),           0                   ],
         [sin(beta),  sin(gamma) cos(beta), cos(gamma) cos(beta)]]

Each row of ``T`` is a unit vector: the direction of a sensor axis in the orthogonal frame whose x axis is the
sensor's x axis and whose y axis lies in the plane of the sensor's x and y axes. Correction (methods.md,
paper B):

    B = T^-1 K^-1 (B_m - b)

so, in trimag's affine form ``B_corrected = matrix @ (B_raw - offset)``: ``matrix = T^-1 K^-1`` and
``offset = b``. The distortion ``K T`` is lower triangular with a positive diagonal (for ``k > 0`` and angles
in (-pi/2, pi/2)); this fixes the rotation that a magnitude-only fit cannot see, so every affine correction
has exactly one ``scalar9`` equivalent with the same corrected magnitudes (:meth:`Scalar9.from_matrix_offset` with
``gauge="magnitude"``).

Angles are in radians in the API; :meth:`Scalar9.angles_deg` gives degrees for reports.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import TrimagInputError
from .base import ErrorModel

__all__ = ["Scalar9", "lq_gauge", "t_matrix", "t_matrix_derivatives"]


def t_matrix(alpha: float, beta: float, gamma: float) -> NDArray[np.float64]:
    """The non-orthogonality matrix ``T`` (3, 3) of methods.md, paper B; angles in radians."""
    sa, ca = math.sin(alpha), math.cos(alpha)
    sb, cb = math.sin(beta), math.cos(beta)
    sg, cg = math.sin(gamma), math.cos(gamma)
    return np.array([[1.0, 0.0, 0.0], [sa, ca, 0.0], [sb, sg * cb, cg * cb]])


def t_matrix_derivatives(alpha: float, beta: float, gamma: float) -> tuple[NDArray[np.float64], ...]:
    """``(dT/dalpha, dT/dbeta, dT/dgamma)``, each (3, 3); used by the analytic Jacobian."""
    sa, ca = math.sin(alpha), math.cos(alpha)
    sb, cb = math.sin(beta), math.cos(beta)
    sg, cg = math.sin(gamma), math.cos(gamma)
    d_alpha = np.array([[0.0, 0.0, 0.0], [ca, -sa, 0.0], [0.0, 0.0, 0.0]])
    d_beta = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [cb, -sg * sb, -cg * sb]])
    d_gamma = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, cg * cb, -sg * cb]])
    return d_alpha, d_beta, d_gamma


def lq_gauge(distortion: ArrayLike) -> NDArray[np.float64]:
    """The lower-triangular, positive-diagonal ``L`` with ``L L^T == D D^T`` (``D = L Q``, ``Q`` orthogonal).

    Corrections ``inv(D)`` and ``inv(L) = Q inv(D)`` differ by a rotation on the left, so they give the same
    corrected magnitudes: ``L`` is the scalar-calibration gauge of ``D``.
    """
    d = np.asarray(distortion, dtype=np.float64)
    # D^T = Q' R  ->  D = R^T Q'^T, R^T lower triangular
    _, r = np.linalg.qr(d.T)
    signs = np.sign(np.diag(r))
    signs[signs == 0] = 1.0
    return (signs[:, None] * r).T


@dataclasses.dataclass(frozen=True)
class Scalar9(ErrorModel):
    """Paper B's sensor: biases ``b1 b2 b3`` (data unit), scale factors ``k1 k2 k3`` (dimensionless) and
    non-orthogonality angles ``alpha beta gamma`` (radians).

    ``B_m = K T B + b`` (see the module docstring for ``T``); the correction is ``B = T^-1 K^-1 (B_m - b)``.

    Examples
    --------
    >>> m = Scalar9(b1=200.0, k1=1.01, alpha=0.005)
    >>> matrix, offset = m.correction()
    >>> matrix.shape, offset.shape
    ((3, 3), (3,))
    >>> round(Scalar9.from_matrix_offset(matrix, offset).k1, 12)
    1.01
    """

    b1: float = 0.0
    b2: float = 0.0
    b3: float = 0.0
    k1: float = 1.0
    k2: float = 1.0
    k3: float = 1.0
    alpha: float = 0.0
    beta: float = 0.0
    gamma: float = 0.0

    name: ClassVar[str] = "scalar9"
    kinds: ClassVar[Mapping[str, str]] = {
        "b1": "offset",
        "b2": "offset",
        "b3": "offset",
        "k1": "gain",
        "k2": "gain",
        "k3": "gain",
        "alpha": "angle",
        "beta": "angle",
        "gamma": "angle",
    }
    n_identifiable: ClassVar[int] = 9

    def __post_init__(self) -> None:
        for key in ("k1", "k2", "k3"):
            value = getattr(self, key)
            if not (math.isfinite(value) and value > 0):
                raise TrimagInputError(f"scale factor `{key}` must be finite and positive; got {value!r}")
        for key in ("alpha", "beta", "gamma"):
            value = getattr(self, key)
            if not (math.isfinite(value) and abs(value) < math.pi / 2):
                raise TrimagInputError(
                    f"angle `{key}` must be in radians within (-pi/2, pi/2); got {value!r} "
                    "(give degrees through Scalar9.from_degrees)"
                )
        for key in ("b1", "b2", "b3"):
            if not math.isfinite(getattr(self, key)):
                raise TrimagInputError(f"bias `{key}` must be finite; got {getattr(self, key)!r}")

    # ------------------------------------------------------------------ pieces
    @property
    def bias(self) -> NDArray[np.float64]:
        """``b`` (3,), data unit."""
        return np.array([self.b1, self.b2, self.b3])

    @property
    def scale(self) -> NDArray[np.float64]:
        """``(k1, k2, k3)`` (3,)."""
        return np.array([self.k1, self.k2, self.k3])

    @property
    def T(self) -> NDArray[np.float64]:
        """Non-orthogonality matrix ``T`` (3, 3)."""
        return t_matrix(self.alpha, self.beta, self.gamma)

    def angles_deg(self) -> dict[str, float]:
        """``{"alpha": ..., "beta": ..., "gamma": ...}`` in degrees (for reports)."""
        return {k: math.degrees(getattr(self, k)) for k in ("alpha", "beta", "gamma")}

    @classmethod
    def from_degrees(cls, **params: float) -> Scalar9:
        """Build with ``alpha``, ``beta``, ``gamma`` given in degrees (other parameters as usual)."""
        conv = {k: (math.radians(v) if k in ("alpha", "beta", "gamma") else v) for k, v in params.items()}
        return cls(**conv)

    # ------------------------------------------------------------------ affine form
    def distortion(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(K T (3, 3), b (3,))`` with ``B_m = K T B + b``."""
        return self.scale[:, None] * self.T, self.bias

    def correction(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(T^-1 K^-1 (3, 3), b (3,))`` with ``B = matrix @ (B_m - b)``."""
        D, b = self.distortion()
        return np.asarray(np.linalg.inv(D), dtype=np.float64), b

    @classmethod
    def from_matrix_offset(
        cls,
        matrix: ArrayLike,
        offset: ArrayLike = (0.0, 0.0, 0.0),
        *,
        gauge: str = "exact",
        atol: float = 1e-9,
    ) -> Scalar9:
        """Recover the nine parameters from a correction ``matrix`` (3, 3) and ``offset`` (3,).

        Parameters
        ----------
        matrix : array_like, shape (3, 3)
            Correction matrix, ``B = matrix @ (B_m - offset)``.
        offset : array_like, shape (3,)
            The biases ``b``, data unit.
        gauge : {"exact", "magnitude"}
            ``"exact"``: ``inv(matrix)`` must already be of the form ``K T`` (lower triangular, positive
            diagonal; checked to ``atol`` relative), and the result reproduces ``matrix`` exactly.
            ``"magnitude"``: any invertible matrix is first reduced to that form by removing a rotation on the
            left (:func:`lq_gauge`); the result gives the same corrected magnitudes ``|matrix @ (B_m - b)|``.
        atol : float
            Tolerance of the ``"exact"`` check, relative to the largest entry of ``inv(matrix)``.

        Raises
        ------
        TrimagInputError
            Wrong shapes, a singular matrix, or (``"exact"``) a matrix the model cannot represent.
        """
        m = np.asarray(matrix, dtype=np.float64)
        b = np.asarray(offset, dtype=np.float64)
        if m.shape != (3, 3) or b.shape != (3,):
            raise TrimagInputError(f"matrix must be (3, 3) and offset (3,); got {m.shape} and {b.shape}")
        if not (np.isfinite(m).all() and np.isfinite(b).all()):
            raise TrimagInputError("matrix and offset must be finite")
        try:
            D = np.linalg.inv(m)
        except np.linalg.LinAlgError:
            raise TrimagInputError("the correction matrix is singular") from None
        if gauge == "magnitude":
            D = lq_gauge(D)
        elif gauge == "exact":
            upper = np.abs(D[np.triu_indices(3, 1)]).max()
            if upper > atol * np.abs(D).max() or (np.diag(D) <= 0).any():
                raise TrimagInputError(
                    "this correction matrix is not of the scalar9 form (inv(matrix) = K T must be lower "
                    "triangular with a positive diagonal); pass gauge='magnitude' to convert it to the "
                    "equivalent scalar9 parameters (same corrected magnitudes)"
                )
        else:
            raise TrimagInputError(f"gauge must be 'exact' or 'magnitude'; got {gauge!r}")
        k = np.linalg.norm(D, axis=1)
        T = D / k[:, None]
        alpha = math.atan2(T[1, 0], T[1, 1])
        beta = math.atan2(T[2, 0], math.hypot(T[2, 1], T[2, 2]))
        gamma = math.atan2(T[2, 1], T[2, 2])
        return cls(
            b1=float(b[0]), b2=float(b[1]), b3=float(b[2]),
            k1=float(k[0]), k2=float(k[1]), k3=float(k[2]),
            alpha=alpha, beta=beta, gamma=gamma,
        )
