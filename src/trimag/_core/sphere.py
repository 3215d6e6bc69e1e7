"""Nearly equal-area points on the unit sphere (not public API; :func:`trimag.quality.diagnostics.fibonacci_sphere`)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["fibonacci_sphere"]


def fibonacci_sphere(n: int) -> NDArray[np.float64]:
    """``n`` nearly equal-area cell centres on the unit sphere, shape (n, 3)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (1.0 + 5**0.5) * i
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])
