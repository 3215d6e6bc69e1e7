"""``linear-vector``: paper C's 12 coefficients by three independent 4-unknown least-squares problems.

    H_m = K @ H_b + c,   H_b = C(attitude)^T @ H_n                        (methods.md, paper C)

Row ``a`` of ``K`` and ``c_a`` only enter sensor axis ``a``: ``H_m[:, a] = [H_b, 1] @ (K[a, :], c_a)``, so the
12 coefficients are three linear least-squares problems sharing one N x 4 design ``A = [H_b, 1]``. ``A`` has
full rank iff the body-frame background fields ``H_b`` of the attitudes do not lie in one plane (for a
constant |H_n| they lie on a sphere; a plane cuts it in a circle, e.g. turns about one axis only), which
needs at least 4 attitudes. The column-normalised condition number of ``A`` is reported; above
``trimag.quality.diagnostics.CONDITION_ERROR`` the fit stops with :class:`~trimag.errors.IdentifiabilityError`
(exit 3).

Attitudes follow ``docs/conventions-attitude.md``: ``Rotation`` body -> NED, ``H_b = R.inv().apply(H_n)``.

Background field ``H_n`` (NED, the data's unit) comes from the caller (``--background-ned``, IGRF vector, or
the mean of an iron-free run, :func:`trimag.io.background.background_from_run`). With
``estimate_background=True`` it is fitted jointly (:func:`fit_with_background`): ``K`` and ``H_n`` are then
identified only up to a common scale (``K s``, ``H_n / s``), fixed here by ``|H_n|`` = the magnitude of the
given background or the given magnitude (or, when neither is given, by ``det(K) = 1``: ``|H_n|`` is then the mean
corrected magnitude), and the sign by ``det(K) > 0``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from .._core.chunks import row_blocks
from .._core.qr import BlockedQR, panel_rows
from .._core.rowwise import count_duplicate_rows
from .._core.solve import levenberg_marquardt
from ..calibration import Calibration
from ..errors import IdentifiabilityError, TrimagInputError
from ..fields.attitude import body_field
from ..fields.reference import ScalarReference, as_background, as_vector
from ..models.interference12 import Interference12
from ..quality.diagnostics import CONDITION_ERROR, check_condition, design_condition, weak_directions
from ._finish import make_uncertainty
from .base import Estimator, build_calibration

__all__ = ["LinearVector"]

_NAMES_A = ("H_b x", "H_b y", "H_b z", "c")
_HINT = (
    "record at least 4 attitudes whose body-frame background fields are not coplanar "
    "(tilt the vehicle in pitch and roll as well as turning it in heading)"
)


def _check_attitude(attitude: Any, n: int) -> Rotation:
    if not isinstance(attitude, Rotation):
        raise TrimagInputError(
            "linear-vector needs the attitude of every sample as a scipy Rotation (body -> NED); "
            "on the command line give `attitude_columns=yaw,pitch,roll` or `quaternion_columns=w,x,y,z`"
        )
    if attitude.single or len(attitude) != n:
        got = 1 if attitude.single else len(attitude)
        raise TrimagInputError(f"need one attitude per sample: {n} samples but {got} attitude(s)")
    return attitude


def _distinct_count(H_b: NDArray[np.float64]) -> int:
    """Distinct attitudes: rows of ``H_b`` (N, 3) that differ after rounding to 1e-9 of the largest value (rows
    hashed, colliding ones compared exactly: :func:`~trimag._core.rowwise.count_duplicate_rows`; sorting whole rows
    took 0.84 of a 1.37 s fit at N = 1e6)."""
    scale = float(np.max(np.abs(H_b))) or 1.0

    def rounded(rows: NDArray[np.float64]) -> NDArray[np.float64]:
        out = rows / scale
        return np.round(out, 9, out=out)

    return len(H_b) - count_duplicate_rows(H_b, prepare=rounded)  # rounded block by block: no (N, 3) copy


def solve_interference(
    H_m: NDArray[np.float64], H_b: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], dict[str, Any]]:
    """Solve ``H_m = K H_b + c`` for ``K`` (3, 3) and ``c`` (3,) by three 4-unknown least squares.

    Parameters
    ----------
    H_m : ndarray, shape (N, 3)
        Measured fields (body frame, with interference).
    H_b : ndarray, shape (N, 3)
        Background field in the body frame at each sample, same unit.

    Returns
    -------
    K, c, info
        ``info`` holds ``condition_number`` (column-normalised, of ``[H_b, 1]``), ``n_attitudes`` (distinct
        ``H_b`` rows), ``residual_rms_axis`` (3,), ``param_std`` (per coefficient) and ``singular_values``.

    Raises
    ------
    IdentifiabilityError
        Fewer than 4 distinct attitudes, or ``H_b`` coplanar (condition number above the error limit).
    """
    n_att = _distinct_count(H_b)
    if n_att < 4:
        raise IdentifiabilityError(
            f"only {n_att} distinct attitude(s): the 12 interference coefficients need at least 4 attitudes "
            f"(each sensor axis is a 4-unknown problem); {_HINT}"
        )
    # [H_b, 1 | H_m] = Q R block by block (trimag._core.qr.BlockedQR): R11 (4, 4) has the singular values
    # and column norms of A = [H_b, 1], R11 X = R12 is the least-squares solution, and R22's column norms are
    # the per-axis residual norms; no (N, 4) design is formed
    qr = BlockedQR(7)
    for rows in row_blocks(len(H_b)):
        block = np.empty((rows.stop - rows.start, 7))
        block[:, :3] = H_b[rows]
        block[:, 3] = 1.0
        block[:, 4:] = H_m[rows]
        qr.add(block)
    R = qr.R
    R11, R12, R22 = R[:4, :4], R[:4, 4:], R[4:, 4:]
    cond, s, vt = design_condition(R11)
    if not np.isfinite(cond) or cond > CONDITION_ERROR:
        raise IdentifiabilityError(
            f"the body-frame background fields of the {n_att} attitudes are coplanar (condition number of "
            f"[H_b, 1] = {cond:.3g}): K is not identifiable; {_HINT}"
        )
    check_condition(
        cond, what="the 12 interference coefficients", hint=_HINT,
        weak=weak_directions(vt, s, _NAMES_A, threshold=1e4),
    )
    X, *_ = np.linalg.lstsq(R11, R12, rcond=None)  # (4, 3): column a = (K[a, :], c_a)
    K = np.asarray(X[:3].T, dtype=np.float64).copy()
    c = np.asarray(X[3], dtype=np.float64).copy()
    resid_ss = np.sum(R22**2, axis=0)  # (3,) per-axis residual sum of squares
    dof = max(len(H_b) - 4, 1)
    s2 = resid_ss / dof  # (3,) per-axis residual variance
    inv_ata = np.linalg.pinv(R11.T @ R11)
    names = [f"k{a + 1}{b + 1}" for a in range(3) for b in range(3)] + ["c1", "c2", "c3"]
    # each axis is its own least-squares problem in (K row a, c_a): a block-diagonal covariance
    cov = np.zeros((12, 12))
    for a in range(3):
        idx = [3 * a, 3 * a + 1, 3 * a + 2, 9 + a]
        cov[np.ix_(idx, idx)] = s2[a] * inv_ata
    info = {
        "condition_number": cond,
        "n_attitudes": n_att,
        "singular_values": s.tolist(),
        "residual_rms_axis": np.sqrt(resid_ss / len(H_b)).tolist(),
        "param_std": dict(zip(names, np.sqrt(np.diag(cov)).tolist(), strict=True)),
        "covariance": cov,
        "names": names,
    }
    return K, c, info


def _vector_sum_squares(
    B: NDArray[np.float64], H_b: NDArray[np.float64], matrix: NDArray[np.float64], offset: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per-axis sums of squares (3,) of ``B - H_b`` and of ``matrix (B - offset) - H_b`` (rows of ``B``, ``H_b``
    (N, 3)), block by block: the vector errors before and after compensation without (N, 3) temporaries."""
    before, after = np.zeros(3), np.zeros(3)
    for rows in row_blocks(len(B)):
        b, h = B[rows], H_b[rows]
        e = b - h
        before += np.einsum("ij,ij->j", e, e)
        e = (b - offset) @ matrix.T - h
        after += np.einsum("ij,ij->j", e, e)
    return before, after


