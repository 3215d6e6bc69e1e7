"""The ``trimag`` command's file-level operations, by their stable names (the pinned public API).

The work lives in :mod:`trimag.app`, one module per command (docs/architecture.md); this module re-exports its
entry points so that ``from trimag.workflow import fit_file`` keeps working, and the CLI and batch runs call
through it.
"""

from __future__ import annotations

from .app._inputs import parse_options
from .app.apply import apply_to_file
from .app.demo import DEMO_DATA, run_demo
from .app.evaluate import evaluate_file
from .app.evaluate_heading import evaluate_heading_file
from .app.evaluate_vector import evaluate_vector_file
from .app.export import export_to_file
from .app.fit import FitResult, fit_file, fit_summary
from .app.simulate import simulate_to_file

__all__ = [
    "DEMO_DATA",
    "FitResult",
    "apply_to_file",
    "evaluate_file",
    "evaluate_heading_file",
    "evaluate_vector_file",
    "export_to_file",
    "fit_file",
    "fit_summary",
    "parse_options",
    "run_demo",
    "simulate_to_file",
]
