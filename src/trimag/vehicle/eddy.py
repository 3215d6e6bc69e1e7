"""Eddy-current terms of the vector vehicle model ``interference12`` (docs/vehicle.md, "Eddy-current terms").

    H_m = K H_b + c + E dH_m/dt                                           (E: 3x3, or its diagonal)

A changing field induces eddy currents in the vehicle's conducting skin, whose field is proportional to the rate of
change; a time lag ``tau`` between the magnetometer and the attitude source acts the same way to first order
(``H(t - tau) ~ H(t) - tau dH/dt``, so ``E ~ -tau I``).

``dH_m/dt`` is the measured vector's own time derivative (the only rate of change available when the data are
compensated, so a calibration applies from the data file alone): per contiguous segment, the central difference
``(H[i+1] - H[i-1]) / (t[i+1] - t[i-1])`` inside and the one-sided difference at each segment's ends (MagNav.jl's
``fdm``, as the Tolles–Lawson model's eddy terms, but per second rather than per sample: ``E`` is in seconds).
Segments are cut where a row is missing or the time step exceeds 1.5 sample periods; a sample alone in its
segment has no derivative and gets 0. The times come from a time column, or from the rows' original (0-based) row
numbers in the file and a given rate: a row not selected (``rows``, ``where``) or dropped (a missing value) is then a
gap as a time column would show it. The rate, the time column and the scheme are recorded in the calibration; data at
another rate are refused. On new data a given time column (``time_column``) replaces the recorded one's name, and a
given rate (``rate_hz``, without a time column) is the data's rate, checked against the calibration's.

The terms reuse the regressor machinery (:mod:`trimag.vehicle.regressors`): the three derivative components are derived
regressors ``dBx/dt, dBy/dt, dBz/dt``, each with three coefficients (a column of ``E``); ``terms=3`` frees only
``E``'s diagonal.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import TrimagInputError

__all__ = ["EDDY_NAMES", "check_rate", "eddy_spec", "eddy_values", "time_derivative"]

#: Names of the derived regressors (the components of dH_m/dt, data unit per second).
EDDY_NAMES = ("dBx/dt", "dBy/dt", "dBz/dt")
#: Relative difference of the sample rate beyond which data are refused (as Tolles–Lawson's evaluate).
RATE_TOLERANCE = 0.01
#: A time step larger than this many sample periods starts a new segment.
GAP_PERIODS = 1.5
#: The column holding each row's original row number, added to the chunks of a streamed evaluation without a time
#: column (the derivative's gaps).
ROW_COLUMN = "_trimag_row"
SCHEME = "central difference per segment (H[i+1] - H[i-1]) / (t[i+1] - t[i-1]), one-sided at the segment ends"


def parse_terms(value: Any) -> int:
    """``eddy=9`` (the full 3x3 E) or ``eddy=3`` (its diagonal) -> 9 or 3."""
    text = str(value).strip().lower()
    if text in ("9", "full", "true", "yes"):
        return 9
    if text in ("3", "diag", "diagonal"):
        return 3
    raise TrimagInputError(f"`eddy` takes 9 (the full 3x3 matrix E) or 3 (its diagonal); got {value!r}")


def time_derivative(B: ArrayLike, t: ArrayLike, max_gap_s: float) -> tuple[NDArray[np.float64], int]:
    """``dB/dt`` per sample: central difference inside each segment, one-sided at its ends (module docstring).

    Parameters
    ----------
    B : array_like, shape (N, 3)
        Measured vector, data unit; rows must be finite.
    t : array_like, shape (N,)
        Time of each row, s, increasing.
    max_gap_s : float
        A time step larger than this (or not positive) ends a segment.

    Returns
    -------
    dB : ndarray, shape (N, 3)
        Data unit per second; 0 for a sample alone in its segment.
    n_isolated : int
        Number of such samples.
    """
    X = np.asarray(B, dtype=np.float64)
    T = np.asarray(t, dtype=np.float64)
    n = len(X)
    out = np.zeros_like(X)
    if n < 2:
        return out, n
    dt = np.diff(T)
    joined = (dt > 0) & (dt <= max_gap_s)  # (N-1,): rows i and i+1 are in the same segment
    has_prev = np.concatenate([[False], joined])
    has_next = np.concatenate([joined, [False]])
    step = np.zeros_like(X[:-1])
    step[joined] = (X[1:] - X[:-1])[joined] / dt[joined, None]
    both = has_prev & has_next
    idx = np.flatnonzero(both)
    out[idx] = (X[idx + 1] - X[idx - 1]) / (T[idx + 1] - T[idx - 1])[:, None]
    first = has_next & ~has_prev
    out[first] = step[np.flatnonzero(first)]
    last = has_prev & ~has_next
    out[last] = step[np.flatnonzero(last) - 1]
    return out, int(np.sum(~has_prev & ~has_next))


def sample_times(
    n: int, *, time_s: ArrayLike | None = None, rate_hz: float | None = None, rows: ArrayLike | None = None
) -> tuple[NDArray[np.float64], float]:
    """Times (N,) s and the sample rate (Hz): from a time column (rate: its median step; ``rate_hz`` is then not
    used) or from the row numbers ``rows`` (default 0..N-1) at ``rate_hz``."""
    if time_s is not None:
        t = np.asarray(time_s, dtype=np.float64)
        if t.shape != (n,) or not np.isfinite(t).all():
            raise TrimagInputError("the time column of the eddy-current terms must have a finite value in every row")
        dt = np.diff(t)
        if n < 2 or not np.any(dt > 0):
            raise TrimagInputError("the time column of the eddy-current terms does not increase")
        rate = 1.0 / float(np.median(dt[dt > 0]))
        return t, rate
    if rate_hz is None or not float(rate_hz) > 0:
        raise TrimagInputError(
            "the eddy-current terms need the sample rate: give a time column (`time_column`) or a rate (`rate_hz`)"
        )
    r = np.arange(n, dtype=np.float64) if rows is None else np.asarray(rows, dtype=np.float64)
    return r / float(rate_hz), float(rate_hz)


def eddy_values(
    B: ArrayLike, *, time_s: ArrayLike | None = None, rate_hz: float | None = None, rows: ArrayLike | None = None
) -> tuple[dict[str, NDArray[np.float64]], float, int]:
    """The derived regressors ``{dBx/dt, dBy/dt, dBz/dt}`` (N,) each, the rate (Hz) and the isolated samples."""
    X = np.asarray(B, dtype=np.float64)
    t, rate = sample_times(len(X), time_s=time_s, rate_hz=rate_hz, rows=rows)
    dB, isolated = time_derivative(X, t, GAP_PERIODS / rate)
    return {name: dB[:, j] for j, name in enumerate(EDDY_NAMES)}, rate, isolated


def eddy_spec(terms: int, rate_hz: float, time_column: str | None) -> dict[str, Any]:
    """The ``regressors["eddy"]`` entry of a calibration: what :func:`eddy_values` needs to recompute the terms."""
    return {"terms": int(terms), "names": list(EDDY_NAMES), "rate_hz": float(rate_hz), "time_column": time_column,
            "scheme": SCHEME, "max_gap_periods": GAP_PERIODS, "unit": "s (data unit per data unit per second)",
            "model": "H_m = K H_b + c + E dH_m/dt; column j of E is the coefficient of dB{x,y,z}/dt"}


def free_mask(terms: int) -> dict[str, list[bool]]:
    """Which coefficients of each derived regressor are fitted: all (9) or the diagonal of ``E`` (3)."""
    return {name: [terms == 9 or a == j for a in range(3)] for j, name in enumerate(EDDY_NAMES)}


def check_rate(spec: Mapping[str, Any], rate_hz: float) -> None:
    """Refuse data sampled at another rate than the calibration's eddy terms were fitted at."""
    fitted = float(spec["rate_hz"])
    if abs(rate_hz - fitted) > RATE_TOLERANCE * fitted:
        raise TrimagInputError(
            f"the data are sampled at {rate_hz:g} Hz but the eddy-current terms were fitted at {fitted:g} Hz: the "
            "finite-difference derivative depends on the rate; resample the data or refit"
        )


