"""Quick recalibration: keep the shape of an earlier calibration and refit only its offset (issue 20, item 5).

A boat or a rover cannot tumble; after a change of its hard iron (a new battery, a moved cable) it can turn
through a few headings at level. With the correction matrix ``M`` of an earlier calibration (soft iron,
alignment) and its regressor terms kept fixed, the new offset ``b`` is the only unknown (docs/vehicle.md):

    c_i = M (x_i - b)                    corrected field, (3,) per sample (x_i: raw minus the prior's regressor terms)
    |c_i| = s F_i                        magnitude, F_i the reference (N,)
    c_i . d_i = s F_i sin(I)             vertical component, when the attitude gives the body-frame down d_i

``s`` is a field scale (nominally 1) that absorbs the reference's error and a drift of the prior's gain: a level
turn sees the horizontal field as a circle, whose centre gives ``b_x, b_y``, but the magnitude alone cannot tell a
vertical offset from a slightly different ``|F|`` (the two trade exactly when the sensor never tilts). The vertical
component adds the inclination ``I`` (fitted too, with a Gaussian prior of ``inclination_sigma_deg``, default
0.2 deg): at level it ties the vertical offset to the inclination's accuracy (``dV = F cos(I) dI``, 1.4 nT per 0.01
deg at I = 68.6 deg... and through ``s`` more), so only **tilt** (roll and pitch changing while the vehicle turns)
identifies the vertical offset from the data themselves.

The fit is a regularised (maximum a posteriori) least squares of ``(b, s)``: the data residuals over the noise
``sigma`` (from the residuals), plus two Gaussian priors,

    b ~ N(b_prior, C_b + sigma_change^2 I)     C_b: the earlier calibration's offset covariance
    s ~ N(1, scale_sigma^2)

``sigma_change`` (``prior_offset_sigma``, data unit; default 10 % of ``F``) is how far the offset may have moved
since the earlier calibration; ``scale_sigma`` (default 0.005: a reference good to 0.5 %, IGRF against a local
field, plus a gain drift) the field scale's. The covariance of the estimate is the inverse of the augmented
information ``J^T J`` (data rows times the residuals' autocorrelation time,
:func:`trimag.quality.honesty.correlation_time`), plus the prior matrix's own covariance propagated through the
estimate (``G C_W G^T``, ``G = -cov J^T J_W`` the sensitivity of the estimate to the matrix entries; ellipsoid
priors, whose covariance holds ``w11 .. w33``, and level turns', the symmetric ``m11 .. m33``).

An offset component counts as **identified by the data** when, with the field scale left free, its posterior
standard deviation is below half its prior one and within 10x the best component's. A component the data alone
cannot fix but the known field magnitude does (the vertical offset of a level turn: ``|c| = s F`` with ``s`` known
to ``scale_sigma``) is **identified by the field's magnitude** when its posterior standard deviation, which then
holds the reference's own uncertainty, is below half its prior one (issue 30, item 5c); each sigma is split into the
data's, the reference's and the prior matrix's parts (``std_from_data``, ``std_from_reference``,
``std_from_prior_matrix``). The others are reported as unidentified, with the sigma the priors give them. No
component that the data inform beyond the prior: :class:`~trimag.errors.IdentifiabilityError` (exit 3).
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._core.solve import levenberg_marquardt
from ..calibration import Calibration, make_uncertainty
from ..errors import IdentifiabilityError, TrimagInputError
from ..quality.honesty import correlation_time

__all__ = ["DEFAULT_SCALE_SIGMA", "OPTIONS", "file_digest", "refit_offset"]

#: Default standard deviation of the field scale ``s`` (relative): the reference's and the gain's uncertainty.
DEFAULT_SCALE_SIGMA = 0.005
#: Default standard deviation of the offset's change since the earlier calibration, as a fraction of ``F``.
DEFAULT_CHANGE_FRACTION = 0.1
#: The ``option`` keys a quick recalibration takes.
OPTIONS = ("prior_offset_sigma", "scale_sigma", "inclination_deg", "inclination_sigma_deg")
#: The standard deviation (relative, and radians) of a reference taken as exact, to split a sigma into its parts.
REFERENCE_EXACT = 1e-7
#: A component is identified when the data shrink its prior standard deviation below this fraction.
IDENTIFIED_RATIO = 0.5
#: ... and when its standard deviation (field scale free) is within this factor of the best component's.
WEAK_RATIO = 10.0

_NAMES = ("offset_x", "offset_y", "offset_z", "field_scale", "inclination_rad")
#: Default standard deviation of the given inclination (degrees): a model's against the local field.
DEFAULT_INCLINATION_SIGMA_DEG = 0.2


def file_digest(path: str | Path) -> str:
    """SHA-256 (hex) of a file's bytes: the provenance of a prior calibration."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _prior_matrix_cov(
    prior: Calibration,
) -> tuple[NDArray[np.float64], NDArray[np.intp], NDArray[np.intp], bool] | None:
    """The covariance (6, 6) of an ellipsoid prior's matrix entries, their row and column indices (upper triangle)
    and whether the matrix is symmetric: the upper-triangular ``w11 .. w33`` of the ellipsoid estimators, or the
    symmetric ``m11 .. m33`` of a level turn (:mod:`trimag.vehicle.level_turn`; ``m12`` is both ``M[0, 1]`` and
    ``M[1, 0]``); None when the prior has neither."""
    unc = prior.uncertainty or {}
    order = list(unc.get("covariance_order") or [])
    cov = unc.get("covariance")
    if prior.model != "ellipsoid" or cov is None:
        return None
    for prefix, symmetric in (("w", False), ("m", True)):
        names = tuple(f"{prefix}{i}{j}" for i, j in ((1, 1), (1, 2), (1, 3), (2, 2), (2, 3), (3, 3)))
        if all(n in order for n in names):
            idx = [order.index(n) for n in names]
            C = np.asarray(cov, dtype=np.float64)[np.ix_(idx, idx)]
            if not np.isfinite(C).all():
                return None
            rows, cols = np.triu_indices(3)
            return 0.5 * (C + C.T), rows.astype(np.intp), cols.astype(np.intp), symmetric
    return None


