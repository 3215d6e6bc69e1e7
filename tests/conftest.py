"""Shared fixtures; helper functions live in `_helpers.py`."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from _helpers import simulate_ellipsoid


@pytest.fixture
def ellipsoid_log(tmp_path: Path) -> Path:
    """A CSV log (header bx,by,bz plus a time column) of a simulated sensor, 600 rows."""
    raw = simulate_ellipsoid(600, noise=5.0, seed=1)
    path = tmp_path / "log.csv"
    t = np.arange(len(raw)) * 0.02
    np.savetxt(path, np.column_stack([t, raw]), delimiter=",", header="t,bx,by,bz", comments="", fmt="%.6f")
    return path
