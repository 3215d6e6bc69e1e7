"""``gauss-newton``: paper B's 9-parameter scalar calibration against a reference magnitude.

Each sample gives one nonlinear equation (methods.md, paper B)

    r_i(p) = |T^-1 K^-1 (B_m,i - b)| - F_i = 0,     p = (b1, b2, b3, k1, k2, k3, alpha, beta, gamma)

and the N equations are solved by Gauss-Newton: ``p <- p + delta`` with ``delta = argmin |J delta + r|``
(solved through a QR factorisation, not by forming ``J^T J``), ``J`` the analytic Jacobian
(:func:`residual_jacobian`). Every sum over samples is taken in chunks of samples
(:func:`~trimag._core.chunks.chunk_rows`; ``[J | -r]`` is
factored block by block, :class:`~trimag._core.qr.BlockedQR`), so memory does not grow with N.

* Start: the algebraic (linear least-squares) quadric fit ``u^T A u + v^T u = 1`` (nine unknowns, exact on
  noise-free data), scaled to the reference (:func:`algebraic_start`), reduced to the scalar9 gauge
  (:func:`~trimag.models.scalar9.lq_gauge`).
* Step control: a step that does not lower the cost is halved (up to ``max_halvings`` times). If no halving
  helps, or ``max_iter`` is reached before convergence, the fit continues with Levenberg-Marquardt
  (:func:`trimag._core.solve.levenberg_marquardt`) from the last point, warns with
  :class:`GaussNewtonFallbackWarning`, and records ``"fallback": "levenberg-marquardt"`` in the diagnostics.
* Converged when the step is below ``xtol`` relative to the parameters, or the cost stops falling
  (relative decrease below ``ftol``).
* History: cost ``0.5 sum r_i^2`` (unit^2), RMS of ``r`` (unit) and step norm per iteration, in
  ``Calibration.diagnostics["history"]``.
* Uncertainty: ``cov = s^2 (J^T J)^-1`` at the solution with ``s^2 = sum r_i^2 / (N - 9)``; standard
  deviations in ``Calibration.uncertainty["param_std"]`` (biases in the data unit, angles in radians, plus degrees).
* Identifiability: samples on one plane (a single-axis turn) cannot identify the model; such data raise
  :class:`~trimag.errors.IdentifiabilityError` (exit 3) with a message naming the missing rotations, also when
  noise makes the plane slightly thick: the spread of the samples out of their best plane is then no larger
  than the residual noise (``min_thickness``), or the predicted parameter spread exceeds ``max_rel_std``.

Reference: a number or one value per sample (the data's unit), or ``"mean"``/``None``: ``F`` = the mean raw
magnitude ``mean |B_m|`` of the fitted samples (the "mean value" reference the paper criticises; the result
then has a relative, not absolute, scale).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._core.chunks import chunk_rows, row_blocks
from .._core.qr import BlockedQR
from .._core.quadric import quadratic_terms
from .._core.rowwise import column_means, scratch, transposed_blocks
from .._core.solve import gauss_newton_rule, levenberg_marquardt
from ..calibration import Calibration
from ..errors import IdentifiabilityError, TrimagInputError, TrimagWarning
from ..fields.reference import ScalarReference
from ..models.scalar9 import Scalar9, t_matrix, t_matrix_derivatives
from ..quality.diagnostics import (
    CONDITION_ERROR,
    CONDITION_WARN,
    check_condition,
    check_not_degenerate,
    coverage_advice,
    design_condition,
    single_axis_turn,
    weak_directions,
)
from ._common import normalisation_stats, scalar_reference
from ._finish import make_uncertainty
from .base import Estimator, build_calibration

__all__ = ["GaussNewton", "GaussNewtonFallbackWarning"]

PARAM_NAMES = Scalar9.param_names()
_ANGLES = ("alpha", "beta", "gamma")
#: Thinnest/widest spread below which samples count as "close to one plane" (a single-axis turn plus noise or
#: wobble); only then is the thickness-to-noise test applied, so that logs with a large residual (model error,
#: disturbances) but a well-spread cloud are not mistaken for a single-axis turn.
_FLAT = 0.2


class GaussNewtonFallbackWarning(TrimagWarning):
    """Gauss-Newton could not make progress (or ran out of iterations) and Levenberg-Marquardt took over."""


# ---------------------------------------------------------------------------------------------- maths
def _unpack(p: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    return p[0:3], p[3:6], p[6:9]


def residual_jacobian(
    x: NDArray[np.float64], target: NDArray[np.float64], p: NDArray[np.float64], *, jacobian: bool = True
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """Residuals ``r_i = |T^-1 K^-1 (x_i - b)| - target_i`` (N,) and their Jacobian (N, 9) w.r.t. ``p``.

    ``p = (b1, b2, b3, k1, k2, k3, alpha, beta, gamma)``; ``x`` (N, 3) and ``b`` in one unit, angles in
    radians. With ``e = x - b``, ``z = e / k``, ``y = T^-1 z``, ``n = y / |y|`` and ``g = n^T T^-1``:

    * ``dr/db_j = -g_j / k_j``
    * ``dr/dk_j = -g_j z_j / k_j``
    * ``dr/dtheta = -g . (dT/dtheta) y``  for ``theta`` in (alpha, beta, gamma)
    """
    b, k, ang = _unpack(p)
    T = t_matrix(*ang)
    Tinv = np.linalg.inv(T)
    # component-major (3, N) layout: each step is one contiguous pass (trimag._core.rowwise)
    z = np.empty((3, len(x)))
    np.subtract(x.T, b[:, None], out=z)
    z *= (1.0 / k)[:, None]
    y = Tinv @ z
    mag = np.sqrt(y[0] * y[0] + y[1] * y[1] + y[2] * y[2])
    r = mag - target
    if not jacobian:
        return r, None
    y *= 1.0 / mag  # y is now n = y / |y|; y itself is mag * n below
    g = Tinv.T @ y
    Jt = np.empty((9, len(x)))
    np.multiply(g, (-1.0 / k)[:, None], out=Jt[0:3])
    np.multiply(Jt[0:3], z, out=Jt[3:6])
    for j, dT in enumerate(t_matrix_derivatives(*ang)):
        v = dT @ y  # (dT/dtheta) n; times mag gives (dT/dtheta) y
        Jt[6 + j] = v[0] * g[0]
        Jt[6 + j] += v[1] * g[1]
        Jt[6 + j] += v[2] * g[2]
        Jt[6 + j] *= -mag
    return r, Jt.T


def _centred_singular_values(B: NDArray[np.float64]) -> NDArray[np.float64]:
    """Singular values (3,), largest first, of the samples ``B`` (N, 3) minus their mean, block by block (the
    triangular factor of a blocked QR has the same singular values: :class:`._qr.BlockedQR`)."""
    qr = BlockedQR(3)
    for _, t in transposed_blocks(B, column_means(B), block=chunk_rows()):
        qr.add(t.T)
    return np.asarray(np.linalg.svd(qr.R, compute_uv=False), dtype=np.float64)


def planarity(B: NDArray[np.float64]) -> float:
    """Thinnest over widest RMS spread of the samples about their mean (0 for samples on one plane).

    A full turn about one axis puts the raw field on an ellipse in a plane: the ratio is then only the noise
    over the field. Turns about three axes give a ratio of order 1.
    """
    sv = _centred_singular_values(B)
    return float(sv[2] / sv[0]) if sv[0] > 0 else 0.0


def algebraic_start(B: NDArray[np.float64], F: NDArray[np.float64]) -> tuple[Scalar9, float]:
    """Start values from a linear least-squares quadric fit, in the scalar9 gauge.

    On centred, scaled samples ``u`` the ellipsoid ``(u - c)^T A (u - c) = F^2`` is, up to a factor,
    ``u^T A' u + v^T u = 1`` (nine unknowns; the centre of the samples lies inside the ellipsoid, so the
    constant term is non-zero and can be set to one). One linear least-squares solve, exact for noise-free
    samples. Then ``c = -A'^-1 v / 2``, ``A = A' mean(F^2) / (1 + c^T A' c)``, ``A = M^T M`` (Cholesky) gives
    the correction ``M``, reduced to the scalar9 gauge by :func:`~trimag.models.scalar9.lq_gauge` (same
    magnitudes).

    The design is accumulated block by block into a QR factorisation (:class:`._qr.BlockedQR`): memory does not
    grow with N.

    Returns
    -------
    start : Scalar9
    cond : float
        Column-normalised condition number of the linear design (infinite for samples on one plane).

    Raises
    ------
    IdentifiabilityError
        When the fitted quadric is not an ellipsoid.
    """
    n = len(B)
    norm = normalisation_stats(B)
    centre, scale = norm.centre, norm.scale
    f2_mean = float(F @ F) / max(n, 1) / scale**2
    # the design D = (x^2, y^2, z^2, 2yz, 2xz, 2xy, x, y, z) of u = (B - centre) / scale, block by block into a
    # QR factorisation: the same minimum-norm solution and condition number as numpy.linalg.lstsq(D, 1)
    qr = BlockedQR(9)
    ones = np.ones(min(max(n, 1), chunk_rows()))
    with scratch(9, min(max(n, 1), chunk_rows())) as design:
        for _, t in transposed_blocks(B, centre, block=chunk_rows()):
            t *= 1.0 / scale
            d = quadratic_terms(t, design[:, : t.shape[1]])
            d[3:6] *= 2.0
            d[6:9] = t
            qr.add(d.T, ones[: t.shape[1]])
    cond, _, _ = design_condition(qr.R)  # R has the singular values and column norms of D
    theta = qr.solve()
    a11, a22, a33, a23, a13, a12 = theta[:6]
    A = np.array([[a11, a12, a13], [a12, a22, a23], [a13, a23, a33]])
    v = theta[6:9]
    try:
        c = -0.5 * np.linalg.solve(A, v)
        lam = f2_mean / (1.0 + float(c @ A @ c))
        M = np.linalg.cholesky(A * lam).T
    except np.linalg.LinAlgError:
        raise IdentifiabilityError("the linear start fit is not an ellipsoid") from None
    # |M (u - c)| = F / scale  <=>  |M (x - (centre + scale c))| = F
    start = Scalar9.from_matrix_offset(M, centre + scale * c, gauge="magnitude")
    return start, cond


def _blocks(
    B: NDArray[np.float64], F: NDArray[np.float64], scale: float
) -> Iterator[tuple[NDArray[np.float64], NDArray[np.float64]]]:
    """Consecutive chunks of samples (:func:`~trimag._core.chunks.chunk_rows`) and their reference, both divided by
    ``scale``."""
    for rows in row_blocks(len(B)):
        yield B[rows] / scale, F[rows] / scale


def half_sum_squares(B: NDArray[np.float64], F: NDArray[np.float64], scale: float, p: NDArray[np.float64]) -> float:
    """``0.5 sum r_i^2`` of :func:`residual_jacobian` on ``B / scale``, ``F / scale``, block by block."""
    total = 0.0
    for x, t in _blocks(B, F, scale):
        r, _ = residual_jacobian(x, t, p, jacobian=False)
        total += float(r @ r)
    return 0.5 * total


def linearise(
    B: NDArray[np.float64], F: NDArray[np.float64], scale: float, p: NDArray[np.float64]
) -> tuple[BlockedQR, float]:
    """The Gauss-Newton system ``min |J delta + r|`` at ``p`` as a QR factorisation accumulated block by block
    (:class:`._qr.BlockedQR` of ``[J | -r]``; ``J`` is never held whole), and ``0.5 sum r_i^2``."""
    qr = BlockedQR(9)
    total = 0.0
    for x, t in _blocks(B, F, scale):
        r, J = residual_jacobian(x, t, p)
        assert J is not None
        qr.add(J, -r)
        total += float(r @ r)
    return qr, 0.5 * total


def gauss_newton(
    B: NDArray[np.float64],
    F: NDArray[np.float64],
    scale: float,
    p0: NDArray[np.float64],
    *,
    max_iter: int = 50,
    xtol: float = 1e-10,
    ftol: float = 1e-14,
    max_halvings: int = 20,
) -> dict[str, Any]:
    """Plain Gauss-Newton with step halving on the samples ``B`` and reference ``F`` divided by ``scale``.

    Each step ``delta = argmin |J delta + r|`` comes from a QR factorisation of ``[J | -r]`` accumulated block by
    block (:func:`linearise`): the least-squares solution of the whole system without forming ``J^T J`` or
    holding ``J`` (N, 9), so memory does not grow with N.

    Returns
    -------
    dict
        ``p`` (9,), ``converged`` (bool), ``iterations`` (int), ``history`` (list of dicts with ``iteration``,
        ``cost`` = 0.5 sum r^2, ``step_norm``, ``step_fraction``), ``stalled`` (no halving lowered the cost),
        ``system`` (the :class:`._qr.BlockedQR` of the system at ``p``) and ``cost`` at ``p``.
    """

    def evaluate(q: NDArray[np.float64]) -> tuple[bool, float]:
        try:
            return True, half_sum_squares(B, F, scale, q)
        except (np.linalg.LinAlgError, FloatingPointError):
            return True, math.inf

    def converged(q: NDArray[np.float64], step_norm: float, cost: float, cost_new: float, fraction: float) -> bool:
        return step_norm <= xtol * (xtol + float(np.linalg.norm(q))) or (
            fraction == 1.0 and cost - cost_new <= ftol * max(cost_new, 1e-300)
        )

    run = gauss_newton_rule(
        evaluate, lambda q, _: linearise(B, F, scale, q)[0], lambda _, qr: qr.solve(), p0, max_steps=max_iter,
        converged=converged, rounding_step=None, halvings=max_halvings,
    )
    history: list[dict[str, Any]] = [
        {"iteration": it, "cost": cost, "step_norm": step_norm, "step_fraction": fraction}
        for it, (cost, step_norm, fraction) in enumerate(
            zip(run.costs, [0.0, *run.step_norms], [0.0, *run.fractions], strict=True)
        )
    ]
    if run.stalled:
        history.append({"iteration": run.steps, "cost": run.cost, "step_norm": 0.0, "step_fraction": 0.0})
    return {"p": run.p, "converged": run.converged, "iterations": run.steps, "history": history,
            "stalled": run.stalled, "system": run.model, "cost": run.cost}


# ---------------------------------------------------------------------------------------------- estimator
class GaussNewton(Estimator):
    """Paper B: Gauss-Newton on ``|T^-1 K^-1 (B_m - b)| = F`` for the nine parameters of ``scalar9``.

    Parameters
    ----------
    model : str
        ``"scalar9"``.
    max_iter : int
        Gauss-Newton iteration limit (the paper reports convergence in 4).
    xtol : float
        Converged when ``|delta| <= xtol * (xtol + |p|)`` (parameters normalised by the field scale).
    ftol : float
        Converged when a full step lowers the cost by less than ``ftol`` relative.
    max_halvings : int
        Step halvings tried before falling back to Levenberg-Marquardt.
    fallback : bool
        Continue with Levenberg-Marquardt (and warn) when Gauss-Newton stalls or runs out of iterations;
        with ``False`` the Gauss-Newton result is returned with ``converged = False`` and a warning.
    max_rel_std : float
        Largest accepted predicted standard deviation of a parameter, relative to its scale (biases: the
        field magnitude; scale factors: 1; angles: 1 rad). Above it the data are declared unable to identify
        the model (``IdentifiabilityError``, exit 3).
    min_thickness : float
        Smallest accepted ratio of the samples' thinnest RMS spread (about their best plane) to the residual
        noise of the fit. A turn about a single axis has a ratio near 1 (its out-of-plane spread is only
        noise): such data raise ``IdentifiabilityError``; turns about three axes give hundreds or more. Applied
        only when the samples are close to one plane (thinnest/widest spread below 0.2).
    start : dict or None
        Start parameters ``{name: value}`` (angles in radians) instead of the algebraic fit.

    Examples
    --------
    >>> import numpy as np
    >>> from trimag.models.scalar9 import Scalar9
    >>> from trimag.simulate import simulate
    >>> truth = Scalar9(b1=300.0, b2=-200.0, b3=150.0, k1=1.01, k2=0.99, k3=1.005, alpha=0.01)
    >>> sim = simulate(truth, n=600, field_nav=(48193.0, 0, 0), attitudes="axes", seed=1)
    >>> est = GaussNewton().fit(sim.raw, 48193.0, units="nT")
    >>> est.calibration_.stats["rms_after"] < 1e-6
    True
    """

    name = "gauss-newton"
    models = ("scalar9",)
    requires_reference = False

    def __init__(
        self,
        model: str = "scalar9",
        max_iter: int = 50,
        xtol: float = 1e-10,
        ftol: float = 1e-14,
        max_halvings: int = 20,
        fallback: bool = True,
        max_rel_std: float = 0.01,
        min_thickness: float = 3.0,
        start: dict[str, float] | None = None,
    ) -> None:
        self.model = model
        self.max_iter = max_iter
        self.xtol = xtol
        self.ftol = ftol
        self.max_halvings = max_halvings
        self.fallback = fallback
        self.max_rel_std = max_rel_std
        self.min_thickness = min_thickness
        self.start = start

    def _check_options(self) -> None:
        if not (isinstance(self.max_iter, int) and self.max_iter >= 1):
            raise TrimagInputError(
                f"gauss-newton option max_iter must be an integer >= 1; got {self.max_iter!r}"
            )
        for key in ("xtol", "ftol", "max_rel_std", "min_thickness"):
            value = getattr(self, key)
            if not (isinstance(value, (int, float)) and value > 0):
                raise TrimagInputError(f"gauss-newton option {key} must be a positive number; got {value!r}")

    def _start(
        self, B: NDArray[np.float64], F: NDArray[np.float64], geometry_hint: Callable[[], str]
    ) -> tuple[Scalar9, str]:
        """The starting model (given, or the linear quadric fit) and how it was obtained."""
        if self.start is not None:
            start = Scalar9.from_dict(self.start)
            start_kind = "given"
        else:
            try:
                start, start_cond = algebraic_start(B, F)
            except IdentifiabilityError as exc:
                raise IdentifiabilityError(
                    f"the data cannot identify the scalar9 model: {geometry_hint()} ({exc})"
                ) from None
            if not np.isfinite(start_cond) or start_cond > CONDITION_ERROR:
                raise IdentifiabilityError(
                    f"the data cannot identify the scalar9 model: {geometry_hint()} (condition number of "
                    f"the linear start fit {start_cond:.3g})"
                )
            start_kind = "linear quadric fit u^T A u + v^T u = 1 scaled to F, scalar9 gauge"
        return start, start_kind

    def _solve(
        self, B: NDArray[np.float64], F: NDArray[np.float64], s: float, p0: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], dict[str, Any], list[dict[str, Any]], bool, str, dict[str, Any] | None]:
        """Gauss-Newton from ``p0`` (normalised parameters), then Levenberg-Marquardt if it does not converge:
        ``(p, gn, history, converged, optimizer, fallback_info)``."""
        with np.errstate(over="raise", invalid="raise", divide="raise"):
            try:
                gn = gauss_newton(
                    B, F, s, p0, max_iter=self.max_iter, xtol=self.xtol, ftol=self.ftol,
                    max_halvings=self.max_halvings,
                )
            except FloatingPointError:
                gn = {"p": p0, "converged": False, "iterations": 0, "history": [], "stalled": True, "system": None}
        p = gn["p"]
        history = gn["history"]
        converged = bool(gn["converged"])
        optimizer = "gauss-newton"
        fallback_info: dict[str, Any] | None = None
        if not converged:
            why = (
                "no step along the Gauss-Newton direction lowered the cost"
                if gn["stalled"]
                else f"not converged after max_iter={self.max_iter} iterations"
            )
            if self.fallback:
                # (the fallback holds the whole (N, 9) Jacobian: MINPACK needs it)
                x, target = B / s, F / s
                res = levenberg_marquardt(
                    lambda q: residual_jacobian(x, target, q, jacobian=False)[0],
                    p,
                    jac=lambda q: np.asarray(residual_jacobian(x, target, q)[1]),
                    xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=2000,
                )
                p = res.x
                converged = bool(res.success)
                optimizer = "gauss-newton -> levenberg-marquardt"
                fallback_info = {"reason": why, "lm_nfev": int(res.nfev), "lm_message": str(res.message)}
                del x, target
                gn["system"] = None  # p moved: the system at p is recomputed below
                history = [*history, {
                    "iteration": len(history), "cost": half_sum_squares(B, F, s, p),
                    "step_norm": float(np.linalg.norm(res.x - gn["p"])), "step_fraction": 1.0,
                    "note": "levenberg-marquardt",
                }]
                warnings.warn(
                    f"gauss-newton: {why}; continued with Levenberg-Marquardt "
                    f"({'converged' if converged else 'did not converge: ' + str(res.message)})",
                    GaussNewtonFallbackWarning,
                    stacklevel=4,
                )
            else:
                warnings.warn(
                    f"gauss-newton: {why}; the result is not converged (fallback=False)",
                    GaussNewtonFallbackWarning,
                    stacklevel=4,
                )
        return p, gn, history, converged, optimizer, fallback_info

    def _covariance(
        self, B: NDArray[np.float64], F: NDArray[np.float64], s: float, p: NDArray[np.float64], gn: dict[str, Any],
        sv: NDArray[np.float64], flatness: float, units: str, geometry_hint: Callable[[], str],
    ) -> tuple[float, NDArray[np.float64], float, float]:
        """Identifiability checks and the covariance at the solution ``p`` (normalised parameters), from the QR
        factorisation of the system at ``p`` (R has the singular values, right singular vectors and column norms of
        J, and J^T J = R^T R): ``(condition number, covariance (9, 9), noise std (data unit), thickness / noise)``.
        """
        if gn.get("system") is not None:
            system, half_ss = gn["system"], float(gn["cost"])
        else:
            system, half_ss = linearise(B, F, s, p)
        R = system.R
        cond, jsv, vt = design_condition(R)
        weak = weak_directions(vt, jsv, PARAM_NAMES, threshold=1e4) if np.isfinite(cond) else []
        # the hint (what the samples saw, a least-squares sphere fit) is only made when a message needs it

        def advice() -> str:
            return geometry_hint() if flatness < _FLAT else (
                "record the sensor turning about all three axes (or tumble it through all attitudes)"
            )

        hint = advice() if not np.isfinite(cond) or cond > CONDITION_WARN else ""
        check_condition(cond, what="the scalar9 model (9 parameters)", hint=hint, weak=weak)
        n = len(B)
        dof = max(n - 9, 1)
        sigma2 = 2.0 * half_ss / dof
        try:
            R_inv = np.linalg.inv(R)
        except np.linalg.LinAlgError:
            raise IdentifiabilityError(f"the data cannot identify the scalar9 model: {hint or advice()}") from None
        cov_n = sigma2 * (R_inv @ R_inv.T)  # sigma^2 (J^T J)^-1
        std_n = np.sqrt(np.clip(np.diag(cov_n), 0.0, None))
        # relative spread: biases / field (normalised units already), k / 1, angles / 1 rad
        noise = math.sqrt(sigma2) * s
        thickness = float(sv[2] / math.sqrt(n))
        thickness_ratio = thickness / noise if noise > 0 else math.inf
        if thickness_ratio < self.min_thickness and flatness < _FLAT:
            raise IdentifiabilityError(
                "the data cannot identify the scalar9 model: the samples' spread out of their best plane "
                f"({thickness:.4g} {units} RMS) is no larger than the fit's residual noise "
                f"({noise:.4g} {units}); {single_axis_turn(B, 'the 9 scalar9 parameters')}"
            )
        too_loose = [name for name, v in zip(PARAM_NAMES, std_n, strict=True) if v > self.max_rel_std]
        if too_loose:
            raise IdentifiabilityError(
                "the data cannot identify the scalar9 model: the predicted standard deviation of "
                f"{', '.join(too_loose)} exceeds {self.max_rel_std:g} (relative to the field / 1 / 1 rad); "
                f"{hint or advice()}"
            )

        return cond, cov_n, noise, thickness_ratio

    def _fit(
        self, B: NDArray[np.float64], reference: Any, *, model: str, units: str, attitude: Any
    ) -> Calibration:
        self._check_options()
        check_not_degenerate(B)
        ref = _reference_or_mean(scalar_reference(reference, len(B), units), B)
        F = ref.values
        assert F is not None
        s = float(np.sqrt(F @ F / len(F)))
        # every sum over samples is taken block by block on B / s, F / s (memory independent of N)
        sv = _centred_singular_values(B)
        flatness = float(sv[2] / sv[0]) if sv[0] > 0 else 0.0

        def geometry_hint() -> str:
            """What the samples saw (the cone of field directions, or the axis they turned about) and what to
            record (trimag.quality.diagnostics.coverage_advice): computed only when a message needs it."""
            return coverage_advice(B, s, what="the 9 scalar9 parameters") + (
                " (the paper pools turns about X, Y and Z and fits them together)"
            )

        start, start_kind = self._start(B, F, geometry_hint)
        p0 = start.as_vector()
        p0[:3] /= s
        p, gn, history, converged, optimizer, fallback_info = self._solve(B, F, s, p0)
        if p[3:6].min() <= 0 or np.abs(p[6:9]).max() >= math.pi / 2:
            raise IdentifiabilityError(
                "the scalar9 fit left the valid region (a scale factor <= 0 or an angle beyond 90 degrees): "
                f"the data do not identify the model. {geometry_hint() if flatness < _FLAT else ''}".strip()
            )

        cond, cov_n, noise, thickness_ratio = self._covariance(B, F, s, p, gn, sv, flatness, units, geometry_hint)
        fitted, uncertainty = _in_data_units(p, cov_n, s, noise)
        matrix, offset = fitted.correction()
        diagnostics: dict[str, Any] = {
            "condition_number": cond,
            "planarity": flatness,
            "thickness_to_noise": thickness_ratio,
            "optimizer": optimizer,
            "start": start_kind,
            "start_params": {k: float(v) for k, v in start.as_dict().items()},
            "history": _history_in_data_units(history, s, len(B)),
            "history_units": {"cost": f"0.5*sum((|B|-F)^2) in {units}^2", "rms": units,
                              "step_norm": "normalised parameters (biases / field scale)"},
            "angles_deg": fitted.angles_deg(),
        }
        if fallback_info is not None:
            diagnostics["fallback"] = "levenberg-marquardt"
            diagnostics["fallback_info"] = fallback_info
        return build_calibration(
            B, matrix, offset, model=model, method=self.name, units=units, reference=ref,
            params=fitted.as_dict(), iterations=int(gn["iterations"]), converged=converged,
            uncertainty=uncertainty, diagnostics=diagnostics,
            extra_stats={"gn_converged": bool(gn["converged"])},
        )


def _reference_or_mean(ref: ScalarReference, B: NDArray[np.float64]) -> ScalarReference:
    """``ref``, or without values the mean raw magnitude ``mean |B_m|`` for every sample (paper B's "mean value"
    reference)."""
    if ref.values is not None:
        return ref
    f_mean = float(np.linalg.norm(B, axis=1).mean())
    return ScalarReference(np.full(len(B), f_mean), f"mean |B_raw| of the {len(B)} fitted samples", ref.unit)


def _in_data_units(
    p: NDArray[np.float64], cov_n: NDArray[np.float64], s: float, noise: float
) -> tuple[Scalar9, dict[str, Any]]:
    """The fitted model and its uncertainty record in data units from the normalised solution ``p`` (biases /
    ``s``) and its covariance."""
    scale_vec = np.concatenate([np.full(3, s), np.ones(6)])
    fitted = Scalar9.from_vector(p * scale_vec)
    cov = cov_n * np.outer(scale_vec, scale_vec)
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    param_std = dict(zip(PARAM_NAMES, std.tolist(), strict=True))
    uncertainty = make_uncertainty(
        PARAM_NAMES, covariance=cov, noise_std=float(noise),
        basis="cov = s^2 (J^T J)^-1 at the solution, s^2 = sum(r^2)/(N-9); biases in the data unit",
        param_std_deg={a: math.degrees(param_std[a]) for a in _ANGLES},
    )
    return fitted, uncertainty


def _history_in_data_units(history: list[dict[str, Any]], s: float, n: int) -> list[dict[str, Any]]:
    """The Gauss-Newton history with ``cost`` (0.5 sum r^2) and ``rms`` in the data unit (squared for the cost)."""
    return [
        {
            **h,
            "cost": float(h["cost"]) * s * s,
            "rms": float(math.sqrt(2.0 * h["cost"] / n)) * s,
            "step_norm": float(h["step_norm"]),
        }
        for h in history
    ]


def params_text(cal: Calibration) -> str:
    """Human-readable parameters of a calibration (see :func:`trimag.quality.report.params_table`)."""
    from ..quality.report import params_table

    return params_table(cal)
