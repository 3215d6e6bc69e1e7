"""One level of the firmware-space fit: the nested parameter sets, their residuals, Jacobians and starts.

The fit works in the algebra both firmwares share (:mod:`trimag.models.firmware`)::

    B~_i = A (u_i + o) + m x_i          A symmetric (3, 3), o (3,), m (3,), x_i the logged current or throttle

against a body-frame field vector ``h_i`` (vector residual ``B~_i - h_i``, 3 per sample: a flight with attitudes),
the field's horizontal and vertical components in the level frame (heading-free residual, 2 per sample:
``|(T_i B~_i)_xy| - H`` and ``(T_i B~_i)_z - Z``, ``T_i`` the roll and pitch of sample ``i``; the heading does not
enter: MAGFit's cost, as least squares) or a field magnitude ``F_i`` (``|B~_i| - F_i``: a tumble without
attitudes). The levels free, in this order (each
nested in the next), the parameters the firmware loads; the others are *held* at the values the firmware had
(``A_held``, from the log's parameters; the identity where none are known)::

    offsets    o                               A = A_held
    scale      o, one scale l                  A = l A_held
    diagonal   o, the diagonal d               A = diag(d) + offdiag(A_held)
    full       o, the symmetric A (6)
    + motor    m (3) on top of any level (COMPASS_MOT / CAL_MAGn_xCOMP)

With a vector residual every level is a linear least-squares problem in ``(A, c = A o, m)``: its solution is the
start (and, away from the firmware's limits, the answer); with a magnitude residual the start is the level below's
solution (or an algebraic sphere fit), refined by Gauss-Newton on the normal equations with the Jacobian in closed
form (:meth:`LevelProblem.jacobian`), MINPACK's Levenberg-Marquardt where a step stalls or the equations are barely
determined (:data:`MAX_NORMAL_COND`; :func:`trimag._core.solve.levenberg_marquardt`), bounded trust-region steps when
a limit is active. The held-out folds start from the whole log's solution (:meth:`LevelProblem.fold_refitter`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._core.solve import GaussNewtonResult, gauss_newton_rule, levenberg_marquardt
from ..errors import IdentifiabilityError

__all__ = ["LEVELS", "LevelProblem", "LevelSolution"]

#: The nested levels, simplest first.
LEVELS = ("offsets", "scale", "diagonal", "full")

_SYM = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


def _rotate(T: list[NDArray[np.float64]], B: NDArray[np.float64]) -> NDArray[np.float64]:
    """``T_n B_n`` for rotations given by their rows ``T`` (3 arrays (n, 3)) and vectors ``B`` (n, 3)."""
    L = np.empty_like(B)
    for i in range(3):
        np.einsum("nj,nj->n", T[i], B, out=L[:, i])
    return L


def _all(rows: Any) -> bool:
    """Whether ``rows`` selects every row (``slice(None)``)."""
    return isinstance(rows, slice) and rows == slice(None)


def _sym(a: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.array([[a[0], a[3], a[4]], [a[3], a[1], a[5]], [a[4], a[5], a[2]]])


@dataclass
class LevelSolution:
    """A level's solution: ``A``, ``o``, ``m``, the parameter vector, its residuals and the covariance inputs."""

    A: NDArray[np.float64]
    o: NDArray[np.float64]
    m: NDArray[np.float64]
    theta: NDArray[np.float64]
    residual: NDArray[np.float64]
    jacobian: NDArray[np.float64]
    converged: bool
    iterations: int
    at_bound: list[int]
    #: the directions fitted (columns, in parameters over ``scales``) when the others are held at ``theta_ref``
    basis: NDArray[np.float64] | None = None
    theta_ref: NDArray[np.float64] | None = None
    scales: NDArray[np.float64] | None = None


