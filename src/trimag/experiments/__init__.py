"""Reproductions of the four papers and the benchmarks, each a module with ``run(...) -> dict``.

``trimag reproduce NAME`` and ``trimag bench NAME`` call :func:`get_experiment` and then ``module.run``.
Every module uses only trimag's public API.

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

__all__ = ["BENCHMARKS", "EXPERIMENTS", "get_experiment"]

EXPERIMENTS: dict[str, str] = {
    "wu2013": "trimag.experiments.wu2013",
    "scalar-gn": "trimag.experiments.scalar_gn",
    "vehicle12": "trimag.experiments.vehicle12",
    "zhang2009": "trimag.experiments.zhang2009",
}

BENCHMARKS: dict[str, str] = {
    "accuracy": "trimag.experiments.accuracy",
    "speed": "trimag.experiments.speed",
}


def get_experiment(name: str, *, kind: str = "reproduce") -> ModuleType:
    """Import the module of experiment (or benchmark) ``name``."""
    table = EXPERIMENTS if kind == "reproduce" else BENCHMARKS
    if name not in table:
        raise TrimagInputError(f"unknown {kind} target {name!r}; choose one of {', '.join(table)}")
    try:
        return importlib.import_module(table[name])
    except ModuleNotFoundError as exc:
        if exc.name == table[name]:
            raise TrimagInputError(f"{kind} target {name!r} is not available in this build") from None
        raise
