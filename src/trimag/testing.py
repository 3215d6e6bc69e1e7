"""Generic checks that every estimator must pass (style guide: scikit-learn's ``check_estimator``).

>>> from trimag.estimators import all_estimators
>>> from trimag.testing import check_estimator
>>> for name, cls in all_estimators():          # doctest: +SKIP
...     check_estimator(cls)

Each check is a function ``check(cls)`` that raises ``AssertionError`` with a message on failure;
:func:`estimator_checks` lists them so that a test file can make each one a named pytest case.

Simulated data: the estimator's own first model (``cls.models[0]``) with every parameter moved away from its
default by a fixed small pattern, 600 noise-free samples in uniformly random attitudes (:func:`trimag.simulate
.simulate`), field magnitude 50 (arbitrary unit). Scalar methods get the magnitude as reference (``None`` for
reference-free methods, ``reference_kind == "none"``); vector methods (``reference_kind == "vector"``) get the
background vector and the attitudes; gyro-aided methods (``reference_kind == "gyro"``) get the magnitude and the
angular rate of a smooth tumble sampled at 100 Hz (:func:`trimag.simulate.simulate_gyro`).
"""

from __future__ import annotations

import copy
import warnings
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .calibration import Calibration
from .errors import NotFittedError, TrimagInputError
from .estimators.base import Estimator
from .models import get_model
from .simulate import Simulation, simulate, simulate_gyro

__all__ = ["check_estimator", "estimator_checks", "simulated_problem"]

_FIELD = np.array([30.0, 20.0, 34.64101615137755])  # |F| = 50 (NED-like, pointing down)
_PATTERN = np.array([0.7, -0.5, 0.4, -0.3, 0.6, -0.45, 0.35, -0.25, 0.5, -0.6, 0.3, -0.4])


def simulated_problem(cls: type[Estimator], *, n: int = 600, seed: int = 0) -> Simulation:
    """Noise-free data from ``cls``'s own model with non-trivial parameters (see module docstring)."""
    model_cls = get_model(cls.models[0])
    base = model_cls().as_vector()
    scale = np.maximum(np.abs(base), 1.0)
    k = len(base)
    pattern = np.resize(_PATTERN, k)
    # offsets in field units (a few % of F); dimensionless parameters by a few %
    names = model_cls.param_names()
    step = np.array([2.0 if model_cls.kind_of(nm) == "offset" else 0.03 for nm in names])
    truth = model_cls.from_vector(base + pattern * step * scale)
    if cls.reference_kind == "gyro":  # a smooth tumble at 100 Hz with a noise-free gyroscope (its bias fitted)
        W, b = truth.correction()
        g = simulate_gyro(n, seed, matrix=W, offset=b, alignment=np.eye(3), mag_noise=0.0, gyro_noise=0.0,
                          field_nav=_FIELD)
        settings = {"n": n, "noise": 0.0, "field_nav": _FIELD.tolist(), "angular_rate": g.angular_rate()}
        return Simulation(g.raw, g.field_body, g.attitude, truth, settings)
    return simulate(truth, n=n, field_nav=_FIELD, noise=0.0, attitudes="random", seed=seed)


def _fit(est: Estimator, sim: Simulation, raw: NDArray[np.float64] | None = None) -> Estimator:
    X = sim.raw if raw is None else raw
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if est.reference_kind == "vector":
            return est.fit(X, np.asarray(sim.settings["field_nav"]), attitude=sim.attitude)
        if est.reference_kind == "none":
            return est.fit(X, None)
        if est.reference_kind == "gyro":
            return est.fit(X, float(np.linalg.norm(_FIELD)), attitude=sim.settings["angular_rate"])
        return est.fit(X, float(np.linalg.norm(_FIELD)))


def check_fit_returns_self(cls: type[Estimator]) -> None:
    """``fit`` returns the estimator itself."""
    est = cls()
    out = _fit(est, simulated_problem(cls))
    assert out is est, f"{cls.__name__}.fit must return self; got {type(out).__name__}"


