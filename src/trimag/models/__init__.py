"""Error models: one module per model, each a frozen dataclass of physical parameters with its own algebra;
models import only the core and :mod:`trimag.errors`.

=====================  =========================================  ==============================
name                   class                                      source
=====================  =========================================  ==============================
``ellipsoid``          :class:`~trimag.models.ellipsoid.Ellipsoid`   hard + soft iron (general)
``ortho-gain``         ``trimag.models.ortho_gain.OrthoGain``         paper A (5 parameters)
``ortho-gain-bias``    ``trimag.models.ortho_gain.OrthoGainBias``     paper A + three offsets
``scalar9``            ``trimag.models.scalar9.Scalar9``              paper B (9 parameters)
``interference12``     ``trimag.models.interference12.Interference12``  paper C (12 coefficients)
``zhang-cheng``        ``trimag.models.zhang_cheng.ZhangCheng``        paper D (9 parameters)
=====================  =========================================  ==============================
"""

from __future__ import annotations

import importlib

from ..errors import TrimagInputError
from .base import ErrorModel

__all__ = ["MODELS", "ErrorModel", "available_models", "get_model"]

#: Registry: model name -> "module:Class". Looked up by name in calibration files and on the command line.
MODELS: dict[str, str] = {
    "ellipsoid": "trimag.models.ellipsoid:Ellipsoid",
    "ortho-gain": "trimag.models.ortho_gain:OrthoGain",
    "ortho-gain-bias": "trimag.models.ortho_gain:OrthoGainBias",
    "scalar9": "trimag.models.scalar9:Scalar9",
    "interference12": "trimag.models.interference12:Interference12",
    "zhang-cheng": "trimag.models.zhang_cheng:ZhangCheng",
}


def get_model(name: str) -> type[ErrorModel]:
    """Return the model class registered under ``name``."""
    target = MODELS.get(name)
    if target is None:
        raise TrimagInputError(f"unknown model {name!r}; choose one of {', '.join(available_models())}")
    module_name, cls_name = target.split(":")
    try:
        cls = getattr(importlib.import_module(module_name), cls_name)
    except (ImportError, AttributeError):
        raise TrimagInputError(f"model {name!r} is not available in this build of trimag") from None
    return cls


def available_models() -> list[str]:
    """Names of the models that can be loaded."""
    names = []
    for name, target in MODELS.items():
        module_name, cls_name = target.split(":")
        try:
            getattr(importlib.import_module(module_name), cls_name)
        except (ImportError, AttributeError):
            continue
        names.append(name)
    return names
