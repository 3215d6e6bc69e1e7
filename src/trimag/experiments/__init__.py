"""Reproductions of the four papers, each a module with ``run(...) -> dict``, written with trimag's public API
only (what a user of the package could write).

``trimag reproduce NAME`` calls :func:`get_experiment` and then ``module.run``. Every module uses only trimag's
public API. (The benchmarks are not here: they live in the repository's ``benchmarks/`` folder, which is not
installed: ``python benchmarks/speed.py``, ``python benchmarks/accuracy.py``.)

Module contract:

``add_arguments(parser: argparse.ArgumentParser) -> None`` (optional)
    Extra command-line options of this experiment.
``run(out_dir: pathlib.Path, *, quick: bool, trials: int | None, seed: int, workers: int, json_mode: bool,
      **extra) -> dict``
    Writes figures (PNG) and numbers (CSV) into ``out_dir`` atomically, and returns the JSON summary.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from ..errors import TrimagInputError

__all__ = ["EXPERIMENTS", "get_experiment"]

EXPERIMENTS: dict[str, str] = {
    "wu2013": "trimag.experiments.wu2013",
    "scalar-gn": "trimag.experiments.scalar_gn",
    "vehicle12": "trimag.experiments.vehicle12",
    "zhang2009": "trimag.experiments.zhang2009",
}


def get_experiment(name: str) -> ModuleType:
    """Import the module of the paper reproduction ``name``."""
    if name not in EXPERIMENTS:
        raise TrimagInputError(f"unknown reproduce target {name!r}; choose one of {', '.join(EXPERIMENTS)}")
    try:
        return importlib.import_module(EXPERIMENTS[name])
    except ModuleNotFoundError as exc:
        if exc.name == EXPERIMENTS[name]:
            raise TrimagInputError(f"reproduce target {name!r} is not available in this build") from None
        raise