def values_for(
    spec: Mapping[str, Any], B: ArrayLike, *, time_s: ArrayLike | None = None, rate_hz: float | None = None,
    rows: ArrayLike | None = None,
) -> dict[str, NDArray[np.float64]]:
    """The derived regressors of a calibration's eddy terms (``spec``, :func:`eddy_spec`) on new data, checking the
    rate: from ``time_s`` when given, else ``rate_hz`` (default: the calibration's)."""
    values, rate, _ = eddy_values(B, time_s=time_s, rate_hz=rate_hz or float(spec["rate_hz"]), rows=rows)
    check_rate(spec, rate)
    return values


def time_source(spec: Mapping[str, Any], time_column: str | None, rate_hz: float | None) -> str | None:
    """The time column of the derivative on new data: ``time_column`` when given, none when only ``rate_hz`` is
    given (the rows' numbers at that rate), else the calibration's (``spec``)."""
    if time_column:
        return time_column
    if rate_hz:
        return None
    column = spec.get("time_column")
    return None if column is None else str(column)


def row_numbers(table: Any) -> NDArray[np.float64] | None:
    """The original 0-based row numbers of a table's rows (its integer index, :class:`trimag.io.Samples`), None when
    its index is not one."""
    index = np.asarray(table.index)
    return index.astype(np.float64) if index.dtype.kind in "iu" else None


