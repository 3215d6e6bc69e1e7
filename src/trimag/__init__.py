"""trimag: calibrate tri-axial magnetometers.

>>> import trimag
>>> cal = trimag.fit(samples, reference=48193.0, units="nT")   # doctest: +SKIP
>>> corrected = cal.apply(samples)                               # doctest: +SKIP
"""

from . import _moved
from ._version import __version__
from .aircraft.compensation import ScalarCompensation
from .calibration import Calibration
from .errors import (
    IdentifiabilityError,
    IdentifiabilityWarning,
    NotFittedError,
    TrimagError,
    TrimagInputError,
    UnitMismatchError,
)
from .estimators import available_methods, get_estimator
from .fitting import fit
from .models import available_models, get_model
from .quality.crlb import crlb

_moved.install()

__all__ = [
    "Calibration",
    "IdentifiabilityError",
    "IdentifiabilityWarning",
    "NotFittedError",
    "ScalarCompensation",
    "TrimagError",
    "TrimagInputError",
    "UnitMismatchError",
    "__version__",
    "available_methods",
    "available_models",
    "crlb",
    "fit",
    "get_estimator",
    "get_model",
]
