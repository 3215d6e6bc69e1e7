"""Paper A's error model: non-orthogonality and gains relative to the Z axis (Wu et al. 2013).

Conventions (``methods.md``, paper A). The ideal orthogonal frame's Z axis coincides with the sensor's Z'
axis and the plane YOZ contains Y'. ``psi`` is the angle between Y' and Y, ``theta`` the angle between X' and
the XOY plane, ``phi`` the angle between the projection of X' on XOY and X. Gains are relative to Z:
``kxz = k'XZ = 1 - kXZ``, ``kyz = k'YZ = 1 - kYZ``, Z gain = 1.

    B' = Gamma B,  Gamma = [[cos(theta)cos(phi)/kxz, cos(theta)sin(phi)/kxz, sin(theta)/kxz],
                            [0,                      cos(psi)/kyz,           sin(psi)/kyz  ],
                            [0,                      0,                      1             ]]

    Gamma^-1 = [[q1, q2, q3], [0, q4, q5], [0, 0, 1]]                        (methods.md, paper A, eq. 4)
    q1 = kxz sec(theta) sec(phi)
    q2 = -kyz tan(phi) sec(psi)      (the paper prints k'XZ; inverting Gamma gives k'YZ, as used here)
    q3 = sec(theta) sec(phi) sec(psi) (cos(theta) sin(phi) sin(psi) - sin(theta) cos(psi))
    q4 = kyz sec(psi)
    q5 = -tan(psi)

The correction is ``B_hat = Gamma^-1 (B' - b)`` with ``b = 0`` for ``ortho-gain`` and three free offsets for
``ortho-gain-bias``. Because the Z gain is the unit, corrected fields are in the unit of the Z axis's output.
Angles are in radians and must lie in (-pi/2, pi/2); gains must be positive.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import ClassVar, Self

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import TrimagInputError
from .base import ErrorModel

#: Indices (rows, columns) of ``q1..q5`` in ``Gamma^-1 = [[q1, q2, q3], [0, q4, q5], [0, 0, 1]]`` (paper A).
Q_INDEX = (np.array([0, 0, 0, 1, 1]), np.array([0, 1, 2, 1, 2]))

__all__ = ["OrthoGain", "OrthoGainBias", "normalised_upper", "params_from_q", "q_from_params"]

#: Relative tolerance for "this matrix has the ortho-gain structure" in :meth:`OrthoGain.from_matrix_offset`.
STRUCTURE_RTOL = 1e-9


def q_from_params(
    theta: ArrayLike, phi: ArrayLike, psi: ArrayLike, kxz: ArrayLike, kyz: ArrayLike
) -> NDArray[np.float64]:
    """``(q1, .., q5)`` from the physical parameters (methods.md, paper A, q1..q5).

    Angles in rad, gains dimensionless; inputs broadcast; returns shape (..., 5).
    """
    t, p, s = (np.asarray(v, dtype=np.float64) for v in (theta, phi, psi))
    kx, ky = np.asarray(kxz, dtype=np.float64), np.asarray(kyz, dtype=np.float64)
    q1 = kx / (np.cos(t) * np.cos(p))
    q2 = -ky * np.tan(p) / np.cos(s)
    q3 = (np.cos(t) * np.sin(p) * np.sin(s) - np.sin(t) * np.cos(s)) / (np.cos(t) * np.cos(p) * np.cos(s))
    q4 = ky / np.cos(s)
    q5 = -np.tan(s)
    return np.stack(np.broadcast_arrays(q1, q2, q3, q4, q5), axis=-1)


def params_from_q(q: ArrayLike) -> NDArray[np.float64]:
    """Exact inverse of :func:`q_from_params`: ``(theta, phi, psi, kxz, kyz)``, shape (..., 5).

    Derivation: ``psi = -atan(q5)``; ``kyz = q4 cos(psi)``; ``q2 / q4 = -tan(phi)``;
    ``q3 = tan(phi) tan(psi) - tan(theta) / cos(phi)`` gives theta; ``kxz = q1 cos(theta) cos(phi)``.
    """
    qq = np.asarray(q, dtype=np.float64)
    if qq.shape[-1:] != (5,):
        raise TrimagInputError(f"`q` must have shape (..., 5) (q1..q5); got {qq.shape}")
    q1, q2, q3, q4, q5 = np.moveaxis(qq, -1, 0)
    if np.any(q1 <= 0) or np.any(q4 <= 0):
        raise TrimagInputError(
            "q1 and q4 (the diagonal of Gamma^-1) must be positive for the ortho-gain model; "
            f"got q1={q1!r}, q4={q4!r}"
        )
    psi = -np.arctan(q5)
    kyz = q4 * np.cos(psi)
    phi = np.arctan(-q2 / q4)
    theta = np.arctan((np.tan(phi) * np.tan(psi) - q3) * np.cos(phi))
    kxz = q1 * np.cos(theta) * np.cos(phi)
    return np.stack([theta, phi, psi, kxz, kyz], axis=-1)


def normalised_upper(matrix: ArrayLike) -> tuple[NDArray[np.float64], float]:
    """Reduce any invertible correction matrix to paper A's gauge.

    Returns ``(C, s)`` with ``C`` upper triangular, positive diagonal, ``C[2, 2] == 1`` and
    ``|matrix @ v| == s * |C @ v|`` for every ``v`` (same magnitudes up to the scale ``s``; a rotation on the
    left is removed). ``C`` is then a valid ``Gamma^-1`` of :class:`OrthoGain`.
    """
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (3, 3):
        raise TrimagInputError(f"`matrix` must have shape (3, 3); got {m.shape}")
    _, r = np.linalg.qr(m)
    signs = np.sign(np.diag(r))
    signs[signs == 0] = 1.0
    r = signs[:, None] * r
    if r[2, 2] <= 0:
        raise TrimagInputError("`matrix` is singular: it cannot be a magnetometer correction")
    return r / r[2, 2], float(r[2, 2])


@dataclasses.dataclass(frozen=True)
class OrthoGain(ErrorModel):
    """Paper A: three non-orthogonality angles and two gains relative to Z, no offsets.

    Attributes
    ----------
    theta : float
        Angle between X' and the XOY plane [rad].
    phi : float
        Angle between the projection of X' on XOY and X [rad].
    psi : float
        Angle between Y' and Y (in the YOZ plane) [rad].
    kxz, kyz : float
        Gains of X' and Y' relative to Z' (``k'XZ``, ``k'YZ``), dimensionless, positive.

    Examples
    --------
    >>> m = OrthoGain(theta=0.06, phi=0.08, psi=-0.04, kxz=0.95, kyz=1.05)
    >>> m.distort([[1.0, 1.0, 2 ** 0.5]]).shape
    (1, 3)
    >>> bool(np.allclose(OrthoGain.from_q(m.q()).as_vector(), m.as_vector(), rtol=1e-14))
    True
    """

    theta: float = 0.0
    phi: float = 0.0
    psi: float = 0.0
    kxz: float = 1.0
    kyz: float = 1.0

    name: ClassVar[str] = "ortho-gain"
    kinds: ClassVar[Mapping[str, str]] = {
        "theta": "angle",
        "phi": "angle",
        "psi": "angle",
        "kxz": "gain",
        "kyz": "gain",
    }
    n_identifiable: ClassVar[int] = 5

    def __post_init__(self) -> None:
        for key in ("theta", "phi", "psi"):
            value = float(getattr(self, key))
            if not (np.isfinite(value) and abs(value) < np.pi / 2):
                raise TrimagInputError(f"`{key}` must be a finite angle in (-pi/2, pi/2) rad; got {value!r}")
        for key in ("kxz", "kyz"):
            value = float(getattr(self, key))
            if not (np.isfinite(value) and value > 0):
                raise TrimagInputError(f"`{key}` must be a finite positive gain; got {value!r}")

    # ---- paper A's matrices
    def gamma(self) -> NDArray[np.float64]:
        """``Gamma`` (3, 3): ``B' = Gamma B`` (methods.md, paper A)."""
        t, p, s, kx, ky = self.theta, self.phi, self.psi, self.kxz, self.kyz
        return np.array(
            [
                [np.cos(t) * np.cos(p) / kx, np.cos(t) * np.sin(p) / kx, np.sin(t) / kx],
                [0.0, np.cos(s) / ky, np.sin(s) / ky],
                [0.0, 0.0, 1.0],
            ]
        )

    def q(self) -> NDArray[np.float64]:
        """``(q1, q2, q3, q4, q5)``, shape (5,)."""
        return q_from_params(self.theta, self.phi, self.psi, self.kxz, self.kyz)

    def gamma_inv(self) -> NDArray[np.float64]:
        """``Gamma^-1 = [[q1, q2, q3], [0, q4, q5], [0, 0, 1]]`` (3, 3)."""
        q1, q2, q3, q4, q5 = self.q()
        return np.array([[q1, q2, q3], [0.0, q4, q5], [0.0, 0.0, 1.0]])

    @classmethod
    def from_q(cls, q: ArrayLike, offset: ArrayLike | None = None) -> Self:
        """Build from ``(q1, .., q5)`` (the exact inverse of :meth:`q`)."""
        params = params_from_q(np.asarray(q, dtype=np.float64).reshape(5))
        return cls._build(params, offset)

    @classmethod
    def _build(cls, params: NDArray[np.float64], offset: ArrayLike | None) -> Self:
        b = np.zeros(3) if offset is None else np.asarray(offset, dtype=np.float64).reshape(3)
        if np.any(b != 0):
            raise TrimagInputError(
                f"model {cls.name!r} has no offsets; got offset {b.tolist()} (use 'ortho-gain-bias')"
            )
        return cls.from_vector(params)

    # ---- ErrorModel contract
    def correction(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        return self.gamma_inv(), np.zeros(3)

    def distortion(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        return self.gamma(), self.correction()[1]

    @classmethod
    def from_matrix_offset(cls, matrix: ArrayLike, offset: ArrayLike = (0.0, 0.0, 0.0)) -> Self:
        """Recover the parameters from ``Gamma^-1`` (upper triangular, ``[2, 2] == 1``) and the offset.

        A general correction matrix can be brought to this form (same magnitudes up to scale) with
        :func:`normalised_upper`.
        """
        m = np.asarray(matrix, dtype=np.float64)
        if m.shape != (3, 3) or not np.isfinite(m).all():
            raise TrimagInputError(f"`matrix` must be a finite (3, 3) array; got shape {m.shape}")
        tol = STRUCTURE_RTOL * float(np.max(np.abs(m)))
        if max(abs(m[1, 0]), abs(m[2, 0]), abs(m[2, 1])) > tol or abs(m[2, 2] - 1.0) > STRUCTURE_RTOL:
            raise TrimagInputError(
                f"model {cls.name!r} represents only upper-triangular correction matrices with "
                f"matrix[2, 2] == 1 (Gamma^-1 of paper A); got {np.array2string(m, precision=6)}. "
                "Reduce it first with trimag.models.ortho_gain.normalised_upper"
            )
        params = params_from_q([m[0, 0], m[0, 1], m[0, 2], m[1, 1], m[1, 2]])
        return cls._build(params, offset)


@dataclasses.dataclass(frozen=True)
class OrthoGainBias(OrthoGain):
    """Paper A's model plus zero offsets ``bx, by, bz`` (in the data's unit): ``B' = Gamma B + b``.

    Real sensors never have exactly zero offsets; this is the model to use on recorded data.
    """

    bx: float = 0.0
    by: float = 0.0
    bz: float = 0.0

    name: ClassVar[str] = "ortho-gain-bias"
    kinds: ClassVar[Mapping[str, str]] = {**OrthoGain.kinds, "bx": "offset", "by": "offset", "bz": "offset"}
    n_identifiable: ClassVar[int] = 8

    def offset(self) -> NDArray[np.float64]:
        """``(bx, by, bz)``, shape (3,)."""
        return np.array([self.bx, self.by, self.bz], dtype=np.float64)

    def correction(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        return self.gamma_inv(), self.offset()

    @classmethod
    def _build(cls, params: NDArray[np.float64], offset: ArrayLike | None) -> Self:
        b = np.zeros(3) if offset is None else np.asarray(offset, dtype=np.float64)
        if b.shape not in ((3,), (1, 3)) or not np.isfinite(b).all():
            raise TrimagInputError(f"`offset` must be a finite (3,) array; got {b!r}")
        return cls.from_vector(np.concatenate([params, b.reshape(3)]))


def q_to_matrix(q: NDArray[np.float64]) -> NDArray[np.float64]:
    """``Gamma^-1 = [[q1, q2, q3], [0, q4, q5], [0, 0, 1]]`` from ``q`` (5,)."""
    C = np.eye(3)
    C[Q_INDEX] = q
    return C


def params_covariance(q: NDArray[np.float64], cov_u: NDArray[np.float64], extra_scales: NDArray) -> NDArray:
    """Propagate a covariance of ``(q1..q5, extras)`` (internal, scaled units) to ``(theta, phi, psi, kxz, kyz,
    extras)``: finite-difference Jacobian of :func:`params_from_q` at ``q``; each extra is multiplied by its
    entry of ``extra_scales`` (e.g. the data scale for offsets)."""
    p = 5 + len(extra_scales)
    A = np.zeros((p, p))
    base = params_from_q(q)
    for j in range(5):
        h = 1e-7 * max(abs(q[j]), 1.0)
        dq = q.copy()
        dq[j] += h
        A[:5, j] = (params_from_q(dq) - base) / h
    A[5:, 5:] = np.diag(extra_scales)
    return A @ cov_u @ A.T
