"""A unit that makes the data's field plausible is named (issue 38, item 6): a uT log declared nT against IGRF was
refused with "the reference or the data's unit is wrong"; the fitted sphere's radius matches IGRF's field in uT, so
the refusal says "the data look like uT"."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from trimag.cli import main
from trimag.fields.reference import igrf

from _helpers import BOAT_SITE


def _sphere_log(path: Path, radius: float, offset: tuple[float, float, float], seed: int = 3) -> Path:
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(600, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    raw = radius * u @ np.diag([1.04, 0.97, 1.0]) + offset + rng.normal(0.0, 0.01 * radius, (600, 3))
    np.savetxt(path, raw, delimiter=",", header="x,y,z", comments="", fmt="%.5f")
    return path


@pytest.mark.parametrize(("declared", "real", "scale"), [("nT", "uT", 1e-3), ("nT", "G", 1e-5), ("mG", "uT", 1e-3)])
def test_a_wrongly_declared_unit_is_named(declared: str, real: str, scale: float, tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    F_nT = float(igrf(*(float(v) for v in BOAT_SITE.split(",")[:3]), BOAT_SITE.split(",")[3]).total_nT)
    path = _sphere_log(tmp_path / "log.csv", F_nT * scale, (12000 * scale, -5000 * scale, 20000 * scale))
    assert main(["fit", str(path), "--units", declared, "--igrf", BOAT_SITE, "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"the data look like {real}" in err[0], err
    assert main(["fit", str(path), "--units", real, "--igrf", BOAT_SITE, "-q"]) == 0
