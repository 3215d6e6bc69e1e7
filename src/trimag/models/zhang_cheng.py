"""Paper D's model (``zhang-cheng``): non-orthogonality angles, gains and zero offsets (Zhang & Cheng 2009).

The sensor output ``V`` (3,) for a true field ``B`` (3,) in the ideal orthogonal frame is (methods.md, paper D)::

    Lx = Bx cos(gamma) cos(alpha) + By sin(gamma) + Bz sin(alpha)
    Ly = By cos(beta) + Bz sin(beta)
    Lz = Bz
    V  = K L + b,   K = diag(kx, ky, kz)      i.e.   V = K A B + b

    A = [[cos(gamma) cos(alpha), sin(gamma), sin(alpha)],
         [0,                     cos(beta),  sin(beta) ],
         [0,                     0,          1         ]]

``A`` (and so ``D = K A``, the distortion matrix) is *upper triangular*: the ideal Z axis is the sensor's Z axis
and the ideal Y axis lies in the sensor's YZ plane. The correction is ``B = M (V - b)`` with ``M = (K A)^-1``,
also upper triangular with a positive diagonal.

Quadratic form and the coefficient vector ``W``. With ``Q = (KA)^-T (KA)^-1 = M^T M``::

    |B|^2 = (V - b)^T Q (V - b)
          = W . phi(V),   phi(V) = (Vx^2, Vy^2, Vz^2, Vx Vy, Vx Vz, Vy Vz, Vx, Vy, Vz, 1)
    W = (Q11, Q22, Q33, 2 Q12, 2 Q13, 2 Q23, -2 (Q b)_x, -2 (Q b)_y, -2 (Q b)_z, b^T Q b)

The first three entries are the diagonal of ``Q``, as in the paper's printed ``W = [0.9616 1.0209 0.9806 -0...]``;
the paper's equation for the remaining order is lost (OCR), so this order is trimag's convention.

Recovery of the physical parameters from ``Q`` (the gauge). ``Q`` fixes ``M`` only up to a rotation on the left
(``(R M)^T (R M) = Q``): a magnitude cannot tell how the ideal frame is oriented. The model fixes that rotation
by requiring ``M`` upper triangular with a positive diagonal, and that factor is unique: it is the transpose of
the ordinary (lower) Cholesky factor, ``Q = L L^T``, ``M = L^T``. Then ``K A = M^-1`` (upper triangular) and

* row 3: ``kz = (KA)33``;
* row 2: ``ky = hypot((KA)22, (KA)23)``, ``beta = atan2((KA)23, (KA)22)``;
* row 1, ``r = (KA)1,:`` = ``kx (cos g cos a, sin g, sin a)`` (not a unit vector): ``u = kx^2`` solves
  ``u^2 - |r|^2 u + r12^2 r13^2 = 0``; the larger root is the one with ``|alpha|, |gamma| < 90 deg``, then
  ``gamma = asin(r12 / kx)``, ``alpha = asin(r13 / kx)``.

Angles are radians in the API (the reports show degrees); ``kx, ky, kz`` are dimensionless; ``bx, by, bz`` are in
the data's unit.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import TrimagInputError
from .base import ErrorModel

__all__ = ["W_TERMS", "ZhangCheng", "quadric_from_w", "upper_from_quadric", "w_from_quadric"]

#: Names of the entries of ``W`` (the monomial each multiplies in ``phi(V)``).
W_TERMS: tuple[str, ...] = ("xx", "yy", "zz", "xy", "xz", "yz", "x", "y", "z", "1")

_ANGLES = ("alpha", "beta", "gamma")


def w_from_quadric(Q: ArrayLike, b: ArrayLike) -> NDArray[np.float64]:
    """``W`` (10,) of ``(V - b)^T Q (V - b)``; ``Q`` (3, 3) symmetric, ``b`` (3,) in the data's unit."""
    q = np.asarray(Q, dtype=np.float64)
    bb = np.asarray(b, dtype=np.float64)
    qb = q @ bb
    return np.array(
        [q[0, 0], q[1, 1], q[2, 2], 2 * q[0, 1], 2 * q[0, 2], 2 * q[1, 2], *(-2.0 * qb), float(bb @ qb)]
    )