def check_no_attributes_before_fit(cls: type[Estimator]) -> None:
    """``__init__`` only stores its keyword arguments: no ``_``-suffixed attribute exists before ``fit``."""
    est = cls()
    fitted = [k for k in vars(est) if k.endswith("_") and not k.startswith("_")]
    assert not fitted, f"{cls.__name__} sets {fitted} before fit"
    assert set(vars(est)) <= set(est._param_names()), (
        f"{cls.__name__}.__init__ stores attributes {sorted(set(vars(est)) - set(est._param_names()))} "
        "that are not its parameters"
    )
    clone = cls(**est.get_params())
    assert clone.get_params() == est.get_params(), f"{cls.__name__}: get_params does not rebuild the estimator"


def check_not_fitted_error(cls: type[Estimator]) -> None:
    """``transform`` before ``fit`` raises :class:`NotFittedError`."""
    est = cls()
    try:
        est.transform(np.ones((5, 3)))
    except NotFittedError:
        return
    raise AssertionError(f"{cls.__name__}.transform before fit must raise NotFittedError")


def check_fit_idempotent(cls: type[Estimator]) -> None:
    """Fitting twice on the same data gives the same calibration."""
    sim = simulated_problem(cls)
    est = cls()
    a = _fit(est, sim).calibration_
    b = _fit(est, sim).calibration_
    assert np.allclose(a.matrix, b.matrix, rtol=1e-10, atol=1e-12) and np.allclose(
        a.offset, b.offset, rtol=1e-10, atol=1e-10
    ), f"{cls.__name__}: a second fit on the same data gives a different result"


def check_input_not_modified(cls: type[Estimator]) -> None:
    """``fit`` leaves the caller's array untouched."""
    sim = simulated_problem(cls)
    raw = sim.raw.copy()
    keep = raw.copy()
    _fit(cls(), sim, raw)
    assert np.array_equal(raw, keep), f"{cls.__name__}.fit modified its input array"


def check_rejects_bad_input(cls: type[Estimator]) -> None:
    """NaN, inf and wrong shapes raise :class:`TrimagInputError` with a message."""
    sim = simulated_problem(cls)
    bad_nan = sim.raw.copy()
    bad_nan[3, 1] = np.nan
    bad_inf = sim.raw.copy()
    bad_inf[5, 0] = np.inf
    for label, X in (
        ("NaN", bad_nan), ("inf", bad_inf), ("shape (N, 4)", np.ones((50, 4))), ("1-D", np.ones(30)),
        ("empty", np.empty((0, 3))),
    ):
        try:
            _fit(cls(), sim, X)
        except TrimagInputError as exc:
            assert str(exc), f"{cls.__name__}: empty message for {label} input"
            continue
        raise AssertionError(f"{cls.__name__}.fit accepted {label} input")


def _gauge_free(cal: Calibration, kind: str) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """What a method can identify: ``W^T W`` (scalar), normalised when no magnitude is given; ``W`` itself
    for vector methods; and the offset."""
    W = np.asarray(cal.matrix)
    if kind == "vector":
        return W, np.asarray(cal.offset)
    M = W.T @ W
    if kind == "none":
        M = M / np.linalg.norm(M)
    return M, np.asarray(cal.offset)


def check_recovers_parameters(cls: type[Estimator]) -> None:
    """Noise-free data from the method's own model: the true correction is recovered (in the gauge the
    method can identify: ``W^T W`` and offset for scalar methods, ``W`` and offset for vector methods) to
    1e-5 relative, and corrected magnitudes equal the field to 1e-6 relative."""
    sim = simulated_problem(cls)
    est = _fit(cls(), sim)
    cal = est.calibration_
    truth = Calibration.from_params(sim.truth.name, sim.truth.as_dict())
    got_M, got_b = _gauge_free(cal, cls.reference_kind)
    want_M, want_b = _gauge_free(truth, cls.reference_kind)
    F = float(np.linalg.norm(_FIELD))
    assert np.allclose(got_M, want_M, rtol=0, atol=1e-5 * np.abs(want_M).max()), (
        f"{cls.__name__}: matrix not recovered from noise-free data:\n{got_M}\nexpected\n{want_M}"
    )
    assert np.allclose(got_b, want_b, rtol=0, atol=1e-5 * F), (
        f"{cls.__name__}: offset not recovered from noise-free data: {got_b} expected {want_b}"
    )
    if cls.reference_kind != "none":
        mags = np.linalg.norm(cal.apply(sim.raw), axis=1)
        assert np.allclose(mags, F, rtol=1e-6), f"{cls.__name__}: corrected magnitudes differ from the field"


