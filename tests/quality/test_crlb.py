"""The Cramér–Rao bound against a brute-force Fisher information of the full model (directions included)."""

from __future__ import annotations

import numpy as np
import pytest

from trimag.errors import IdentifiabilityError, TrimagInputError
from trimag.models import get_model
from trimag.models.ellipsoid import Ellipsoid
from trimag.quality.crlb import crlb, parametrisation
from trimag.simulate import great_circle_directions, uniform_directions


def _ellipsoid() -> Ellipsoid:
    rng = np.random.default_rng(1)
    return Ellipsoid.from_matrix_offset(np.eye(3) + 0.1 * rng.normal(size=(3, 3)), 0.3 * rng.normal(size=3))


def _brute(truth, u, sigma, F, known):
    """Full Fisher information of x_i = D(theta) F u(angles_i) + b(theta) by central differences over
    (theta, 2N angles[, F]), inverted, the theta block kept (gauge det W fixed when F is unknown and free: the
    bordered matrix [[J, g], [g^T, 0]] with g the gradient of log det W, inverted by numpy; nothing of trimag's
    constrained inverse)."""
    _, theta, param = parametrisation(truth)
    p, N = len(theta), len(u)
    ang = np.column_stack([np.arccos(u[:, 2]), np.arctan2(u[:, 1], u[:, 0])])

    def h(z):
        W, b = param(z[:p])
        a = z[p : p + 2 * N].reshape(N, 2)
        f = F if known else z[-1]
        uu = np.column_stack([np.sin(a[:, 0]) * np.cos(a[:, 1]), np.sin(a[:, 0]) * np.sin(a[:, 1]), np.cos(a[:, 0])])
        return ((f * uu) @ np.linalg.inv(W).T + b).ravel()

    z0 = np.concatenate([theta, ang.ravel(), [] if known else [F]])
    H = np.empty((3 * N, len(z0)))
    for k in range(len(z0)):
        d = 1e-6 * max(1.0, abs(z0[k]))
        zp, zm = z0.copy(), z0.copy()
        zp[k] += d
        zm[k] -= d
        H[:, k] = (h(zp) - h(zm)) / (2 * d)
    J = H.T @ H / sigma**2
    if known:
        return np.linalg.inv(J)[:p, :p]
    grad = np.zeros(len(z0))
    scale_free = truth.name in ("ellipsoid", "scalar9")
    if scale_free:
        for k in range(p):
            d = 1e-6 * max(1.0, abs(theta[k]))
            tp, tm = theta.copy(), theta.copy()
            tp[k] += d
            tm[k] -= d
            grad[k] = (np.log(abs(np.linalg.det(param(tp)[0]))) - np.log(abs(np.linalg.det(param(tm)[0])))) / (2 * d)
    if scale_free:  # constrained CRB (Stoica & Ng 1998) from the bordered information matrix, not trimag's own inverse
        n = len(z0)
        bordered = np.zeros((n + 1, n + 1))
        bordered[:n, :n] = J
        bordered[:n, n] = bordered[n, :n] = grad
        C = np.linalg.inv(bordered)[:n, :n]
    else:
        C = np.linalg.inv(J)
    idx = [*range(p), len(z0) - 1]
    return C[np.ix_(idx, idx)]


def _truth(model):
    if model == "ellipsoid":
        return _ellipsoid()
    cls = get_model(model)
    base = cls().as_vector()
    return cls.from_vector(base + 0.03 * np.resize([1.0, -0.6, 0.4, -0.8, 0.5, 0.7, -0.3, 0.9, -0.5], len(base)))


@pytest.mark.parametrize("known", [True, False], ids=["known-F", "unknown-F"])
@pytest.mark.parametrize("model", ["ellipsoid", "scalar9", "ortho-gain"])
def test_crlb_matches_brute_force_fisher(model, known):
    """The reduced (Schur complement) Fisher information equals the full one: relative error < 1e-6
    (central differences with step 1e-6 are accurate to ~1e-9 here)."""
    pytest.importorskip(f"trimag.models.{model.replace('-', '_')}")
    truth = _truth(model)
    u = uniform_directions(25, seed=3)
    bound = crlb(truth, u, 0.02, magnitude=1.5, known_magnitude=known)
    brute = _brute(truth, u, 0.02, 1.5, known)
    assert np.max(np.abs(bound.covariance - brute)) <= 1e-6 * np.max(np.abs(brute))


