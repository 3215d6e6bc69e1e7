"""Level turn: the calibration of a vehicle that turns but cannot tilt (a boat, a rover, a large multicopter), with
no earlier calibration (issue 30, item 5a; docs/autopilot.md, "Large vehicles").

The correction is the firmware's: a symmetric matrix ``M`` after the offset (ArduPilot ``COMPASS_DIA/ODI``, PX4
``CAL_MAGn_xSCALE/xODIAG``), ``c_i = M (x_i - b)``. Each sample gives two residuals (``d_i`` the body-frame down
direction: ``(0, 0, 1)`` for a level vehicle, ``R_i^T (0, 0, 1)`` with attitudes), uncorrelated with each other:

    |c_i - (c_i . d_i) d_i| - s F_i cos(I)     horizontal magnitude, F the reference, I the inclination
    c_i . d_i - s F_i sin(I)                   vertical component

What a level turn identifies (docs/autopilot.md derives it): the raw samples trace an ellipse, ``x(psi) = b + S_3 V +
[S_1 S_2] H u(psi)`` with ``S = M^-1`` (symmetric), ``H = F cos I``, ``V = F sin I`` and ``u`` the unit circle. The
ellipse's shape gives the horizontal block of ``S`` and its coupling to z (``S_13, S_23``); its centre gives
``b_x, b_y`` (``S_13 V``, ``S_23 V`` known) and ``b_z + S_33 V``: the vertical offset trades exactly with the
vertical scale ``S_33``. So:

- the **vertical scale is held**: ``M_33 - (M_11 + M_22) / 2 ~ N(0, vertical_scale_sigma^2)`` (the sensor's vertical
  gain taken as its horizontal one; tilt, when the log has it, identifies it, and the fit then says so);
- the **vertical offset comes from the field**: ``V = F sin I`` with the inclination known (IGRF: ``I ~ N(I_igrf,
  inclination_sigma^2)``); with the magnitude alone the inclination is free and the horizontal gain is held
  instead, ``(M_11 + M_22) / 2 ~ N(1, gain_sigma^2)`` (the data's unit trusted, as ArduPilot's ``MAG_CAL_YAW``
  assumes), which gives ``H`` from the ellipse's size and ``V = +-sqrt(F^2 - H^2)``: the sign a level turn cannot
  see is taken from the inclination when given, else the smaller vertical offset is chosen and the other named;
- the reference's own uncertainty enters as a field scale ``s ~ N(1, scale_sigma^2)``.

The estimate is a regularised (maximum a posteriori) least squares, Levenberg-Marquardt (:mod:`trimag._core.solve`),
each kind of residual weighted by its own noise (from the residuals, two passes) times the magnitude residuals'
autocorrelation time (:func:`trimag.quality.honesty.correlation_time`). The covariance is the inverse of the
augmented information; the vertical offset's variance is split into what the data, the held vertical scale and the
reference contribute (``diagnostics["level_turn"]["offset_z_sigma_parts"]``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._core.solve import levenberg_marquardt
from ..calibration import Calibration, make_uncertainty
from ..errors import IdentifiabilityError, TrimagInputError
from ..quality.honesty import correlation_time

__all__ = ["DEFAULTS", "NAMES", "fit_level_turn", "symmetric_matrix"]

#: Parameter names, in the order of the covariance: the symmetric matrix ``M`` (``m12 = M[0, 1] = M[1, 0]``), the
#: offset, the field scale and the inclination (radians).
NAMES = ("m11", "m12", "m13", "m22", "m23", "m33", "hard_iron_x", "hard_iron_y", "hard_iron_z", "field_scale",
         "inclination_rad")
#: Default standard deviations of the priors (relative, or degrees): ``option KEY=VALUE`` changes them.
DEFAULTS = {"vertical_scale_sigma": 0.01, "gain_sigma": 0.02, "scale_sigma": 0.005, "inclination_sigma_deg": 0.2}
#: The samples' RMS scatter about the horizontal ellipse, relative to its size, above which they trace none.
MAX_ELLIPSE_SCATTER = 0.2
#: The residuals' RMS above this fraction of the field: the samples do not follow a level turn.
MAX_RESIDUAL_FRACTION = 0.05
#: The heading error the calibration predicts (1 sigma, RMS over headings, degrees) above which it is refused.
MAX_HEADING_SIGMA_DEG = 5.0
#: The halves' offsets differ by more than this many combined sigmas: the field or the vehicle's iron changed.
HALVES_Z = 3.0
#: At least this much of the circle of headings must be covered (degrees).
MIN_TURN_DEG = 90.0
_SYM = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def symmetric_matrix(m: ArrayLike) -> NDArray[np.float64]:
    """The symmetric 3 x 3 matrix of ``m = (m11, m12, m13, m22, m23, m33)``."""
    a = np.asarray(m, dtype=np.float64)
    return np.array([[a[0], a[1], a[2]], [a[1], a[3], a[4]], [a[2], a[4], a[5]]])


@dataclass
class _Problem:
    """The augmented residuals (data over their noise, then the priors' whitened rows) and their Jacobian."""

    X: NDArray[np.float64]
    F: NDArray[np.float64]
    down: NDArray[np.float64]
    incl0: float | None
    sigmas: dict[str, float]
    w_mag: float = 1.0
    w_vert: float = 1.0

    def data(self, q: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Unweighted residuals (2N,: horizontal magnitude over the horizontal gain ``(m11 + m22) / 2``, then the
        vertical component over the vertical gain ``m33``) and their Jacobian (2N, 11).

        The horizontal magnitude ``|c - (c . d) d| - s F cos(I)`` rather than ``|c| - s F``: the noise of the
        vertical axis would otherwise enter both residuals (correlated by ``sin I``, 0.9 at 65 deg)."""
        M, b, s, incl = symmetric_matrix(q[:6]), q[6:9], q[9], q[10]
        d = self.X - b
        c = d @ M  # M symmetric: (M d_i)^T = d_i^T M
        vert = np.einsum("ij,ij->i", c, self.down)
        c_h = c - vert[:, None] * self.down
        mag_h = np.linalg.norm(c_h, axis=1)
        n = c_h / mag_h[:, None]  # d|c_h|/dc = n (n is across the down direction)
        r_h = mag_h - s * self.F * np.cos(incl)
        r_vert = vert - s * self.F * np.sin(incl)
        J = np.zeros((2 * len(d), 11))
        for k, (i, j) in enumerate(_SYM):  # d(u . M d)/dM_ij for a symmetric entry
            J[: len(d), k] = n[:, i] * d[:, j] + (n[:, j] * d[:, i] if i != j else 0.0)
            J[len(d):, k] = self.down[:, i] * d[:, j] + (self.down[:, j] * d[:, i] if i != j else 0.0)
        J[: len(d), 6:9] = -(n @ M)
        J[len(d):, 6:9] = -(self.down @ M)
        J[: len(d), 9] = -self.F * np.cos(incl)
        J[: len(d), 10] = s * self.F * np.sin(incl)
        J[len(d):, 9] = -self.F * np.sin(incl)
        J[len(d):, 10] = -s * self.F * np.cos(incl)
        # in the raw data's scale (each residual over its axes' gain): the corrected noise scales with M, and a fit
        # in the corrected scale would shrink M (the vertical scale above all) to fit better than the noise
        n_s = len(d)
        g_h, g_v = 0.5 * (q[0] + q[3]), q[5]
        J[:n_s] /= g_h
        J[:n_s, [0, 3]] -= (r_h / (2.0 * g_h * g_h))[:, None]
        J[n_s:] /= g_v
        J[n_s:, 5] -= r_vert / (g_v * g_v)
        return np.concatenate([r_h / g_h, r_vert / g_v]), J

    def prior_rows(self, q: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The priors' whitened residuals and Jacobian rows."""
        rows, values = [], []
        e = np.zeros(11)
        e[5], e[0], e[3] = 1.0, -0.5, -0.5  # the vertical scale held at the horizontal ones
        rows.append(e / self.sigmas["vertical_scale_sigma"])
        values.append((q[5] - 0.5 * (q[0] + q[3])) / self.sigmas["vertical_scale_sigma"])
        e = np.zeros(11)
        e[9] = 1.0 / self.sigmas["scale_sigma"]
        rows.append(e)
        values.append((q[9] - 1.0) / self.sigmas["scale_sigma"])
        e = np.zeros(11)
        if self.incl0 is not None:  # the inclination known to inclination_sigma
            sigma = np.radians(self.sigmas["inclination_sigma_deg"])
            e[10] = 1.0 / sigma
            values.append((q[10] - self.incl0) / sigma)
        else:  # the magnitude alone: the horizontal gain held at the data's unit
            e[0] = e[3] = 0.5 / self.sigmas["gain_sigma"]
            values.append((0.5 * (q[0] + q[3]) - 1.0) / self.sigmas["gain_sigma"])
        rows.append(e)
        return np.asarray(values), np.vstack(rows)

    def weights(self, n: int) -> NDArray[np.float64]:
        return np.concatenate([np.full(n, self.w_mag), np.full(n, self.w_vert)])

    def residuals(self, q: NDArray[np.float64]) -> NDArray[np.float64]:
        r, _ = self.data(q)
        return np.concatenate([self.weights(len(self.X)) * r, self.prior_rows(q)[0]])

    def jacobian(self, q: NDArray[np.float64]) -> NDArray[np.float64]:
        _, J = self.data(q)
        return np.vstack([self.weights(len(self.X))[:, None] * J, self.prior_rows(q)[1]])


def _down(attitude: Any, n: int) -> NDArray[np.float64]:
    """Body-frame down directions (N, 3): from the attitudes (body -> NED), else level."""
    if attitude is None:
        return np.tile([0.0, 0.0, 1.0], (n, 1))
    down = np.atleast_2d(attitude.inv().apply([0.0, 0.0, 1.0]))
    if len(down) != n:
        raise TrimagInputError(f"`attitude` has {len(down)} rotations for {n} samples")
    return np.asarray(down, dtype=np.float64)


def _ellipse_start(X: NDArray[np.float64], down: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
    """The horizontal ellipse (algebraic conic fit of the body's x, y components; a rough start when ``down`` says
    the vehicle tilted): centre (2,), the shape ``Q`` (2, 2; ``(p - c)^T Q (p - c) = 1``), the mean vertical reading
    and the turn covered (degrees, around a circle's centre)."""
    x, y = X[:, 0], X[:, 1]
    scale = float(np.std(np.concatenate([x, y]))) or 1.0
    xm, ym = x.mean(), y.mean()
    u, v = (x - xm) / scale, (y - ym) / scale
    D = np.column_stack([u * u, u * v, v * v, u, v])
    coef, *_ = np.linalg.lstsq(D, np.ones(len(u)), rcond=None)
    A = np.array([[coef[0], coef[1] / 2], [coef[1] / 2, coef[2]]])
    if np.any(np.linalg.eigvalsh(A) <= 0):
        raise IdentifiabilityError(
            f"the horizontal field of these {len(X)} samples is not an ellipse: the vehicle did not turn (or the "
            "field changed while it did); turn it through a full circle, slowly and level"
        )
    centre_n = np.linalg.solve(2 * A, -coef[3:5])
    k = 1.0 + centre_n @ A @ centre_n
    Q = A / k / scale**2
    centre = centre_n * scale + np.array([xm, ym])
    p = np.column_stack([x, y]) - centre
    radius = np.sqrt(np.einsum("ij,jk,ik->i", p, Q, p))  # 1 on the ellipse
    tilted = float(np.sqrt(np.mean(1.0 - down[:, 2] ** 2))) > np.sin(np.radians(3.0))  # the ellipse a rough start
    scatter = float(np.sqrt(np.mean((radius - 1.0) ** 2)))
    if not tilted and scatter > MAX_ELLIPSE_SCATTER:
        raise IdentifiabilityError(
            f"the horizontal field of these {len(X)} samples does not trace an ellipse (their scatter about the best "
            f"one is {100 * scatter:.0f} % of its size): the vehicle did not turn, it tilted (give its attitudes), "
            "or the field changed while it did; turn it through a full circle, slowly and level"
        )
    # the turn covered, seen from a circle's centre (three parameters: steadier than an ellipse's on a short arc)
    kasa, *_ = np.linalg.lstsq(np.column_stack([u, v, np.ones(len(u))]), u * u + v * v, rcond=None)
    circle = np.array([kasa[0], kasa[1]]) / 2 * scale + np.array([xm, ym])
    angle = np.sort(np.mod(np.degrees(np.arctan2(y - circle[1], x - circle[0])), 360.0))
    gaps = np.diff(np.concatenate([angle, [angle[0] + 360.0]]))
    return centre, Q, np.array([float(np.mean(X[:, 2]))]), np.array([360.0 - float(gaps.max())])


def _starts(X: NDArray[np.float64], F: NDArray[np.float64], down: NDArray[np.float64], incl0: float | None
            ) -> tuple[list[NDArray[np.float64]], float]:
    """Start points of the fit (two when the sign of the vertical field is unknown) and the turn covered."""
    centre, Q, z_mean, covered = _ellipse_start(X, down)
    w, V = np.linalg.eigh(Q)
    root = V @ np.diag(np.sqrt(w)) @ V.T  # |root (p - c)| = 1 on the ellipse
    F_mean = float(np.mean(F))
    if incl0 is not None:
        H, verticals = F_mean * np.cos(incl0), [F_mean * np.sin(incl0)]
    else:
        H = float(np.mean(1.0 / np.sqrt(w)))  # the gain held at 1: H is the ellipse's mean radius
        Vz = float(np.sqrt(max(F_mean**2 - H**2, 0.0)))
        verticals = [Vz, -Vz]
    Mh = root * H
    gain = 0.5 * (Mh[0, 0] + Mh[1, 1])
    starts = []
    for Vz in verticals:
        incl = float(np.arctan2(Vz, H))
        m = [Mh[0, 0], Mh[0, 1], 0.0, Mh[1, 1], 0.0, gain]
        b = [centre[0], centre[1], float(z_mean[0]) - Vz / gain]
        starts.append(np.array([*m, *b, 1.0, incl]))
    return starts, float(covered[0])


def _solve(problem: _Problem, q0: NDArray[np.float64]) -> tuple[NDArray[np.float64], dict[str, Any]]:
    """Two passes (the noise of each kind of residual from the first): the estimate and the run's record."""
    n = len(problem.X)
    problem.w_mag = problem.w_vert = 1.0 / (1e-3 * float(np.mean(problem.F)))
    q, nfev, ok, tau, s_mag, s_vert = q0, 0, True, 1.0, 0.0, 0.0
    for _ in range(2):
        res = levenberg_marquardt(problem.residuals, q, jac=problem.jacobian, xtol=1e-12, ftol=1e-12, gtol=1e-12,
                                  max_nfev=400)
        q, nfev, ok = np.asarray(res.x, dtype=np.float64), nfev + int(res.nfev), bool(res.success)
        r = problem.data(q)[0]
        s_mag = float(np.sqrt(np.mean(r[:n] ** 2))) or 1e-12
        s_vert = float(np.sqrt(np.mean(r[n:] ** 2))) or 1e-12
        tau = max(correlation_time(r[:n]), 1.0)
        problem.w_mag = 1.0 / (s_mag * np.sqrt(tau))
        problem.w_vert = 1.0 / (s_vert * np.sqrt(max(correlation_time(r[n:]), 1.0)))
    cost = float(np.sum(problem.residuals(q) ** 2))
    return q, {"nfev": nfev, "converged": ok, "tau": tau, "noise_magnitude": s_mag, "noise_vertical": s_vert,
               "cost": cost, "weights": (problem.w_mag, problem.w_vert)}


def _covariance(problem: _Problem, q: NDArray[np.float64], sigmas: dict[str, float]) -> NDArray[np.float64]:
    """The posterior covariance (11, 11) with the priors' standard deviations ``sigmas``."""
    saved = problem.sigmas
    problem.sigmas = sigmas
    try:
        J = problem.jacobian(q)
    finally:
        problem.sigmas = saved
    return np.asarray(np.linalg.inv(J.T @ J), dtype=np.float64)


def fit_level_turn(
    B: ArrayLike,
    reference: ArrayLike,
    *,
    inclination_deg: float | None = None,
    attitude: Any = None,
    units: str = "unknown",
    vertical_scale_sigma: float = DEFAULTS["vertical_scale_sigma"],
    gain_sigma: float = DEFAULTS["gain_sigma"],
    scale_sigma: float = DEFAULTS["scale_sigma"],
    inclination_sigma_deg: float = DEFAULTS["inclination_sigma_deg"],
    check_halves: bool = True,
) -> Calibration:
    """Fit a symmetric soft-iron matrix and the offset from a level turn (module docstring).

    Parameters
    ----------
    B : array_like, shape (N, 3)
        Raw samples (body frame), ``units``.
    reference : float or array_like, shape (N,)
        Field magnitude ``F`` in ``units`` (IGRF at the site, or a local survey).
    inclination_deg : float, optional
        Inclination of the field (degrees, positive down; IGRF's): fixes the vertical field. Without it the
        horizontal gain is held at the data's unit and the inclination fitted.
    attitude : scipy.spatial.transform.Rotation, optional
        N attitudes (body -> NED; only roll and pitch matter): the body-frame down of each sample (level without).
    units : str
        The data's unit, recorded.
    vertical_scale_sigma, gain_sigma, scale_sigma : float
        Standard deviations (relative) of the held vertical scale (against the horizontal ones), of the held
        horizontal gain (magnitude only) and of the reference's magnitude.
    inclination_sigma_deg : float
        Standard deviation (degrees) of ``inclination_deg``.
    check_halves : bool
        Also fit the log's first and second halves (each that turned through :data:`MIN_TURN_DEG`) and compare
        their offsets (``diagnostics["level_turn"]["halves"]``): offsets that differ by more than
        :data:`HALVES_Z` of their combined sigma say that the field or the vehicle's iron changed during the log.

    Returns
    -------
    Calibration
        Model ``ellipsoid`` with a symmetric matrix, method ``level-turn``; ``uncertainty`` over :data:`NAMES`;
        ``diagnostics["level_turn"]``: what was fitted and held, the turn covered, the sign choice, the vertical
        offset's sigma split into its sources.

    Raises
    ------
    TrimagInputError
        Misshapen samples, no positive magnitude, bad sigmas.
    IdentifiabilityError
        The vehicle did not turn (not an ellipse) or turned through less than :data:`MIN_TURN_DEG`.
    """
    X = np.asarray(B, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or len(X) < 10 or not np.isfinite(X).all():
        raise TrimagInputError(f"`B` must have shape (N, 3), N >= 10, finite; got {X.shape}")
    F = np.broadcast_to(np.asarray(reference, dtype=np.float64), (len(X),)).astype(np.float64)
    if not (np.isfinite(F).all() and np.all(F > 0)):
        raise TrimagInputError("a level turn needs the field magnitude: give `reference=F` or "
                               "`igrf_spec=LAT,LON,ALT_M,DATE`")
    sigmas = {"vertical_scale_sigma": vertical_scale_sigma, "gain_sigma": gain_sigma, "scale_sigma": scale_sigma,
              "inclination_sigma_deg": inclination_sigma_deg}
    for key, value in sigmas.items():
        if not (np.isfinite(value) and value > 0):
            raise TrimagInputError(f"`option {key}` must be a positive number; got {value}")
    down = _down(attitude, len(X))
    incl0 = None if inclination_deg is None else float(np.radians(inclination_deg))
    starts, covered = _starts(X, F, down, incl0)
    if attitude is not None:  # the attitudes' own yaw (an autopilot's, even one the compass steered) says it too
        covered = min(covered, _covered_deg(np.atleast_2d(attitude.as_euler("ZYX", degrees=True))[:, 0]))
    if covered < MIN_TURN_DEG:
        raise IdentifiabilityError(
            f"the vehicle turned through only {covered:.0f} deg of heading (at least {MIN_TURN_DEG:.0f} needed, a "
            "full circle best): turn it through all headings, slowly and level"
        )
    problem = _Problem(X, F, down, incl0, sigmas)
    fits = sorted((_solve(problem, q0) for q0 in starts), key=lambda f: f[1]["cost"])
    q, run = fits[0]
    alternative = None
    if len(fits) > 1:  # without the inclination: two mirror solutions, told apart only by tilt
        other, other_run = fits[1]
        sigma_z = float(np.sqrt(_covariance(problem, q, sigmas)[8, 8]))
        if other_run["cost"] - run["cost"] < 9.0 and abs(other[8] - q[8]) > 3.0 * sigma_z:
            if abs(other[8]) < abs(q[8]):  # as good a fit: the smaller vertical offset, the other one named
                (q, run), (other, other_run) = (other, other_run), (q, run)
            alternative = float(other[8])
    problem.w_mag, problem.w_vert = run["weights"]
    cal = _assemble(problem, q, run, covered, alternative, units, inclination_deg, sigmas)
    _refuse_a_poor_turn(cal, float(np.mean(F)))
    if not check_halves:
        return cal
    halves = _halves(X, F, inclination_deg, attitude, units, sigmas)
    return cal.with_diagnostics(level_turn={**cal.diagnostics["level_turn"], "halves": halves})


def _covered_deg(heading_deg: NDArray[np.float64]) -> float:
    """The part of the circle (degrees) that the headings cover: 360 minus the largest gap between them."""
    angle = np.sort(np.mod(heading_deg, 360.0))
    return 360.0 - float(np.diff(np.concatenate([angle, [angle[0] + 360.0]])).max())


def _refuse_a_poor_turn(cal: Calibration, F_mean: float) -> None:
    """Refuse (exit 3) a fit whose samples do not follow a level turn in a steady field (residuals above
    :data:`MAX_RESIDUAL_FRACTION` of the field) or that does not determine the heading (the heading error it
    predicts above :data:`MAX_HEADING_SIGMA_DEG`, 1 sigma RMS over headings)."""
    from .heading import predicted_heading_sigma

    d = cal.diagnostics["level_turn"]
    rms = float(np.hypot(d["noise_magnitude"], d["noise_vertical"]))
    if rms > MAX_RESIDUAL_FRACTION * F_mean:
        raise IdentifiabilityError(
            f"the samples do not follow a level turn in a steady field: they miss the fitted one by {rms:.3g} "
            f"{cal.units} RMS ({100 * rms / F_mean:.0f} % of the field; a level turn is fitted to the noise): the "
            "vehicle tilted without attitudes, or the field changed (motors, nearby iron); record the turns level "
            "and slow, away from iron"
        )
    sigma = predicted_heading_sigma(cal, d["fitted_inclination_deg"])["rms_deg"]
    if sigma > MAX_HEADING_SIGMA_DEG:
        raise IdentifiabilityError(
            f"this turn does not determine the heading: the calibration it gives would be uncertain by "
            f"{sigma:.2g} deg of heading (1 sigma, RMS over headings; it turned through {d['turn_covered_deg']:.0f} "
            "deg): turn the vehicle through a full circle or two, slowly and level"
        )


def _halves(X: NDArray[np.float64], F: NDArray[np.float64], inclination_deg: float | None, attitude: Any, units: str,
            sigmas: dict[str, float]) -> dict[str, Any] | None:
    """The offsets of the log's first and second halves and how far apart they are (in their combined sigma); None
    when a half did not turn enough to be fitted."""
    n = len(X)
    offsets, stds = [], []
    for part in (slice(0, n // 2), slice(n // 2, n)):
        try:
            half = fit_level_turn(X[part], F[part], inclination_deg=inclination_deg,
                                  attitude=None if attitude is None else attitude[part], units=units,
                                  vertical_scale_sigma=sigmas["vertical_scale_sigma"], gain_sigma=sigmas["gain_sigma"],
                                  scale_sigma=sigmas["scale_sigma"],
                                  inclination_sigma_deg=sigmas["inclination_sigma_deg"], check_halves=False)
        except (IdentifiabilityError, TrimagInputError):
            return None
        offsets.append(np.asarray(half.offset))
        stds.append(np.array([half.uncertainty["param_std"][f"hard_iron_{a}"] for a in "xyz"]))  # type: ignore[index]
    z = np.abs(offsets[0] - offsets[1]) / np.hypot(stds[0], stds[1])
    return {"offsets": [o.tolist() for o in offsets], "std": [s.tolist() for s in stds], "z": z.tolist(),
            "agree": bool(z.max() <= HALVES_Z)}


def _offset_z_parts(problem: _Problem, q: NDArray[np.float64], sigmas: dict[str, float]) -> dict[str, float]:
    """The vertical offset's standard deviation and what the data, the held vertical scale and the reference
    (magnitude and inclination) contribute to it (root of the variance differences)."""
    tiny = 1e-9
    full = _covariance(problem, q, sigmas)[8, 8]
    held = _covariance(problem, q, {**sigmas, "vertical_scale_sigma": tiny})[8, 8]
    exact = _covariance(problem, q, {**sigmas, "vertical_scale_sigma": tiny, "scale_sigma": tiny,
                                     "inclination_sigma_deg": tiny if problem.incl0 is not None else
                                     sigmas["inclination_sigma_deg"]})[8, 8]
    return {"total": float(np.sqrt(full)), "vertical_scale": float(np.sqrt(max(full - held, 0.0))),
            "reference": float(np.sqrt(max(held - exact, 0.0))), "data": float(np.sqrt(max(exact, 0.0)))}


def _assemble(problem: _Problem, q: NDArray[np.float64], run: dict[str, Any], covered: float,
              alternative: float | None, units: str, inclination_deg: float | None,
              sigmas: dict[str, float]) -> Calibration:
    """The Calibration of a level turn."""
    from ..models import get_model

    M, b = symmetric_matrix(q[:6]), q[6:9]
    cov = _covariance(problem, q, sigmas)
    # the vertical scale counts as fitted when the data (tilt) shrink its prior below half
    scale_part = np.array([-0.5, 0, 0, -0.5, 0, 1.0, 0, 0, 0, 0, 0])
    vertical_std = float(np.sqrt(scale_part @ cov @ scale_part))
    vertical_fitted = vertical_std < 0.5 * sigmas["vertical_scale_sigma"]
    X, F, n = problem.X, problem.F, len(problem.X)
    mag_before, mag_after = np.linalg.norm(X, axis=1), np.linalg.norm((X - b) @ M, axis=1)
    r = problem.data(q)[0]
    parts = _offset_z_parts(problem, q, sigmas)
    held = [] if vertical_fitted else ["the vertical scale m33 (as the horizontal ones: (m11 + m22) / 2)"]
    if problem.incl0 is None:
        held.append("the horizontal gain (m11 + m22) / 2 at the data's unit")
    diagnostics = {"level_turn": {
        "fitted": ["m11", "m12", "m13", "m22", "m23", "hard_iron_x", "hard_iron_y", "hard_iron_z",
                   *(["m33"] if vertical_fitted else [])],
        "held": held, "vertical_scale_fitted": vertical_fitted, "vertical_scale_std": vertical_std,
        "turn_covered_deg": covered, "offset_z_sigma_parts": parts,
        "offset_z_from": "the field's magnitude and inclination" if problem.incl0 is not None else
                         "the field's magnitude (the horizontal gain held)",
        "offset_z_alternative": alternative,
        "inclination_deg": inclination_deg, "fitted_inclination_deg": float(np.degrees(q[10])),
        "field_scale": float(q[9]), "priors": dict(sigmas),
        "noise_magnitude": run["noise_magnitude"], "noise_vertical": run["noise_vertical"],
        "tilt_rms_deg": float(np.degrees(np.sqrt(np.mean(np.arccos(np.clip(problem.down[:, 2], -1, 1)) ** 2)))),
        "equations": "c = M (x - b), M symmetric; |c - (c . d) d| = s F cos(I); c . d = s F sin(I); "
                     "m33 - (m11 + m22)/2 ~ N(0, vertical_scale_sigma^2); s ~ N(1, scale_sigma^2); "
                     + ("I ~ N(I_ref, inclination_sigma^2)" if problem.incl0 is not None else
                        "(m11 + m22)/2 ~ N(1, gain_sigma^2)"),
    }}
    uncertainty = make_uncertainty(
        list(NAMES), covariance=cov, noise_std=run["noise_magnitude"],
        gauge="symmetric matrix M (the firmware's DIA/ODI): m12 = M[0, 1] = M[1, 0]",
        basis="inverse of the augmented information: magnitude and vertical-component residuals (each with its "
              "noise from the residuals, times their autocorrelation time) plus the Gaussian priors of the held "
              "vertical scale, the reference's magnitude and inclination (trimag.vehicle.level_turn)",
        inflation={"total": run["tau"], "correlated_residuals": run["tau"]},
    )
    err_before, err_after = mag_before - F, mag_after - F
    stats = {
        "n_samples": n, "n_used": n, "iterations": run["nfev"], "converged": run["converged"],
        "rms_before": float(np.sqrt(np.mean(err_before**2))), "rms_after": float(np.sqrt(np.mean(err_after**2))),
        "max_abs_before": float(np.max(np.abs(err_before))), "max_abs_after": float(np.max(np.abs(err_after))),
        "mean_norm_before": float(np.mean(mag_before)), "std_norm_before": float(np.std(mag_before)),
        "mean_norm_after": float(np.mean(mag_after)), "std_norm_after": float(np.std(mag_after)),
        "p2p_before": float(np.ptp(mag_before)), "p2p_after": float(np.ptp(mag_after)),
        "rms_vertical_after": float(np.sqrt(np.mean(r[n:] ** 2))),
    }
    F_value = float(F[0]) if np.all(F == F[0]) else None
    return Calibration.from_matrix_offset(
        M, b, units=units, model="ellipsoid", method="level-turn",
        params=get_model("ellipsoid").from_matrix_offset(M, b).as_dict(),
        reference={"value": F_value if F_value is not None else float(np.mean(F)),
                   "source": "given" if F_value is not None else "per-sample", "unit": units},
        stats=stats, uncertainty=uncertainty, diagnostics=diagnostics,
    )