def table_times(table: Any, column: str, path: Any) -> NDArray[np.float64]:
    """The time column ``column`` (s) of a pandas table; one line naming the file and its columns when absent."""
    import pandas as pd

    if column not in table.columns:
        raise TrimagInputError(
            f"{path}: no time column {column!r} (the eddy-current terms' derivative needs it); the columns are "
            f"{', '.join(map(str, table.columns))}"
        )
    return np.asarray(pd.to_numeric(table[column], errors="coerce"), dtype=np.float64)


def values_from_table(
    spec: Mapping[str, Any], table: Any, B: ArrayLike, path: Any, *, time_column: str | None = None,
    rate_hz: float | None = None,
) -> dict[str, NDArray[np.float64]]:
    """The eddy regressors of a calibration on the rows of ``table`` (aligned with ``B``): the derivative from
    ``time_column`` (default: the calibration's, which the data must then have) or from ``rate_hz`` (default: the
    calibration's rate) at the rows' original numbers (the table's index: a jump is a gap), the rate checked against
    the calibration's (:func:`time_source`)."""
    column = time_source(spec, time_column, rate_hz)
    if column is not None:
        return values_for(spec, B, time_s=table_times(table, column, path))
    return values_for(spec, B, rate_hz=rate_hz, rows=row_numbers(table))


# ------------------------------------------------------------------ the application layer's uses (fit, apply, evaluate)
def fit_values(
    samples: Any, terms: int, time_column: str | None, rate_hz: float | None, path: Any
) -> tuple[dict[str, NDArray[np.float64]], dict[str, Any], list[str]]:
    """The derived regressors of a fit on ``samples`` (:class:`trimag.io.Samples`, its kept rows), the calibration's
    record of them (:func:`eddy_spec`) and the messages for the user."""
    t = None if time_column is None else table_times(samples.table, time_column, path)
    rows = None if time_column is not None else row_numbers(samples.table)
    values, rate, isolated = eddy_values(samples.field, time_s=t, rate_hz=rate_hz, rows=rows)
    messages = [f"eddy-current terms ({terms}): dB/dt by central differences at {rate:g} Hz "
                f"({'from ' + time_column if time_column else 'given rate'})"]
    n_gaps = 0 if rows is None else int(np.sum(np.diff(rows) > 1))
    if n_gaps:
        messages.append(f"{n_gaps} gaps in the row numbers (rows not selected or dropped) cut the derivative's "
                        "segments")
    if isolated:
        messages.append(f"{isolated} samples alone in their segment have no derivative (eddy term 0)")
    return values, eddy_spec(terms, rate, time_column), messages


