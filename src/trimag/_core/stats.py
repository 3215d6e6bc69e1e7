"""The one streaming-statistics accumulator (not public API).

Every one-pass statistic over chunks of samples (the before/after tables of ``norm_stats``, streaming ``apply``
and ``evaluate``) accumulates :class:`StreamingMoments`: Chan et al.'s pairwise update of count, mean and sum of
squared deviations, so there is no cancellation when the mean is large and the spread tiny (a 50 000 nT field
varying by 0.1 nT), unlike running sums of squares.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["StreamingMoments"]


class StreamingMoments:
    """Count, mean, sum of squared deviations, min and max of a stream of blocks."""

    def __init__(self) -> None:
        self.n, self.mean, self.m2 = 0, 0.0, 0.0
        self.lo, self.hi = np.inf, -np.inf

    def add(self, x: NDArray[np.float64], scratch: NDArray[np.float64] | None = None) -> None:
        """Add the values ``x`` (m,); ``scratch`` (at least m,) avoids a temporary."""
        m = len(x)
        if m == 0:
            return
        mean = float(np.sum(x)) / m
        dev = np.subtract(x, mean, out=None if scratch is None else scratch[:m])
        m2 = float(np.dot(dev, dev))
        total = self.n + m
        delta = mean - self.mean
        self.mean += delta * m / total
        self.m2 += m2 + delta * delta * self.n * m / total
        self.n = total
        self.lo, self.hi = min(self.lo, float(x.min())), max(self.hi, float(x.max()))

    @property
    def variance(self) -> float:
        """Population variance (0 when empty)."""
        return max(self.m2, 0.0) / self.n if self.n else 0.0

    def rms_about(self, value: float) -> float:
        """Root mean square of ``x - value`` over everything added."""
        bias = self.mean - value
        return float(np.sqrt(self.variance + bias * bias))
