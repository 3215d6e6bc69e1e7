"""``trimag.solvers``: the public solver API gives the solution its estimator turns into a calibration."""

from __future__ import annotations

import numpy as np

from trimag import solvers
from trimag.estimators.geometric import Geometric
from trimag.estimators.linear_vector import LinearVector
from trimag.fields.attitude import body_field
from trimag.models.interference12 import Interference12
from trimag.simulate import random_attitudes


def _sensor(n: int = 400, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    T = np.array([[1.05, 0.02, -0.01], [0.0, 0.97, 0.03], [0.0, 0.0, 1.01]])
    return 50_000.0 * u @ T.T + np.array([300.0, -150.0, 80.0]) + rng.normal(scale=5.0, size=(n, 3))


def test_solve_geometric_is_what_the_estimator_fits():
    B = _sensor()
    sol = solvers.solve_geometric(B, bias=True)
    cal = Geometric(model="ortho-gain-bias").fit(B).calibration_
    np.testing.assert_allclose(cal.matrix, sol.C, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(cal.offset, sol.b, rtol=1e-12)
    np.testing.assert_allclose(sol.b, [300.0, -150.0, 80.0], atol=5.0)  # the truth, within the noise


def test_solve_interference_recovers_K_and_c_exactly_without_noise():
    att = random_attitudes(60, seed=1)
    H_b = body_field(att, np.array([18_000.0, 1_000.0, 45_000.0]))
    K = np.array([[1.02, 0.03, -0.01], [0.01, 0.98, 0.02], [-0.02, 0.01, 1.05]])
    c = np.array([120.0, -60.0, 300.0])
    K_hat, c_hat, _ = solvers.solve_interference(H_b @ K.T + c, H_b)
    np.testing.assert_allclose(K_hat, K, atol=1e-10)
    np.testing.assert_allclose(c_hat, c, atol=1e-6)
    cal = LinearVector().fit(H_b @ K.T + c, np.array([18_000.0, 1_000.0, 45_000.0]), attitude=att).calibration_
    np.testing.assert_allclose(Interference12.from_dict(cal.params).correct(H_b @ K.T + c), H_b, atol=1e-6)


def test_identifiability_report_names_what_a_single_axis_turn_leaves_undetermined():
    t = np.linspace(0, 2 * np.pi, 50, endpoint=False)
    V = np.column_stack([np.cos(t), np.sin(t), np.full_like(t, 0.5)])
    report = solvers.identifiability_report(V, 1.25)
    assert report.rank < 10
    assert report.undetermined
