"""Gauss-Newton with the Levenberg-Marquardt fallback (trimag._core.solve)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from trimag._core.solve import (
    GaussNewtonResult,
    GaussNewtonRun,
    contraction,
    gauss_newton_rule,
    gauss_newton_then_lm,
    levenberg_marquardt,
)


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


def _atan_rule(**options: object) -> GaussNewtonRun:
    """Gauss-Newton by the rule on r(p) = atan(p) from p = 2 (the full step overshoots to -3.5)."""

    def evaluate(p: np.ndarray) -> tuple[float, float]:
        return float(np.arctan(p[0])), float(np.arctan(p[0]) ** 2)

    return gauss_newton_rule(
        evaluate, lambda p, r: 1.0 / (1.0 + p[0] ** 2), lambda r, j: np.array([-r / j]), np.array([2.0]),
        max_steps=50, xtol=1e-13, **options,  # type: ignore[arg-type]
    )


def test_the_rule_stalls_on_a_step_that_raises_the_cost_without_halving() -> None:
    run = _atan_rule()
    assert run.stalled and not run.converged
    assert run.p[0] == 2.0 and run.nfev == 2 and run.steps == 1


def test_step_halving_turns_the_overshoot_into_a_converged_run() -> None:
    run = _atan_rule(halvings=20)
    assert run.converged and not run.stalled
    assert run.p[0] == pytest.approx(0.0, abs=1e-12)
    assert run.fractions[0] < 1.0  # the first step was halved ...
    assert run.fractions[-1] == 1.0  # ... the last ones, near the minimum, are full Gauss-Newton steps
    assert len(run.costs) == len(run.step_norms) + 1 and run.costs == sorted(run.costs, reverse=True)


def test_a_caller_stop_before_evaluation_saves_the_evaluation() -> None:
    A = np.array([[1.0, 0.0], [0.0, 2.0], [1.0, 1.0]])
    y = np.array([1.0, 2.0, 3.0])
    seen = []

    def evaluate(p: np.ndarray) -> tuple[np.ndarray, float]:
        seen.append(p.copy())
        r = A @ p - y
        return r, float(r @ r)

    run = gauss_newton_rule(
        evaluate, lambda p, r: A, lambda r, J: -np.linalg.solve(J.T @ J, J.T @ r), np.zeros(2), max_steps=10,
        final=lambda p_new, delta, r, J: True,
    )
    assert run.converged and run.nfev == 1 and len(seen) == 1  # the step's end point was never evaluated
    np.testing.assert_allclose(run.p, np.linalg.lstsq(A, y, rcond=None)[0], rtol=1e-12)
    assert run.cost == pytest.approx(float(y @ y))  # the cost is that of the point before the step


def test_a_caller_rise_test_decides_acceptance() -> None:
    # with every step accepted the overshoot is taken, and Gauss-Newton on atan diverges from p = 2
    never = gauss_newton_rule(
        lambda p: (float(np.arctan(p[0])), float(np.arctan(p[0]) ** 2)), lambda p, r: 1.0 / (1.0 + p[0] ** 2),
        lambda r, j: np.array([-r / j]), np.array([2.0]), max_steps=3, rises=lambda new, old: False,
    )
    assert not never.converged and not never.stalled and never.steps == 3 and abs(never.p[0]) > 2.0


def test_levenberg_marquardt_is_scipys_least_squares_in_the_core_result_type() -> None:
    t = np.linspace(0, 3, 100)
    y = 2.0 * np.exp(-1.3 * t)

    def fun(p: np.ndarray) -> np.ndarray:
        return np.asarray(p[0] * np.exp(-p[1] * t) - y)

    res = levenberg_marquardt(fun, np.array([1.0, 1.0]), xtol=1e-12)
    ref = least_squares(fun, np.array([1.0, 1.0]), method="lm", xtol=1e-12)
    assert isinstance(res, GaussNewtonResult) and res.method == "levenberg-marquardt"
    np.testing.assert_array_equal(res.x, ref.x)
    assert res.nfev == ref.nfev and res.message == ref.message
    res.message = "changed"  # attributes are the dict's keys, as in OptimizeResult
    assert res["message"] == "changed"
    trf = levenberg_marquardt(fun, np.array([1.0, 1.0]), method="trf", loss="soft_l1")
    assert trf.method == "trust-region" and trf.x == pytest.approx([2.0, 1.3], rel=1e-6)


def test_least_squares_is_called_only_by_the_core() -> None:
    from pathlib import Path

    import trimag

    root = Path(trimag.__file__).parent
    callers = sorted(
        str(path.relative_to(root)) for path in root.rglob("*.py")
        if "least_squares(" in "\n".join(
            line for line in path.read_text(encoding="utf-8").splitlines() if "``" not in line
        )
    )
    assert callers == ["_core/solve.py"]