class LevelProblem:
    """The residuals of one level (see the module docstring).

    Parameters
    ----------
    u : ndarray, shape (N, 3)
        Raw readings in the firmware's frame, in its unit.
    level : str
        One of :data:`LEVELS`.
    motor : ndarray, shape (N,), or None
        The logged power (current A, throttle 0..1): the level then also frees ``m``.
    target : ndarray, shape (N, 3) or (N,)
        The body-frame field (vector residual) or its magnitude.
    A_held, o_held : ndarray
        The values held by the lower levels.
    fixed : ndarray, shape (N, 3), optional
        A term added to ``B~`` as it is (the firmware's own motor term, held when the level does not fit one).
    tilt : ndarray, shape (N, 3, 3), optional
        The heading-free residual: each sample's roll-and-pitch rotation (fit frame -> level frame); ``target`` is
        then (N, 2): the horizontal and vertical field.
    """

    def __init__(self, u: NDArray[np.float64], level: str, motor: NDArray[np.float64] | None,
                 target: NDArray[np.float64], A_held: NDArray[np.float64], o_held: NDArray[np.float64],
                 fixed: NDArray[np.float64] | None = None, tilt: NDArray[np.float64] | None = None) -> None:
        self.u, self.level, self.x, self.target, self.fixed, self.tilt = u, level, motor, target, fixed, tilt
        #: the tilt's three rows, each contiguous (n, 3): the residual's products read them at full speed
        self._tilt_rows = None if tilt is None else [np.ascontiguousarray(tilt[:, i, :]) for i in range(3)]
        self._last: tuple[Any, ...] | None = None  # (theta, rows, B, L) of the last residual (see _field)
        self.vector = target.ndim == 2 and tilt is None
        #: residuals per sample: 3 (vector), 2 (heading-free), 1 (magnitude)
        self.width = 3 if self.vector else (2 if tilt is not None else 1)
        self.A_held, self.o_held = np.asarray(A_held, dtype=np.float64), np.asarray(o_held, dtype=np.float64)
        self.off_held = self.A_held - np.diag(np.diag(self.A_held))
        self.n_A = {"offsets": 0, "scale": 1, "diagonal": 3, "full": 6}[level]
        self.n_params = self.n_A + 3 + (3 if motor is not None else 0)

    # ------------------------------------------------------------------ parameters
    def names(self) -> list[str]:
        """Algebra names of the parameters, in order (``l``, ``d_x``, ``A_xy``, ``o_x``, ``m_x``)."""
        a = {"offsets": [], "scale": ["l"], "diagonal": ["d_x", "d_y", "d_z"],
             "full": ["A_xx", "A_yy", "A_zz", "A_xy", "A_xz", "A_yz"]}[self.level]
        return a + ["o_x", "o_y", "o_z"] + (["m_x", "m_y", "m_z"] if self.x is not None else [])

    def unpack(self, theta: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64],
                                                          NDArray[np.float64]]:
        """``(A, o, m)`` of a parameter vector."""
        k = self.n_A
        if self.level == "offsets":
            A = self.A_held
        elif self.level == "scale":
            A = theta[0] * self.A_held
        elif self.level == "diagonal":
            A = np.diag(theta[:3]) + self.off_held
        else:
            A = _sym(theta[:6])
        o = theta[k:k + 3]
        m = theta[k + 3:k + 6] if self.x is not None else np.zeros(3)
        return A, o, m

    def pack(self, A: NDArray[np.float64], o: NDArray[np.float64], m: NDArray[np.float64]) -> NDArray[np.float64]:
        """The parameter vector nearest to ``(A, o, m)`` (the start from another level's solution)."""
        if self.level == "offsets":
            a: list[float] = []
        elif self.level == "scale":
            a = [float(np.sum(A * self.A_held) / np.sum(self.A_held * self.A_held))]
        elif self.level == "diagonal":
            a = np.diag(A).tolist()
        else:
            a = [float(A[i, j]) for i, j in _SYM]
        return np.array(a + list(o) + (list(m) if self.x is not None else []), dtype=np.float64)

    # ------------------------------------------------------------------ residuals
    def predict(self, theta: NDArray[np.float64], rows: Any = slice(None)) -> NDArray[np.float64]:
        """``B~`` (n, 3) of the rows."""
        A, o, m = self.unpack(theta)
        B = (self.u[rows] + o) @ A.T
        if self.x is not None:
            B = B + self.x[rows][:, None] * m
        if self.fixed is not None:
            B = B + self.fixed[rows]
        return np.asarray(B, dtype=np.float64)

    def residual(self, theta: NDArray[np.float64], rows: Any = slice(None)) -> NDArray[np.float64]:
        """Vector residuals (3 n,), heading-free residuals (2 n,) or magnitude residuals (n,) of the rows."""
        B, L = self._field(theta, rows)
        if self.vector:
            return np.asarray((B - self.target[rows]).ravel(), dtype=np.float64)
        if L is not None:
            out = np.empty((len(B), 2))
            np.hypot(L[:, 0], L[:, 1], out=out[:, 0])
            out[:, 1] = L[:, 2]
            out -= self.target[rows]
            return out.ravel()
        return np.asarray(np.sqrt(np.einsum("ni,ni->n", B, B)) - self.target[rows], dtype=np.float64)

    def _field_jacobian(self, theta: NDArray[np.float64], rows: Any) -> NDArray[np.float64]:
        """``dB~/dtheta``, shape (n, 3, p)."""
        A, o, _ = self.unpack(theta)
        w = self.u[rows] + o
        n = len(w)
        J = np.zeros((n, 3, self.n_params))
        k = self.n_A
        if self.level == "scale":
            J[:, :, 0] = w @ self.A_held.T
        elif self.level == "diagonal":
            for j in range(3):
                J[:, j, j] = w[:, j]
        elif self.level == "full":
            for col, (i, j) in enumerate(_SYM):
                J[:, i, col] += w[:, j]
                if i != j:
                    J[:, j, col] += w[:, i]
        J[:, :, k:k + 3] = A  # dB/do = A, the same for every row
        if self.x is not None:
            for j in range(3):
                J[:, j, k + 3 + j] = self.x[rows]
        return J

    def _field(self, theta: NDArray[np.float64], rows: Any) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """``B~`` of the rows and, heading-free, its level-frame ``L = T B~``; the last pair is kept, for the
        Jacobian at the point whose residual was just evaluated (what a Gauss-Newton step does next)."""
        last = self._last
        if last is not None and (last[1] is rows or (_all(last[1]) and _all(rows))) and np.array_equal(last[0], theta):
            return last[2], last[3]
        B = self.predict(theta, rows)
        L = None
        if self._tilt_rows is not None:
            L = _rotate([t[rows] for t in self._tilt_rows] if not _all(rows) else self._tilt_rows, B)
        self._last = (np.array(theta, dtype=np.float64), rows, B, L)
        return B, L

    def _contract(self, q: NDArray[np.float64], w: NDArray[np.float64], A: NDArray[np.float64],
                  x: NDArray[np.float64] | None) -> NDArray[np.float64]:
        """``q_n . dB~_n/dtheta`` in closed form, shape (n, p), for row vectors ``q`` (n, 3) (``w = u + o`` of the
        rows, ``x`` the motor channel's): what :meth:`_field_jacobian` gives, without its (n, 3, p) array."""
        n, k = len(q), self.n_A
        out = np.empty((n, self.n_params))
        if self.level == "scale":
            out[:, 0] = np.einsum("ni,ni->n", q, w @ self.A_held.T)
        elif self.level == "diagonal":
            np.multiply(q, w, out=out[:, :3])
        elif self.level == "full":
            for col, (i, j) in enumerate(_SYM):
                out[:, col] = q[:, i] * w[:, j] + q[:, j] * w[:, i] if i != j else q[:, i] * w[:, j]
        out[:, k:k + 3] = q @ A  # dB/do = A
        if x is not None:
            np.multiply(q, x[:, None], out=out[:, k + 3:k + 6])
        return out

    def jacobian(self, theta: NDArray[np.float64], rows: Any = slice(None)) -> NDArray[np.float64]:
        """Jacobian of :meth:`residual`, shape (3 n, p) or (n, p); in closed form, row by row (the chain rule
        through the residual's unit vector of each sample)."""
        if self.vector:
            return self._field_jacobian(theta, rows).reshape(-1, self.n_params)
        A, o, _ = self.unpack(theta)
        w = self.u[rows] + o
        x = self.x[rows] if self.x is not None else None
        B, L = self._field(theta, rows)
        if L is not None and self._tilt_rows is not None:  # the horizontal length through the tilt's first two
            T = self._tilt_rows if _all(rows) else [t[rows] for t in self._tilt_rows]  # rows, the vertical its third
            horizontal = np.hypot(L[:, 0], L[:, 1])[:, None]
            q_h = (L[:, 0:1] * T[0] + L[:, 1:2] * T[1]) / horizontal
            out = np.empty((len(B), 2, self.n_params))
            out[:, 0] = self._contract(q_h, w, A, x)
            out[:, 1] = self._contract(T[2], w, A, x)
            return out.reshape(-1, self.n_params)
        unit = B / np.sqrt(np.einsum("ni,ni->n", B, B))[:, None]
        return self._contract(unit, w, A, x)

    # ------------------------------------------------------------------ starts and the solve
    def linear_start(self, rows: Any = slice(None)) -> NDArray[np.float64]:
        """The vector residual's exact least-squares solution (linear in ``(A, c = A o, m)``)."""
        u, h = self.u[rows], self.target[rows]
        n = len(u)
        k = self.n_A
        design = self._field_jacobian(np.zeros(self.n_params), rows)  # the A columns depend on u only (o = 0)
        design[:, :, k:k + 3] = np.eye(3)  # c = A o, one column per axis
        rhs = h.copy() if self.fixed is None else h - self.fixed[rows]
        if self.level == "offsets":
            rhs = rhs - u @ self.A_held.T
        elif self.level == "diagonal":
            rhs = rhs - u @ self.off_held.T
        X, *_ = np.linalg.lstsq(design.reshape(3 * n, -1), rhs.ravel(), rcond=None)
        if self.level == "offsets":
            A = self.A_held
        else:
            A, _, _ = self.unpack(np.concatenate([X[:k], np.zeros(3), X[k + 3:]]))
        try:
            o = np.linalg.solve(A, X[k:k + 3])
        except np.linalg.LinAlgError:
            raise IdentifiabilityError(f"the {self.level} level's matrix is singular on these data") from None
        m = X[k + 3:k + 6] if self.x is not None else np.zeros(3)
        return self.pack(A, o, m)

    def sphere_start(self, rows: Any = slice(None)) -> NDArray[np.float64]:
        """An algebraic start of the magnitude residual: the centre of the sphere ``|A_held (u + o)| = F``."""
        y = self.u[rows] @ self.A_held.T
        F = self.target[rows] if self.target.ndim == 1 else np.linalg.norm(self.target[rows], axis=1)
        design = np.column_stack([2.0 * y, np.ones(len(y))])
        X, *_ = np.linalg.lstsq(design, F**2 - np.sum(y * y, axis=1), rcond=None)
        centre = -X[:3]  # |y - centre|^2 = F^2
        o = np.linalg.solve(self.A_held, -centre)
        return self.pack(self.A_held, o, np.zeros(3))

    def solve(self, start: NDArray[np.float64], rows: Any = slice(None),
              bounds: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None) -> LevelSolution:
        """Refine ``start`` (Levenberg-Marquardt; bounded trust-region with ``bounds``). A vector residual without
        bounds is solved exactly (:meth:`linear_start`): ``start`` is not needed."""
        p0 = np.asarray(start, dtype=np.float64)
        if bounds is None and self.vector:
            theta = self.linear_start(rows)
            A, o, m = self.unpack(theta)
            return LevelSolution(A, o.copy(), m.copy(), theta, self.residual(theta, rows),
                                 self.jacobian(theta, rows), True, 1, [])
        if bounds is not None:
            lo, hi = bounds
            margin = np.where(np.isfinite(hi - lo), 1e-9 * (hi - lo), 0.0)
            p0 = np.clip(p0, lo + margin, hi - margin)
            res = levenberg_marquardt(lambda p: self.residual(p, rows), p0, jac=lambda p: self.jacobian(p, rows),
                                      method="trf", bounds=(lo, hi), x_scale="jac", max_nfev=200)
            span = np.where(np.isfinite(hi - lo), np.maximum(hi - lo, 1e-12), 1.0)
            at = [k for k in range(len(p0)) if min(res.x[k] - lo[k], hi[k] - res.x[k]) < 1e-6 * span[k]]
        else:  # Gauss-Newton on the normal equations; MINPACK's LM where it stalls (see _gauss_newton)
            res = self._gauss_newton(p0, rows)
            if res is None:
                res = levenberg_marquardt(lambda p: self.residual(p, rows), p0,
                                          jac=lambda p: self.jacobian(p, rows), method="lm", xtol=1e-12,
                                          ftol=1e-12, max_nfev=200)
            at = []
        theta = np.asarray(res.x, dtype=np.float64)
        A, o, m = self.unpack(theta)
        return LevelSolution(A, o.copy(), m.copy(), theta, np.asarray(res.fun, dtype=np.float64),
                             np.asarray(res.jac, dtype=np.float64), bool(res.success), int(res.nfev), at)

    def solve_in(self, theta_ref: NDArray[np.float64], basis: NDArray[np.float64], scales: NDArray[np.float64],
                 rows: Any = slice(None), max_steps: int = 50) -> LevelSolution:
        """The least-squares solution within ``theta_ref + scales * (basis @ c)``: the directions not in ``basis``
        (the ones the data do not identify) are held at ``theta_ref``. Gauss-Newton on ``c`` with step halving."""
        theta = np.asarray(theta_ref, dtype=np.float64).copy()
        r = self.residual(theta, rows)
        cost = float(r @ r)
        steps = 0
        for steps in range(1, max_steps + 1):  # noqa: B007
            dc = _normal_step((self.jacobian(theta, rows) * scales) @ basis, r)
            step = scales * (basis @ dc)
            for _ in range(20):
                trial = theta + step
                r_trial = self.residual(trial, rows)
                if float(r_trial @ r_trial) <= cost:
                    break
                step = step / 2.0
            else:
                break
            theta, r, cost_old, cost = trial, r_trial, cost, float(r_trial @ r_trial)
            if np.linalg.norm(dc) < 1e-10 * (1.0 + np.linalg.norm(theta / scales)) or cost_old - cost < 1e-14 * cost:
                break
        A, o, m = self.unpack(theta)
        return LevelSolution(A, o.copy(), m.copy(), theta, r, self.jacobian(theta, rows), True, steps, [], basis,
                             np.asarray(theta_ref, dtype=np.float64), scales)

    def _gauss_newton(self, p0: NDArray[np.float64], rows: Any, ftol: float = 1e-12,
                      xtol: float = 1e-12) -> Any:
        """Gauss-Newton from ``p0`` (:func:`trimag._core.solve.gauss_newton_rule`: the Jacobi-scaled normal
        equations, a step that raises the cost halved up to 5 times) to the tolerances MINPACK's LM had here: a
        step that lowers the cost by at most ``ftol`` of it, or a relative step at most ``xtol``. The result as
        ``least_squares`` gives it (``x``, ``fun``, ``jac``, ``nfev``, ``success``), or None when it stalls."""

        def evaluate(p: NDArray[np.float64]) -> tuple[NDArray[np.float64], float]:
            r = self.residual(p, rows)
            return r, float(r @ r)

        def converged(p_new: NDArray[np.float64], step: float, cost: float, cost_new: float, _f: float) -> bool:
            return cost - cost_new <= ftol * cost or step <= xtol * (1.0 + float(np.linalg.norm(p_new)))

        def direction(r: NDArray[np.float64], J: NDArray[np.float64]) -> NDArray[np.float64] | None:
            step = _solve_normal(J.T @ J, J.T @ r)
            return None if step is None else -step

        run = gauss_newton_rule(evaluate, lambda p, r: self.jacobian(p, rows), direction, p0, max_steps=100,
                                converged=converged, halvings=5)
        if not run.converged:
            return None
        return GaussNewtonResult(x=run.p, fun=run.state, jac=run.model, nfev=run.nfev, success=True)

    # ------------------------------------------------------------------ held-out folds
    def subset(self, rows: NDArray[np.int64]) -> LevelProblem:
        """The same level on the samples ``rows`` only."""
        def part(a: NDArray[np.float64] | None) -> Any:
            return None if a is None else a[rows]

        return LevelProblem(self.u[rows], self.level, part(self.x), self.target[rows], self.A_held, self.o_held,
                            part(self.fixed), part(self.tilt))

    def fold_refitter(self, sol: LevelSolution, xtol: float = 1e-10, ftol: float = 1e-10,
                      max_steps: int = 30) -> Any:
        """A function ``refit(a, b)`` -> the parameters fitted to every sample but ``a:b`` (a contiguous fold), or None
        (the caller then solves as before), as :meth:`solve` / :meth:`solve_in` would from ``sol``.

        Gauss-Newton from the whole log's solution ``sol`` (within its directions ``sol.basis``, if any), to the
        relative step ``xtol`` or a step that lowers the cost by at most ``ftol`` of it (the held-out RMS is quoted to
        4 digits): the fold's minimum is near it. Its first step reuses the whole log's normal
        equations at ``sol`` less the fold's rows (no pass over the other samples); each further step evaluates the
        training rows once. None when a step raises the cost (far from the minimum) or the system is singular."""
        J, r = sol.jacobian, sol.residual
        N_all, g_all, w, n = J.T @ J, J.T @ r, self.width, len(self.u)
        P = None if sol.basis is None or sol.scales is None else sol.scales[:, None] * sol.basis

        def refit(a: int, b: int) -> NDArray[np.float64] | None:
            Jk, rk = J[a * w:b * w], r[a * w:b * w]
            N, g = N_all - Jk.T @ Jk, g_all - Jk.T @ rk
            keep = np.concatenate([np.arange(a), np.arange(b, n)])
            train = self.subset(keep)  # the training rows copied once, not at every evaluation
            rows = slice(None)
            theta = np.asarray(sol.theta, dtype=np.float64).copy()
            cost = float(r @ r) - float(rk @ rk)
            for _ in range(max_steps):
                if P is None:
                    step = _solve_normal(N, g)
                else:
                    c = _solve_normal(P.T @ N @ P, P.T @ g)
                    step = None if c is None else P @ c
                if step is None:
                    return None
                trial = theta - step
                r_trial = train.residual(trial, rows)
                cost_trial = float(r_trial @ r_trial)
                relative = float(np.linalg.norm(step)) / (1.0 + float(np.linalg.norm(trial)))
                if not np.isfinite(cost_trial) or cost_trial > cost * (1.0 + 1e-12):
                    return theta if relative <= 1e-8 else None  # the cost rose by rounding only: converged
                theta, cost, cost_before = trial, cost_trial, cost
                if relative <= xtol or cost_before - cost <= ftol * cost_before:
                    return theta
                Jt = train.jacobian(theta, rows)
                N, g = Jt.T @ Jt, Jt.T @ r_trial
            return None

        return refit


