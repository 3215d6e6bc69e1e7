"""Band-pass filtering of time series in contiguous segments (Tolles–Lawson fits and their evaluation).

Conventions (docs/method-tolles-lawson.md, "The filter"):

- A *segment* is a run of consecutive samples with every input finite; a NaN/inf row ends a segment, and a
  user-given time range (``--segments``) cuts one. Each segment is filtered on its own, then the segments are
  stacked: a filter never runs across a gap.
- The filter is a zero-phase Butterworth band-pass (``scipy.signal.butter`` in second-order sections, applied
  forwards and backwards by ``sosfiltfilt``): ``poles`` is the order of the low-pass prototype, so the
  band-pass has order ``2 * poles`` (as DSP.jl's ``Bandpass`` + ``Butterworth(poles)`` in MagNav.jl).
- Edges: the segment is extended at both ends by an odd reflection of ``6 * n_sections`` samples (DSP.jl's
  ``filtfilt`` pad length for second-order sections) with scipy's steady-state initial conditions; then
  ``trim`` samples are dropped at each end of every filtered segment (MagNav default 20) where the transient
  of the filter remains.
- A segment too short to filter is skipped and counted: it needs ``3 * pad + 2 * trim + 1`` samples for the edges,
  and one period of the band's low edge (``rate / low`` samples): a shorter one holds no cycle of the band, only the
  filter's transient.
- The rate must be at most ``1e6`` times the band's low edge (with the default 0.1 Hz: 200 kHz, far above any
  survey's): beyond it the Butterworth sections lose their precision (at 1e7 the pass-band gain is 0.3 % off, at
  1e8 the filter's initial conditions are singular).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import TrimagInputError

__all__ = ["BandPass", "finite_runs", "split_segments"]

#: the band's low edge must be at least this fraction of the Nyquist frequency (see the module's conventions)
_MIN_RELATIVE_LOW = 1e-6


@dataclass(frozen=True)
class BandPass:
    """A zero-phase Butterworth band-pass (see the module's conventions).

    Attributes
    ----------
    low_hz, high_hz : float
        Pass band edges, Hz (MagNav default 0.1 and 0.9).
    rate_hz : float
        Sample rate, Hz.
    poles : int
        Order of the low-pass prototype (default 4: an order-8 band-pass).
    trim : int
        Samples dropped at each end of every filtered segment.
    """

    low_hz: float = 0.1
    high_hz: float = 0.9
    rate_hz: float = 10.0
    poles: int = 4
    trim: int = 20

    def __post_init__(self) -> None:
        nyquist = self.rate_hz / 2.0
        if not (self.rate_hz > 0 and np.isfinite(self.rate_hz)):
            raise TrimagInputError(f"the sample rate must be a positive number of Hz; got {self.rate_hz}")
        if not 0 < self.low_hz < self.high_hz < nyquist:
            raise TrimagInputError(
                f"the pass band must satisfy 0 < low < high < rate/2 = {nyquist:g} Hz; "
                f"got {self.low_hz:g}-{self.high_hz:g} Hz"
            )
        if self.low_hz < _MIN_RELATIVE_LOW * nyquist:
            raise TrimagInputError(
                f"a sample rate of {self.rate_hz:g} Hz is {self.rate_hz / self.low_hz:.3g}x the pass band's low edge "
                f"{self.low_hz:g} Hz: no filter can be computed that narrow (at most {2 / _MIN_RELATIVE_LOW:.0e}x); "
                "check `rate_hz` (or the time column's unit: seconds)"
            )
        if self.poles < 1 or self.trim < 0:
            raise TrimagInputError("the filter needs poles >= 1 and trim >= 0")

    def sos(self) -> NDArray[np.float64]:
        """Second-order sections of the filter."""
        from scipy import signal

        return np.asarray(
            signal.butter(self.poles, [self.low_hz, self.high_hz], btype="bandpass", fs=self.rate_hz, output="sos")
        )

    @property
    def pad(self) -> int:
        """Samples of odd reflection added at each end before filtering (6 per second-order section)."""
        return 6 * self.poles

    @property
    def min_length(self) -> int:
        """Shortest segment that is filtered (shorter ones are skipped): the filter's edges, and at least one period
        of the band's low edge."""
        return max(3 * self.pad + 2 * self.trim + 1, math.ceil(self.rate_hz / self.low_hz))

    def apply(self, x: ArrayLike) -> NDArray[np.float64]:
        """Filter one contiguous segment along axis 0 and drop ``trim`` samples at each end.

        Parameters
        ----------
        x : array_like, shape (n,) or (n, k)

        Returns
        -------
        ndarray, shape (n - 2 * trim,) or (n - 2 * trim, k)
        """
        from scipy import signal

        a = np.asarray(x, dtype=np.float64)
        if len(a) < self.min_length:
            raise TrimagInputError(
                f"a segment of {len(a)} samples is too short for this filter (needs {self.min_length})"
            )
        y = signal.sosfiltfilt(self.sos(), a, axis=0, padtype="odd", padlen=self.pad)
        return y[self.trim : len(y) - self.trim] if self.trim else y

    def as_dict(self) -> dict[str, float | int | str]:
        """What a compensation file records of the filter."""
        return {
            "type": "butterworth band-pass, zero phase (sosfiltfilt)",
            "low_hz": self.low_hz,
            "high_hz": self.high_hz,
            "rate_hz": self.rate_hz,
            "poles": self.poles,
            "order": 2 * self.poles,
            "pad": self.pad,
            "padtype": "odd",
            "trim": self.trim,
        }


def finite_runs(ok: NDArray[np.bool_]) -> list[tuple[int, int]]:
    """``[start, stop)`` index ranges of the runs of True in ``ok`` (vectorised)."""
    flag = np.concatenate([[False], np.asarray(ok, dtype=bool), [False]])
    edges = np.flatnonzero(np.diff(flag.astype(np.int8)))
    return [(int(a), int(b)) for a, b in zip(edges[0::2], edges[1::2], strict=True)]


def split_segments(
    ok: NDArray[np.bool_],
    time_s: ArrayLike | None = None,
    ranges: Sequence[tuple[float, float]] | None = None,
    *,
    max_gap_s: float | None = None,
) -> list[tuple[int, int]]:
    """Contiguous segments ``[start, stop)`` of rows: runs of finite rows, cut at time gaps and to ``ranges``.

    Parameters
    ----------
    ok : ndarray of bool, shape (N,)
        Rows whose inputs are all finite.
    time_s : array_like, shape (N,), optional
        Time of each row, s (needed for ``ranges`` and gap detection).
    ranges : sequence of (t0, t1), optional
        Keep only rows with ``t0 <= t <= t1``, each range its own segment.
    max_gap_s : float, optional
        A step in time larger than this also ends a segment (e.g. 1.5 sample periods).
    """
    keep = np.asarray(ok, dtype=bool).copy()
    cut = np.zeros(len(keep), dtype=bool)  # True where a new segment must start
    t = None if time_s is None else np.asarray(time_s, dtype=np.float64)
    if t is not None and max_gap_s is not None and len(t) > 1:
        cut[1:] |= ~(np.diff(t) <= max_gap_s)
    if ranges:
        if t is None:
            raise TrimagInputError("segments given as times need a time column (time_column) or a rate")
        label = np.full(len(keep), -1)
        for k, (t0, t1) in enumerate(ranges):
            label[(t >= t0) & (t <= t1)] = k
        keep &= label >= 0
        cut[1:] |= label[1:] != label[:-1]
    out: list[tuple[int, int]] = []
    for start, stop in finite_runs(keep):
        inner = np.flatnonzero(cut[start + 1 : stop]) + start + 1
        bounds = [start, *inner.tolist(), stop]
        out += list(itertools.pairwise(bounds))
    return out
