"""``trimag demo``: the bundled real log fitted, with its calibration and report written."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from .fit import FitResult, fit_file

__all__ = ["DEMO_DATA", "run_demo"]


#: The bundled real log used by ``trimag demo`` (see ``trimag/data/README.md`` for its source and licence).
DEMO_DATA = "qmc5883l_noisy_raw_data.csv"


def run_demo(out_dir: str | Path = ".") -> FitResult:
    """Fit the bundled real log (QMC5883L, raw counts) and write the calibration and report into ``out_dir``."""
    out = Path(out_dir)
    data = resources.files("trimag") / "data" / DEMO_DATA
    with resources.as_file(data) as path:
        return fit_file(
            path,
            units="counts",
            model="ellipsoid",
            out=out / "trimag-demo-calibration.json",
            report=out / "trimag-demo-report.png",
        )