def streamed_calibrate(
    cal: Any, spec: Mapping[str, Any], data_path: Any, *, fmt: str | None, columns: str | None, var: str | None,
    chunk_rows: int, sensor: Any = None,
) -> tuple[Any, tuple[str, ...]]:
    """The streamed correction (:func:`trimag.io.apply_file`) of a calibration with eddy-current terms:
    ``(calibrate, the columns it reads)``.

    A first pass reads x, y, z (and the time column and the logged regressors) and takes the derivative over the
    rows that will be corrected (finite in all of them; without a time column at their row numbers, so a row left
    uncorrected is a gap), so segments continue across chunks; the second pass
    (``apply_file``) hands each chunk's corrected rows in order, and a cursor picks their derivatives.
    Memory: 4-5 doubles per row.
    """
    from ..io.stream import chunk_columns, open_chunks

    logged = tuple(n for n in cal.regressors["names"] if n not in EDDY_NAMES)
    tcol = spec.get("time_column")
    read = logged + ((str(tcol),) if tcol else ())
    _, chunks = open_chunks(data_path, fmt=fmt, columns=columns, var=var, chunk_rows=chunk_rows, sensor=sensor)
    xyz_parts, t_parts = [], []
    for chunk in chunks:
        u = chunk_columns(chunk, read, data_path) if read else np.empty((len(chunk), 0))
        ok = np.isfinite(chunk.xyz).all(axis=1) & np.isfinite(u).all(axis=1)
        xyz_parts.append(chunk.xyz[ok])
        t_parts.append(u[ok, -1] if tcol else (chunk.start + np.flatnonzero(ok)).astype(np.float64))
    xyz_all = np.concatenate(xyz_parts) if xyz_parts else np.empty((0, 3))
    t_all = np.concatenate(t_parts) if t_parts else np.empty(0)
    derived = values_for(spec, xyz_all, time_s=t_all if tcol else None, rows=None if tcol else t_all)
    dB = np.column_stack([derived[n] for n in EDDY_NAMES])
    cursor = [0]

    def calibrate(xyz: NDArray[np.float64], *u: NDArray[np.float64]) -> NDArray[np.float64]:
        start, stop = cursor[0], cursor[0] + len(xyz)
        cursor[0] = stop
        if not np.array_equal(xyz, xyz_all[start:stop]):
            raise TrimagInputError(f"{data_path}: the file changed while it was being corrected")
        values = dict(zip(EDDY_NAMES, dB[start:stop].T, strict=True))
        if logged:
            values.update(zip(logged, u[0][:, : len(logged)].T, strict=True))
        return np.asarray(cal.apply(xyz, regressors=values), dtype=np.float64)

    return calibrate, read


def evaluate_columns(
    cal: Any, spec: Mapping[str, Any], time_column: str | None = None, rate_hz: float | None = None
) -> tuple[str, ...]:
    """The columns a streamed evaluation reads for a calibration with eddy terms: its logged regressors, then the
    time column (:func:`time_source`) or, without one, :data:`ROW_COLUMN` (:func:`with_row_numbers`)."""
    logged = tuple(n for n in cal.regressors["names"] if n not in EDDY_NAMES)
    return (*logged, time_source(spec, time_column, rate_hz) or ROW_COLUMN)


def with_row_numbers(chunk: Any) -> Any:
    """``chunk`` (:class:`trimag.io.stream.Chunk`) with the column :data:`ROW_COLUMN`: each row's number in the file."""
    from ..io.stream import Chunk

    rows = chunk.start + np.arange(len(chunk), dtype=np.float64)
    if chunk.has_arrow:
        import pyarrow as pa

        return Chunk(None, chunk.xyz, chunk.start, arrow=chunk.arrow.append_column(ROW_COLUMN, pa.array(rows)))
    return Chunk(chunk.table.assign(**{ROW_COLUMN: rows}), chunk.xyz, chunk.start)


def corrected_magnitudes(
    cal: Any, spec: Mapping[str, Any], kept: list[tuple[Any, ...]], time_column: str | None = None,
    rate_hz: float | None = None,
) -> tuple[NDArray[np.float64], Any]:
    """Corrected magnitudes of the rows ``kept`` (per chunk: x, y, z; the :func:`evaluate_columns` values, the last
    one the time or the row number; the reference) of a calibration with eddy-current terms, and their
    references."""
    xyz = np.concatenate([k[0] for k in kept])
    U = np.concatenate([k[1] for k in kept])
    logged = [n for n in cal.regressors["names"] if n not in EDDY_NAMES]
    if time_source(spec, time_column, rate_hz) is not None:
        values = values_for(spec, xyz, time_s=U[:, -1])
    else:
        values = values_for(spec, xyz, rate_hz=rate_hz, rows=U[:, -1])
    if logged:
        values.update(zip(logged, U[:, : len(logged)].T, strict=True))
    refs = [k[2] for k in kept]
    ref: Any = refs[0] if refs[0] is None or np.ndim(refs[0]) == 0 else np.concatenate(refs)
    return np.linalg.norm(cal.apply(xyz, regressors=values), axis=1), ref
