"""The application layer: what each ``trimag`` command does with files, one module per command, on top of the
library (which never imports it); the CLI and ``trimag live`` call its entry points.

Every entry point takes one typed request (:mod:`trimag.app.requests`), reads through :mod:`trimag.io`, works through
the library, writes its outputs atomically and returns a result the CLI prints; ``from trimag.app import fit_file``
is the one public import path of the file-level commands (``trimag.workflow`` is its deprecated former name). The
modules are imported on first use, so ``trimag.app.requests`` stays light. See docs/architecture.md (the app layer).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ._inputs import parse_options
    from .apply import apply_to_file
    from .demo import DEMO_DATA, run_demo
    from .evaluate import evaluate_file
    from .evaluate_heading import evaluate_heading_file
    from .evaluate_vector import evaluate_vector_file
    from .export import export_to_file
    from .fit import FitResult, fit_file, fit_summary
    from .fit_all import AllSensorsResult, fit_all_sensors
    from .simulate import simulate_to_file

__all__ = [
    "DEMO_DATA",
    "AllSensorsResult",
    "FitResult",
    "apply_to_file",
    "evaluate_file",
    "evaluate_heading_file",
    "evaluate_vector_file",
    "export_to_file",
    "fit_all_sensors",
    "fit_file",
    "fit_summary",
    "parse_options",
    "run_demo",
    "simulate_to_file",
]

_HOME = {
    "parse_options": "_inputs", "apply_to_file": "apply", "DEMO_DATA": "demo", "run_demo": "demo",
    "evaluate_file": "evaluate", "evaluate_heading_file": "evaluate_heading",
    "evaluate_vector_file": "evaluate_vector", "export_to_file": "export", "FitResult": "fit", "fit_file": "fit",
    "fit_summary": "fit", "simulate_to_file": "simulate", "AllSensorsResult": "fit_all",
    "fit_all_sensors": "fit_all",
}


def __getattr__(name: str) -> Any:
    if name in _HOME:
        value = getattr(importlib.import_module(f".{_HOME[name]}", __name__), name)
        globals()[name] = value  # later look-ups (and monkeypatch) see a plain attribute
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
