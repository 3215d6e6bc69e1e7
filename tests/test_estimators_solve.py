"""Gauss-Newton with the Levenberg-Marquardt fallback (trimag._core.solve)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from trimag._core.solve import contraction, gauss_newton_then_lm


def test_linear_problem_is_solved_in_one_step() -> None:
    rng = np.random.default_rng(0)
    A = rng.normal(size=(50, 4)) * [1.0, 10.0, 1e-3, 1e3]  # very different column scales
    y = rng.normal(size=50)
    res = gauss_newton_then_lm(lambda p: A @ p - y, lambda p: A, np.zeros(4))
    assert res.method == "gauss-newton" and res.success
    np.testing.assert_allclose(res.x, np.linalg.lstsq(A, y, rcond=None)[0], rtol=1e-10)
    np.testing.assert_allclose(res.fun, A @ res.x - y)
    assert res.jac.shape == (50, 4) and res.nfev <= 3


def test_nonlinear_fit_reaches_a_smaller_gradient_than_minpack() -> None:
    t = np.linspace(0, 3, 200)
    rng = np.random.default_rng(1)
    y = 2.0 * np.exp(-1.3 * t) + 0.01 * rng.normal(size=t.size)

    def fun(p: np.ndarray) -> np.ndarray:
        return np.asarray(p[0] * np.exp(-p[1] * t) - y)

    def jac(p: np.ndarray) -> np.ndarray:
        e = np.exp(-p[1] * t)
        return np.column_stack([e, -p[0] * t * e])

    p0 = np.array([1.9, 1.25])
    res = gauss_newton_then_lm(fun, jac, p0)
    lm = least_squares(fun, p0, jac=jac, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    assert res.method == "gauss-newton"
    np.testing.assert_allclose(res.x, lm.x, rtol=1e-7)
    grad = float(np.linalg.norm(jac(res.x).T @ fun(res.x)))
    assert grad <= max(float(np.linalg.norm(jac(lm.x).T @ fun(lm.x))), 1e-12)


def test_a_step_that_raises_the_cost_hands_over_to_levenberg_marquardt() -> None:
    # r(p) = atan(p): the Gauss-Newton step from p = 2 overshoots to p = -3.5, where |r| is larger
    res = gauss_newton_then_lm(lambda p: np.arctan(p), lambda p: np.array([[1.0 / (1.0 + p[0] ** 2)]]),
                               np.array([2.0]), lm_options={"xtol": 1e-12})
    assert res.method == "levenberg-marquardt" and "Gauss-Newton did not converge" in res.message
    assert res.x[0] == pytest.approx(0.0, abs=1e-8)


def test_running_out_of_steps_hands_over_too() -> None:
    calls = []

    def fun(p: np.ndarray) -> np.ndarray:
        calls.append(1)
        return np.array([p[0] ** 2 - 4.0, 0.1 * (p[0] - 2.0)])

    def jac(p: np.ndarray) -> np.ndarray:
        return np.array([[2 * p[0]], [0.1]])

    res = gauss_newton_then_lm(fun, jac, np.array([50.0]), max_steps=1)
    assert res.method == "levenberg-marquardt" and res.x[0] == pytest.approx(2.0, rel=1e-6)


def test_contraction_is_the_ratio_of_the_later_steps() -> None:
    # the first step (leaving the start) is not used; the larger of the last two ratios is
    assert contraction([1.0, 1e-3, 2e-6, 1e-9]) == pytest.approx(2e-3)
    assert contraction([1.0, 1e-2, 1e-5]) == pytest.approx(1e-3)
    assert contraction([1.0, 1e-2]) is None  # too few steps to see the linear phase
    assert contraction([]) is None


def test_gauss_newton_reports_its_steps_and_their_contraction() -> None:
    # a noisy exponential: nonzero residuals, so Gauss-Newton converges linearly at a fixed rate
    t = np.linspace(0, 3, 200)
    y = 2.0 * np.exp(-1.3 * t) + 0.05 * np.random.default_rng(2).normal(size=t.size)
    res = gauss_newton_then_lm(
        lambda p: np.asarray(p[0] * np.exp(-p[1] * t) - y),
        lambda p: np.column_stack([np.exp(-p[1] * t), -p[0] * t * np.exp(-p[1] * t)]),
        np.array([1.5, 1.0]), xtol=1e-14,
    )
    steps = res.step_norms
    assert res.method == "gauss-newton" and len(steps) >= 4
    rho = contraction(steps)
    assert rho is not None and 0 < rho < 0.5
    # linear convergence: once the start is left, consecutive steps shrink by about the same factor
    ratios = np.array(steps[1:]) / np.array(steps[:-1])
    assert np.all(np.abs(np.log(ratios[2:] / rho)) < np.log(1.5))
    assert ratios[-1] <= rho and ratios[-2] <= rho
