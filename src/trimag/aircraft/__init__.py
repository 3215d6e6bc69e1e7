"""Survey-aircraft compensation: the Tolles–Lawson result of a scalar magnetometer (``compensation``) and the
band-pass filters and segments it is fitted through (``filtering``); the estimator is ``estimators.tolles_lawson``.

May import the foundation (``errors``, ``units``, ``calibration``), ``_core``, ``models`` and ``io``. The commands
(``trimag fit --model tolles-lawson``, apply, evaluate) are in :mod:`trimag.app.tolles_lawson`.
"""

from __future__ import annotations

from typing import Any

from .._moved import forward

# ``trimag.aircraft`` was the Tolles–Lawson command module before it became this package (0.x, issue 29): its
# public names still resolve here, with a DeprecationWarning naming the new home.
_FORMER = ("TollesLawsonFitRequest", "apply_compensation_file", "evaluate_compensation_file",
           "fit_compensation_file", "is_compensation_file", "parse_segments")


def __getattr__(name: str) -> Any:
    if name in _FORMER:
        return forward("trimag.aircraft", "trimag.app.tolles_lawson", name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