def quadric_from_w(W: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """Split ``W`` (10,) into ``(Q (3, 3), l (3,), c)`` with ``phi(V) @ W = V^T Q V + l . V + c``."""
    w = np.asarray(W, dtype=np.float64)
    if w.shape != (10,):
        raise TrimagInputError(f"`W` must have shape (10,); got {w.shape}")
    Q = np.array(
        [[w[0], w[3] / 2, w[4] / 2], [w[3] / 2, w[1], w[5] / 2], [w[4] / 2, w[5] / 2, w[2]]]
    )
    return Q, w[6:9].copy(), float(w[9])


def upper_from_quadric(Q: ArrayLike) -> NDArray[np.float64]:
    """The unique upper-triangular, positive-diagonal ``M`` with ``M^T M = Q`` (``M = cholesky(Q)^T``).

    Raises
    ------
    TrimagInputError
        ``Q`` is not symmetric positive definite (the data do not describe an ellipsoid).
    """
    q = np.asarray(Q, dtype=np.float64)
    try:
        L = np.linalg.cholesky(0.5 * (q + q.T))
    except np.linalg.LinAlgError:
        raise TrimagInputError(
            "the quadratic form Q is not positive definite: the samples do not describe an ellipsoid"
        ) from None
    return np.ascontiguousarray(L.T)


@dataclasses.dataclass(frozen=True)
class ZhangCheng(ErrorModel):
    """Paper D's nine parameters: ``alpha, beta, gamma`` (rad), ``kx, ky, kz`` (1), ``bx, by, bz`` (data unit).

    Examples
    --------
    >>> import numpy as np
    >>> m = ZhangCheng(*np.radians([0.8, 0.5, 1.1]), 1.02, 0.99, 1.01, 0.03, 0.02, 0.01)
    >>> np.round(m.w_vector()[:3], 5)
    array([0.96171, 1.02076, 0.98056])
    >>> ZhangCheng.from_matrix_offset(*m.correction()).as_vector().round(12).tolist() == \
m.as_vector().round(12).tolist()
    True
    """

    alpha: float = 0.0
    beta: float = 0.0
    gamma: float = 0.0
    kx: float = 1.0
    ky: float = 1.0
    kz: float = 1.0
    bx: float = 0.0
    by: float = 0.0
    bz: float = 0.0

    name: ClassVar[str] = "zhang-cheng"
    kinds: ClassVar[Mapping[str, str]] = {
        "alpha": "angle",
        "beta": "angle",
        "gamma": "angle",
        "kx": "gain",
        "ky": "gain",
        "kz": "gain",
        "bx": "offset",
        "by": "offset",
        "bz": "offset",
    }
    n_identifiable: ClassVar[int] = 9
    #: Parameters that are angles (radians in the API, degrees in reports).
    angle_params: ClassVar[tuple[str, ...]] = _ANGLES

    def __post_init__(self) -> None:
        values = self.as_vector()
        if not np.isfinite(values).all():
            raise TrimagInputError(f"zhang-cheng parameters must be finite; got {self.as_dict()}")
        if min(self.kx, self.ky, self.kz) <= 0:
            raise TrimagInputError(f"gains kx, ky, kz must be positive; got {self.kx}, {self.ky}, {self.kz}")
        if max(abs(self.alpha), abs(self.beta), abs(self.gamma)) >= np.pi / 2:
            raise TrimagInputError("angles alpha, beta, gamma must lie within (-90, 90) degrees (radians in the API)")

    # ------------------------------------------------------------------ matrices
    def a_matrix(self) -> NDArray[np.float64]:
        """The non-orthogonality matrix ``A`` (3, 3), upper triangular (methods.md, paper D)."""
        ca, sa = np.cos(self.alpha), np.sin(self.alpha)
        cb, sb = np.cos(self.beta), np.sin(self.beta)
        cg, sg = np.cos(self.gamma), np.sin(self.gamma)
        return np.array([[cg * ca, sg, sa], [0.0, cb, sb], [0.0, 0.0, 1.0]])

    def distortion(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(K A (3, 3), b (3,))`` with ``V = K A B + b``."""
        K = np.array([self.kx, self.ky, self.kz], dtype=np.float64)
        D: NDArray[np.float64] = K[:, None] * self.a_matrix()
        return D, np.array([self.bx, self.by, self.bz], dtype=np.float64)

    def correction(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(M = (K A)^-1 (3, 3), b (3,))`` with ``B = M (V - b)``; ``M`` is upper triangular."""
        D, b = self.distortion()
        M = np.linalg.solve(D, np.eye(3)).astype(np.float64)
        M[np.tril_indices(3, -1)] = 0.0
        return M, b

    def quadric(self) -> NDArray[np.float64]:
        """``Q = (KA)^-T (KA)^-1`` (3, 3), so that ``|B|^2 = (V - b)^T Q (V - b)``."""
        M, _ = self.correction()
        return M.T @ M

    def w_vector(self) -> NDArray[np.float64]:
        """The coefficient vector ``W`` (10,) of the quadratic form (see the module docstring)."""
        return w_from_quadric(self.quadric(), [self.bx, self.by, self.bz])

    # ------------------------------------------------------------------ inverse maps
    @classmethod
    def from_matrix_offset(
        cls, matrix: ArrayLike, offset: ArrayLike = (0.0, 0.0, 0.0), *, rtol: float = 1e-9
    ) -> ZhangCheng:
        """Parameters from an upper-triangular correction matrix ``M = (KA)^-1`` (3, 3) and offset ``b`` (3,).

        Exact inverse of :meth:`correction`. A matrix with a lower triangle larger than ``rtol * max|M|`` is
        refused: it is a rotated version of the model (use :func:`upper_from_quadric` on ``M^T M`` to bring a
        magnitude-only fit into the model's gauge).
        """
        M = np.asarray(matrix, dtype=np.float64)
        b = np.asarray(offset, dtype=np.float64)
        if M.shape != (3, 3) or b.shape != (3,):
            raise TrimagInputError(f"matrix must be (3, 3) and offset (3,); got {M.shape} and {b.shape}")
        if not (np.isfinite(M).all() and np.isfinite(b).all()):
            raise TrimagInputError("matrix and offset must be finite")
        lower = np.abs(M[np.tril_indices(3, -1)]).max()
        if lower > rtol * np.abs(M).max():
            raise TrimagInputError(
                "the zhang-cheng model needs an upper-triangular correction matrix (ideal Z = sensor Z, ideal Y "
                f"in the sensor's YZ plane); this one has lower-triangle entries up to {lower:.3g}. Convert it "
                "with trimag.models.zhang_cheng.upper_from_quadric(M.T @ M)"
            )
        if np.any(np.diag(M) <= 0):
            raise TrimagInputError(f"the correction matrix needs a positive diagonal; got {np.diag(M).tolist()}")
        D = np.linalg.solve(np.triu(M), np.eye(3))
        kz = D[2, 2]
        ky = float(np.hypot(D[1, 1], D[1, 2]))
        beta = float(np.arctan2(D[1, 2], D[1, 1]))
        r11, r12, r13 = D[0]
        S = r11 * r11 + r12 * r12 + r13 * r13
        disc = max(S * S - 4.0 * (r12 * r13) ** 2, 0.0)
        kx = float(np.sqrt(0.5 * (S + np.sqrt(disc))))
        gamma = float(np.arcsin(np.clip(r12 / kx, -1.0, 1.0)))
        alpha = float(np.arcsin(np.clip(r13 / kx, -1.0, 1.0)))
        return cls(alpha, beta, gamma, kx, ky, float(kz), float(b[0]), float(b[1]), float(b[2]))

    @classmethod
    def from_quadric(cls, Q: ArrayLike, offset: ArrayLike) -> ZhangCheng:
        """Parameters from ``Q`` (3, 3) symmetric positive definite and the offset ``b`` (3,)."""
        return cls.from_matrix_offset(upper_from_quadric(Q), offset)

    @classmethod
    def from_w(cls, W: ArrayLike, field_magnitude: float = 1.0) -> ZhangCheng:
        """Parameters from a coefficient vector ``W`` (10,) fitted with ``phi(V) @ W = F^2``.

        ``b = -Q^-1 l / 2``; when ``W`` does not satisfy its constraint ``W[9] = b^T Q b`` exactly (a noisy fit),
        ``Q`` is rescaled so that the fitted ellipsoid is ``(V - b)^T Q' (V - b) = F^2``:
        ``Q' = Q F^2 / (F^2 - W[9] + b^T Q b)``. For an exact ``W`` the factor is 1.
        """
        Q, lin, c = quadric_from_w(W)
        Qs = 0.5 * (Q + Q.T)
        try:
            b = np.linalg.solve(Qs, -0.5 * lin)
        except np.linalg.LinAlgError:
            raise TrimagInputError("the quadratic form in W is singular: not an ellipsoid") from None
        F2 = float(field_magnitude) ** 2
        level = F2 - c + float(b @ Qs @ b)
        if not level > 0:
            raise TrimagInputError("W does not describe a real ellipsoid (non-positive level)")
        return cls.from_quadric(Qs * (F2 / level), b)

    # ------------------------------------------------------------------ display
    def as_report(self) -> dict[str, float]:
        """Parameters for display: angles in degrees (``alpha_deg`` ...), the rest unchanged."""
        out: dict[str, float] = {}
        for k, v in self.as_dict().items():
            if k in _ANGLES:
                out[f"{k}_deg"] = float(np.degrees(v))
            else:
                out[k] = v
        return out
