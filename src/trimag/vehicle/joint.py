"""Joint fit of a vector magnetometer (``interference12``, with its regressor and eddy-current terms) and a
scalar magnetometer on the same vehicle (issue 21, item 5; docs/method-tolles-lawson.md, "Past Tolles–Lawson").

The vector model's reference is the background rotated by the attitudes, whose errors (an INS at 0.05 deg is
~45 nT at 50 000 nT) limit ``K``; a compensated scalar magnetometer (optically pumped, Tolles–Lawson-compensated:
``trimag apply`` of a ``tolles-lawson`` calibration, column ``S_compensated``) knows the magnitude to ~0.1 nT
without attitudes. The joint fit stacks both kinds of rows, in the corrected (body) frame:

    y_i = M (H_m,i - c - sum_j k_j (u_ij - mean_j))          (M = K^-1; the regressors u include dH_m/dt)
    vector rows:     (y_i - C_i^T H_n,i) / sigma_v            (3 per sample)
    magnitude rows:  (|y_i| - (S_i - d)) / sigma_s            (1 per sample; d: the scalar's free offset, because a
                                                               band-passed TL fit leaves its constant open)

``sigma_v`` and ``sigma_s`` are the RMS residuals of each kind of row, estimated from the start (the vector-only
fit) and re-estimated once after the first solve. Gauss-Newton / Levenberg-Marquardt
(:func:`trimag._core.solve.gauss_newton_then_lm`) from the vector-only fit; covariance ``(J^T J)^-1`` of the
weighted rows times their reduced chi-square. Measured (benchmarks/joint_fit.py): on simulated boxes with 0.05 deg
INS errors the held-out magnitude error falls from ~10 nT (vector only) to ~1.7 nT.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._core.solve import gauss_newton_then_lm
from ..calibration import Calibration, make_uncertainty
from ..errors import TrimagInputError

__all__ = ["fit_joint_scalar"]

_AXES = ("x", "y", "z")


class _Joint:
    """Residuals (4N,) and Jacobian (4N, P) of the joint rows in normalised units (module docstring).

    Parameters ``p``: ``M`` (9, row-major), ``c`` (3), the free regressor coefficients (``free`` order: regressor
    j, axis a), ``d`` (1).
    """

    def __init__(self, H_m: NDArray[np.float64], U: NDArray[np.float64], free: NDArray[np.bool_],
                 H_b: NDArray[np.float64], S: NDArray[np.float64]) -> None:
        self.H_m, self.U, self.free, self.H_b, self.S = H_m, U, free, H_b, S
        self.jf, self.af = np.nonzero(free)  # (regressor, axis) of each free coefficient
        self.wv = self.ws = 1.0

    def unpack(self, p: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64],
                                                       NDArray[np.float64], float]:
        Kr = np.zeros(self.free.shape)
        Kr[self.jf, self.af] = p[12:-1]
        return p[:9].reshape(3, 3), p[9:12], Kr, float(p[-1])

    def parts(self, p: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        M, c, Kr, _ = self.unpack(p)
        z = self.H_m - c - self.U @ Kr
        y = z @ M.T
        return z, y, np.sqrt(np.einsum("ij,ij->i", y, y))

    def residual(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        _, y, mag = self.parts(p)
        return np.concatenate([self.wv * (y - self.H_b).ravel(), self.ws * (mag - self.S + p[-1])])

    def jacobian(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        M = p[:9].reshape(3, 3)
        z, y, mag = self.parts(p)
        n, P = len(z), len(p)
        Jy = np.zeros((n, 3, P))  # dy_i / dp
        for a in range(3):
            Jy[:, a, 3 * a : 3 * a + 3] = z
        Jy[:, :, 9:12] = -M[None, :, :]
        for q, (j, k) in enumerate(zip(self.jf, self.af, strict=True)):
            Jy[:, :, 12 + q] = -self.U[:, j, None] * M[None, :, k]
        unit = y / mag[:, None]
        Jm = np.einsum("ik,ikp->ip", unit, Jy)
        Jm[:, -1] = 1.0
        return np.concatenate([self.wv * Jy.reshape(3 * n, P), self.ws * Jm])


def fit_joint_scalar(
    base: Calibration,
    B: ArrayLike,
    scalar: ArrayLike,
    *,
    attitude: Any,
    background: ArrayLike,
    regressors: Mapping[str, ArrayLike] | None = None,
    scalar_source: str = "scalar",
    max_iter: int = 50,
) -> Calibration:
    """Refit an ``interference12`` calibration jointly with a compensated scalar magnetometer (module docstring).

    Parameters
    ----------
    base : Calibration
        The vector-only fit of the same samples (model ``interference12``, with or without regressor / eddy terms).
    B : array_like, shape (N, 3)
        The vector magnetometer's samples, data unit.
    scalar : array_like, shape (N,)
        The compensated scalar magnetometer at the same samples, data unit.
    attitude : scipy.spatial.transform.Rotation
        The N attitudes (body -> NED).
    background : array_like, shape (3,) or (N, 3)
        The background field (NED) of ``base``'s fit, data unit.
    regressors : mapping str -> (N,), optional
        The values of ``base``'s regressors (required when it has terms).
    scalar_source : str
        Where the scalar came from (recorded).

    Returns
    -------
    Calibration
        The same model and terms, refitted; ``diagnostics["joint_scalar"]``: the scalar's offset ``d``, the RMS of
        the vector and magnitude rows (held-in), the weights, and the vector-only values for comparison.
    """
    from scipy.spatial.transform import Rotation

    from ..fields.attitude import body_field
    from ..models import get_model

    if base.model != "interference12":
        raise TrimagInputError(f"the joint scalar fit refines an interference12 calibration; got {base.model!r}")
    X = np.asarray(B, dtype=np.float64)
    n = len(X)
    S = np.asarray(scalar, dtype=np.float64)
    if X.shape != (n, 3) or S.shape != (n,) or not np.isfinite(S).all():
        raise TrimagInputError(f"the scalar magnetometer needs one finite value per sample ({n}); got {S.shape}")
    if not isinstance(attitude, Rotation) or attitude.single or len(attitude) != n:
        raise TrimagInputError("the joint scalar fit needs the attitude of every sample (a Rotation)")
    H_b = body_field(attitude, np.asarray(background, dtype=np.float64))
    expected = float(np.median(np.linalg.norm(H_b, axis=1)))
    if not 0.5 < float(np.median(S)) / expected < 2.0:  # the magnitudes of one field agree to a few percent
        raise TrimagInputError(
            f"the scalar magnetometer (median {float(np.median(S)):.6g}) is not in the vector data's unit (background "
            f"magnitude {expected:.6g} {base.units}): convert the column, or check that it is the compensated scalar"
        )
    terms = base.regressors
    names, U, Kr0, free = _regressor_terms(terms, regressors, n)
    # normalised units: fields over their RMS magnitude, regressors over their standard deviations
    scale = float(np.sqrt(np.mean(np.sum(X**2, axis=1)))) or 1.0
    u_scale = U.std(axis=0) if U.shape[1] else np.ones(0)
    u_scale[u_scale == 0] = 1.0
    problem = _Joint(X / scale, U / u_scale, free, H_b / scale, S / scale)
    M0 = np.asarray(base.matrix, dtype=np.float64)
    c0 = np.asarray(base.offset, dtype=np.float64) / scale
    Kn0 = Kr0 * (u_scale / scale)[:, None]
    mag0 = np.linalg.norm((problem.H_m - c0 - problem.U @ Kn0) @ M0.T, axis=1)
    p = np.concatenate([M0.ravel(), c0, Kn0[free], [float(np.mean(problem.S - mag0))]])
    start = _rms_parts(problem, p, scale)
    converged, nfev = True, 0
    for _ in range(2):  # weights from each kind of row's RMS residual, re-estimated once
        _, rms_v, rms_s = _rms_parts(problem, p, 1.0)
        problem.wv, problem.ws = 1.0 / max(rms_v, 1e-15), 1.0 / max(rms_s, 1e-15)
        res = gauss_newton_then_lm(problem.residual, problem.jacobian, p, max_steps=max_iter,
                                   lm_options={"xtol": 1e-12, "ftol": 1e-12, "gtol": 1e-12, "max_nfev": 20 * max_iter})
        p = np.asarray(res.x, dtype=np.float64)
        converged, nfev = converged and bool(res.success), nfev + int(res.nfev)
    chi2, cov_n = _covariance(problem, p)
    M, c_n, Kn, d_n = problem.unpack(p)
    offset = c_n * scale
    Kr = Kn * (scale / u_scale)[:, None] if len(names) else Kn
    param_std = _param_std(M, cov_n, scale, u_scale, names, free)
    _, rms_v, rms_s = _rms_parts(problem, p, scale)
    joint = {
        "scalar": scalar_source, "scalar_offset_d": d_n * scale,
        "model": "rows: M (H_m - c - sum_j k_j u_j) - C^T H_n (vector), |M (...)| - (S - d) (magnitude), each "
                 "weighted by 1 / its RMS residual",
        "vector_rms_axis_after": rms_v, "scalar_rms_after": rms_s,
        "vector_only": {"vector_rms_axis_after": start[1], "scalar_rms_after": start[2]},
        "sigma_vector": 1.0 / problem.wv * scale, "sigma_scalar": 1.0 / problem.ws * scale,
        "reduced_chi2": chi2, "evaluations": nfev, "converged": converged,
    }
    new_terms = None
    if terms is not None:
        new_terms = {**dict(terms), "coefficients": Kr.tolist()}
    stats = _stats(base, np.linalg.norm(problem.parts(p)[1], axis=1) * scale, H_b, rms_v, converged)
    uncertainty = make_uncertainty(
        list(param_std), param_std=list(param_std.values()), gauge="K, c", noise_std=1.0 / problem.wv * scale,
        basis="joint vector + scalar rows: chi2_red (J^T J)^-1 of the weighted rows (trimag.vehicle.joint); K by the "
              "delta method from M = K^-1",
    )
    diagnostics = {**dict(base.diagnostics), "joint_scalar": joint}
    return Calibration.from_matrix_offset(
        M, offset, units=base.units, model=base.model, method=base.method,
        params=get_model("interference12").from_matrix_offset(M, offset).as_dict(), reference=base.reference,
        stats=stats, uncertainty=uncertainty, diagnostics=diagnostics, regressors=new_terms,
    )


def _regressor_terms(
    terms: Mapping[str, Any] | None, regressors: Mapping[str, ArrayLike] | None, n: int
) -> tuple[list[str], NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """The base fit's regressor terms: ``(names, centred values (n, m), coefficients (m, 3), free (m, 3))``
    (an ``eddy=3`` term is free on its own axis only); empty without terms."""
    if terms is None:
        return [], np.zeros((n, 0)), np.zeros((0, 3)), np.zeros((0, 3), dtype=bool)
    if regressors is None:
        raise TrimagInputError(f"give the values of the regressors {', '.join(terms['names'])}")
    names = list(terms["names"])
    U = np.column_stack([np.asarray(regressors[k], dtype=np.float64) for k in names]) - np.asarray(terms["means"])
    eddy = terms.get("eddy") or {}
    free = np.ones((len(names), 3), dtype=bool)
    for j, name in enumerate(names):
        if eddy and name in eddy.get("names", ()) and int(eddy.get("terms", 9)) == 3:
            free[j] = [a == eddy["names"].index(name) for a in range(3)]
    return names, U, np.asarray(terms["coefficients"], dtype=np.float64), free


def _covariance(problem: _Joint, p: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
    """``(reduced chi2, chi2 (J^T J)^-1)`` of the weighted rows at ``p`` (normalised units; Jacobi-scaled inverse)."""
    r, J = problem.residual(p), problem.jacobian(p)
    chi2 = float(r @ r) / max(len(r) - len(p), 1)
    d_col = np.sqrt(np.einsum("ij,ij->j", J, J))
    d_col[d_col == 0] = 1.0
    return chi2, chi2 * np.linalg.inv((J.T @ J) / np.outer(d_col, d_col)) / np.outer(d_col, d_col)


def _param_std(
    M: NDArray[np.float64], cov_n: NDArray[np.float64], scale: float, u_scale: NDArray[np.float64],
    names: list[str], free: NDArray[np.bool_],
) -> dict[str, float]:
    """Standard deviations: ``K = M^-1`` by the delta method, ``c`` and the regressor coefficients in data units
    (0 for a coefficient held at zero)."""
    K = np.linalg.inv(M)
    G = -np.kron(K, K.T)
    std_K = np.sqrt(np.clip(np.diag(G @ cov_n[:9, :9] @ G.T), 0, None))
    std = np.sqrt(np.clip(np.diag(cov_n), 0, None))
    param_std = {f"k{i + 1}{j + 1}": float(std_K[3 * i + j]) for i in range(3) for j in range(3)}
    param_std.update({f"c{k + 1}": float(std[9 + k] * scale) for k in range(3)})
    for q, (j, a) in enumerate(zip(*np.nonzero(free), strict=True)):
        param_std[f"k_{names[j]}_{_AXES[a]}"] = float(std[12 + q] * scale / u_scale[j])
    for name in names:
        for axis in _AXES:
            param_std.setdefault(f"k_{name}_{axis}", 0.0)
    return param_std


def _stats(
    base: Calibration, corrected_mag: NDArray[np.float64], H_b: NDArray[np.float64], rms_v: float, converged: bool
) -> dict[str, Any]:
    """The base fit's statistics with the joint fit's: magnitude errors against ``|H_b|``, the vector RMS."""
    err = corrected_mag - np.linalg.norm(H_b, axis=1)
    stats = dict(base.stats)
    stats.update({"rms_after": float(np.sqrt(np.mean(err**2))), "max_abs_after": float(np.max(np.abs(err))),
                  "p2p_after": float(np.ptp(corrected_mag))})
    stats.update({"vector_rms_after": float(rms_v * np.sqrt(3)),
                  "vector_rms_after_vector_only": base.stats.get("vector_rms_after"),
                  "converged": bool(base.stats.get("converged", True)) and converged,
                  "std_norm_after": float(np.std(corrected_mag)), "mean_norm_after": float(np.mean(corrected_mag))})
    return stats


def _rms_parts(problem: _Joint, p: NDArray[np.float64], scale: float) -> tuple[float, float, float]:
    """``(0, vector RMS per axis, magnitude RMS)`` of the unweighted rows, times ``scale``."""
    _, y, mag = problem.parts(p)
    rv = y - problem.H_b
    rs = mag - problem.S + p[-1]
    return 0.0, float(np.sqrt(np.mean(rv**2))) * scale, float(np.sqrt(np.mean(rs**2))) * scale
