"""The numerical shortcuts of the firmware fit (issue 40 item 3) against the plain computations they replace: the
closed-form Jacobian against finite differences, the fold refit (Gauss-Newton from the whole log's solution, its
first step from the whole log's normal equations) against a fresh solve on the training rows, and the orientation
search's one-pass scale fit against a regression per rotation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from trimag.vehicle._firmware_levels import LEVELS, LevelProblem
from trimag.vehicle.firmware import _ScaleFit


def _problem(level: str, motor: bool, kind: str, n: int = 400, seed: int = 3) -> tuple[LevelProblem, np.ndarray]:
    rng = np.random.default_rng(seed)
    attitude = Rotation.random(n, random_state=seed)
    h = attitude.inv().apply([190.0, -3.0, 455.0])  # the body-frame field, mG
    x = rng.uniform(0.0, 30.0, n)
    A_true = np.array([[1.03, 0.02, -0.01], [0.02, 0.97, 0.03], [-0.01, 0.03, 1.01]])
    u = np.linalg.solve(A_true, (h - np.outer(x, [2.0, -1.5, 3.0])).T).T - [120.0, -80.0, 40.0]
    u += rng.normal(0.0, 2.0, u.shape)
    if kind == "vector":
        target, tilt = h, None
    elif kind == "heading-free":
        tilt = Rotation.from_euler("ZYX", np.column_stack([np.zeros(n), attitude.as_euler("ZYX")[:, 1:]])).as_matrix()
        level_h = np.einsum("nij,nj->ni", tilt, h)
        target = np.column_stack([np.hypot(level_h[:, 0], level_h[:, 1]), level_h[:, 2]])
    else:
        target, tilt = np.linalg.norm(h, axis=1), None
    problem = LevelProblem(u, level, x if motor else None, target, np.eye(3) * 1.01, np.array([100.0, -70.0, 30.0]),
                           None, tilt)
    theta = problem.pack(A_true, np.array([118.0, -79.0, 41.0]), np.array([1.9, -1.4, 3.1]))
    return problem, theta


@pytest.mark.parametrize("kind", ["vector", "heading-free", "magnitude"])
@pytest.mark.parametrize("level", LEVELS)
def test_the_closed_form_jacobian_is_the_residuals_derivative(level: str, kind: str) -> None:
    for motor in (False, True):
        problem, theta = _problem(level, motor, kind)
        rows = np.arange(50, 400, 2)
        J = problem.jacobian(theta, rows)
        numeric = np.empty_like(J)
        for k in range(len(theta)):
            step = 1e-6 * max(1.0, abs(theta[k]))
            up, down = theta.copy(), theta.copy()
            up[k] += step
            down[k] -= step
            numeric[:, k] = (problem.residual(up, rows) - problem.residual(down, rows)) / (2 * step)
        np.testing.assert_allclose(J, numeric, rtol=1e-6, atol=1e-6 * np.abs(numeric).max())


@pytest.mark.parametrize("kind", ["vector", "heading-free", "magnitude"])
def test_a_fold_refit_is_the_fresh_solve_on_the_training_rows(kind: str) -> None:
    problem, theta = _problem("full", True, kind, n=600)
    whole = problem.solve(theta)
    refit = problem.fold_refitter(whole)
    for a, b in ((0, 120), (240, 360), (480, 600)):
        train = np.concatenate([np.arange(a), np.arange(b, 600)])
        fresh = problem.solve(whole.theta, rows=train).theta
        fast = refit(a, b)
        assert fast is not None
        scale = np.abs(fresh) + 1.0
        assert np.max(np.abs(fast - fresh) / scale) < 1e-7, (fast, fresh)
        # what the held-out RMS is made of: the fold's residuals, the same to 1e-6 relative
        r_fast, r_fresh = problem.residual(fast, np.arange(a, b)), problem.residual(fresh, np.arange(a, b))
        assert abs(np.sqrt(np.mean(r_fast**2)) / np.sqrt(np.mean(r_fresh**2)) - 1.0) < 1e-6


def test_the_scale_fit_of_every_rotation_from_one_pass_is_the_regression() -> None:
    rng = np.random.default_rng(4)
    u = rng.normal(0.0, 300.0, (500, 3)) + np.array([40.0, -20.0, 10.0])
    h = u @ Rotation.from_euler("z", 90, degrees=True).as_matrix().T * 1.05 + rng.normal(0.0, 3.0, (500, 3))
    fit = _ScaleFit(u, h)
    for R in Rotation.random(6, random_state=5).as_matrix():
        P_u, P_h = R, Rotation.from_euler("x", 30, degrees=True).as_matrix()
        uu, hh = u @ P_u.T, h @ P_h.T
        design = np.zeros((500, 3, 4))
        design[:, :, 0] = uu
        design[:, :, 1:] = np.eye(3)
        X, *_ = np.linalg.lstsq(design.reshape(-1, 4), hh.ravel(), rcond=None)
        r = design.reshape(-1, 4) @ X - hh.ravel()
        rms, scale = fit.rms(P_u, P_h)
        assert scale == pytest.approx(X[0], rel=1e-9)
        assert rms == pytest.approx(np.sqrt(np.mean(r**2) * 3), rel=1e-9)


@pytest.mark.parametrize("kind", ["vector", "heading-free"])
def test_the_verdict_s_folds_from_the_refit_are_those_of_fresh_solves(kind: str) -> None:
    """The verdict's held-out folds through the firmware's formula (``fold_rms``) start each fold from the whole
    log's solution (the fold refit) instead of a fresh solve on the training rows: the same RMS to 1e-6."""
    from trimag.models.firmware import ArduPilotCompass
    from trimag.vehicle._firmware_trust import fold_rms

    problem, theta = _problem("full", True, kind, n=600)
    whole = problem.solve(theta)
    rng = np.random.default_rng(3)
    attitude = Rotation.random(600, random_state=3)
    h = attitude.inv().apply([190.0, -3.0, 455.0])
    x = rng.uniform(0.0, 30.0, 600)
    tilt = Rotation.from_euler("ZYX", np.column_stack([np.zeros(600), attitude.as_euler("ZYX")[:, 1:]])).as_matrix()

    def to_compass(sol):  # type: ignore[no-untyped-def]
        return ArduPilotCompass.from_algebra(sol.A, sol.o, sol.m, orientation=0, motor_type="current")

    def folds(p: LevelProblem) -> float:
        return fold_rms(p, whole, None, 5, to_compass, problem.u, h, {"current": x},
                        None if kind == "vector" else tilt)[0]

    assert problem.fold_refitter(whole)(0, 120) is not None  # the refit is what the fast side takes
    fast = folds(problem)
    problem.fold_refitter = lambda sol, **_: (lambda a, b: None)  # type: ignore[method-assign]
    fresh = folds(problem)
    assert abs(fast / fresh - 1.0) < 1e-6, (fast, fresh)
