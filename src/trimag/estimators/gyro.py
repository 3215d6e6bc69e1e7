"""``gyro``: the ellipsoid model fitted with the gyroscope beside the magnetometer (issue 31; docs/method-gyro.md).

Model (raw samples ``x_i``, data unit; the gyroscope's frame):

    x_i = M h_i + b + e_i,     e_i ~ N(0, sigma^2 I_3),     dh/dt = -(omega - bias_g) x h,     |h_i| = F

``M`` (3 x 3, "soft iron": the inverse of the correction, including the rotation from the gyroscope's frame to the
magnetometer's), ``b`` the hard iron, ``bias_g`` the gyroscope's bias (rad/s) and, when the gyroscope has its own
clock, the lag between the streams. The field ``h`` in the gyroscope's frame turns as the gyroscope says: within a
segment of the log (``segment_s`` seconds, by default 2) it is ``h_i = G_i^T G_s h_s``, ``G`` the attitude integrated
from the rate (:mod:`trimag.fields.gyro`) and ``h_s`` the field at the segment's first sample, a unit direction
times ``F``: two unknowns per segment. This is ``ml``'s likelihood (``|h_i| = F``, unknown directions: a segment of one
sample) with the directions of consecutive samples tied by the gyroscope; and, as in MAGYC (Rodríguez-Martín et
al. 2024) and Kok & Schön (2016), the rotation the magnitude cannot see is no longer arbitrary, so ``M`` is a full
matrix: ``inv(M) = R W``, ``W`` the upper-triangular correction of every ellipsoid fit and ``R`` the rotation from
the corrected magnetometer frame to the gyroscope's (reported: ``diagnostics["gyro_alignment"]``). Segments keep the
gyroscope's own errors (noise, scale factor, a slowly moving bias) from accumulating: each restarts the integration.

Identification (normalised samples ``u = (x - c) / s``, the fit on ``|h| = 1``; the scale is set afterwards by the
reference magnitude, or by ``det W = 1`` when it is unknown, as ``ml`` does):

1. Start: with the bias 0, ``A u_i - dR_i^T A u_s - (I - dR_i^T) c = 0`` (``A = inv(M)``, ``c = A b``,
   ``dR_i = G_s^T G_i``) is linear and homogeneous in ``(A, c)``: its total least squares (the smallest eigenvector
   of a 12 x 12 scatter accumulated block by block) is MAGYC-LS's estimate (its eq. 14), scaled to ``mean |A (u -
   b)| = 1``. With a second clock, the lag starts at the minimum of that fit's smallest eigenvalue over a grid.
2. Gauss-Newton (:func:`trimag._core.solve.gauss_newton_rule`, with step halving) on all unknowns; the two per
   segment are eliminated from each step's normal equations (a Schur complement of 2 x 2 blocks, accumulated over
   blocks of segments: :func:`trimag._core.chunks.row_blocks`), so a step solves 15 (16 with the lag) equations
   whatever the length of the log.
3. Uncertainty: ``sigma^2`` times the inverse of the reduced normal matrix at the solution (the Cramér–Rao bound of
   the model with the directions as nuisance parameters), ``sigma^2 = sum r^2 / (3 N - p)``; propagated to the
   ellipsoid's parameters (upper ``W``, hard iron, ``F``), the gyroscope's bias, the rotation ``R`` and the lag by
   the Jacobian of that map; then :mod:`trimag.quality.honesty` as for every fit.
4. Identifiability: the column-normalised condition number of the reduced normal matrix (refused above
   ``trimag.quality.diagnostics.CONDITION_ERROR``) and the parameters whose variance is inflated by their
   correlation with the others (``poorly_determined``), next to what a magnitude-only fit of the same samples
   would leave poorly determined (``magnitude_only``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from .._core.chunks import row_blocks
from .._core.solve import gauss_newton_rule
from ..calibration import Calibration, make_uncertainty
from ..errors import IdentifiabilityError, TrimagError, TrimagInputError
from ..fields.gyro import AngularRate, GyroAttitude, describe, integrate_rate, skew
from ..models.ellipsoid import Ellipsoid, to_symmetric
from ..quality.crlb import (
    UPPER,
    UPPER_NAMES,
    _constrained_inverse,
    _upper_param,
    ellipsoid_fisher,
    ellipsoid_geometry,
    predicted_errors,
)
from ..quality.diagnostics import (
    CONDITION_WARN,
    check_condition,
    diagnostic_subsample,
    gram_condition,
    sphere_coverage,
    weak_directions,
)
from ._common import algebraic_ellipsoid, normalise, scalar_reference
from ._finish import INFLATION_WARN, VIF_REPORT, VIF_WARN, _inflation_vs_full_sphere
from .base import Estimator, build_calibration

__all__ = ["GyroAided"]

_NATIVE = (*(f"soft_iron_{a}{b}" for a in (1, 2, 3) for b in (1, 2, 3)), "hard_iron_x", "hard_iron_y",
           "hard_iron_z", "gyro_bias_x", "gyro_bias_y", "gyro_bias_z")
_BIAS = ("gyro_bias_x", "gyro_bias_y", "gyro_bias_z")
_ROTATION = ("gyro_alignment_x", "gyro_alignment_y", "gyro_alignment_z")
_HINT = ("record the sensor turning about at least two axes while the gyroscope logs (or a longer `segment_s`); "
         "the magnitude-only fit (`method=ml`) needs turns about all three")
#: A parameter whose standard deviation is more than this many times a full sphere's (of as many samples, fitted by
#: magnitude alone) is listed as poorly determined; more than ``INFLATION_WARN`` (30) times: unidentified (warned).
POORLY_DETERMINED = 10.0
#: A gap between samples longer than this many median intervals ends a segment (the integration does not bridge it).
GAP_INTERVALS = 5.0
#: The gyroscope is taken not to match the magnetometer (wrong unit, a reversed axis, a wrong time scale) when the
#: fit's vector residual exceeds this many times the magnitude residual of an ellipsoid alone on the same samples
#: (isotropic noise gives sqrt(3) = 1.7; measured 1.35-1.88 on BROAD, the robot and phone logs of
#: docs/method-gyro.md; a slow turn in deg/s read as rad/s: 18) ...
MISMATCH_RATIO = 3.0
#: ... and this fraction of the field (below it the gyroscope's own noise may dominate a very quiet magnetometer's:
#: docs/method-gyro.md, "Limitations").
MISMATCH_FLOOR = 0.01
#: A segment over which the gyroscope turned by more than this (median, degrees) did turn: a start that the
#: equations do not single out then means that the two sensors disagree, not that the sensor stood still.
TURNED_DEG = 5.0


@dataclass
class _Problem:
    """What every evaluation needs: normalised samples ``u`` (N, 3), the segments (first sample of each, and each
    sample's segment), the gyroscope, and which of bias and lag are estimated."""

    u: NDArray[np.float64]
    starts: NDArray[np.int64]
    seg: NDArray[np.int64]
    gyro: AngularRate
    fit_bias: bool
    fit_lag: bool

    @property
    def p(self) -> int:
        return 12 + 3 * self.fit_bias + self.fit_lag


@dataclass
class _State:
    """One evaluation: the unknowns unpacked, the attitude, the predicted field ``q`` (N, 3) and residuals ``r``."""

    p: NDArray[np.float64]
    M: NDArray[np.float64]
    b: NDArray[np.float64]
    bias: NDArray[np.float64]
    lag: float
    h: NDArray[np.float64]
    att: GyroAttitude
    q: NDArray[np.float64]
    r: NDArray[np.float64]


def _segments(t: NDArray[np.float64], length_s: float) -> NDArray[np.int64]:
    """First sample of each segment: a new one every ``length_s`` seconds and after every gap in time."""
    dt = np.diff(t)
    gap = dt > GAP_INTERVALS * float(np.median(dt)) if len(dt) else np.zeros(0, dtype=bool)
    piece = np.concatenate([[0], np.cumsum(gap)])  # which gap-free piece each sample is in
    starts_of_piece = np.concatenate([[0], np.flatnonzero(gap) + 1])
    since = t - t[starts_of_piece[piece]]
    slot = np.floor(since / length_s).astype(np.int64)
    new = np.concatenate([[True], (piece[1:] != piece[:-1]) | (slot[1:] != slot[:-1])])
    return np.flatnonzero(new).astype(np.int64)


def _unpack(problem: _Problem, p: NDArray[np.float64]) -> tuple[Any, ...]:
    M = p[:9].reshape(3, 3)
    b = p[9:12]
    k = 12
    bias = p[k:k + 3] if problem.fit_bias else np.zeros(3)
    k += 3 * problem.fit_bias
    lag = float(p[k]) if problem.fit_lag else problem.gyro.lag_s
    h = p[problem.p:].reshape(-1, 3)
    return M, b, bias, lag, h / np.linalg.norm(h, axis=1, keepdims=True)


def _evaluate(problem: _Problem, p: NDArray[np.float64]) -> tuple[_State | None, float]:
    M, b, bias, lag, h = _unpack(problem, p)
    try:
        att = integrate_rate(problem.gyro, bias, lag)
    except (ValueError, IndexError):
        return None, float("inf")
    G = att.G
    world = np.einsum("kij,kj->ki", G[problem.starts], h)  # G_s h_s: the field in the integration's frame
    q = np.einsum("nji,nj->ni", G, world[problem.seg])  # G_i^T G_s h_s
    r = problem.u - b - q @ M.T
    return _State(np.asarray(p, dtype=np.float64), M, b, bias, lag, h, att, q, r), float(np.sum(r * r))


def _tangent(h: NDArray[np.float64]) -> NDArray[np.float64]:
    """Orthonormal bases (n, 3, 2) of the planes perpendicular to the unit vectors ``h`` (n, 3)."""
    a = np.zeros_like(h)
    a[np.arange(len(h)), np.argmin(np.abs(h), axis=1)] = 1.0
    e1 = np.cross(h, a)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return np.stack([e1, np.cross(h, e1)], axis=2)


def _jacobians(problem: _Problem, st: _State, rows: slice, E: NDArray[np.float64]
               ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per-sample Jacobians of the residual for the samples ``rows``: global (m, 3, p) and local (m, 3, 2)."""
    G, S, q, M = st.att.G[rows], st.att.S[rows], st.q[rows], st.M
    seg = problem.seg[rows]
    first = problem.starts[seg]
    m = len(q)
    J = np.zeros((m, 3, problem.p))
    for a in range(3):  # d r_a / d M_ac = -q_c
        J[:, a, 3 * a:3 * a + 3] = -q
    J[:, :, 9:12] = -np.eye(3)
    Mq = M @ skew(q)  # (m, 3, 3): M [q]x
    k = 12
    if problem.fit_bias:  # r = -M q: dq/dbias = -[q]x G_i^T (S_i - S_s)
        P = np.einsum("nji,njk->nik", G, S - st.att.S[first])
        J[:, :, k:k + 3] = Mq @ P
        k += 3
    if problem.fit_lag:  # dq/dlag = [q]x (w_i - dR^T w_s), dR^T = G_i^T G_s
        w_s = np.einsum("nij,nj->ni", st.att.G[first], st.att.rate[first])
        J[:, :, k] = -np.einsum("nij,nj->ni", Mq, st.att.rate[rows] - np.einsum("nji,nj->ni", G, w_s))
    # local: dq/dh_s = G_i^T G_s (tangent plane of h_s)
    V = np.einsum("sij,sjk->sik", st.att.G[problem.starts], E)  # (n_seg, 3, 2) in the integration's frame
    L = -np.einsum("ab,nbk->nak", M, np.einsum("nji,njk->nik", G, V[seg]))
    return J, L


def _normal_equations(problem: _Problem, st: _State) -> dict[str, Any]:
    """The normal equations with the segments' unknowns eliminated (Schur complement), accumulated over blocks
    of whole segments: ``S`` (p, p), ``g`` (p,) reduced; per segment ``Hll_inv`` (2, 2), ``Hlg`` (2, p), ``gl``."""
    n_seg, p = len(problem.starts), problem.p
    E = _tangent(st.h)
    S, g = np.zeros((p, p)), np.zeros(p)
    Hll_inv, Hlg, gl = np.empty((n_seg, 2, 2)), np.empty((n_seg, 2, p)), np.empty((n_seg, 2))
    per_seg = max(len(problem.u) / n_seg, 1.0)
    ends = np.append(problem.starts[1:], len(problem.u))
    for block in row_blocks(n_seg, 12.0 * (p + 2) * per_seg):
        rows = slice(int(problem.starts[block.start]), int(ends[block.stop - 1]))
        J, L = _jacobians(problem, st, rows, E)
        r = st.r[rows]
        local_starts = problem.starts[block] - rows.start
        Hgg = np.einsum("nap,naq->pq", J, J)
        hll = np.add.reduceat(np.einsum("nak,nal->nkl", L, L), local_starts, axis=0)
        hlg = np.add.reduceat(np.einsum("nak,nap->nkp", L, J), local_starts, axis=0)
        gll = np.add.reduceat(np.einsum("nak,na->nk", L, r), local_starts, axis=0)
        inv = np.linalg.inv(hll)
        X = inv @ hlg  # (b, 2, p)
        S += Hgg - np.einsum("bkp,bkq->pq", hlg, X)
        g += np.einsum("nap,na->p", J, r) - np.einsum("bkp,bk->p", X, gll)
        Hll_inv[block], Hlg[block], gl[block] = inv, hlg, gll
    return {"S": S, "g": g, "Hll_inv": Hll_inv, "Hlg": Hlg, "gl": gl, "E": E}


def _direction(problem: _Problem, st: _State, ne: dict[str, Any]) -> NDArray[np.float64] | None:
    """The Gauss-Newton step: the reduced system for the global unknowns, then each segment's (its direction turned
    on the unit sphere, the stored vector's length kept)."""
    try:
        dg = -np.linalg.solve(ne["S"], ne["g"])
    except np.linalg.LinAlgError:
        return None
    dl = -np.einsum("skl,sl->sk", ne["Hll_inv"], ne["gl"] + ne["Hlg"] @ dg)
    h_new = st.h + np.einsum("sik,sk->si", ne["E"], dl)
    h_new /= np.linalg.norm(h_new, axis=1, keepdims=True)
    h_old = st.p[problem.p:].reshape(-1, 3)
    norm_old = np.linalg.norm(h_old, axis=1, keepdims=True)
    return np.concatenate([dg, (h_new * norm_old - h_old).ravel()])


def _scatter_start(problem: _Problem, att: GyroAttitude) -> tuple[NDArray[np.float64], float]:
    """The 12 x 12 scatter of the linear start's equations (module docstring, step 1) and its smallest eigenvalue
    relative to the trace (the lag grid's criterion)."""
    D = np.zeros((12, 12))
    for rows in row_blocks(len(problem.u), 60.0):
        first = problem.starts[problem.seg[rows]]
        u, u0 = problem.u[rows], problem.u[first]
        dRt = np.einsum("nji,njk->nik", att.G[rows], att.G[first])  # G_i^T G_s
        m = len(u)
        X = np.zeros((m, 3, 12))
        for a in range(3):
            X[:, a, 3 * a:3 * a + 3] = u
            X[:, a, :9] -= np.einsum("nb,nc->nbc", dRt[:, a, :], u0).reshape(m, 9)
        X[:, :, 9:] = -(np.eye(3) - dRt)
        D += np.einsum("nap,naq->pq", X, X)
    ev = np.linalg.eigvalsh(D)
    return D, float(ev[0] / max(np.trace(D), 1e-300))


def _linear_start(problem: _Problem, lag: float) -> NDArray[np.float64]:
    """Start vector (module docstring, step 1): ``M``, ``b``, zero bias, the lag, and each segment's direction."""
    att = integrate_rate(problem.gyro, np.zeros(3), lag)
    D, _ = _scatter_start(problem, att)
    ev, vecs = np.linalg.eigh(D)
    x = vecs[:, 0]
    A, c = x[:9].reshape(3, 3), x[9:]
    if np.linalg.det(A) < 0:  # (A, c) and (-A, -c) fit alike (the field's sign is free): a right-handed sensor
        A, c = -A, -c
    # a second (near-)null direction: the equations do not single out a start (no turning within the segments)
    if not abs(np.linalg.det(A)) > 0 or not ev[1] > max(1.5 * ev[0], 1e-10 * float(np.sum(ev))):
        turned = _turned_deg(problem, att)
        if turned > TURNED_DEG:
            raise IdentifiabilityError(_mismatch(problem.gyro, f"no calibration turns the samples as the gyroscope "
                                                 f"says (it turned {turned:.3g} deg in a median segment)"))
        per_segment = len(problem.u) / len(problem.starts)
        if per_segment < 3:
            raise IdentifiabilityError(f"the gyro-aided fit's segments hold {per_segment:.2g} samples each: check "
                                       "that the time column is in seconds (or give a longer `segment_s`)")
        raise IdentifiabilityError("the gyroscope and the magnetometer do not determine the start of the gyro-aided "
                                   f"fit (the sensor barely turns within the segments: {turned:.2g} deg in a median "
                                   f"one); {_HINT}")
    b = np.linalg.solve(A, c)
    y = (problem.u - b) @ A.T
    A /= float(np.mean(np.linalg.norm(y, axis=1)))
    y = (problem.u - b) @ A.T
    # each segment's first-sample field: the mean of the samples' fields turned back to the segment's start
    back = np.einsum("nij,nj->ni", att.G, y)  # G_i y_i: the integration's frame
    world = np.add.reduceat(back, problem.starts, axis=0)
    h = np.einsum("sji,sj->si", att.G[problem.starts], world)
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    parts = [np.linalg.inv(A).ravel(), b]
    if problem.fit_bias:
        parts.append(np.zeros(3))
    if problem.fit_lag:
        parts.append(np.array([lag]))
    return np.concatenate([*parts, h.ravel()])


def _turned_deg(problem: _Problem, att: GyroAttitude) -> float:
    """The median over segments of the angle (degrees) the gyroscope turned between a segment's first and last
    sample."""
    ends = np.append(problem.starts[1:], len(problem.u)) - 1
    rel = np.einsum("sji,sjk->sik", att.G[problem.starts], att.G[ends])
    return float(np.degrees(np.median(Rotation.from_matrix(rel).magnitude())))


def _mismatch(gyro: AngularRate, what: str) -> str:
    """The refusal of a gyroscope that does not match the magnetometer: ``what`` was seen, and what to check."""
    rms = float(np.sqrt(np.mean(np.sum(gyro.rate**2, axis=1))))
    unit = ("; the numbers look like deg/s" if rms > 20.0 else
            "; numbers in deg/s read as rad/s turn it 57x too far, rad/s read as deg/s 57x too little")
    return (f"the gyroscope's turns do not match the magnetometer's: {what}. Check the rate's unit ({rms:.3g} rad/s "
            f"RMS as read{unit}; `gyro_unit` rad/s or deg/s), that the gyroscope's columns are its x, y, z axes with "
            "their signs (right-handed), and that the time is in seconds; a field that changes where the sensor "
            "moves does the same. `method=ml` fits the magnitude alone")


def _check_consistent(problem: _Problem, st: _State, sc: _Scale, units: str) -> None:
    """Refuse (exit 3) a fit in which the gyroscope and the magnetometer disagree: a mirror-image solution, or a
    vector residual over ``MISMATCH_RATIO`` times the magnitude residual that an ellipsoid alone leaves on these
    samples (the algebraic fit of :func:`._common.algebraic_ellipsoid`; skipped when it cannot fit them) and over
    ``MISMATCH_FLOOR`` of the field."""
    import warnings

    det = float(np.linalg.det(st.M))
    if not det > 0:
        raise IdentifiabilityError(_mismatch(problem.gyro, "the fit turned into the mirror image of a sensor"))
    radius = det ** (1.0 / 3.0)  # the field's magnitude in the normalised samples
    vector = float(np.sqrt(np.mean(np.sum(st.r**2, axis=1))))
    if not vector > MISMATCH_FLOOR * radius:
        return
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            W, c, _ = algebraic_ellipsoid(problem.u)
    except TrimagError:
        return
    magnitude = float(np.sqrt(np.mean((np.linalg.norm((problem.u - c) @ W.T, axis=1) - 1.0) ** 2))
                      / abs(np.linalg.det(W)) ** (1.0 / 3.0))
    if vector > MISMATCH_RATIO * magnitude:
        raise IdentifiabilityError(_mismatch(
            problem.gyro, f"the field they predict misses the samples by {vector * sc.scale:.3g} {units} RMS, "
                          f"{vector / magnitude:.3g}x the {magnitude * sc.scale:.3g} {units} an ellipsoid alone "
                          "leaves"))


def _lag_start(problem: _Problem, max_lag: float) -> float:
    """The lag (s) minimising the linear start's relative smallest eigenvalue over a grid of at most 81 lags in
    ``[-max_lag, max_lag]`` around the given one (on at most 4096 evenly spread segments' samples)."""
    gyro = problem.gyro
    t = gyro.time_s
    step = max(0.5 * gyro.median_interval, 2 * max_lag / 80)
    grid = gyro.lag_s + np.arange(-max_lag, max_lag + 0.5 * step, step)
    span = (gyro.gyro_time_s[0] - t.min(), gyro.gyro_time_s[-1] - t.max())
    grid = grid[(grid >= span[0]) & (grid <= span[1])]
    if len(grid) < 3:
        raise TrimagInputError(f"the magnetometer's samples do not lie inside the gyroscope's span for lags within "
                               f"+-{max_lag:g} s: check the two files' time columns")
    values = np.array([_scatter_start(problem, integrate_rate(gyro, np.zeros(3), float(lag)))[1] for lag in grid])
    k = int(np.argmin(values))
    if values.max() - values.min() <= 1e-3 * values.max():
        raise IdentifiabilityError("the fit's quality does not depend on the lag between the gyroscope and the "
                                   f"magnetometer (the sensor barely turns); {_HINT}")
    if k in (0, len(grid) - 1) and len(grid) > 3:
        raise IdentifiabilityError(f"the best lag between the gyroscope and the magnetometer is at the edge of the "
                                   f"search ({grid[k]:+.4g} s): widen it (`option max_lag`), check the clocks, or "
                                   "check that the sensor turned while both logged")
    return float(grid[k])


def _solve(problem: _Problem, p0: NDArray[np.float64], max_iter: int) -> Any:
    """Gauss-Newton from ``p0`` (:func:`trimag._core.solve.gauss_newton_rule`, up to 10 step halvings): converged
    when a step lowers the sum of squares by less than 1e-10 of its expected change per unknown (``sigma^2 p``)."""
    n_obs = max(3 * len(problem.u) - problem.p - 2 * len(problem.starts), 1)

    def converged(p_new: NDArray[np.float64], step_norm: float, cost: float, cost_new: float, fraction: float) -> bool:
        return bool(cost - cost_new <= 1e-10 * max(cost_new / n_obs, 1e-300) * problem.p
                    or step_norm <= 1e-13 * (1.0 + float(np.linalg.norm(p_new))))

    return gauss_newton_rule(
        lambda p: _evaluate(problem, p), lambda p, st: _normal_equations(problem, st),
        lambda st, ne: _direction(problem, st, ne), p0, max_steps=max_iter, converged=converged, halvings=10,
    )


@dataclass(frozen=True)
class _Scale:
    """From normalised to data units: samples ``u = (x - centre) / scale``; ``F`` the reference magnitude (None:
    unknown, the gauge ``det W = 1``)."""

    centre: NDArray[np.float64]
    scale: float
    F: float | None


def _outputs(theta: NDArray[np.float64], problem: _Problem, sc: _Scale, R_ref: NDArray[np.float64] | None = None
             ) -> tuple[NDArray[np.float64], dict[str, Any]]:
    """The reported parameters from the global unknowns ``theta`` (normalised): upper ``W`` (6), hard iron (3),
    ``F`` (unknown magnitude), the gyroscope's bias (3), the rotation of the corrected frame to the gyroscope's
    as a rotation vector relative to ``R_ref`` (3; rad), the lag; and the matrices they come from."""
    M = theta[:9].reshape(3, 3)
    A = np.linalg.inv(M) / sc.scale  # field (|h| = 1) per data unit
    if sc.F is None:
        k = float(np.linalg.det(A)) ** (-1.0 / 3.0)
        A, F_hat = A * k, k
    else:
        A, F_hat = A * sc.F, None
    Q, W = np.linalg.qr(A)  # A = Q W: W upper triangular; positive diagonal below
    d = np.sign(np.diag(W))
    Q, W = Q * d, np.triu(d[:, None] * W) + 0.0  # (+ 0.0: no -0 below the diagonal)
    offset = sc.centre + sc.scale * theta[9:12]
    ref = Q if R_ref is None else R_ref
    rho = Rotation.from_matrix(Q @ ref.T).as_rotvec()
    parts = [W[UPPER], offset] + ([np.array([F_hat])] if F_hat is not None else [])
    k0 = 12
    if problem.fit_bias:
        parts.append(theta[k0:k0 + 3])
        k0 += 3
    parts.append(rho)
    if problem.fit_lag:
        parts.append(theta[k0:k0 + 1])
    return np.concatenate(parts), {"W": W, "R": Q, "A": A, "offset": offset, "F_hat": F_hat}


def _output_names(problem: _Problem, known: bool) -> tuple[str, ...]:
    return (*UPPER_NAMES, *(() if known else ("F",)), *(_BIAS if problem.fit_bias else ()), *_ROTATION,
            *(("lag_s",) if problem.fit_lag else ()))


def _propagate(theta: NDArray[np.float64], cov: NDArray[np.float64], problem: _Problem, sc: _Scale
               ) -> tuple[NDArray[np.float64], dict[str, Any]]:
    """The reported parameters' covariance: ``T cov T^T`` with ``T`` their Jacobian in the global unknowns by
    central differences (steps of 1e-4 of each unknown's standard deviation: the map is smooth, the error
    ``O(1e-8)`` relative)."""
    out0, mats = _outputs(theta, problem, sc)
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    T = np.zeros((len(out0), len(theta)))
    for k in range(len(theta)):
        h = 1e-4 * std[k] if std[k] > 0 else 1e-8
        e = np.zeros(len(theta))
        e[k] = h
        T[:, k] = (_outputs(theta + e, problem, sc, mats["R"])[0] - _outputs(theta - e, problem, sc, mats["R"])[0]
                   ) / (2 * h)
    return T @ cov @ T.T, mats


def _fisher_and_covariance(J: NDArray[np.float64], W: NDArray[np.float64], known: bool
                           ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A magnitude-only Fisher information ``J`` of (upper ``W``, ``b``[, ``F``]) and its covariance (gauge ``det W =
    1`` when the magnitude is unknown); an infinite covariance when ``J`` is singular."""
    grad = None
    if not known:
        Winv = np.linalg.inv(W)
        grad = np.concatenate([[Winv[j, i] for i, j in zip(*UPPER, strict=True)], np.zeros(4)])
    try:
        return J, _constrained_inverse(J, grad)
    except IdentifiabilityError:
        return J, np.full_like(J, np.inf)


def _magnitude_only(B: NDArray[np.float64], W: NDArray[np.float64], offset: NDArray[np.float64], sigma: float,
                    known: bool, F: float) -> dict[str, Any]:
    """What a magnitude-only fit (``ml``) would know at this estimate (``trimag.quality.crlb.ellipsoid_fisher``):
    of these samples (``fisher``, ``covariance``) and of a full sphere of as many samples (``reference``,
    ``reference_covariance``: 500 directions scaled to N, as ``ml``'s own identifiability check)."""
    idx = diagnostic_subsample(len(B))
    J = ellipsoid_fisher(ellipsoid_geometry(B[idx], W, offset), sigma, known_magnitude=known) * (len(B) / len(idx))
    X_test = (F * _sphere(500)) @ np.linalg.inv(W).T + offset
    J_ref = ellipsoid_fisher(ellipsoid_geometry(X_test, W, offset), sigma, known_magnitude=known) * (len(B) / 500)
    J, C = _fisher_and_covariance(J, W, known)
    J_ref, C_ref = _fisher_and_covariance(J_ref, W, known)
    return {"fisher": J, "covariance": C, "reference": J_ref, "reference_covariance": C_ref}


def _inflation(C: NDArray[np.float64], C_ref: NDArray[np.float64], names: tuple[str, ...]) -> tuple[float, list[str]]:
    """The largest ratio of standard deviations of any combination of parameters, covariance ``C`` against
    ``C_ref`` (both (p, p); with an unknown magnitude both singular along the same gauge direction, which is left
    out), and the parameters that dominate that combination (in units of their reference standard deviations)."""
    if not (np.isfinite(C).all() and np.isfinite(C_ref).all()):
        return float("inf"), list(names)
    lam, V = np.linalg.eigh(C_ref)
    keep = lam > 1e-12 * lam.max()
    T = V[:, keep] / np.sqrt(lam[keep])  # whitening of the reference
    mu, vecs = np.linalg.eigh(T.T @ C @ T)
    d = np.abs(V[:, keep] @ (np.sqrt(lam[keep]) * vecs[:, -1])) / np.sqrt(np.clip(np.diag(C_ref), 1e-300, None))
    return float(np.sqrt(max(mu[-1], 0.0))), [names[k] for k in np.nonzero(d > 0.3 * d.max())[0]]


def _identifiability(S: NDArray[np.float64], problem: _Problem, cov_out: NDArray[np.float64],
                     names: tuple[str, ...], mag: dict[str, Any]) -> dict[str, Any]:
    """The verdict of the gyro-aided fit, next to a magnitude-only fit's on the same samples.

    * Refused (exit 3) when the reduced normal matrix's column-normalised condition number exceeds the error limit,
      naming the weak unknowns (native ones: the soft-iron matrix ``M``, the hard iron, the gyroscope's bias).
    * For ``W``, the hard iron (and ``F``): each standard deviation against a full sphere's of as many samples
      (``std_ratio_vs_full_sphere``; above :data:`POORLY_DETERMINED`: ``poorly_determined``, above
      ``INFLATION_WARN``: ``unidentified``, warned), and the worst-determined combination's
      (``std_inflation_vs_full_sphere``, the smallest generalised eigenvalue of the marginal information of these
      parameters against the full sphere's; warned above ``INFLATION_WARN``, as ``ml`` does).
    * ``magnitude_only``: the same for ``ml`` on these samples (its variance inflation factors above ``VIF_WARN``
      and its worst combination's inflation: what it calls unidentified), and ``identified_by_gyro``: what it
      calls unidentified that the gyro-aided fit determines (within ``INFLATION_WARN`` times a full sphere).
    """
    native = (*_NATIVE[:12], *(_BIAS if problem.fit_bias else ()), *(("lag_s",) if problem.fit_lag else ()))
    cond, s, vt = gram_condition(S)
    weak = weak_directions(vt, s, native, threshold=1e4) if np.isfinite(cond) else list(native)
    check_condition(cond, what="the gyro-aided model", hint=_HINT, weak=weak, warn=np.inf)
    k = len(mag["covariance"])
    keys = names[:k]
    std_ref = np.sqrt(np.clip(np.diag(mag["reference_covariance"]), 0.0, None))
    gyro_std = np.sqrt(np.clip(np.diag(cov_out)[:k], 0.0, None))
    ratio = gyro_std / np.where(std_ref > 0, std_ref, np.inf)
    inflation, weakest = _inflation(cov_out[:9, :9], mag["reference_covariance"][:9, :9], keys[:9])
    mag_vif = np.diag(mag["covariance"]) * np.diag(mag["fisher"])
    mag_inflation, mag_weakest = _inflation_vs_full_sphere(mag["fisher"][:9, :9], mag["reference"][:9, :9], keys[:9])
    mag_bad = [n for n, v in zip(keys, mag_vif, strict=True) if not v <= VIF_WARN]
    if not mag_inflation <= INFLATION_WARN:
        mag_bad += [n for n in mag_weakest if n not in mag_bad]
    poor = [n for n, v in zip(keys, ratio, strict=True) if not v <= POORLY_DETERMINED]
    unidentified = [n for n, v in zip(keys, ratio, strict=True) if not v <= INFLATION_WARN]
    reasons = [f"condition number {cond:.3g}"] if cond > CONDITION_WARN else []
    if unidentified:
        reasons.append(f"{', '.join(unidentified)}: more than {INFLATION_WARN:g}x the standard deviation a full "
                       "sphere of as many samples would give")
    elif not inflation <= INFLATION_WARN:
        reasons.append(f"the worst-determined combination ({', '.join(weakest)}) has {inflation:.3g}x the standard "
                       "deviation a full sphere of as many samples would give")
    mag_std = np.sqrt(np.clip(np.diag(mag["covariance"]), 0.0, None))
    return {
        "condition_number_reduced": cond,
        "weak_combination_native": weak,
        "std_ratio_vs_full_sphere": dict(zip(keys, ratio.tolist(), strict=True)),
        "std_inflation_vs_full_sphere": inflation,
        "weakest_combination": weakest,
        "poorly_determined": poor,
        "unidentified": unidentified,
        "warning": "; ".join(reasons) or None,
        "magnitude_only": {
            "variance_inflation": dict(zip(keys, mag_vif.tolist(), strict=True)),
            "poorly_determined": [n for n, v in zip(keys, mag_vif, strict=True) if not v <= VIF_REPORT],
            "std_inflation_vs_full_sphere": mag_inflation, "weakest_combination": mag_weakest,
            "unidentified": mag_bad,
            "std_ratio_to_gyro": {n: (float(a / g) if g > 0 and np.isfinite(a) else None)
                                  for n, a, g in zip(keys, mag_std, gyro_std, strict=True)},
        },
        "identified_by_gyro": [n for n in mag_bad if n not in unidentified],
    }


def _alignment(mats: dict[str, Any], cov_out: NDArray[np.float64], names: tuple[str, ...]) -> dict[str, Any]:
    """``diagnostics["gyro_alignment"]``: the rotation of the corrected frame to the gyroscope's (``R``, with ``inv
    M = R W``) and of the sensor's own axes (``R Q``, ``W = Q P`` the polar decomposition: the symmetric soft iron
    autopilots apply in the sensor's axes)."""
    R, W = mats["R"], mats["W"]
    U, _, Vt = np.linalg.svd(W)
    Q = U @ Vt
    sensor = R @ Q
    k = names.index(_ROTATION[0])
    std = np.degrees(np.sqrt(np.clip(np.diag(cov_out)[k:k + 3], 0.0, None)))
    rot, rot_s = Rotation.from_matrix(R), Rotation.from_matrix(sensor)
    return {
        "matrix": R.tolist(),
        "rotvec_deg": np.degrees(rot.as_rotvec()).tolist(),
        "euler_zyx_deg": rot.as_euler("ZYX", degrees=True).tolist(),
        "sensor_matrix": sensor.tolist(),
        "sensor_euler_zyx_deg": rot_s.as_euler("ZYX", degrees=True).tolist(),
        "rotation_std_deg": std.tolist(),
        "convention": "matrix: corrected magnetometer frame -> gyroscope frame (cal.apply(B) @ matrix.T is the field "
                      "in the gyroscope's axes); sensor_matrix: the magnetometer's own axes -> gyroscope frame",
    }


class GyroAided(Estimator):
    """The ellipsoid model fitted with the gyroscope's angular rate (module docstring; docs/method-gyro.md).

    ``fit(B, reference=F or None, attitude=AngularRate(...))``: ``B`` (N, 3) raw samples in time order,
    ``attitude`` the gyroscope (:class:`trimag.fields.gyro.AngularRate`: the samples' time stamps and the rate,
    rad/s), ``reference`` one field magnitude or None.

    Parameters
    ----------
    model : str
        ``"ellipsoid"``.
    form : {"upper", "symmetric"}
        Gauge of the returned soft-iron correction (the rotation to the gyroscope's frame is in
        ``diagnostics["gyro_alignment"]`` either way).
    segment_s : float
        Length of the segments within which the gyroscope's integrated attitude is trusted, s.
    estimate_bias : bool
        Fit the gyroscope's bias (default True); False takes the rate as unbiased.
    estimate_lag : bool or None
        Fit the lag between the streams; None (default): when the gyroscope has its own clock.
    max_lag : float
        Half-width of the lag's starting grid, s.
    max_iter : int
        Gauss-Newton steps at most.
    """

    name = "gyro"
    models = ("ellipsoid",)
    reference_kind = "gyro"

    def __init__(self, model: str = "ellipsoid", form: str = "upper", segment_s: float = 2.0,
                 estimate_bias: bool = True, estimate_lag: bool | None = None, max_lag: float = 0.5,
                 max_iter: int = 50) -> None:
        self.model = model
        self.form = form
        self.segment_s = segment_s
        self.estimate_bias = estimate_bias
        self.estimate_lag = estimate_lag
        self.max_lag = max_lag
        self.max_iter = max_iter

    def _problem(self, B: NDArray[np.float64], gyro: Any) -> tuple[_Problem, Any]:
        if not isinstance(gyro, AngularRate):
            raise TrimagInputError("the gyro-aided fit needs the gyroscope's angular rate (`attitude=AngularRate(...)`;"
                                   " on the command line `gyro_columns=GX,GY,GZ` with `time_column=T`, or "
                                   "`gyro_file`)")
        if self.form not in ("upper", "symmetric"):
            raise TrimagInputError(f"`form` must be 'upper' or 'symmetric'; got {self.form!r}")
        if not (np.isfinite(self.segment_s) and self.segment_s > 0):
            raise TrimagInputError(f"`segment_s` must be a positive number of seconds; got {self.segment_s!r}")
        gyro.check(len(B))
        if np.any(np.diff(gyro.time_s) < 0):
            raise TrimagInputError("the gyro-aided fit needs the samples in time order (their time stamps decrease)")
        fit_lag = bool(gyro.own_clock if self.estimate_lag is None else self.estimate_lag)
        u, norm = normalise(B)
        starts = _segments(gyro.time_s, float(self.segment_s))
        seg = np.repeat(np.arange(len(starts)), np.diff(np.append(starts, len(B))))
        return _Problem(u, starts, seg, gyro, bool(self.estimate_bias), fit_lag), norm

    def _fit(self, B: NDArray[np.float64], reference: Any, *, model: str, units: str, attitude: Any) -> Calibration:
        problem, norm = self._problem(B, attitude)
        ref = scalar_reference(reference, len(B), units)
        if ref.values is not None and np.ptp(ref.values) > 1e-9 * float(np.abs(ref.values).max()):
            raise TrimagInputError("the gyro-aided fit takes one field magnitude (the field is constant over the "
                                   "log); give `reference=F` or none")
        sc = _Scale(norm.centre, float(norm.scale), None if ref.values is None else float(ref.values[0]))
        lag0 = _lag_start(problem, float(self.max_lag)) if problem.fit_lag else problem.gyro.lag_s
        run = _solve(problem, _linear_start(problem, lag0), int(self.max_iter))
        st, ne = run.state, run.model
        if st is None or ne is None:
            raise IdentifiabilityError(f"the gyro-aided fit did not converge; {_HINT}")
        _check_consistent(problem, st, sc, units)
        n_free = 3 * len(B) - problem.p - 2 * len(problem.starts)
        sigma2 = float(np.sum(st.r**2)) / max(n_free, 1)
        theta = st.p[:problem.p]
        try:
            cov = sigma2 * np.linalg.inv(ne["S"])
        except np.linalg.LinAlgError:
            raise IdentifiabilityError(f"the gyro-aided model is not identified by these data; {_HINT}") from None
        names = _output_names(problem, sc.F is not None)
        cov_out, mats = _propagate(theta, cov, problem, sc)
        sigma = float(np.sqrt(sigma2) * sc.scale)
        return self._result(B, problem, st, run, mats, cov_out, names, sigma, ref, sc, model, units)

    def _result(self, B: NDArray[np.float64], problem: _Problem, st: _State, run: Any, mats: dict[str, Any],
                cov_out: NDArray[np.float64], names: tuple[str, ...], sigma: float, ref: Any, sc: _Scale,
                model: str, units: str) -> Calibration:
        import warnings

        from ..errors import IdentifiabilityWarning

        W, offset, known = mats["W"], mats["offset"], sc.F is not None
        Fm = float(sc.F) if sc.F is not None else float(mats["F_hat"])
        mag = _magnitude_only(B, W, offset, sigma, known, Fm)
        ident = _identifiability(run.model["S"], problem, cov_out, names, mag)
        if ident["warning"]:
            warnings.warn(f"the gyro-aided calibration is poorly identified: {ident['warning']}; {_HINT}",
                          IdentifiabilityWarning, stacklevel=4)
        k = len(mag["covariance"])
        theta = np.concatenate([W[UPPER], offset])
        X_test = (Fm * _sphere(500)) @ np.linalg.inv(W).T + offset
        field_rms, mag_rms = predicted_errors(cov_out[:k, :k], _upper_param, theta, X_test)
        std = np.sqrt(np.clip(np.diag(cov_out), 0.0, None))
        uncertainty = make_uncertainty(
            names, covariance=cov_out, noise_std=sigma, predicted_field_rms=field_rms, predicted_magnitude_rms=mag_rms,
            basis="sigma^2 times the inverse of the reduced normal matrix (segments' directions eliminated) at the "
                  "estimate, propagated to the reported parameters",
            gauge="upper-triangular W" + ("" if known else ", det(W) = 1, F estimated")
                  + "; gyro_alignment: small rotation (rad) of the corrected frame to the gyroscope's",
            param_std_deg={n: float(np.degrees(std[names.index(n)])) for n in _ROTATION},
        )
        gyro_diag = {
            **describe(problem.gyro),
            "bias_rad_s": st.bias.tolist(), "bias_estimated": problem.fit_bias,
            "lag_s": st.lag, "lag_estimated": problem.fit_lag, "segment_s": float(self.segment_s),
            "n_segments": len(problem.starts),
            "vector_rms": float(np.sqrt(np.mean(np.sum(st.r**2, axis=1))) * sc.scale),
            "unit": "rad/s", "lag_convention": "gyroscope clock - magnetometer clock",
        }
        W_out = to_symmetric(W) if self.form == "symmetric" else W
        coverage = sphere_coverage((B[diagnostic_subsample(len(B))] - offset) @ W.T)
        diagnostics = {"gyro": gyro_diag, "gyro_alignment": _alignment(mats, cov_out, names),
                       "identifiability": ident, "condition_number": ident["condition_number_reduced"],
                       "optimizer": f"Gauss-Newton, {run.steps} steps, {'converged' if run.converged else 'stopped'}"}
        return build_calibration(
            B, W_out, offset, model=model, method=self.name, units=units, reference=ref,
            params=Ellipsoid.from_matrix_offset(W_out, offset).as_dict(), iterations=run.nfev,
            converged=bool(run.converged), fitted_magnitude=mats["F_hat"], uncertainty=uncertainty,
            diagnostics=diagnostics, coverage=coverage,
        )


def _sphere(n: int) -> NDArray[np.float64]:
    from .._core.sphere import fibonacci_sphere

    return np.asarray(fibonacci_sphere(n), dtype=np.float64)