def _orthonormal_complement(u: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    a = np.eye(3)[int(np.argmin(np.abs(u)))]
    e1 = np.cross(u, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(u, e1)


def _factor_background_design(
    B: NDArray[np.float64], attitude: Rotation, *, block: int | None = None
) -> NDArray[np.float64]:
    """Triangular factor ``R`` of ``[D10 | B]`` (N, 13), ``D10 = [vec(C_i^T), 1]``, by a blocked QR factorisation.

    Each block of rows (its ``C_i^T`` computed from its own attitudes) is stacked under the factor of the rows
    before and factored again (TSQR, as :class:`~trimag._core.qr.BlockedQR` does), so
    only (block, 13) arrays are formed.

    Parameters
    ----------
    B : ndarray, shape (N, 3)
        Measured fields.
    attitude : Rotation, N rotations (body -> NED)
    block : int, optional
        Rows per block (default: a QR panel of 13 columns, :func:`~trimag._core.qr.panel_rows`, factored from
        cache).

    Returns
    -------
    ndarray, shape (min(N, 13), 13)
        Upper-triangular (trapezoidal when N < 13) ``R`` with ``[D10 | B] = Q R``, ``Q`` (N, min(N, 13)) with
        orthonormal columns: ``R[:10, :10]`` is the factor of ``D10`` (same singular values and column norms) and
        ``R[:10, 10:] = Q_1^T B``.
    """
    n = len(B)
    R = np.zeros((0, 13))
    for rows in row_blocks(n, rows=block or panel_rows(13)):
        m, k = rows.stop - rows.start, len(R)
        stacked = np.empty((k + m, 13), order="F")  # LAPACK's layout
        stacked[:k] = R
        stacked[k:, :9] = attitude[rows].inv().as_matrix().reshape(m, 9)  # rows (b, j) of C^T
        stacked[k:, 9] = 1.0
        stacked[k:, 10:] = B[rows]
        R = np.asarray(np.linalg.qr(stacked, mode="r"), dtype=np.float64)
    return R


class _ReducedProjection:
    """Variable projection of the background direction on the 13-row factor of ``[D10 | B]``.

    ``A(h) = [C_i^T h, 1] = D10 E(h)`` with ``E(h)`` (10, 4) linear in ``h``; with ``[D10 | B] = Q R`` (``Q``
    orthonormal columns spanning both), ``B - A(h) X = Q (R[:, 10:] - R[:, :10] E(h) X)`` for every ``h`` and
    ``X``: the least-squares ``X``, the residual norm and the Jacobian (up to the same ``Q``) follow from the
    13 x 4 matrix ``A_s(h) = R[:, :10] E(h)``. Nothing here depends on N.

    Parameters
    ----------
    R : ndarray, shape (r, 13)
        From :func:`_factor_background_design`.
    magnitude : float
        ``|H_n|``.
    h0 : ndarray, shape (3,)
        Unit start direction; ``p = (p0, p1)`` parametrises ``h(p) = magnitude v / |v|``,
        ``v = h0 + p0 e1 + p1 e2`` (``e1``, ``e2`` orthonormal, perpendicular to ``h0``).
    """

    def __init__(self, R: NDArray[np.float64], magnitude: float, h0: NDArray[np.float64]) -> None:
        self.G = np.ascontiguousarray(R[:, :9]).reshape(len(R), 3, 3)  # A_s[:, b] = G[:, b, :] @ h
        self.ones = R[:, 9].copy()  # the constant column of A_s (E's last column is e_9)
        self.Bs = R[:, 10:].copy()  # Q^T B
        self.magnitude = float(magnitude)
        self.h0 = np.asarray(h0, dtype=np.float64)
        self.e1, self.e2 = _orthonormal_complement(self.h0)

    def design(self, h: NDArray[np.float64]) -> NDArray[np.float64]:
        """``A_s(h) = R[:, :10] E(h)``, shape (r, 4)."""
        return np.column_stack([self.G @ h, self.ones])

    def background(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """``h(p) = magnitude v / |v|``, shape (3,)."""
        v = self.h0 + p[0] * self.e1 + p[1] * self.e2
        return np.asarray(self.magnitude * (v / np.linalg.norm(v)), dtype=np.float64)

    def background_derivative(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """``dh / dp_k`` as rows, shape (2, 3): ``magnitude (I - u u^T) e_k / |v|`` with ``u = v / |v|``."""
        v = self.h0 + p[0] * self.e1 + p[1] * self.e2
        nv = float(np.linalg.norm(v))
        u = v / nv
        E = np.stack([self.e1, self.e2])  # (2, 3)
        return np.asarray(self.magnitude * (E - np.outer(E @ u, u)) / nv, dtype=np.float64)

    def residual_matrix(self, h: NDArray[np.float64]) -> NDArray[np.float64]:
        """``R[:, 10:] - A_s(h) X(h)`` (r, 3), ``X(h)`` the least-squares solution: its Frobenius norm equals
        ``min_X |B - A(h) X|_F`` on the full data."""
        A = self.design(h)
        X, *_ = np.linalg.lstsq(A, self.Bs, rcond=None)
        return np.asarray(self.Bs - A @ X, dtype=np.float64)

    def residual(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """The projected residual at ``p`` as a vector (3 r,)."""
        return self.residual_matrix(self.background(p)).ravel()

    def jacobian(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """Exact variable-projection Jacobian (Golub & Pereyra 1973) of :meth:`residual`, shape (3 r, 2).

        For every right-hand side ``b`` (column of ``R[:, 10:]``) with ``x = A^+ b`` and ``r = b - A x``:
        ``dr / dp_k = -(P_perp dA_k x + (A^+)^T dA_k^T r)``, ``P_perp = I - A A^+``,
        ``dA_k = [G dh_k, 0]`` (the constant column does not move).
        """
        h = self.background(p)
        A = self.design(h)
        pinv = np.linalg.pinv(A)  # (4, r)
        X = pinv @ self.Bs  # (4, 3)
        res = self.Bs - A @ X  # (r, 3)
        P_perp = np.eye(len(A)) - A @ pinv
        dh = self.background_derivative(p)
        J = np.empty((res.size, 2))
        for k in range(2):
            dA = np.column_stack([self.G @ dh[k], np.zeros(len(A))])
            J[:, k] = -(P_perp @ (dA @ X) + pinv.T @ (dA.T @ res)).ravel()
        return J


def _per_sample_source(H_n: NDArray[np.float64]) -> str:
    """A per-sample background (N, 3) described in one line: its mean, spread and magnitude range."""
    F = np.linalg.norm(H_n, axis=1)
    return (f"per-sample background NED, mean {np.round(H_n.mean(axis=0), 6).tolist()}, peak-to-peak "
            f"{np.round(np.ptp(H_n, axis=0), 6).tolist()} (|H_n| {F.min():.6g} to {F.max():.6g})")


def fit_with_background(
    H_m: ArrayLike, attitude: Rotation, magnitude: float, *, max_iter: int = 50
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], dict[str, Any]]:
    """Fit ``K``, ``c`` and the background ``H_n`` (NED) jointly, with ``|H_n| = magnitude``.

    ``K C_i^T H_n`` is linear in the 27 products ``K[a, b] H_n[j]``: a 10-unknown linear least squares per
    axis on the entries of ``C_i^T`` gives them, and the rank-1 factorisation (SVD) of the 9 x 3 matrix
    ``vec(K) H_n^T`` gives the start (:func:`_background_start`). The direction of ``H_n`` is then refined by
    variable projection (``K``, ``c`` solved linearly for each trial direction; Levenberg-Marquardt,
    :func:`trimag._core.solve.levenberg_marquardt`).

    Both steps work on one blocked QR factorisation ``[D10 | B] = Q R`` (N x 13, ``D10 = [vec(C_i^T), 1]``;
    :func:`_factor_background_design`), taken once: memory O(block x 13), and every later step is independent
    of N. The linear start is ``R11 X = R12`` (the least-squares solution of ``D10 X = B``; ``R11`` has the
    singular values and column norms of ``D10``, so also its condition number). As ``A(h) = [C_i^T h, 1] =
    D10 E(h)`` with ``E(h)`` (10 x 4) linear in ``h``, ``min_X |B - A(h) X|_F = min_X |R[:, 10:] -
    R[:, :10] E(h) X|_F``: the projected residual has 13 x 3 entries instead of N x 3 (``Q`` times the small one,
    so the same norm, Jacobian products ``J^T J``, ``J^T r`` and Levenberg-Marquardt steps).

    The Jacobian is analytic: the exact variable-projection Jacobian of Golub & Pereyra,
    ``J_k = -(P_perp dA_k X + (A^+)^T dA_k^T r)`` (see :class:`_ReducedProjection`), not Kaufman's approximation
    (which drops the second term). Kaufman's has the same gradient ``J^T r`` and so the same minimum, but a
    different ``J^T J``, hence other Levenberg-Marquardt steps and iteration counts than the finite-difference
    Jacobian of the exact residual used before; on a 13 x 4 system the second term costs nothing.

    Parameters
    ----------
    H_m : array_like, shape (N, 3)
        Measured fields, body frame.
    attitude : Rotation, N rotations (body -> NED)
    magnitude : float
        ``|H_n|``, in the unit of ``H_m`` (the scale gauge).
    max_iter : int
        At most ``3 max_iter`` residual evaluations of the refinement (``least_squares``' ``max_nfev``;
        Jacobian evaluations are not counted).

    Returns
    -------
    K (3, 3), c (3,), H_n (3,), info
        ``info``: ``linear_condition_number`` (the 10-column design), ``condition_number`` (final
        ``[H_b, 1]``), ``iterations`` (residual evaluations of the refinement), ``converged``,
        ``background_start`` and the :func:`solve_interference` entries.

    Raises
    ------
    TrimagInputError
        ``H_m`` not (N, 3), or ``attitude`` not N rotations.
    IdentifiabilityError
        The attitudes cannot separate ``K`` from ``H_n`` (too few or too similar).
    """
    B = np.asarray(H_m, dtype=np.float64)
    if B.ndim != 2 or B.shape[1] != 3:
        raise TrimagInputError(f"H_m must have shape (N, 3), got {B.shape}")
    _check_attitude(attitude, len(B))
    R = _factor_background_design(B, attitude)
    h0, cond_lin = _background_start(R)
    proj = _ReducedProjection(R, magnitude, h0)
    res = levenberg_marquardt(
        proj.residual, np.zeros(2), jac=proj.jacobian, xtol=1e-14, ftol=1e-14, max_nfev=max_iter * 3
    )
    H_n = proj.background(res.x)
    K, c, info = solve_interference(B, body_field(attitude, H_n))
    if np.linalg.det(K) < 0:  # sign gauge: det(K) > 0
        H_n = -H_n
        K, c, info = solve_interference(B, body_field(attitude, H_n))
    info.update(
        {
            "linear_condition_number": cond_lin,
            "iterations": int(res.nfev),
            "converged": bool(res.success),
            "background_start": (magnitude * h0).tolist(),
        }
    )
    return K, c, H_n, info


def _background_start(R: NDArray[np.float64]) -> tuple[NDArray[np.float64], float]:
    """The linear start of :func:`fit_with_background` from the triangular factor ``R`` of ``[D10 | B]``: the
    direction of ``H_n`` (3,), unit, from the rank-1 factorisation of ``vec(K) H_n^T`` (sign: ``det K > 0``), and the
    condition number of ``D10``."""
    R11, R12 = R[:10, :10], R[:10, 10:]  # fewer rows when N < 10: the same singular values as D10
    cond_lin, _, _ = design_condition(R11)
    if not np.isfinite(cond_lin) or cond_lin > CONDITION_ERROR:
        raise IdentifiabilityError(
            f"the attitudes cannot separate K from the background field (condition number {cond_lin:.3g}); "
            "record the vehicle turning about all three axes, or give the background vector"
        )
    X, *_ = np.linalg.lstsq(R11, R12, rcond=None)  # (10, 3): lstsq(D10, B)
    Z = X[:9].T.reshape(9, 3)  # rows (a, b), columns j: K[a, b] * H_n[j]
    u, sv, vt = np.linalg.svd(Z, full_matrices=False)
    h0 = vt[0]
    K0 = (sv[0] * u[:, 0]).reshape(3, 3)
    if np.linalg.det(K0) < 0:
        h0 = -h0
    return h0, cond_lin


def _background_magnitude(reference: Any, estimate_background: bool) -> float | None:
    """``|H_n|`` a joint background fit is scaled to: a given magnitude (a number or a constant
    :class:`ScalarReference`), the magnitude of a given background vector, or None (the gauge ``det K = 1``).
    A magnitude without ``estimate_background`` is refused: the fit needs the background's direction."""
    if isinstance(reference, ScalarReference) or (reference is not None and np.ndim(reference) == 0):
        if not estimate_background:
            raise TrimagInputError("linear-vector needs a background VECTOR (N, E, D), not a magnitude (or "
                                   "`option estimate_background=true`, which takes a magnitude as the scale)")
        values = reference.values if isinstance(reference, ScalarReference) else np.array([float(reference)])
        if values is None:
            return None
        if not (np.all(np.isfinite(values)) and np.ptp(values) <= 1e-9 * np.abs(values).max() and values[0] > 0):
            raise TrimagInputError("`estimate_background` takes one positive field magnitude as its scale; got "
                                   "a per-sample or non-positive magnitude")
        return float(values[0])
    if reference is None or np.ndim(reference) == 2:
        return None
    return float(np.linalg.norm(as_vector(reference)))


def _raw_scale(B: NDArray[np.float64]) -> float:
    """A provisional ``|H_n|`` for the joint fit before its ``det K = 1`` scaling: the RMS distance of the samples
    from their mean (any positive number would do; this one keeps ``K`` near unit size)."""
    return float(np.sqrt(np.mean(np.sum((B - B.mean(axis=0)) ** 2, axis=1)))) or 1.0


class LinearVector(Estimator):
    """Paper C's 12-coefficient compensation from attitudes and a background field vector.

    ``fit(H_m, reference=H_n, attitude=R)`` with ``H_m`` (N, 3) measured on the vehicle, ``H_n`` (3,) the
    background field in NED (same unit) and ``R`` the N attitudes (body -> NED). The result's
    ``matrix = inv(K)`` and ``offset = c``, so ``cal.apply(H_m) = inv(K) (H_m - c)`` is the compensated
    body-frame field.

    Parameters
    ----------
    model : str
        ``"interference12"``.
    estimate_background : bool
        Fit ``H_n`` jointly. ``K`` and ``H_n`` share one scale: ``|H_n|`` is the given magnitude (``reference``
        a number), the magnitude of a given background vector (its direction is not used), or, when
        ``reference`` is None, set by the gauge ``det K = 1`` (``|H_n|`` is then the mean corrected magnitude).
        Use when no iron-free run or trustworthy vector exists and the attitudes cover all three axes.
    max_iter : int
        Iteration limit of the joint fit.
    """

    name = "linear-vector"
    models = ("interference12",)
    reference_kind = "vector"
    requires_reference = True

    def __init__(self, model: str = "interference12", estimate_background: bool = False, max_iter: int = 50):
        self.model = model
        self.estimate_background = estimate_background
        self.max_iter = max_iter

    def _min_samples(self, model: str) -> int:
        return 4

    def _residual_target(self, corrected: NDArray[np.float64], reference: Any, ref_value: Any) -> Any:
        if reference is not None and np.ndim(reference) == 2:  # a per-sample background: its magnitudes
            return np.linalg.norm(np.asarray(reference, dtype=np.float64), axis=1)
        return float(ref_value)

    def _fit(
        self, B: NDArray[np.float64], reference: Any, *, model: str, units: str, attitude: Any
    ) -> Calibration:
        att = _check_attitude(attitude, len(B))
        if reference is None and not self.estimate_background:
            raise TrimagInputError(
                "linear-vector needs the background field vector H_n (N, E, D) in the data's unit: "
                "`background_ned=N,E,D`, `igrf_spec=LAT,LON,ALT_M,DATE`, or `background_run=FILE` "
                "(or `option estimate_background=true`)"
            )
        magnitude = _background_magnitude(reference, self.estimate_background)
        diag: dict[str, Any] = {"background_fitted": bool(self.estimate_background)}
        if self.estimate_background and reference is not None and np.ndim(reference) == 2:
            raise TrimagInputError(
                "`estimate_background` fits one background vector; a per-sample background is used as given: "
                "drop the option, or give one vector"
            )
        if self.estimate_background:
            K, c, H_n, info = fit_with_background(B, att, magnitude or _raw_scale(B), max_iter=self.max_iter)
            if magnitude is None:  # the scale gauge det(K) = 1: |H_n| is then the mean corrected magnitude
                s = float(np.cbrt(np.linalg.det(K)))
                K, H_n = K / s, H_n * s
                D = np.concatenate([np.full(9, 1.0 / s), np.ones(3)])  # K / s; c unchanged
                info = {**info, "covariance": info["covariance"] * np.outer(D, D)}
                scale_src = "det(K) = 1: |H_n| is the mean corrected magnitude"
            elif np.ndim(reference) == 0 or isinstance(reference, ScalarReference):
                scale_src = "the given magnitude"
            else:
                scale_src = "the magnitude of the given background; its direction is not used"
            source = f"fitted background NED {np.round(H_n, 6).tolist()} (|H_n| {np.linalg.norm(H_n):.6g}: {scale_src})"
            diag["background_given"] = (None if reference is None or np.ndim(reference) == 0
                                        or isinstance(reference, ScalarReference) else as_vector(reference).tolist())
            diag["background_scale"] = scale_src
            H_b = body_field(att, H_n)
        else:
            H_n = as_background(reference, len(B))
            H_b = body_field(att, H_n)
            K, c, info = solve_interference(B, H_b)
            source = f"background NED {np.round(H_n, 6).tolist()}" if H_n.ndim == 1 else _per_sample_source(H_n)
        F_i = np.linalg.norm(H_n, axis=-1)  # () or (N,)
        per_sample = H_n.ndim == 2
        matrix = np.asarray(np.linalg.inv(K), dtype=np.float64)
        ss_before, ss_after = _vector_sum_squares(B, H_b, matrix, c)
        diag.update(
            {
                "condition_number": info["condition_number"],
                "n_attitudes": info["n_attitudes"],
                "background_ned": (H_n.mean(axis=0) if per_sample else H_n).tolist(),
                "background_per_sample": per_sample,
                "residual_rms_axis": info["residual_rms_axis"],
            }
        )
        for key in ("linear_condition_number", "background_start"):
            if key in info:
                diag[key] = info[key]
        n = len(B)
        extra = {
            "vector_rms_before_axis": np.sqrt(ss_before / n).tolist(),
            "vector_rms_after_axis": np.sqrt(ss_after / n).tolist(),
            "vector_rms_before": float(np.sqrt(np.sum(ss_before) / n)),
            "vector_rms_after": float(np.sqrt(np.sum(ss_after) / n)),
        }
        ref = ScalarReference(np.broadcast_to(F_i, (len(B),)).astype(np.float64), source, units)
        return build_calibration(
            B, matrix, c, model=model, method=self.name, units=units, reference=ref,
            params=Interference12.from_K_c(K, c).as_dict(), iterations=int(info.get("iterations", 1)),
            converged=bool(info.get("converged", True)),
            uncertainty=make_uncertainty(
                info["names"], covariance=info["covariance"],
                basis="per-axis least-squares standard errors: s_a^2 (A^T A)^-1 for each sensor axis a, A = [H_b, 1]",
            ),
            diagnostics=diag, extra_stats=extra,
        )
