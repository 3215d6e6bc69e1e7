"""``twostep``: TWOSTEP, the complete linear attitude-independent calibration of Alonso & Shuster (2002).

R. Alonso, M. D. Shuster, "Complete linear attitude-independent magnetometer calibration", J. Astronaut. Sci.
50(4), 2002. With ``A = I + D`` symmetric (the correction), ``b`` the offset and ``F_k`` the reference magnitude,
each sample gives the scalar measurement

    z_k = |x_k|^2 - F_k^2 = -x_k^T E x_k + 2 x_k^T c - |c|_E^2 + v_k,
    E = A^2 - I,   c = (I + E) b,   |c|_E^2 = c^T (I + E)^-1 c = b^T A^2 b,

whose noise ``v_k`` has mean ``mu = -sigma^2 tr(I + E)`` (``E|x + e|^2``) and variance
``sigma_k^2 = 4 sigma^2 |A y_k|^2`` (to first order; ``y_k`` the corrected field).

* **Step 1 (centred, linear)**: treating the constant ``|c|_E^2 + mu`` as one more unknown makes ``z_k`` linear in
  ``(E, c, const)``; the weighted linear least-squares solution is the "centred" estimate (the constant is what
  centring removes).
  With one magnitude for every sample (the usual ground calibration) this centred problem is degenerate
  (``E = -I``, ``c = 0`` fits exactly, since ``|x|^2`` is a combination of the design's columns); Alonso &
  Shuster's orbit data have a varying ``F_k``. Step 1 then starts from the algebraic fit (``ellipsoid-fit``).
* **Step 2**: Gauss-Newton on the full nonlinear model (the constant tied to ``c`` and ``E``, the noise mean
  subtracted) with the weights ``1 / sigma_k^2``, started from step 1.

The noise ``sigma`` TWOSTEP needs is an option (``noise_std``); when it is not given it is estimated from the
step-1 residuals. The fit is made on normalised data; without a reference the magnitude is 1 there and the
result is scaled to ``det W = 1``. TWOSTEP's step 1 is an algebraic fit: its errors-in-variables bias is what
step 2 reduces but does not remove at strong noise (``docs/accuracy.md``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._core.chunks import chunk_rows
from .._core.rowwise import row_dot, scratch, sum_squares, transposed_blocks
from .._core.solve import GaussNewtonResult, gauss_newton_rule, levenberg_marquardt
from ..calibration import Calibration
from ..errors import IdentifiabilityError
from ..models.ellipsoid import to_upper
from ..quality.diagnostics import CONDITION_WARN, check_not_degenerate, design_condition
from ._common import (
    Normalisation,
    algebraic_ellipsoid,
    check_ellipsoid_options,
    gauge_scale,
    normalisation_stats,
    normalise,
    scalar_reference,
)
from ._finish import ellipsoid_result
from .base import Estimator

__all__ = ["TwoStep"]

_SYM = (np.array([0, 1, 2, 1, 0, 0]), np.array([0, 1, 2, 2, 2, 1]))  # E11 E22 E33 E23 E13 E12
_TERMS = ("E11", "E22", "E33", "E23", "E13", "E12", "c1", "c2", "c3", "const")


def _sym(e: NDArray[np.float64]) -> NDArray[np.float64]:
    E = np.zeros((3, 3))
    E[_SYM] = e
    E[_SYM[1], _SYM[0]] = e
    return E


def _design_rows(t: NDArray[np.float64], out: NDArray[np.float64]) -> NDArray[np.float64]:
    """The design's rows ``(-x^2, -y^2, -z^2, -2yz, -2xz, -2xy, 2x, 2y, 2z)`` (9, m) of the component-major samples
    ``t`` (3, m), written into ``out``: ``z_k = L_k (e, c) - const``."""
    x, y, z = t
    for k, (a, b, f) in enumerate(((x, x, -1.0), (y, y, -1.0), (z, z, -1.0), (y, z, -2.0), (x, z, -2.0),
                                   (x, y, -2.0))):
        np.multiply(a, b, out=out[k])
        out[k] *= f
    np.multiply(t, 2.0, out=out[6:9])
    return out


def _design(u: NDArray[np.float64]) -> NDArray[np.float64]:
    """The (N, 9) design (:func:`_design_rows` of every sample), for the paths that need it whole."""
    Lt = np.empty((9, len(u)))
    _design_rows(np.ascontiguousarray(u.T), Lt)
    return Lt.T


#: Measurement weights: an array (N,), or ``(b, M)`` to compute ``1 / |M (u_k - b)|^2`` block by block.
Weights = NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]
#: Field magnitudes: one number for every sample, or an array (N,).
Magnitudes = float | NDArray[np.float64]


def _blocks(u: NDArray[np.float64], rows: int, norm: Normalisation | None = None) -> Any:
    """``(start, t, work)`` per block of :func:`transposed_blocks`, ``work`` a reused (rows, m) buffer. With
    ``norm``, ``u`` are raw samples and ``t`` is normalised (``(x - centre) / scale``): no normalised copy."""
    with scratch(rows, min(max(len(u), 1), chunk_rows())) as work:
        for start, t in transposed_blocks(u, None if norm is None else norm.centre):
            if norm is not None:
                t *= 1.0 / norm.scale
            yield start, t, work[:, : t.shape[1]]


def _block_weights(t: NDArray[np.float64], w: Weights, start: int, out: NDArray[np.float64],
                   work: NDArray[np.float64]) -> NDArray[np.float64]:
    """The weights of the block ``t`` (3, m) starting at sample ``start`` into ``out`` (m,); ``work`` (8, m)."""
    m = t.shape[1]
    if not isinstance(w, tuple):
        np.copyto(out, w[start : start + m])
        return out
    b, M = w
    e = np.subtract(t, b[:, None], out=work[:3])
    y = np.matmul(M, e, out=work[3:6])
    q = sum_squares(y, out=work[6], tmp=work[7])
    return np.divide(1.0, np.maximum(q, 1e-12, out=q), out=out)


def _block_z(t: NDArray[np.float64], F: Magnitudes, start: int, out: NDArray[np.float64],
             tmp: NDArray[np.float64]) -> NDArray[np.float64]:
    """``z_k = |u_k|^2 - F_k^2`` of the block ``t`` (3, m) starting at sample ``start`` into ``out`` (m,)."""
    sum_squares(t, out=out, tmp=tmp)
    if np.ndim(F) == 0:
        out -= float(F) ** 2
    else:
        Fb = F[start : start + t.shape[1]]  # type: ignore[index]
        out -= np.multiply(Fb, Fb, out=tmp)
    return out


def _weights(u: NDArray[np.float64], b: NDArray[np.float64], M: NDArray[np.float64]) -> NDArray[np.float64]:
    """TWOSTEP's measurement weights ``1 / |M (u_k - b)|^2`` with ``M = A^2`` symmetric: ``|A^2 (x - b)|^2 =
    (x - b)^T M^2 (x - b) ~ |A y|^2``, shape (N,). Computed in blocks (no (N, 3) temporary)."""
    w = np.empty(len(u))
    M = np.ascontiguousarray(M)
    for start, t, work in _blocks(u, 8):
        _block_weights(t, (b, M), start, w[start : start + t.shape[1]], work)
    return w


def _centred_start(
    u: NDArray[np.float64], F: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """TWOSTEP's centred linear estimate ``(M, b)`` of normalised samples ``u`` (N, 3) with per-sample magnitudes
    ``F`` (N,): weighted least squares of ``z_k`` on the design and a constant, with one reweighting. None when the
    design is degenerate (F nearly constant) or the estimate is not an ellipsoid."""
    z = row_dot(u, u) - F**2
    A1 = np.column_stack([_design(u), -np.ones(len(u))])
    cond, _, _ = design_condition(A1)
    if not np.isfinite(cond) or cond > CONDITION_WARN:
        return None
    w = np.ones(len(u))
    for _ in range(2):
        sw = np.sqrt(w)
        x1, *_ = np.linalg.lstsq(A1 * sw[:, None], z * sw, rcond=None)
        M1 = np.eye(3) + _sym(x1[:6])
        if np.any(np.linalg.eigvalsh(M1) <= 0):
            return None
        b1 = np.linalg.solve(M1, x1[6:9])
        w = _weights(u, b1, M1)
    return M1, b1


def _magnitude_misfit(u: NDArray[np.float64], A: NDArray[np.float64], b: NDArray[np.float64],
                      F: Magnitudes, norm: Normalisation | None = None) -> float:
    """``mean((|A (u_k - b)| - F_k)^2)``, in blocks (``norm``: as :func:`_blocks`)."""
    total = 0.0
    A = np.ascontiguousarray(A)
    for start, t, work in _blocks(u, 5, norm):
        t -= b[:, None]
        y = np.matmul(A, t, out=work[:3])
        mag = np.sqrt(sum_squares(y, out=work[3], tmp=work[4]), out=work[3])
        mag -= F if np.ndim(F) == 0 else F[start : start + t.shape[1]]  # type: ignore[index]
        total += float(mag @ mag)
    return total / len(u)


def _step2_statistics(
    u: NDArray[np.float64], w: Weights, F: Magnitudes, norm: Normalisation | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], float, float, float]:
    """``G = Lw^T Lw``, ``h = Lw^T sw``, ``k = Lw^T zw``, ``sw^T sw``, ``sw^T zw``, ``zw^T zw`` with ``sw = sqrt(w)``,
    ``Lw = sw L``, ``zw = sw z``, ``z_k = |u_k|^2 - F_k^2``: step 2's sufficient statistics, accumulated block by
    block (the (N, 9) design is never formed; ``norm``: as :func:`_blocks`)."""
    G, h, k = np.zeros((9, 9)), np.zeros(9), np.zeros(9)
    s0 = s1 = s2 = 0.0
    for start, t, work in _blocks(u, 19, norm):
        Lw, sw, zw = work[:9], work[9], work[10]
        _block_weights(t, w, start, sw, work[11:19])
        np.sqrt(sw, out=sw)
        _block_z(t, F, start, zw, work[11])
        zw *= sw
        _design_rows(t, Lw)
        Lw *= sw
        G += Lw @ Lw.T
        h += Lw @ sw
        k += Lw @ zw
        s0, s1, s2 = s0 + float(sw @ sw), s1 + float(sw @ zw), s2 + float(zw @ zw)
    return G, h, k, s0, s1, s2


def _weighted_residual_sum(
    u: NDArray[np.float64], w: Weights, F: Magnitudes, x: NDArray[np.float64], norm: Normalisation | None = None
) -> float:
    """``sum w_k (L_k x[:9] - x[9] - z_k)^2`` (step 1's weighted residuals), in blocks (``norm``: as
    :func:`_blocks`)."""
    total = 0.0
    for start, t, work in _blocks(u, 20, norm):
        r = np.matmul(x[:9], _design_rows(t, work[:9]), out=work[9])
        r -= x[9]
        r -= _block_z(t, F, start, work[10], work[11])
        wb = _block_weights(t, w, start, work[11], work[12:20])
        total += float(np.dot(np.multiply(wb, r, out=work[10]), r))
    return total


def _gauss_newton_step2(
    stats: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], float, float, float],
    p0: NDArray[np.float64], const_and_grad: Any, *, max_steps: int = 50, xtol: float = 1e-12,
) -> GaussNewtonResult | None:
    """Step 2 by Gauss-Newton (:func:`trimag._core.solve.gauss_newton_rule`) on 9 x 9 sufficient statistics, or
    None when a step raises the cost.

    The residual ``r = sw (L p - const(p) - z)`` is linear in ``p`` but for the scalar ``const``, so ``J^T J``,
    ``J^T r`` and ``r^T r`` follow from ``stats`` = (``G = Lw^T Lw``, ``h = Lw^T sw``, ``k = Lw^T zw``, and three
    scalars; ``Lw = sw L``, ``zw = sw z``; :func:`_step2_statistics`), computed once: each step costs O(1)
    instead of an (N, 9) Jacobian. A step counts as raising the cost above ``1e-10`` relative plus ``1e-12``
    of ``zw^T zw``; converged when ``|step| <= xtol (1 + |p|)``.
    """
    G, h, k, s0, s1, s2 = stats

    def evaluate(p: NDArray[np.float64]) -> tuple[tuple[NDArray[np.float64], float, NDArray[np.float64]], float]:
        const, dconst = const_and_grad(p)
        return (p, const, dconst), float(p @ G @ p - 2.0 * p @ (h * const + k) + s0 * const**2 + 2.0 * const * s1 + s2)

    def direction(state: tuple[NDArray[np.float64], float, NDArray[np.float64]], _: Any) -> NDArray[np.float64] | None:
        p, const, dconst = state
        JtJ = G - np.outer(h, dconst) - np.outer(dconst, h) + s0 * np.outer(dconst, dconst)
        Jtr = (G @ p - h * const - k) - dconst * (h @ p - s0 * const - s1)
        try:
            return np.asarray(-np.linalg.solve(JtJ, Jtr), dtype=np.float64)
        except np.linalg.LinAlgError:
            return None

    run = gauss_newton_rule(
        evaluate, lambda p, state: None, direction, p0, max_steps=max_steps,
        converged=lambda p, step, *_: bool(step <= xtol * (1.0 + np.linalg.norm(p))),
        rises=lambda f_new, f: f_new > f + 1e-10 * abs(f) + 1e-12 * s2, rounding_step=0.0,
    )
    if not run.converged:
        return None
    return GaussNewtonResult(
        x=run.p, nfev=run.nfev, success=True,
        message=f"Gauss-Newton on sufficient statistics converged in {run.nfev - 1} steps",
    )


class TwoStep(Estimator):
    """TWOSTEP (Alonso & Shuster 2002): centred linear estimate, then Gauss-Newton with measurement weights.

    Parameters
    ----------
    model : str
        ``"ellipsoid"``.
    form : {"upper", "symmetric"}
        Gauge of the returned soft-iron matrix (TWOSTEP's own is symmetric).
    noise_std : float, optional
        Noise standard deviation per axis, data unit; estimated from the step-1 residuals when None.
    max_iter : int
        Gauss-Newton iteration limit of step 2.
    """

    name = "twostep"
    models = ("ellipsoid",)

    def __init__(
        self, model: str = "ellipsoid", form: str = "upper", noise_std: float | None = None, max_iter: int = 50
    ) -> None:
        self.model = model
        self.form = form
        self.noise_std = noise_std
        self.max_iter = max_iter

    def _fit(
        self, B: NDArray[np.float64], reference: Any, *, model: str, units: str, attitude: Any
    ) -> Calibration:
        check_ellipsoid_options(self.form, self.noise_std)
        principal = check_not_degenerate(B)
        ref = scalar_reference(reference, len(B), units)
        f_scale = 1.0
        F: Magnitudes = 1.0
        if ref.values is not None:
            f_scale = float(np.sqrt(np.mean(ref.values**2)))
            F = ref.values / f_scale
        s1 = _step1(B, F)
        if self.noise_std is not None:
            sigma2 = (float(self.noise_std) / s1.norm.scale) ** 2
        else:
            sigma2 = _weighted_residual_sum(s1.src, s1.w, s1.F, s1.x1, s1.src_norm) / (4.0 * max(len(B) - 10, 1))
        res = _step2(s1, sigma2, self.max_iter)
        A, b_u, step2_used = _guarded_estimate(res, s1)
        W = to_upper(A) * f_scale / s1.norm.scale
        offset = s1.norm.centre + s1.norm.scale * b_u
        F_hat = None
        if ref.values is None:
            W, F_hat = gauge_scale(W, None)
        return ellipsoid_result(
            B, W, offset, ref=ref, F_hat=F_hat, sigma=float(np.sqrt(sigma2) * s1.norm.scale), model=model,
            method=self.name, units=units, form=self.form, iterations=int(res.nfev), converged=bool(res.success),
            diagnostics={"condition_number": s1.cond, "optimizer": str(res.message), "step2_used": step2_used,
                         "step1_start": s1.start},
            uncertainty_note="Fisher information at the estimate (a lower bound; TWOSTEP is not bias-free at "
            "strong noise)",
            principal=principal,
        )


@dataclass
class _Step1:
    """Step 1's estimate ``M1``, ``b1`` (normalised units) and its linear parameters ``x1`` (10,), the magnitudes
    ``F`` (one number when constant), the normalisation, the samples the block sums read (``src``: raw with
    ``src_norm``, or normalised), the measurement weights, the condition number and the start's kind."""

    F: Magnitudes
    norm: Normalisation
    src: NDArray[np.float64]
    src_norm: Normalisation | None
    M1: NDArray[np.float64]
    b1: NDArray[np.float64]
    x1: NDArray[np.float64]
    w: Weights
    cond: float
    start: str


def _step1(B: NDArray[np.float64], F: Magnitudes) -> _Step1:
    """Step 1: centred linear estimate (the constant as an extra unknown), unit weights then one reweighting."""
    if np.ndim(F) == 0 or float(np.ptp(F)) <= 1e-9 * float(np.mean(F)):
        # one magnitude for every sample: z_k = |u_k|^2 - F^2 and the weights are recomputed block by block
        # from the raw samples, so no normalised copy and no per-sample array is made (memory independent
        # of N). The centred problem is degenerate here (E = -I, c = 0 fits z exactly: |x|^2 is a
        # combination of the design's columns), so step 1 starts from the algebraic fit.
        F = float(np.mean(F))
        norm = normalisation_stats(B)
        W0, c0, cond = algebraic_ellipsoid(B, norm)  # also the identifiability check
        M1 = F**2 * (W0.T @ W0)
        b1 = c0
        x1 = np.concatenate([(M1 - np.eye(3))[_SYM], M1 @ b1, [b1 @ M1 @ b1]])
        return _Step1(F, norm, B, norm, M1, b1, x1, (b1, np.ascontiguousarray(M1)), cond, "algebraic")
    u, norm = normalise(B)
    # the algebraic start (scaled to the mean magnitude) is always made; the centred linear estimate
    # only replaces it when it fits the per-sample magnitudes better. When F varies little (a
    # per-sample IGRF or scalar-magnetometer reference over a survey) the centred problem is as
    # degenerate as with one magnitude (E = -I, c = 0 nearly fits z): used alone it found no ellipsoid,
    # or one with a wrong scale (issue 22: mean |B| 22 420 against a 53 941 reference)
    W0, c0, cond = algebraic_ellipsoid(B, norm)  # also the identifiability check
    M1 = float(np.mean(F**2)) * (W0.T @ W0)
    b1 = c0
    start = "algebraic"
    centred = _centred_start(u, np.asarray(F, dtype=np.float64))
    if centred is not None:
        ev_c, evec_c = np.linalg.eigh(centred[0])
        ev_a, evec_a = np.linalg.eigh(M1)
        misfit_c = _magnitude_misfit(u, (evec_c * np.sqrt(ev_c)) @ evec_c.T, centred[1], F)
        misfit_a = _magnitude_misfit(u, (evec_a * np.sqrt(ev_a)) @ evec_a.T, b1, F)
        if misfit_c < misfit_a:
            M1, b1 = centred
            start = "centred"
    x1 = np.concatenate([(M1 - np.eye(3))[_SYM], M1 @ b1, [b1 @ M1 @ b1]])
    return _Step1(F, norm, u, None, M1, b1, x1, _weights(u, b1, M1), cond, start)


def _const_and_grad(sigma2: float) -> Callable[[NDArray[np.float64]], tuple[float, NDArray[np.float64]]]:
    """Step 2's constant ``c^T M^-1 c - sigma^2 tr(M)`` and its gradient in ``p`` (9,), as a function of ``p``."""

    def const_and_grad(p: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
        E, c = _sym(p[:6]), p[6:9]
        M = np.eye(3) + E
        bb = np.linalg.solve(M, c)
        dconst = np.empty(9)
        # d(c^T M^-1 c)/dE_ij = -(b b^T)_ij (x2 off the diagonal); d tr(M)/dE_ii = 1
        outer = np.outer(bb, bb)
        for k, (i, j) in enumerate(zip(*_SYM, strict=True)):
            dconst[k] = -outer[i, j] * (1.0 if i == j else 2.0) - (sigma2 if i == j else 0.0)
        dconst[6:9] = 2 * bb
        return float(c @ bb - sigma2 * np.trace(M)), dconst

    return const_and_grad


def _step2(s1: _Step1, sigma2: float, max_iter: int) -> GaussNewtonResult:
    """Step 2: Gauss-Newton on the nonlinear model with the noise mean subtracted (sufficient statistics,
    :func:`_gauss_newton_step2`); when a step raises the cost, Levenberg-Marquardt from the same start on the whole
    design."""
    const_and_grad = _const_and_grad(sigma2)
    res = _gauss_newton_step2(_step2_statistics(s1.src, s1.w, s1.F, s1.src_norm), s1.x1[:9], const_and_grad,
                              max_steps=max_iter)
    if res is not None:
        return res
    u_all = s1.src if s1.src_norm is None else s1.src_norm.forward(s1.src)
    w_all = _weights(u_all, *s1.w) if isinstance(s1.w, tuple) else s1.w
    z = row_dot(u_all, u_all) - np.square(s1.F)
    L, sw = _design(u_all), np.sqrt(w_all)

    def fun(p: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.asarray(sw * (L @ p - const_and_grad(p)[0] - z), dtype=np.float64)

    def jac(p: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.asarray(sw[:, None] * (L - const_and_grad(p)[1][None, :]), dtype=np.float64)

    return levenberg_marquardt(fun, s1.x1[:9], jac=jac, max_nfev=max_iter * 10, xtol=1e-12, ftol=1e-12, gtol=1e-12)


def _guarded_estimate(
    res: GaussNewtonResult, s1: _Step1
) -> tuple[NDArray[np.float64], NDArray[np.float64], bool]:
    """``A`` (symmetric square root of ``M``) and ``b`` of step 2, or of step 1 when step 2 failed or fits the
    magnitudes worse (it can run away on poorly covered data, e.g. one hemisphere at strong noise); and whether
    step 2 was used."""
    E, c = _sym(res.x[:6]), res.x[6:9]
    M = np.eye(3) + E
    ev, evec = np.linalg.eigh(M)
    if np.any(ev <= 0):
        raise IdentifiabilityError(
            "TWOSTEP converged to a matrix that is not positive definite; record the sensor turning "
            "through many more attitudes (or use `method=ml`)"
        )
    A = (evec * np.sqrt(ev)) @ evec.T
    b_u = np.linalg.solve(M, c)
    ev1, evec1 = np.linalg.eigh(s1.M1)
    A1m = (evec1 * np.sqrt(np.clip(ev1, 0, None))) @ evec1.T
    fit2 = _magnitude_misfit(s1.src, A, b_u, s1.F, s1.src_norm)
    fit1 = _magnitude_misfit(s1.src, A1m, s1.b1, s1.F, s1.src_norm)
    step2_used = bool(res.success) and fit2 <= fit1 * 1.5
    if not step2_used:
        return A1m, s1.b1, False
    return A, b_u, True