def check_json_round_trip(cls: type[Estimator]) -> None:
    """The fitted calibration survives ``to_json`` / ``from_json`` exactly."""
    cal = _fit(cls(), simulated_problem(cls)).calibration_
    back = Calibration.from_json(cal.to_json())
    assert back == cal, f"{cls.__name__}: JSON round trip changed the calibration"
    assert np.array_equal(back.matrix, cal.matrix) and np.array_equal(back.offset, cal.offset), (
        f"{cls.__name__}: JSON round trip is not exact"
    )


def check_params_not_mutated(cls: type[Estimator]) -> None:
    """``fit`` does not change the constructor parameters."""
    est = cls()
    before = copy.deepcopy(est.get_params())
    _fit(est, simulated_problem(cls))
    assert est.get_params() == before, f"{cls.__name__}.fit changed its parameters"


def check_uncertainty_fields(cls: type[Estimator]) -> None:
    """A reported uncertainty has the same fields for every estimator
    (:data:`trimag.calibration.UNCERTAINTY_FIELDS`), its ``param_std`` names the model's parameters in
    ``covariance_order``, and a covariance, when given, is square and matches that order."""
    from .calibration import UNCERTAINTY_FIELDS

    sim = simulated_problem(cls)
    noisy = sim.raw + np.random.default_rng(5).normal(scale=0.05, size=sim.raw.shape)
    unc = _fit(cls(), sim, noisy).calibration_.uncertainty
    if unc is None:
        return
    missing = [k for k in UNCERTAINTY_FIELDS if k not in unc]
    assert not missing, f"{cls.__name__}'s uncertainty lacks {missing}"
    assert list(unc["param_std"]) == list(unc["covariance_order"]), f"{cls.__name__}: param_std order"
    if unc["covariance"] is not None:
        cov = np.asarray(unc["covariance"], dtype=np.float64)
        assert cov.shape == (len(unc["covariance_order"]),) * 2, f"{cls.__name__}: covariance shape {cov.shape}"


_CHECKS: tuple[Callable[[type[Estimator]], None], ...] = (
    check_no_attributes_before_fit,
    check_not_fitted_error,
    check_fit_returns_self,
    check_params_not_mutated,
    check_fit_idempotent,
    check_input_not_modified,
    check_rejects_bad_input,
    check_recovers_parameters,
    check_json_round_trip,
    check_uncertainty_fields,
)


def estimator_checks(cls: type[Estimator]) -> Iterator[tuple[str, Callable[[], None]]]:
    """``(check name, zero-argument callable)`` for every generic check of ``cls``."""
    for check in _CHECKS:

        def run(check: Callable[[type[Estimator]], None] = check) -> None:
            check(cls)

        yield check.__name__, run


def check_estimator(cls: type[Estimator]) -> dict[str, Any]:
    """Run every generic check on ``cls``; raise ``AssertionError`` listing the ones that fail.

    Returns
    -------
    dict
        ``{check name: "ok"}``.
    """
    failures = {}
    for name, run in estimator_checks(cls):
        try:
            run()
        except Exception as exc:  # an unexpected error is a failed check too
            failures[name] = f"{type(exc).__name__}: {exc}"
    if failures:
        raise AssertionError(f"{cls.__name__} fails: " + "; ".join(f"{k}: {v}" for k, v in failures.items()))
    return {name: "ok" for name, _ in estimator_checks(cls)}
