"""trimag: calibrate tri-axial magnetometers.

>>> import trimag
>>> cal = trimag.fit(samples, reference=48193.0, units="nT")   # doctest: +SKIP
>>> corrected = cal.apply(samples)                               # doctest: +SKIP
"""

from ._version import __version__
from .calibration import Calibration
from .errors import (
    IdentifiabilityError,
    IdentifiabilityWarning,
    NotFittedError,
    TrimagError,
    TrimagInputError,
    UnitMismatchError,
)
from .fitting import fit

__all__ = [
    "Calibration",
    "IdentifiabilityError",
    "IdentifiabilityWarning",
    "NotFittedError",
    "TrimagError",
    "TrimagInputError",
    "UnitMismatchError",
    "__version__",
    "fit",
]