def _prior_offset_cov(prior: Calibration) -> NDArray[np.float64]:
    """The earlier calibration's offset covariance (3, 3), zeros when it did not report one."""
    unc = prior.uncertainty or {}
    order = list(unc.get("covariance_order") or [])
    cov = unc.get("covariance")
    for names in (("hard_iron_x", "hard_iron_y", "hard_iron_z"), ("c1", "c2", "c3"), ("b1", "b2", "b3")):
        if cov is not None and all(n in order for n in names):
            idx = [order.index(n) for n in names]
            C = np.asarray(cov, dtype=np.float64)[np.ix_(idx, idx)]
            if np.isfinite(C).all():
                return 0.5 * (C + C.T)
    std = unc.get("param_std") or {}
    for names in (("hard_iron_x", "hard_iron_y", "hard_iron_z"), ("c1", "c2", "c3")):
        if all(n in std and std[n] is not None for n in names):
            return np.diag([float(std[n]) ** 2 for n in names])
    return np.zeros((3, 3))


class _Problem:
    """Augmented residuals and Jacobian of ``(b, s)``: data rows over ``sigma`` (times ``1/sqrt(tau)``), then the
    priors' whitened rows."""

    def __init__(self, M: NDArray[np.float64], X: NDArray[np.float64], F: NDArray[np.float64],
                 down: NDArray[np.float64] | None, incl: float, incl_sigma: float, b_prior: NDArray[np.float64],
                 prior_cov: NDArray[np.float64], scale_sigma: float) -> None:
        self.M, self.X, self.F, self.down, self.incl, self.incl_sigma = M, X, F, down, incl, incl_sigma
        self.b_prior = b_prior
        self.L_inv = np.linalg.inv(np.linalg.cholesky(prior_cov))  # whitening: L^-1 (b - b_prior)
        self.scale_sigma = scale_sigma
        self.weight = 1.0

    def data(self, q: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Unweighted data residuals (N or 2N,) and their Jacobian (.., 4)."""
        b, s, incl = q[:3], q[3], q[4]
        c = (self.X - b) @ self.M.T
        mag = np.linalg.norm(c, axis=1)
        n = c / mag[:, None]
        r = [mag - s * self.F]
        J = [np.column_stack([-(n @ self.M), -self.F, np.zeros(len(c))])]
        if self.down is not None:
            r.append(np.einsum("ij,ij->i", c, self.down) - s * self.F * np.sin(incl))
            J.append(np.column_stack([-(self.down @ self.M), -self.F * np.sin(incl), -s * self.F * np.cos(incl)]))
        return np.concatenate(r), np.vstack(J)

    def matrix_jacobian(self, q: NDArray[np.float64], rows: NDArray[np.intp], cols: NDArray[np.intp]
                        ) -> NDArray[np.float64]:
        """Unweighted Jacobian (N or 2N, k) of the data residuals with respect to the matrix entries
        ``M[rows[j], cols[j]]``."""
        d = self.X - q[:3]
        c = d @ self.M.T
        n = c / np.linalg.norm(c, axis=1)[:, None]
        J = [n[:, rows] * d[:, cols]]
        if self.down is not None:
            J.append(self.down[:, rows] * d[:, cols])
        return np.vstack(J)

    def residuals(self, q: NDArray[np.float64]) -> NDArray[np.float64]:
        r, _ = self.data(q)
        return np.concatenate([self.weight * r, self.L_inv @ (q[:3] - self.b_prior),
                               [(q[3] - 1.0) / self.scale_sigma, (q[4] - self.incl) / self.incl_sigma]])

    def jacobian(self, q: NDArray[np.float64]) -> NDArray[np.float64]:
        _, J = self.data(q)
        prior = np.zeros((5, 5))
        prior[:3, :3] = self.L_inv
        prior[3, 3] = 1.0 / self.scale_sigma
        prior[4, 4] = 1.0 / self.incl_sigma
        return np.vstack([self.weight * J, prior])


def refit_offset(
    prior: Calibration,
    B: ArrayLike,
    reference: ArrayLike,
    *,
    regressors: Mapping[str, ArrayLike] | None = None,
    attitude: Any = None,
    inclination_deg: float | None = None,
    prior_offset_sigma: float | None = None,
    scale_sigma: float = DEFAULT_SCALE_SIGMA,
    inclination_sigma_deg: float = DEFAULT_INCLINATION_SIGMA_DEG,
    prior_source: Mapping[str, Any] | None = None,
) -> Calibration:
    """Refit the offset of ``prior`` from new samples, its matrix and regressor terms kept (module docstring).

    Parameters
    ----------
    prior : Calibration
        The earlier calibration (any model): ``matrix`` (3, 3) and ``regressors`` are kept, ``offset`` (3,) and
        its covariance are the prior of the new offset.
    B : array_like, shape (N, 3)
        Raw samples in ``prior.units``.
    reference : float or array_like, shape (N,)
        Field magnitude ``F`` in ``prior.units``.
    regressors : mapping str -> array_like (N,), optional
        Values of the prior's regressors at each sample (required when it has regressor terms).
    attitude : scipy.spatial.transform.Rotation, optional
        N attitudes (body -> NED); with ``inclination_deg`` they add the vertical component's residual.
    inclination_deg : float, optional
        Inclination of the field (degrees, positive down).
    prior_offset_sigma : float, optional
        Standard deviation of the offset's change since ``prior`` (data unit); default 10 % of ``F``.
    scale_sigma : float
        Standard deviation of the field scale ``s`` (relative).
    inclination_sigma_deg : float
        Standard deviation of ``inclination_deg`` (degrees): the inclination is fitted with this Gaussian prior.
    prior_source : mapping, optional
        Provenance of the prior (``path``, ``sha256``) stored in ``diagnostics["prior"]``.

    Returns
    -------
    Calibration
        Same ``matrix``, ``regressors``, ``model`` as ``prior``; the new ``offset``; method ``prior-offset``;
        ``uncertainty["param_std"]`` of ``offset_x, offset_y, offset_z, field_scale``; ``diagnostics["prior"]``:
        the source, what was refitted and kept, and per offset component whether the data identified it.

    Raises
    ------
    TrimagInputError
        Misshapen samples, a missing reference or regressor values, bad priors.
    IdentifiabilityError
        The data identify no component of the offset.
    """
    X, F = _checked_samples(prior, B, reference, regressors)
    n = len(X)
    change = _checked_change(scale_sigma, prior_offset_sigma, float(np.mean(F)))
    prior_cov = _prior_offset_cov(prior) + change**2 * np.eye(3)
    down, incl = _down_directions(attitude, inclination_deg, inclination_sigma_deg, n)
    M = np.asarray(prior.matrix, dtype=np.float64)
    b_prior = np.asarray(prior.offset, dtype=np.float64)
    incl_sigma = float(np.radians(inclination_sigma_deg))
    problem = _Problem(M, X, F, down, incl, incl_sigma, b_prior, prior_cov, scale_sigma)
    q, r, sigma, tau, nfev, converged = _solve(problem, prior, n)
    cov, info, prior_info = _posterior(problem, prior, q, incl_sigma, scale_sigma)
    std = np.sqrt(np.diag(cov))
    std_free, prior_std, informed, identified = _identified_components(info, prior_info, prior_cov)
    axes = ("x", "y", "z")
    if not informed.any():
        raise IdentifiabilityError(
            f"these {n} samples identify no component of the offset beyond the prior (with the field scale free, "
            f"the sigmas stay {np.round(std_free, 3).tolist()} against the prior's {np.round(prior_std, 3).tolist()} "
            f"{prior.units}): turn the vehicle through several headings (at least three, spread over the circle)"
        )
    # the reference's own uncertainty in each sigma: the posterior with the magnitude (and inclination) exact
    exact_sigmas = (REFERENCE_EXACT if down is not None else incl_sigma, REFERENCE_EXACT)
    exact = np.diag(_posterior(problem, prior, q, *exact_sigmas)[0])[:3]
    data_only = np.diag(_posterior(problem, prior, q, *exact_sigmas, with_matrix=False)[0])[:3]
    std_reference = np.sqrt(np.clip(np.diag(cov)[:3] - exact, 0.0, None))
    parts = {"data": np.sqrt(np.clip(data_only, 0.0, None)), "reference": std_reference,
             "prior_matrix": np.sqrt(np.clip(exact - data_only, 0.0, None)),
             "by_reference": std[:3] < IDENTIFIED_RATIO * prior_std}
    return _assemble(prior, X, F, q, r, sigma, tau, cov, std, std_free, prior_std, identified, axes, nfev,
                     converged, change, scale_sigma, down is not None, inclination_deg, inclination_sigma_deg,
                     prior_source, parts)


def _checked_samples(
    prior: Calibration, B: ArrayLike, reference: ArrayLike, regressors: Mapping[str, ArrayLike] | None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The samples (N, 3) with the prior's regressor terms removed, and the field magnitude per sample (N,)."""
    X = np.asarray(B, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or len(X) < 3:
        raise TrimagInputError(f"`B` must have shape (N, 3) with N >= 3; got {X.shape}")
    F = np.broadcast_to(np.asarray(reference, dtype=np.float64), (len(X),)).astype(np.float64)
    if not (np.isfinite(F).all() and np.all(F > 0)):
        raise TrimagInputError("a quick recalibration (`prior`) needs a known, positive field magnitude: give "
                               "`reference=F` or `igrf_spec=LAT,LON,ALT_M,DATE`")
    if prior.regressors is not None:
        X = X - prior.regressor_shift(regressors, X.shape)
    elif regressors:
        raise TrimagInputError("the prior calibration has no regressor terms; drop `regressors`")
    return X, F


def _checked_change(scale_sigma: float, prior_offset_sigma: float | None, F_mean: float) -> float:
    """The standard deviation of the offset's change since the prior (data unit; default 10 % of ``F_mean``),
    after checking it and ``scale_sigma``."""
    if not (scale_sigma > 0 and np.isfinite(scale_sigma)):
        raise TrimagInputError(f"`option scale_sigma` must be a positive number; got {scale_sigma}")
    change = DEFAULT_CHANGE_FRACTION * F_mean if prior_offset_sigma is None else float(prior_offset_sigma)
    if not (change > 0 and np.isfinite(change)):
        raise TrimagInputError(f"`option prior_offset_sigma` must be a positive number; got {prior_offset_sigma}")
    return change


def _down_directions(
    attitude: Any, inclination_deg: float | None, inclination_sigma_deg: float, n: int
) -> tuple[NDArray[np.float64] | None, float]:
    """The body-frame down direction of each sample (N, 3; None without attitudes and inclination) and the
    inclination (radians; 0 without)."""
    if not (inclination_sigma_deg > 0 and np.isfinite(inclination_sigma_deg)):
        raise TrimagInputError(f"`option inclination_sigma_deg` must be a positive number; got {inclination_sigma_deg}")
    if attitude is None or inclination_deg is None:
        return None, 0.0
    down = np.atleast_2d(attitude.inv().apply([0.0, 0.0, 1.0]))
    if len(down) != n:
        raise TrimagInputError(f"`attitude` has {len(down)} rotations for {n} samples")
    return down, float(np.radians(inclination_deg))


def _posterior(
    problem: _Problem, prior: Calibration, q: NDArray[np.float64], incl_sigma: float, scale_sigma: float,
    with_matrix: bool = True,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The covariance (5, 5) of ``q`` (with the prior matrix's own covariance propagated when it has one and
    ``with_matrix``), the data's information ``J^T J`` and the priors' information (scale prior excluded)."""
    J_data = problem.weight * problem.data(q)[1]
    info = J_data.T @ J_data
    prior_info = np.zeros((5, 5))
    prior_info[:3, :3] = problem.L_inv.T @ problem.L_inv
    prior_info[4, 4] = 1.0 / incl_sigma**2
    cov = np.asarray(np.linalg.inv(info + prior_info + np.diag([0, 0, 0, 1.0 / scale_sigma**2, 0])), dtype=np.float64)
    matrix_cov = _prior_matrix_cov(prior) if with_matrix else None
    if matrix_cov is not None:  # the prior's matrix is uncertain too: its covariance propagated to the estimate
        C_w, rows, cols, symmetric = matrix_cov
        J_w = problem.matrix_jacobian(q, rows, cols)
        if symmetric:  # an off-diagonal entry of a symmetric matrix is in two places
            J_w = J_w + np.where(rows != cols, problem.matrix_jacobian(q, cols, rows), 0.0)
        G = -cov @ (J_data.T @ (problem.weight * J_w))
        cov = cov + G @ C_w @ G.T
    return cov, info, prior_info


def _identified_components(
    info: NDArray[np.float64], prior_info: NDArray[np.float64], prior_cov: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_], NDArray[np.bool_]]:
    """Per offset component: its standard deviation with the field scale free, the prior's, whether the data
    inform it (beyond the prior) and whether they identify it (informed, and not far worse than the best)."""
    # the field scale left free (and the inclination with its prior): what the data say of b beyond |F|
    free = prior_info + np.diag([0, 0, 0, 1e-12, 0])
    cov_free = np.linalg.inv(info + free)
    prior_std = np.sqrt(np.diag(prior_cov))
    std_free = np.asarray(np.sqrt(np.clip(np.diag(cov_free)[:3], 0.0, None)), dtype=np.float64)
    informed = std_free < IDENTIFIED_RATIO * prior_std
    # a component the data determine far worse than the best one (e.g. the vertical offset of a level turn, which
    # only the small tilts of the log inform) is reported as unidentified too, with the sigma it has
    identified = informed & (std_free < WEAK_RATIO * std_free.min())
    return std_free, prior_std, informed, identified


def _solve(problem: _Problem, prior: Calibration, n: int) -> tuple[Any, ...]:
    """Two passes: the noise from the prior (or 0.1 % of F), then from the residuals of the first fit."""
    q0 = np.concatenate([problem.b_prior, [1.0, problem.incl]])
    noise0 = (prior.uncertainty or {}).get("noise_std") or prior.stats.get("rms_after") or 1e-3 * float(
        np.mean(problem.F))
    sigma, tau = float(noise0), 1.0
    nfev, converged = 0, True
    q = q0
    for _ in range(2):
        problem.weight = 1.0 / (sigma * np.sqrt(tau))
        res = levenberg_marquardt(problem.residuals, q, jac=problem.jacobian, xtol=1e-12, ftol=1e-12, gtol=1e-12,
                                  max_nfev=200)
        q, nfev, converged = np.asarray(res.x, dtype=np.float64), nfev + int(res.nfev), bool(res.success)
        r = problem.data(q)[0]
        sigma = float(np.sqrt(r @ r / max(len(r) - 5, 1))) or sigma
        tau = max(correlation_time(r[:n]), 1.0)
    problem.weight = 1.0 / (sigma * np.sqrt(tau))
    return q, r, sigma, tau, nfev, converged


def _assemble(prior: Calibration, X: NDArray[np.float64], F: NDArray[np.float64], q: NDArray[np.float64],
              r: NDArray[np.float64], sigma: float, tau: float, cov: NDArray[np.float64], std: NDArray[np.float64],
              std_free: NDArray[np.float64], prior_std: NDArray[np.float64], identified: NDArray[np.bool_],
              axes: tuple[str, ...], nfev: int, converged: bool, change: float, scale_sigma: float,
              vertical: bool, inclination_deg: float | None, inclination_sigma_deg: float,
              prior_source: Mapping[str, Any] | None, parts: Mapping[str, NDArray[Any]]) -> Calibration:
    """The Calibration of a quick recalibration: the prior's shape, the new offset, what was identified (by the
    data, or by the data and the reference's magnitude), the sigmas' parts (``parts``: ``data``, ``reference``,
    ``by_reference``)."""
    from ..models import get_model

    M = np.asarray(prior.matrix, dtype=np.float64)
    b = q[:3]
    n = len(X)
    mag_before = np.linalg.norm(X, axis=1)  # raw samples minus the prior's regressor terms
    mag_after = np.linalg.norm((X - b) @ M.T, axis=1)
    err_before, err_after = mag_before - F, mag_after - F
    try:
        params = get_model(prior.model).from_matrix_offset(M, b).as_dict()
    except Exception:  # an 'affine' prior, or a model whose parameters do not hold this matrix exactly
        params = dict(prior.params)
    by = [("data" if identified[k] else ("the field's magnitude" + (" and inclination" if vertical else ""))
           if parts["by_reference"][k] else None) for k in range(3)]
    unidentified = [f"offset_{a}" for a, how in zip(axes, by, strict=True) if how is None]
    k_par = 5 if vertical else 4  # the inclination is a parameter only with the vertical component's residuals
    names, cov, std = list(_NAMES[:k_par]), cov[:k_par, :k_par], std[:k_par]
    components = {
        f"offset_{a}": {
            "value": float(b[k]), "std": float(std[k]), "prior_value": float(prior.offset[k]),
            "prior_std": float(prior_std[k]), "std_with_free_scale": float(std_free[k]),
            "identified_by_data": bool(identified[k]),
            "identified": by[k] is not None, "identified_by": by[k],
            "std_from_data": float(parts["data"][k]), "std_from_reference": float(parts["reference"][k]),
            "std_from_prior_matrix": float(parts["prior_matrix"][k]),
        }
        for k, a in enumerate(axes)
    }
    diagnostics = {
        "prior": {
            **dict(prior_source or {}),
            "method": prior.method, "model": prior.model, "created": prior.created,
            "refitted": ["offset"], "kept": ["matrix", *(["regressors"] if prior.regressors is not None else [])],
            "components": components,
            "unidentified": unidentified,
            "field_scale": {"value": float(q[3]), "std": float(std[3]), "prior_std": scale_sigma},
            "prior_offset_sigma": change,
            "residuals": "magnitude" + (" and vertical component (inclination, attitude)" if vertical else ""),
            "inclination_deg": inclination_deg,
            **({"inclination": {"value_deg": float(np.degrees(q[4])), "std_deg": float(np.degrees(std[4])),
                                "prior_deg": inclination_deg, "prior_std_deg": inclination_sigma_deg}}
               if vertical else {}),
            "equations": "c = M (x - b); |c| = s F" + ("; c . d = s F sin(I)" if vertical else "")
                     + "; b ~ N(b_prior, C_b + prior_offset_sigma^2 I), s ~ N(1, scale_sigma^2)"
                     + ("; I ~ N(inclination_deg, inclination_sigma_deg^2)" if vertical else ""),
        },
    }
    if prior.diagnostics.get("regressors") is not None:
        diagnostics["regressors"] = prior.diagnostics["regressors"]
    uncertainty = make_uncertainty(
        names, covariance=cov, noise_std=sigma, gauge="the prior calibration's matrix, held fixed",
        basis="inverse of the augmented information: data (sigma from the residuals, times their autocorrelation "
              "time) plus the Gaussian priors of the offset and the field scale (trimag.vehicle.prior)",
        inflation={"total": tau, "correlated_residuals": tau},
    )
    if prior.model == "ellipsoid":  # the offset under the ellipsoid model's own names too
        uncertainty["param_std"].update({f"hard_iron_{a}": float(std[k]) for k, a in enumerate(axes)})
    stats = {
        "n_samples": n, "n_used": n, "iterations": nfev, "converged": converged,
        "rms_before": float(np.sqrt(np.mean(err_before**2))), "rms_after": float(np.sqrt(np.mean(err_after**2))),
        "max_abs_before": float(np.max(np.abs(err_before))), "max_abs_after": float(np.max(np.abs(err_after))),
        "mean_norm_before": float(np.mean(mag_before)), "std_norm_before": float(np.std(mag_before)),
        "mean_norm_after": float(np.mean(mag_after)), "std_norm_after": float(np.std(mag_after)),
        "p2p_before": float(np.ptp(mag_before)), "p2p_after": float(np.ptp(mag_after)),
        "rms_vertical_after": (float(np.sqrt(np.mean(r[n:] ** 2))) if vertical else None),
    }
    F_value = float(F[0]) if np.all(F == F[0]) else None
    return Calibration.from_matrix_offset(
        M, b, units=prior.units, model=prior.model, method="prior-offset", params=params,
        reference={"value": F_value, "source": "given" if F_value is not None else "per-sample", "unit": prior.units},
        stats=stats, uncertainty=uncertainty, diagnostics=diagnostics, regressors=prior.regressors,
    )
