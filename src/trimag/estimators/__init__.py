"""Identification methods: one module per method, each an :class:`~trimag.estimators.base.Estimator`, and the
registry; an estimator imports its base, the shared private modules and the core, never a sibling.

The public entry point is :func:`trimag.fit`; the classes follow a scikit-learn-like contract.
"""

from __future__ import annotations

import importlib
from typing import Any

from ..errors import TrimagInputError
from .base import Estimator, build_calibration

__all__ = [
    "DEFAULT_METHOD",
    "METHODS",
    "Estimator",
    "all_estimators",
    "available_methods",
    "build_calibration",
    "get_estimator",
]

#: Registry: method name -> "module:Class".
METHODS: dict[str, str] = {
    # general hard + soft iron (foundation, issue 7)
    "ellipsoid-fit": "trimag.estimators.ellipsoid_fit:EllipsoidFit",
    "ml": "trimag.estimators.ml:MaximumLikelihood",
    # the ellipsoid with the gyroscope beside the magnetometer (issue 31)
    "gyro": "trimag.estimators.gyro:GyroAided",
    "twostep": "trimag.estimators.twostep:TwoStep",
    "als": "trimag.estimators.als:AdjustedLeastSquares",
    # paper A
    "pairwise": "trimag.estimators.pairwise:Pairwise",
    "wen2008": "trimag.estimators.wen2008:Wen2008",
    "geometric": "trimag.estimators.geometric:Geometric",
    # paper B
    "gauss-newton": "trimag.estimators.gauss_newton:GaussNewton",
    # paper C
    "linear-vector": "trimag.estimators.linear_vector:LinearVector",
    # paper D
    "quadric": "trimag.estimators.quadric:Quadric",
    "lms": "trimag.estimators.lms:LMS",
    "bfgs": "trimag.estimators.bfgs:BFGS",
}

#: Default method for each model (``trimag fit --model M`` without ``--method``).
DEFAULT_METHOD: dict[str, str] = {
    "ellipsoid": "ml",
    "ortho-gain": "pairwise",
    "ortho-gain-bias": "geometric",
    "scalar9": "gauss-newton",
    "interference12": "linear-vector",
    "zhang-cheng": "quadric",
}


def _load(name: str) -> type[Estimator] | None:
    module_name, cls_name = METHODS[name].split(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name == module_name:
            return None
        raise
    return getattr(module, cls_name, None)


def get_estimator(name: str) -> type[Estimator]:
    """Return the estimator class registered as ``name``."""
    if name not in METHODS:
        raise TrimagInputError(f"unknown method {name!r}; choose one of {', '.join(available_methods())}")
    cls = _load(name)
    if cls is None:
        raise TrimagInputError(f"method {name!r} is not available in this build of trimag")
    return cls


def available_methods(model: str | None = None) -> list[str]:
    """Names of the methods that can be loaded (those that identify ``model``, when given)."""
    out = []
    for name in METHODS:
        cls = _load(name)
        if cls is not None and (model is None or model in cls.models):
            out.append(name)
    return out


def all_estimators() -> list[tuple[str, type[Estimator]]]:
    """``(name, class)`` for every registered method that is available."""
    return [(name, get_estimator(name)) for name in available_methods()]


def make_estimator(model: str, method: str | None, options: dict[str, Any] | None = None) -> Estimator:
    """Instantiate the estimator for ``model`` (default method when ``method`` is None) with ``options``."""
    from ..models import get_model

    get_model(model)
    name = method or DEFAULT_METHOD.get(model)
    if name is None:
        raise TrimagInputError(f"model {model!r} has no default method; give `method`")
    cls = get_estimator(name)
    if model not in cls.models:
        raise TrimagInputError(
            f"method {name!r} cannot identify model {model!r}; it identifies {', '.join(cls.models)}. "
            f"Methods for {model!r}: {', '.join(available_methods(model))}"
        )
    est = cls()
    if "model" in est._param_names():
        est.set_params(model=model)
    est.set_params(**(options or {}))
    return est
