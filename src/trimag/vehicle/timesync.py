"""Two streams, one clock: attitudes from a second file, interpolated to the magnetometer's time stamps, and the
constant lag between the two streams (issue 20, item 6; docs/vehicle.md).

Convention: the **lag** ``L`` (s) is the attitude stream's clock minus the magnetometer's. The magnetometer sample
stamped ``t`` is paired with the attitude stamped ``t + L``, interpolated on the unit-quaternion great circle
between its neighbours (:class:`scipy.spatial.transform.Slerp`). A magnetometer sample whose ``t + L`` lies outside
the attitude stream's span is dropped (and counted).

The lag is estimated by maximising the quality of paper C's vector fit (``interference12``: ``H_m = K H_b + c``,
a linear least squares per sensor axis): the residual sum of squares ``SS(L)`` over the samples inside the span for
every lag of the search, on a grid over ``[-max_lag, max_lag]`` (step: half the attitude stream's median interval,
at most 401 points; on a regular subsample of at least 8192 samples), then refined on every sample by a bounded
scalar minimisation around the best grid point. Its standard
deviation is the profile-likelihood one, ``sigma_L^2 = 2 sigma^2 / SS''(L)`` with ``sigma^2 = SS / (3 N - 12)`` and
``SS''`` by central differences, times the residuals' integrated autocorrelation time
(:func:`trimag.quality.honesty.correlation_time`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation, Slerp

from ..errors import IdentifiabilityError, TrimagInputError
from ..fields.attitude import attitude_from_table, body_field
from ..quality.honesty import correlation_time

__all__ = ["AttitudeStream", "estimate_lag", "interpolate_attitude", "read_attitude_stream", "time_values"]

#: At most this many lags on the search grid.
MAX_GRID = 401
#: The grid search uses every k-th sample, at least this many (the refinement and the sigma use all of them).
GRID_SAMPLES = 8192


@dataclass(frozen=True)
class AttitudeStream:
    """Attitudes with their own time stamps: ``times`` (M,) in s, strictly increasing; ``rotation`` (M rotations,
    body -> NED); ``source`` (the file); ``n_dropped`` rows without a finite time or attitude."""

    times: NDArray[np.float64]
    rotation: Rotation
    source: str = ""
    n_dropped: int = 0

    @property
    def span(self) -> tuple[float, float]:
        """First and last time stamp, s."""
        return float(self.times[0]), float(self.times[-1])

    @property
    def median_interval(self) -> float:
        """Median time between attitude samples, s."""
        return float(np.median(np.diff(self.times)))


def time_values(table: pd.DataFrame, column: str, what: str) -> NDArray[np.float64]:
    """The numeric values (N,) of a time column (s); one line naming the columns when it is not there."""
    if column not in table.columns:
        raise TrimagInputError(
            f"{what}: no time column {column!r}; the columns are {', '.join(map(str, table.columns))}"
        )
    return np.asarray(pd.to_numeric(table[column], errors="coerce"), dtype=np.float64)


def read_attitude_stream(
    path: str | Path,
    *,
    time_column: str,
    attitude_columns: str | None = None,
    quaternion_columns: str | None = None,
    scalar_first: bool = True,
    frame: str = "ned",
    fmt: str | None = None,
) -> AttitudeStream:
    """Read attitudes with their time stamps from a file of their own.

    Parameters
    ----------
    path : str or Path
        A table (CSV, Parquet, ...; :func:`trimag.io.tables.read_table`).
    time_column : str
        Time stamps in s, on the same clock as the magnetometer's up to a constant lag.
    attitude_columns, quaternion_columns, scalar_first, frame
        As in :func:`trimag.fields.attitude.attitude_from_table` (exactly one column set).
    fmt : str, optional
        File format (default: from the extension).

    Returns
    -------
    AttitudeStream
        Sorted by time; rows with a missing time or attitude dropped and counted; repeated time stamps keep the
        first row.

    Raises
    ------
    TrimagInputError
        No such column, fewer than two valid rows.
    """
    from ..io.tables import read_table

    table = read_table(Path(path), fmt=fmt)
    t = time_values(table, time_column, f"{path} (`attitude_file`)")
    names = [c.strip() for c in (attitude_columns or quaternion_columns or "").split(",") if c.strip()]
    cells = np.column_stack([np.asarray(pd.to_numeric(table[c], errors="coerce"), dtype=np.float64)
                             for c in names if c in table.columns] or [np.zeros(len(table))])
    ok = np.isfinite(t) & np.isfinite(cells).all(axis=1)
    table, t = table[ok].reset_index(drop=True), t[ok]
    order = np.argsort(t, kind="stable")
    keep = order[np.concatenate([[True], np.diff(t[order]) > 0])]
    if len(keep) < 2:
        raise TrimagInputError(f"{path}: fewer than two rows with a finite time and attitude (`attitude_file`)")
    rot = attitude_from_table(table.iloc[keep], euler_columns=attitude_columns, quaternion_columns=quaternion_columns,
                              scalar_first=scalar_first, frame=frame)
    return AttitudeStream(t[keep], rot, str(path), int((~ok).sum()) + int(ok.sum() - len(keep)))


def interpolate_attitude(
    stream: AttitudeStream, t: ArrayLike, lag: float = 0.0
) -> tuple[Rotation | None, NDArray[np.bool_]]:
    """The attitudes at the magnetometer's time stamps ``t`` (N,) (s), paired with the stream at ``t + lag``.

    Returns
    -------
    rotation : Rotation or None
        One per sample inside the stream's span (None when there is none).
    inside : ndarray of bool, shape (N,)
        Which samples are inside the span (the others have no attitude and are to be dropped).
    """
    tq = np.asarray(t, dtype=np.float64) + float(lag)
    t0, t1 = stream.span
    inside = np.isfinite(tq) & (tq >= t0) & (tq <= t1)
    if not inside.any():
        return None, inside
    return Slerp(stream.times, stream.rotation)(tq[inside]), inside


def _vector_ss(B: NDArray[np.float64], H_b: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
    """Residual sum of squares of ``B ~ K H_b + c`` (three axes, design ``[H_b, 1]``) and the residuals (N, 3)."""
    A = np.column_stack([H_b, np.ones(len(H_b))])
    X, *_ = np.linalg.lstsq(A, B, rcond=None)
    r = B - A @ X
    return float(np.sum(r**2)), r


def estimate_lag(
    B: ArrayLike,
    t: ArrayLike,
    stream: AttitudeStream,
    background_ned: ArrayLike,
    *,
    max_lag: float = 1.0,
) -> dict[str, Any]:
    """The constant lag between the attitude stream and the magnetometer (module docstring).

    Parameters
    ----------
    B : array_like, shape (N, 3)
        Raw magnetometer samples (any unit).
    t : array_like, shape (N,)
        Their time stamps, s.
    stream : AttitudeStream
        The attitudes with their own time stamps.
    background_ned : array_like, shape (3,)
        The background field (N, E, D), same unit as ``B``.
    max_lag : float
        The search covers lags in ``[-max_lag, max_lag]`` s; only samples inside the stream's span for every lag of
        the search are used.

    Returns
    -------
    dict
        ``lag_s``, ``lag_std_s``, ``rms_at_lag`` and ``rms_at_zero`` (vector RMS of the interference12 fit, data
        unit), ``n_used``, ``grid_step_s``, ``max_lag_s``, ``correlation_time``, ``method``.

    Raises
    ------
    TrimagInputError
        A bad ``max_lag``, or too few samples inside the span.
    IdentifiabilityError
        The fit's quality does not depend on the lag (the attitude does not change), or the best lag is at the
        edge of the search.
    """
    X = np.asarray(B, dtype=np.float64)
    tm = np.asarray(t, dtype=np.float64)
    H_n = np.asarray(background_ned, dtype=np.float64)
    if not (np.isfinite(max_lag) and max_lag > 0):
        raise TrimagInputError(f"`option max_lag` must be a positive number of seconds; got {max_lag}")
    t0, t1 = stream.span
    common = np.isfinite(tm) & (tm - max_lag >= t0) & (tm + max_lag <= t1)
    if common.sum() < 20:
        raise TrimagInputError(
            f"only {int(common.sum())} magnetometer samples lie inside the attitude stream's span ({t0:.6g}..{t1:.6g}"
            f" s) for every lag within +-{max_lag:g} s; a lag search needs at least 20 (a smaller `option max_lag`?)"
        )
    X, tm = X[common], tm[common]
    slerp = Slerp(stream.times, stream.rotation)

    def at(times: NDArray[np.float64]) -> Rotation:  # the grid's edge may pass the span by a rounding error
        return slerp(np.clip(times, t0, t1))

    def ss(lag: float, every: int = 1) -> float:
        return _vector_ss(X[::every], body_field(at(tm[::every] + lag), H_n))[0]

    step = max(min(0.5 * stream.median_interval, max_lag / 20), 2 * max_lag / (MAX_GRID - 1))
    lag = _minimise_on_grid(ss, max_lag, step, every=max(len(X) // GRID_SAMPLES, 1))
    ss_lag, resid = _vector_ss(X, body_field(at(tm + lag), H_n))
    n = len(X)
    sigma2 = ss_lag / max(3 * n - 12, 1)
    h = step
    curvature = (ss(lag + h) - 2 * ss_lag + ss(lag - h)) / h**2
    tau = max(max(correlation_time(resid[:, a]) for a in range(3)), 1.0)
    std = float(np.sqrt(2 * sigma2 / curvature * tau)) if curvature > 0 else float("inf")
    return {
        "lag_s": lag,
        "lag_std_s": std,
        "rms_at_lag": float(np.sqrt(ss_lag / n)),
        "rms_at_zero": float(np.sqrt(ss(0.0) / n)),
        "n_used": n,
        "grid_step_s": float(step),
        "max_lag_s": float(max_lag),
        "correlation_time": tau,
        "method": "minimum of the interference12 residual sum of squares over a lag grid, refined; sigma from its "
                  "curvature (profile likelihood), times the residuals' autocorrelation time",
    }


def _minimise_on_grid(ss: Callable[..., float], max_lag: float, step: float, *, every: int) -> float:
    """The lag (s) minimising ``ss(lag)``: a grid over ``[-max_lag, max_lag]`` with ``step`` on every ``every``-th
    sample, then a bounded scalar minimisation between the grid points around the best one, on every sample.
    Refuses a flat ``ss`` (the attitude does not change) and a best lag at the edge of the search."""
    from scipy.optimize import minimize_scalar

    grid = np.arange(-max_lag, max_lag + 0.5 * step, step)
    values = np.array([ss(float(g), every) for g in grid])
    k = int(np.argmin(values))
    if values.max() - values.min() <= 1e-12 * max(values.max(), 1e-300):
        raise IdentifiabilityError("the vector fit's quality does not depend on the lag (the attitude barely "
                                   "changes): record the vehicle turning to estimate the lag")
    if k in (0, len(grid) - 1):
        raise IdentifiabilityError(
            f"the best lag is at the edge of the search (+-{max_lag:g} s): widen it (`option max_lag`) or check that "
            "the two files share a clock"
        )
    res = minimize_scalar(ss, bounds=(float(grid[k - 1]), float(grid[k + 1])), method="bounded",
                          options={"xatol": 1e-6 * max(step, 1e-9)})
    return float(res.x)
