"""The Cramér–Rao lower bound of the scalar (attitude-independent) calibration problem.

Measurement model (``docs/accuracy.md``): the sensor sees the true body field ``y_i = F u_i`` (``|u_i| = 1``,
``F`` the field magnitude) through the distortion of an error model, with white Gaussian noise of standard
deviation ``sigma`` on each raw axis,

    x_i = inv(W(theta)) y_i + b(theta) + e_i,        e_i ~ N(0, sigma^2 I_3),

and only the magnitude constraint ``|W (x_i - b)| = F`` links the data to the parameters (the directions
``u_i`` are unknown nuisance parameters). Eliminating the two nuisance angles of each sample (Schur complement
of the full Fisher information) leaves one scalar piece of information per sample, along the normal of the
ellipsoid at ``x_i``:

    J(theta) = sigma^-2 sum_i  a_i a_i^T / |W^T n_i|^2,      a_i = d g_i / d theta,
    g_i = |W (x_i - b)| - F,   n_i = W (x_i - b) / |W (x_i - b)|.

``|W^T n_i|`` is the length of the gradient of ``g`` with respect to ``x``: ``g_i / |W^T n_i|`` is, to first
order, the signed distance of the sample from the ellipsoid, whose variance is ``sigma^2``. The test
``tests/quality/test_crlb.py`` checks this reduced form against the brute-force Fisher information of the full model
(directions included) computed by finite differences.

Gauges
------
* ``ellipsoid``: a magnitude cannot see a rotation on the left of ``W``; the bound is stated for the
  upper-triangular ``W`` (6 entries) and the offset (3).
* other models use their own parameters (``ErrorModel.param_names()``).
* unknown magnitude: ``F`` becomes a parameter. When the model can scale ``W`` freely (``ellipsoid``,
  ``scalar9``) the scale of ``W`` and ``F`` trade off, and the gauge ``det W = det W_true`` is imposed through
  the constrained bound ``C = U (U^T J U)^-1 U^T`` (``U`` spans the null space of the constraint's gradient);
  models with a fixed scale (``ortho-gain``: ``w33 = 1``) need no constraint.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._core.rowwise import row_dot, scratch
from .._core.sphere import fibonacci_sphere
from ..errors import IdentifiabilityError, TrimagInputError
from ..models.base import ErrorModel
from ..models.ellipsoid import UPPER

__all__ = [
    "UPPER_NAMES",
    "Bound",
    "EllipsoidGeometry",
    "crlb",
    "ellipsoid_fisher",
    "ellipsoid_geometry",
    "fisher_information",
    "parametrisation",
    "predicted_errors",
]

#: Parameter names of the ``ellipsoid`` model in the upper-triangular gauge.
UPPER_NAMES = ("w11", "w12", "w13", "w22", "w23", "w33", "hard_iron_x", "hard_iron_y", "hard_iron_z")

Param = Callable[[NDArray[np.float64]], tuple[NDArray[np.float64], NDArray[np.float64]]]


@dataclass(frozen=True)
class Bound:
    """A Cramér–Rao bound (or a Fisher covariance at an estimate).

    Attributes
    ----------
    names : tuple of str
        Parameter names, in the order of ``covariance`` (``"F"`` last when the magnitude is unknown).
    covariance : ndarray, shape (p, p)
        Lower bound on the covariance of any unbiased estimator, in the parameters' units.
    std : ndarray, shape (p,)
        ``sqrt(diag(covariance))``.
    field_rms : float
        Predicted RMS error of the corrected field vector over the test directions (field unit), in the gauge of
        the parameters (upper-triangular ``W`` for ``ellipsoid``).
    magnitude_rms : float
        Predicted RMS error of the corrected magnitude over the test directions (field unit).
    fisher : ndarray, shape (p, p)
        The Fisher information (before the gauge constraint).
    info : dict
        ``known_magnitude``, ``gauge``, ``sigma``, ``n_samples``, ``condition_number``.
    """

    names: tuple[str, ...]
    covariance: NDArray[np.float64]
    std: NDArray[np.float64]
    field_rms: float
    magnitude_rms: float
    fisher: NDArray[np.float64]
    info: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """Plain-JSON form: ``{"std": {name: value}, "covariance": [[...]], ...}``."""
        return {
            "names": list(self.names),
            "std": dict(zip(self.names, self.std.tolist(), strict=True)),
            "covariance": self.covariance.tolist(),
            "field_rms": self.field_rms,
            "magnitude_rms": self.magnitude_rms,
            **self.info,
        }


def _upper_param(theta: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    W = np.zeros((3, 3))
    W[UPPER] = theta[:6]
    return W, np.asarray(theta[6:9], dtype=np.float64)


def parametrisation(truth: ErrorModel) -> tuple[tuple[str, ...], NDArray[np.float64], Param]:
    """Parameter names, values and the map ``theta -> (W, b)`` used by the bound for ``truth``'s model.

    ``ellipsoid`` uses the upper-triangular gauge of ``W`` (the correction matrix is replaced by the
    upper-triangular matrix with the same magnitudes); other models use their own parameters.
    """
    if truth.name == "ellipsoid":
        from ..models.ellipsoid import to_upper

        W, b = truth.correction()
        theta = np.concatenate([to_upper(W)[UPPER], b])
        return UPPER_NAMES, theta, _upper_param
    cls = type(truth)

    def fn(theta: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        W, b = cls.from_vector(theta).correction()
        return np.asarray(W, dtype=np.float64), np.asarray(b, dtype=np.float64)

    return tuple(truth.param_names()), truth.as_vector(), fn


def _derivatives(
    param: Param, theta: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """``W``, ``b`` and their derivatives ``dW`` (p, 3, 3), ``db`` (p, 3) by central differences."""
    W, b = param(theta)
    p = len(theta)
    dW = np.empty((p, 3, 3))
    db = np.empty((p, 3))
    for k in range(p):
        h = 1e-6 * max(1.0, abs(float(theta[k])))
        tp, tm = theta.copy(), theta.copy()
        tp[k] += h
        tm[k] -= h
        Wp, bp = param(tp)
        Wm, bm = param(tm)
        dW[k] = (Wp - Wm) / (2 * h)
        db[k] = (bp - bm) / (2 * h)
    return W, b, dW, db


def _field_jacobian(
    X: NDArray[np.float64], W: NDArray[np.float64], b: NDArray[np.float64], dW: NDArray[np.float64],
    db: NDArray[np.float64],
) -> NDArray[np.float64]:
    """``d (W (x - b)) / d theta`` for every row of ``X``: shape (N, 3, p)."""
    e = X - b
    term_w = np.einsum("kij,nj->nik", dW, e)
    term_b = -np.einsum("ij,kj->ik", W, db)  # (3, p)
    return np.asarray(term_w + term_b[None], dtype=np.float64)


@dataclass(frozen=True)
class EllipsoidGeometry:
    """Per-sample quantities of the magnitude model at ``(W, b)`` for raw samples ``X`` (N, 3), stored
    component-major (one contiguous row per component: numpy is 5-10x faster on rows than on (N, 3) columns).

    Attributes
    ----------
    e : ndarray (3, N)
        ``x_i - b``.
    magnitude : ndarray (N,)
        ``|W (x_i - b)|``.
    normal : ndarray (3, N)
        Corrected direction ``n_i = W (x_i - b) / |W (x_i - b)|``.
    gradient : ndarray (3, N)
        ``W^T n_i``: gradient of the magnitude with respect to the raw sample.
    weight : ndarray (N,)
        ``1 / |W^T n_i|^2``: the weight that turns a squared magnitude residual into a squared distance.
    """

    e: NDArray[np.float64]
    magnitude: NDArray[np.float64]
    normal: NDArray[np.float64]
    gradient: NDArray[np.float64]
    weight: NDArray[np.float64]


def ellipsoid_geometry(X: NDArray[np.float64], W: NDArray[np.float64], b: NDArray[np.float64]) -> EllipsoidGeometry:
    """:class:`EllipsoidGeometry` of samples ``X`` (N, 3) under the correction ``W`` (3, 3), offset ``b`` (3,)."""
    X = np.asarray(X, dtype=np.float64)
    e = np.empty((3, len(X)))  # a new array: X (possibly a view of the caller's data) is never written
    np.subtract(X.T, np.asarray(b, dtype=np.float64)[:, None], out=e)
    n = W @ e
    mag = np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
    n /= mag  # the corrected field, normalised in place
    q = W.T @ n
    w = 1.0 / (q[0] * q[0] + q[1] * q[1] + q[2] * q[2])
    return EllipsoidGeometry(e, mag, n, q, w)


def ellipsoid_fisher(
    geometry: EllipsoidGeometry, sigma: float, *, known_magnitude: bool = True
) -> NDArray[np.float64]:
    """:func:`fisher_information` of the ``ellipsoid`` model in the upper-triangular gauge, in closed form.

    ``a_i = d|W (x_i - b)| / d theta`` has the entries ``n_i[r] e_i[c]`` for the upper entry ``(r, c)`` of ``W``
    and ``-(W^T n_i)_m`` for ``b_m`` (and ``-1`` for ``F`` when the magnitude is unknown); the information is
    ``sigma^-2 sum_i w_i a_i a_i^T`` (module docstring). Shape (9, 9), or (10, 10) with ``F`` last.
    """
    g = geometry
    p = 9 if known_magnitude else 10
    # component-major: a[k] is parameter k's derivative for every sample (a reused buffer, trimag._core.rowwise.scratch)
    with scratch(p, len(g.weight)) as a:
        for k, (r, c) in enumerate(zip(*UPPER, strict=True)):
            np.multiply(g.normal[r], g.e[c], out=a[k])
        np.negative(g.gradient, out=a[6:9])
        if not known_magnitude:
            a[9] = -1.0
        a *= np.sqrt(g.weight)  # in place: the information is then one symmetric product
        return np.asarray(a @ a.T / sigma**2, dtype=np.float64)


def fisher_information(
    X: ArrayLike, param: Param, theta: ArrayLike, sigma: float, *, known_magnitude: bool = True
) -> NDArray[np.float64]:
    """Fisher information of the magnitude model at ``theta`` for raw samples on (or near) the ellipsoid.

    Parameters
    ----------
    X : array_like, shape (N, 3)
        Noise-free raw samples (for a bound) or the measured ones (for the covariance at an estimate).
    param : callable
        ``theta -> (W (3, 3), b (3,))``.
    theta : array_like, shape (p,)
    sigma : float
        Noise standard deviation per raw axis (field unit).
    known_magnitude : bool
        If False, one more parameter, ``F``, is appended (last row/column).

    Returns
    -------
    ndarray, shape (p, p) or (p + 1, p + 1)
    """
    X = np.asarray(X, dtype=np.float64)
    th = np.asarray(theta, dtype=np.float64)
    if param is _upper_param:  # the ellipsoid's own gauge: closed form, no finite differences
        W, b = _upper_param(th)
        return ellipsoid_fisher(ellipsoid_geometry(X, W, b), sigma, known_magnitude=known_magnitude)
    W, b, dW, db = _derivatives(param, th)
    G = _field_jacobian(X, W, b, dW, db)  # (N, 3, p)
    y = (X - b) @ W.T
    n = y / np.linalg.norm(y, axis=1, keepdims=True)
    a = np.einsum("ni,nik->nk", n, G)  # d|W(x-b)|/dtheta
    if not known_magnitude:
        a = np.column_stack([a, -np.ones(len(X))])
    grad_x = n @ W  # rows: W^T n
    w = 1.0 / row_dot(grad_x, grad_x)
    return np.asarray((a * w[:, None]).T @ a / sigma**2, dtype=np.float64)


def _scale_is_free(param: Param, theta: NDArray[np.float64]) -> bool:
    """True if some change of ``theta`` scales ``W`` uniformly while keeping ``b`` (scale/F trade-off)."""
    W, _, dW, db = _derivatives(param, theta)
    A = np.vstack([dW.reshape(len(theta), 9).T, db.T])  # (12, p)
    target = np.concatenate([W.ravel(), np.zeros(3)])
    sol, *_ = np.linalg.lstsq(A, target, rcond=None)
    return bool(np.linalg.norm(A @ sol - target) < 1e-6 * np.linalg.norm(target))


def _constrained_inverse(J: NDArray[np.float64], grad: NDArray[np.float64] | None) -> NDArray[np.float64]:
    if grad is None:
        U = np.eye(len(J))
    else:
        _, _, vt = np.linalg.svd(grad[None, :])
        U = vt[1:].T
    M = U.T @ J @ U
    # Jacobi scaling before the singularity test: parameters in different units (a dimensionless matrix, offsets
    # in nT or uT) give eigenvalues that differ by the unit's square, so an unscaled threshold depended on the unit
    d = np.sqrt(np.clip(np.diag(M), 0.0, None))
    if not np.all(d > 0):
        raise IdentifiabilityError(
            "the Fisher information is singular: the directions given cannot identify the model's "
            "parameters; add directions turning the sensor about all three axes"
        )
    Ms = M / np.outer(d, d)
    ev = np.linalg.eigvalsh(Ms)
    if ev[0] <= ev[-1] * 1e-14:
        raise IdentifiabilityError(
            "the Fisher information is singular: the directions given cannot identify the model's "
            "parameters; add directions turning the sensor about all three axes"
        )
    inv = np.linalg.solve(Ms, np.eye(len(Ms))) / np.outer(d, d)
    return np.asarray(U @ inv @ U.T, dtype=np.float64)


def predicted_errors(
    covariance: NDArray[np.float64], param: Param, theta: NDArray[np.float64], X_test: NDArray[np.float64]
) -> tuple[float, float]:
    """Predicted RMS error of the corrected field vector and of its magnitude at raw test points ``X_test``.

    ``covariance`` is (p, p) or (p + 1, p + 1) with the magnitude last (ignored: a corrected field does not
    depend on it).
    """
    p = len(theta)
    C = covariance[:p, :p]
    if param is _upper_param:  # the ellipsoid's own gauge: closed form, no finite differences
        return _upper_predicted_errors(C, theta, X_test)
    W, b, dW, db = _derivatives(param, theta)
    G = _field_jacobian(X_test, W, b, dW, db)
    field_ms = float(np.einsum("nik,nik->", G @ C, G)) / len(G)
    y = (X_test - b) @ W.T
    n = y / np.linalg.norm(y, axis=1, keepdims=True)
    m = np.einsum("ni,nik->nk", n, G)
    mag_ms = float(np.einsum("nk,nk->", m @ C, m)) / len(m)
    return float(np.sqrt(max(field_ms, 0.0))), float(np.sqrt(max(mag_ms, 0.0)))


def _upper_predicted_errors(
    C: NDArray[np.float64], theta: NDArray[np.float64], X_test: NDArray[np.float64]
) -> tuple[float, float]:
    """:func:`predicted_errors` for :func:`_upper_param` (upper-triangular ``W``, then ``b``), in closed form.

    The corrected field ``y = W (x - b)`` has ``dy/dW_rc = e_c u_r`` (``e = x - b``, ``u_r`` the unit vector) and
    ``dy/db = -W``, so ``mean |dy|_C^2 = sum(C * M)`` with ``M`` built from the first two moments of ``e``:
    ``M[rc, r'c'] = [r = r'] <e_c e_c'>``, ``M[rc, m] = -W[r, m] <e_c>``, ``M[m, m'] = (W^T W)[m, m']``. The
    magnitude's derivatives are ``n_r e_c`` and ``-(W^T n)_m`` (``n = y / |y|``), as in :func:`ellipsoid_fisher`.
    """
    W, b = _upper_param(theta)
    e = np.asarray(X_test, dtype=np.float64) - b  # (n, 3); a few hundred test points
    k = len(e)
    ee = e.T @ e / k
    e_mean = e.mean(axis=0)
    rows, cols = UPPER
    M = np.empty((9, 9))
    M[:6, :6] = (rows[:, None] == rows[None, :]) * ee[cols[:, None], cols[None, :]]
    M[:6, 6:] = -W[rows, :] * e_mean[cols, None]
    M[6:, :6] = M[:6, 6:].T
    M[6:, 6:] = W.T @ W
    y = e @ W.T
    n = y / np.sqrt(row_dot(y, y))[:, None]
    a = np.empty((k, 9))
    a[:, :6] = n[:, rows] * e[:, cols]
    a[:, 6:] = -(n @ W)
    field_ms = float(np.sum(C * M))
    mag_ms = float(np.sum((a @ C) * a)) / k
    return float(np.sqrt(max(field_ms, 0.0))), float(np.sqrt(max(mag_ms, 0.0)))


def _test_directions(n: int = 500) -> NDArray[np.float64]:
    return fibonacci_sphere(n)


def _resolve_truth(truth: Any, params: Mapping[str, float] | None) -> ErrorModel:
    if isinstance(truth, ErrorModel):
        return truth
    if isinstance(truth, str):
        from ..models import get_model

        cls = get_model(truth)
        return cls.from_dict(params) if params is not None else cls()
    raise TrimagInputError(f"`truth` must be an ErrorModel or a model name; got {type(truth).__name__}")


def crlb(
    truth: ErrorModel | str,
    directions: ArrayLike,
    sigma: float,
    *,
    magnitude: float = 1.0,
    known_magnitude: bool = True,
    params: Mapping[str, float] | None = None,
    test_directions: ArrayLike | None = None,
) -> Bound:
    """Cramér–Rao lower bound of the scalar calibration problem.

    Parameters
    ----------
    truth : ErrorModel or str
        The true error model (e.g. ``Ellipsoid(...)``, ``Scalar9(...)``), or a model name with ``params``.
    directions : array_like, shape (N, 3)
        True field directions in the body frame at the N samples (normalised internally).
    sigma : float
        Noise standard deviation per raw axis, in the field unit (> 0).
    magnitude : float
        The field magnitude ``F`` in the same unit.
    known_magnitude : bool
        True: ``F`` is given (a reference); False: ``F`` is estimated with the other parameters and the gauge
        ``det W`` fixed when the model has a free scale.
    params : mapping, optional
        Parameters when ``truth`` is a model name.
    test_directions : array_like, shape (M, 3), optional
        Noise-free directions at which the corrected-field error is predicted (default: 500 directions evenly
        spread over the sphere).

    Returns
    -------
    Bound
        ``names``, ``covariance``, ``std``, ``field_rms``, ``magnitude_rms``, ``fisher``, ``info``.

    Examples
    --------
    >>> import numpy as np
    >>> from trimag.models.ellipsoid import Ellipsoid
    >>> from trimag.simulate import uniform_directions
    >>> bound = crlb(Ellipsoid(), uniform_directions(1000, seed=0), 0.01)
    >>> bound.std.shape
    (9,)
    """
    model = _resolve_truth(truth, params)
    if not (np.isfinite(sigma) and sigma > 0):
        raise TrimagInputError(f"`sigma` must be a positive number; got {sigma!r}")
    if not (np.isfinite(magnitude) and magnitude > 0):
        raise TrimagInputError(f"`magnitude` must be a positive number; got {magnitude!r}")
    u = np.asarray(directions, dtype=np.float64)
    if u.ndim != 2 or u.shape[1] != 3 or len(u) == 0:
        raise TrimagInputError(f"`directions` must have shape (N, 3); got {u.shape}")
    u = u / np.linalg.norm(u, axis=1, keepdims=True)
    names, theta, param = parametrisation(model)
    W, b = param(theta)
    D = np.linalg.inv(W)
    X = (magnitude * u) @ D.T + b
    J = fisher_information(X, param, theta, sigma, known_magnitude=known_magnitude)
    grad = None
    gauge = "upper-triangular W" if model.name == "ellipsoid" else "model parameters"
    out_names = tuple(names)
    if not known_magnitude:
        out_names = (*names, "F")
        if _scale_is_free(param, theta):
            _, _, dW, _ = _derivatives(param, theta)
            Winv = np.linalg.inv(W)
            grad = np.concatenate([np.einsum("ij,kji->k", Winv, dW), [0.0]])  # d log det W / d theta
            gauge += ", det W fixed"
    C = _constrained_inverse(J, grad)
    t = u if test_directions is None else np.asarray(test_directions, dtype=np.float64)
    if test_directions is None:
        t = _test_directions()
    t = t / np.linalg.norm(t, axis=1, keepdims=True)
    X_test = (magnitude * t) @ D.T + b
    field_rms, magnitude_rms = predicted_errors(C, param, theta, X_test)
    ev = np.linalg.eigvalsh(J / np.sqrt(np.outer(np.diag(J), np.diag(J))))
    info = {
        "known_magnitude": bool(known_magnitude),
        "gauge": gauge,
        "sigma": float(sigma),
        "n_samples": len(u),
        "condition_number": float(np.sqrt(ev[-1] / ev[0])) if ev[0] > 0 else float("inf"),
    }
    return Bound(out_names, C, np.sqrt(np.clip(np.diag(C), 0, None)), field_rms, magnitude_rms, J, info)
