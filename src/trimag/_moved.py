"""The former import paths of modules moved into the job packages (issue 29), kept with a DeprecationWarning.

``import trimag.metrics`` (or ``from trimag.metrics import rms``) still works: a finder on ``sys.meta_path`` answers
each former name with the module at its new home (the same module object, so a class's identity and pickles are
unchanged) and warns once per name. The table below is the map of the move (docs/architecture.md, "Former paths").
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import types
import warnings
from collections.abc import Sequence
from typing import Any

#: former module -> its home since the job packages (docs/architecture.md)
MOVED = {
    "trimag.regressors": "trimag.vehicle.regressors",
    "trimag.eddy": "trimag.vehicle.eddy",
    "trimag.joint": "trimag.vehicle.joint",
    "trimag.prior": "trimag.vehicle.prior",
    "trimag.alignment": "trimag.vehicle.alignment",
    "trimag.heading": "trimag.vehicle.heading",
    "trimag.timesync": "trimag.vehicle.timesync",
    "trimag.policy": "trimag.vehicle.policy",
    "trimag.compensation": "trimag.aircraft.compensation",
    "trimag.filtering": "trimag.aircraft.filtering",
    "trimag.crlb": "trimag.quality.crlb",
    "trimag.diagnostics": "trimag.quality.diagnostics",
    "trimag.honesty": "trimag.quality.honesty",
    "trimag.metrics": "trimag.quality.metrics",
    "trimag.report": "trimag.quality.report",
    "trimag.reference": "trimag.fields.reference",
    "trimag.attitude": "trimag.fields.attitude",
    "trimag.requests": "trimag.app.requests",
    "trimag.batch": "trimag.app.batch",
    "trimag.workflow": "trimag.app",
}

__all__ = ["MOVED", "forward"]


def _warn(old: str, new: str) -> None:
    warnings.warn(f"{old} is deprecated: import {new} instead (docs/architecture.md, 'Former paths')",
                  DeprecationWarning, stacklevel=4)


def forward(old_module: str, new_module: str, name: str) -> Any:
    """``new_module.name``, with a DeprecationWarning that ``old_module.name`` moved."""
    _warn(f"{old_module}.{name}", f"{new_module}.{name}")
    return getattr(importlib.import_module(new_module), name)


class _Alias(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Answers a former module name with the module at its new home."""

    def find_spec(self, fullname: str, path: Sequence[str] | None, target: types.ModuleType | None = None
                  ) -> importlib.machinery.ModuleSpec | None:
        if fullname not in MOVED:
            return None
        return importlib.machinery.ModuleSpec(fullname, self)

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> types.ModuleType:
        _warn(spec.name, MOVED[spec.name])
        return importlib.import_module(MOVED[spec.name])

    def exec_module(self, module: types.ModuleType) -> None:
        """The module at the new home is already executed."""


def install() -> None:
    """Put the finder on ``sys.meta_path`` once (called by ``trimag/__init__``)."""
    if not any(isinstance(f, _Alias) for f in sys.meta_path):
        sys.meta_path.append(_Alias())