#: Largest condition number of the Jacobi-scaled normal equations a Gauss-Newton step is taken from: beyond it a
#: direction is barely determined (a log that barely turned), and MINPACK's Levenberg-Marquardt takes over, as the
#: fit always did there (the minimum along a flat valley depends on the path).
MAX_NORMAL_COND = 1e5


def _solve_normal(N: NDArray[np.float64], g: NDArray[np.float64],
                  max_cond: float = MAX_NORMAL_COND) -> NDArray[np.float64] | None:
    """``N^-1 g`` by the Jacobi-scaled normal equations, or None when their condition number exceeds ``max_cond``."""
    d = np.sqrt(np.diag(N))
    if not np.all(np.isfinite(d)) or np.any(d == 0):
        return None
    scaled = N / np.outer(d, d)
    if not np.linalg.cond(scaled) < max_cond:
        return None
    return np.asarray(np.linalg.solve(scaled, g / d) / d, dtype=np.float64)


def _normal_step(J: NDArray[np.float64], r: NDArray[np.float64]) -> NDArray[np.float64]:
    """The least-squares step ``argmin |J d + r|`` from the Jacobi-scaled normal equations (k x k: one BLAS product
    over the rows, where an SVD of the (n, k) Jacobian costs many); by SVD when they are singular."""
    G = J.T @ J
    d = np.sqrt(np.diag(G))
    if np.all(np.isfinite(d)) and np.all(d > 0):
        scaled = G / np.outer(d, d)
        if np.linalg.cond(scaled) < 1e10:
            return np.asarray(-np.linalg.solve(scaled, (J.T @ r) / d) / d, dtype=np.float64)
    step, *_ = np.linalg.lstsq(J, -r, rcond=None)
    return np.asarray(step, dtype=np.float64)