def test_crlb_scales_with_sigma_and_n():
    """std is proportional to sigma and to 1/sqrt(N) (same directions repeated)."""
    t = _ellipsoid()
    u = uniform_directions(200, seed=0)
    a = crlb(t, u, 0.01)
    b = crlb(t, u, 0.02)
    c = crlb(t, np.vstack([u] * 4), 0.01)
    np.testing.assert_allclose(b.std, 2 * a.std, rtol=1e-8)
    np.testing.assert_allclose(c.std, a.std / 2, rtol=1e-8)
    assert b.magnitude_rms == pytest.approx(2 * a.magnitude_rms, rel=1e-8)


def test_crlb_sphere_closed_form():
    """Unit sphere, W = I, known F: for uniform directions the offset bound is sigma^2 * 3 / N per axis."""
    u = uniform_directions(20000, seed=2)
    bound = crlb(Ellipsoid(), u, 0.01)
    np.testing.assert_allclose(bound.std[6:] ** 2, 3e-4 / 20000, rtol=0.05)


def test_crlb_rejects_unidentifiable_and_bad_input():
    u = great_circle_directions(30)[:10]  # ten directions on one circle: a plane
    with pytest.raises(IdentifiabilityError, match="singular"):
        crlb(_ellipsoid(), u, 0.01)
    with pytest.raises(TrimagInputError, match="sigma"):
        crlb(_ellipsoid(), uniform_directions(50, seed=0), -1.0)
    with pytest.raises(TrimagInputError, match="directions"):
        crlb(_ellipsoid(), np.ones((5, 2)), 0.01)


def test_metrics_reexports_crlb():
    from trimag.quality import metrics

    assert metrics.crlb is crlb


@pytest.mark.parametrize("known", [True, False], ids=["known-F", "unknown-F"])
def test_closed_form_ellipsoid_fisher_equals_generic_path(known):
    """``fisher_information`` takes a closed form for the ellipsoid's upper gauge; the generic finite-difference
    path (any other parametrisation callable) gives the same matrix on noisy samples off the ellipsoid."""
    from trimag.quality.crlb import _upper_param, fisher_information

    truth = _ellipsoid()
    _, theta, param = parametrisation(truth)
    assert param is _upper_param
    rng = np.random.default_rng(5)
    W, b = param(theta)
    X = uniform_directions(400, seed=4) @ np.linalg.inv(W).T + b + 0.05 * rng.standard_normal((400, 3))
    fast = fisher_information(X, param, theta, 0.05, known_magnitude=known)
    generic = fisher_information(X, lambda t: _upper_param(t), theta, 0.05, known_magnitude=known)
    assert fast.shape == ((9, 9) if known else (10, 10))
    assert np.max(np.abs(fast - generic)) <= 1e-8 * np.max(np.abs(generic))


def test_closed_form_predicted_errors_equal_the_finite_difference_path() -> None:
    """``predicted_errors`` in the ellipsoid's upper-triangular gauge (closed form) equals the generic path
    (central differences of any ``theta -> (W, b)``), here forced by wrapping the same parametrisation."""
    from trimag.quality.crlb import _upper_param, predicted_errors
    from trimag.quality.diagnostics import fibonacci_sphere

    rng = np.random.default_rng(5)
    W = np.triu(rng.normal(size=(3, 3))) * 0.1 + np.eye(3)
    b = rng.normal(size=3) * 0.2
    theta = np.concatenate([W[np.triu_indices(3)], b])
    X_test = 48.0 * fibonacci_sphere(300) @ np.linalg.inv(W).T + b
    A = rng.normal(size=(9, 9))
    cov = A @ A.T * 1e-6
    closed = predicted_errors(cov, _upper_param, theta, X_test)
    generic = predicted_errors(cov, lambda t: _upper_param(t), theta, X_test)
    np.testing.assert_allclose(closed, generic, rtol=1e-8)
    assert closed[0] > closed[1] > 0  # the vector error exceeds the magnitude error (it adds the direction)
