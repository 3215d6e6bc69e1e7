"""Application layer of aircraft (Tolles–Lawson) compensation: typed requests -> read -> fit / apply / evaluate.

``trimag fit DATA --model tolles-lawson ...``, ``trimag apply COMP.json DATA -o OUT`` and
``trimag evaluate COMP.json DATA`` call these functions (docs/method-tolles-lawson.md, "Command line").
Columns are header names, ``STRUCT.FIELD`` paths in MAT files, or 0-based indices.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from .._core.extras import require
from ..aircraft.compensation import ScalarCompensation
from ..aircraft.filtering import BandPass, split_segments
from ..errors import TrimagInputError
from ..estimators.tolles_lawson import fit_tolles_lawson, manoeuvre_content, segment_std
from ..io.atomic import atomic_write_text
from ..io.tables import _numeric, detect_csv_layout, guess_format, read_table

__all__ = [
    "TollesLawsonFitRequest",
    "apply_compensation_file",
    "evaluate_compensation_file",
    "fit_compensation_file",
    "is_compensation_file",
    "parse_segments",
]


def parse_segments(text: str | None) -> list[tuple[float, float]] | None:
    """``"T0:T1,T0:T1"`` (seconds of the time column, or of row / rate) -> list of (t0, t1)."""
    if text is None or not str(text).strip():
        return None
    out = []
    for part in str(text).split(","):
        try:
            a, b = (float(x) for x in part.split(":"))
        except ValueError:
            raise TrimagInputError(f"segments must look like T0:T1[,T0:T1...] (seconds); got {part!r}") from None
        if not b > a:
            raise TrimagInputError(f"segment {part!r}: the end must be after the start")
        out.append((a, b))
    return out


def _column(df: pd.DataFrame, spec: str | int, what: str) -> NDArray[np.float64]:
    """Numeric values of a column named by header, ``STRUCT.FIELD`` or 0-based index."""
    name: Any = spec
    if name not in df.columns:
        text = str(spec).strip()
        if text in df.columns:
            name = text
        elif text.lstrip("-").isdigit() and -df.shape[1] <= int(text) < df.shape[1]:
            name = df.columns[int(text)]
        else:
            shown = ", ".join(map(str, list(df.columns)[:30]))
            raise TrimagInputError(f"no column {spec!r} for the {what}; the columns are {shown}")
    return _numeric(df[name])


@dataclass
class TollesLawsonFitRequest:
    """What ``trimag fit --model tolles-lawson`` asks for (every field typed; see the CLI's help)."""

    data: Path
    vector_columns: Sequence[str]
    scalar_column: str
    time_column: str | None = None
    rate_hz: float | None = None
    segments: list[tuple[float, float]] | None = None
    fmt: str | None = None
    var: str | None = None
    units: str | None = None
    terms: str | None = None
    band_hz: tuple[float, float] = (0.1, 0.9)
    poles: int = 4
    trim: int = 20
    ridge: float | str = 0.0
    Bt_source: str = "vector"
    bootstrap: int = 200
    attitude_columns: Sequence[str] | None = None
    options: dict[str, Any] = field(default_factory=dict)


def _options_into(request: TollesLawsonFitRequest) -> TollesLawsonFitRequest:
    """Apply ``--option KEY=VALUE`` entries (terms, band, ridge, poles, trim, Bt, bootstrap) to the request."""
    known = {"terms", "band", "ridge", "poles", "trim", "bt", "bt_source", "bootstrap"}
    for key, value in request.options.items():
        k = key.lower()
        if k not in known:
            raise TrimagInputError(
                f"unknown tolles-lawson option {key!r}; options are terms, band, ridge, poles, trim, Bt, bootstrap"
            )
        if k == "terms":
            request.terms = ",".join(value) if isinstance(value, list) else str(value)
        elif k == "band":
            parts = value if isinstance(value, list) else str(value).split(",")
            try:
                low, high = (float(x) for x in parts)
            except (TypeError, ValueError):
                raise TrimagInputError(f"band must be LOW,HIGH in Hz; got {value!r}") from None
            request.band_hz = (low, high)
        elif k == "ridge":
            request.ridge = value if isinstance(value, (int, float)) else str(value)
            if isinstance(request.ridge, str) and request.ridge.lower() != "cv":
                try:
                    request.ridge = float(request.ridge)
                except ValueError:
                    raise TrimagInputError(f"ridge must be a number >= 0 or 'cv'; got {value!r}") from None
        elif k in ("poles", "trim", "bootstrap"):
            try:
                setattr(request, k, int(value))
            except (TypeError, ValueError):
                raise TrimagInputError(f"{k} must be an integer; got {value!r}") from None
        else:
            request.Bt_source = str(value).lower()
    return request


def _unit_factor(units: str | None) -> float:
    """Factor to nT of a declared unit (TL coefficients and Bt_scale are in nT)."""
    from ..units import convert, normalise_unit

    unit = normalise_unit(units)
    if unit in ("unknown", "nT"):
        return 1.0
    if unit == "counts":
        raise TrimagInputError("Tolles–Lawson needs calibrated magnetometers in a physical unit (nT, uT, G, mG)")
    return float(convert(1.0, unit, "nT"))


def _time_axis(df: pd.DataFrame, time_column: str | None, rate_hz: float | None) -> tuple[NDArray[np.float64], float]:
    if time_column is not None:
        t = _column(df, time_column, "time")
        dt = np.diff(t[np.isfinite(t)])
        if len(dt) == 0 or not np.all(dt > 0):
            raise TrimagInputError(f"the time column {time_column!r} must increase strictly from row to row")
        rate = float(rate_hz) if rate_hz else 1.0 / float(np.median(dt))
        return t, rate
    if not rate_hz or rate_hz <= 0:
        raise TrimagInputError("Tolles–Lawson needs the sample rate: give a time column or a rate in Hz")
    return np.arange(len(df)) / float(rate_hz), float(rate_hz)


def _read_series(
    path: Path, fmt: str | None, var: str | None, vector_columns: Sequence[str], scalar_column: str, units: str | None
) -> tuple[pd.DataFrame, NDArray[np.float64], NDArray[np.float64]]:
    df = read_table(path, fmt=fmt, var=var)
    if len(vector_columns) != 3:
        raise TrimagInputError(f"give three vector magnetometer columns (x, y, z); got {len(vector_columns)}")
    factor = _unit_factor(units)
    vector = np.column_stack([_column(df, c, "vector magnetometer") for c in vector_columns]) * factor
    scalar = _column(df, scalar_column, "scalar magnetometer") * factor
    _check_same_unit(vector, scalar, vector_columns, scalar_column)
    return df, vector, scalar


def _check_same_unit(vector: NDArray[np.float64], scalar: NDArray[np.float64], vector_columns: Sequence[str],
                     scalar_column: str) -> None:
    """Refuse a scalar and a vector magnetometer in different units: both read the same Earth field, so their
    magnitudes agree to a few percent (the aircraft's field is hundreds of nT); beyond 2x they are not in one unit
    (a scalar in uT beside a vector in nT was fitted, with coefficients 1000x off)."""
    ok = np.isfinite(vector).all(axis=1) & np.isfinite(scalar)
    if not ok.any():
        return
    m_scalar = float(np.median(np.abs(scalar[ok])))
    m_vector = float(np.median(np.linalg.norm(vector[ok], axis=1)))
    if m_vector > 0 and m_scalar > 0 and 0.5 <= m_scalar / m_vector <= 2.0:
        return
    raise TrimagInputError(
        f"the scalar magnetometer {scalar_column!r} reads {m_scalar:.6g} (median) where the vector magnetometer "
        f"{', '.join(map(str, vector_columns))} reads |B| = {m_vector:.6g}: they measure the same field, so they are "
        "not in the same unit; convert one of the columns (both in nT, or both in the unit given by `units`)"
    )


def fit_compensation_file(request: TollesLawsonFitRequest) -> tuple[ScalarCompensation, list[str]]:
    """Read the data, fit Tolles–Lawson coefficients; returns the compensation and messages for the user."""
    request = _options_into(request)
    df, vector, scalar = _read_series(request.data, request.fmt, request.var, request.vector_columns,
                                      request.scalar_column, request.units)
    t, rate = _time_axis(df, request.time_column, request.rate_hz)
    ok = np.isfinite(vector).all(axis=1) & np.isfinite(scalar)
    segments = split_segments(ok, t, request.segments, max_gap_s=1.5 / rate)
    attitude = None
    if request.attitude_columns:
        attitude = np.column_stack([_column(df, c, "attitude") for c in request.attitude_columns])
    comp = fit_tolles_lawson(
        vector, scalar, rate_hz=rate, segments=segments, terms=request.terms, band_hz=request.band_hz,
        poles=request.poles, trim=request.trim, ridge=request.ridge, Bt_source=request.Bt_source,
        bootstrap=request.bootstrap, attitude_deg=attitude,
        sensors={"source": str(request.data), "vector_columns": [str(c) for c in request.vector_columns],
                 "scalar_column": str(request.scalar_column), "time_column": request.time_column,
                 "units": "nT", "input_units": request.units or "nT"},
    )
    messages = [
        f"vector magnetometer {', '.join(map(str, request.vector_columns))}; scalar {request.scalar_column}; "
        f"{rate:g} Hz ({'from ' + request.time_column if request.time_column else 'given'})",
    ]
    n_bad = int((~ok).sum())
    if n_bad:
        messages.append(f"{n_bad} of {len(ok)} rows have a missing or non-finite value: they split the segments")
    if comp.stats["n_skipped_segments"]:
        messages.append(
            f"skipped {comp.stats['n_skipped_segments']} segment(s) ({comp.stats['n_skipped_rows']} rows) too short "
            f"for the band-pass filter (< {comp.bandpass.min_length} samples)"
        )
    messages += [f"warning: {w}" for w in comp.diagnostics.get("warnings", [])]
    return comp, messages


def not_fitted_by(command: str) -> str:
    """The one line that says ``trimag command`` (live, batch) does not fit a Tolles-Lawson compensation, and
    which commands do (issue 39: they said "unknown model" or refused its flags one by one)."""
    return (f"trimag {command} does not fit a Tolles-Lawson compensation (an aircraft's scalar magnetometer, fitted "
            "on a whole calibration flight): fit each flight with `trimag fit FILE --model tolles-lawson --columns "
            "VX,VY,VZ --scalar-column S`, then run `trimag apply` or `trimag evaluate` with it")


def is_compensation_file(path: str | Path) -> bool:
    """True when ``path`` is a trimag compensation (Tolles–Lawson) JSON file."""
    p = Path(path)
    if not p.is_file():
        return False
    try:
        with p.open("r", encoding="utf-8") as fh:
            head = fh.read(4096)
    except (OSError, UnicodeDecodeError):
        return False
    return '"trimag-compensation"' in head


@dataclass
class _Compensated:
    """A data file compensated: its table, series (nT), time axis, rate and the segments the compensation ran on."""

    df: pd.DataFrame
    vector: NDArray[np.float64]
    scalar: NDArray[np.float64]
    compensated: NDArray[np.float64]
    scalar_column: str
    vector_columns: list[str]
    time_s: NDArray[np.float64]
    rate_hz: float
    ok: NDArray[np.bool_]


def _compensate(comp: ScalarCompensation, data: Path, fmt: str | None, var: str | None,
                columns: Sequence[str] | None, scalar_column: str | None, units: str | None,
                time_column: str | None = None, rate_hz: float | None = None) -> _Compensated:
    """Read ``data`` and compensate it, segment by segment as the fit cut them: at missing rows and at gaps in the
    time (``time_column``, default the one the fit recorded when the data have it; else rows at ``rate_hz``,
    default the fit's rate), so that no derivative of the eddy-current terms spans a gap."""
    vec_cols = list(columns) if columns else list(comp.sensors.get("vector_columns") or [])
    s_col = scalar_column or comp.sensors.get("scalar_column")
    if not vec_cols or not s_col:
        raise TrimagInputError("name the vector columns (columns) and the scalar column (scalar_column)")
    unit = units if units is not None else comp.sensors.get("input_units")
    df, vector, scalar = _read_series(data, fmt, var, vec_cols, str(s_col), unit)
    if time_column is None:
        recorded = comp.sensors.get("time_column")
        time_column = recorded if recorded is not None and str(recorded) in map(str, df.columns) else None
    t, rate = _time_axis(df, time_column, rate_hz or (None if time_column else comp.bandpass.rate_hz))
    ok = np.isfinite(vector).all(axis=1) & np.isfinite(scalar)
    compensated = comp.apply(vector, scalar, split_segments(ok, t, None, max_gap_s=1.5 / rate))
    return _Compensated(df, vector, scalar, compensated, str(s_col), [str(c) for c in vec_cols], t, rate, ok)


def _sensor_line(comp: ScalarCompensation, data: Path, c: _Compensated) -> str:
    """Which magnetometers were read for ``comp`` and whether they are the ones it was fitted to, in one line:
    ``sensor: vector fx, fy, fz and scalar mag of box.csv, nT: the compensation's``."""

    def said(vector: Sequence[Any], scalar: Any, source: Any) -> str:
        return f"vector {', '.join(map(str, vector))} and scalar {scalar} of {Path(str(source)).name}"

    read = said(c.vector_columns, c.scalar_column, data)
    fitted = comp.sensors
    if not fitted.get("vector_columns") or not fitted.get("scalar_column"):
        return f"sensor: {read}, nT"
    own = said(fitted["vector_columns"], fitted["scalar_column"], fitted.get("source") or "?")
    same = (list(map(str, fitted["vector_columns"])) == c.vector_columns
            and str(fitted["scalar_column"]) == c.scalar_column)
    return f"sensor: {read}, nT" + (": the compensation's" if same else f" (the compensation was fitted to {own})")


def apply_compensation_file(
    comp_path: str | Path, data: str | Path, out: str | Path, *, fmt: str | None = None, var: str | None = None,
    columns: Sequence[str] | None = None, scalar_column: str | None = None, units: str | None = None,
) -> dict[str, Any]:
    """Write every input column unchanged plus ``<scalar>_compensated`` (nT) to ``out`` (CSV, Parquet or NPZ)."""
    from ..io.atomic import check_distinct_outputs

    check_distinct_outputs({"the compensation": comp_path, "the input": data}, {"out": out})
    comp = ScalarCompensation.from_file(comp_path)
    data_p, out_p = Path(data), Path(out)
    out_kind = guess_format(out_p) if out_p.suffix else "csv"
    if out_kind == "parquet":  # before the work
        require("pyarrow.parquet", "writing Parquet files")
    c = _compensate(comp, data_p, fmt, var, columns, scalar_column, units)
    df, compensated, name = c.df, c.compensated, f"{c.scalar_column}_compensated"
    sensor = _sensor_line(comp, data_p, c)
    n_bad = int((~np.isfinite(compensated)).sum())
    if out_kind in ("csv", "txt") and guess_format(data_p, fmt) in ("csv", "txt"):
        _write_text_with_column(data_p, out_p, df, name, compensated)
    elif out_kind in ("csv", "txt"):
        table = df.copy()
        table[name] = compensated
        atomic_write_text(out_p, table.to_csv(index=False, lineterminator="\n"))
    elif out_kind == "parquet":
        table = df.copy()
        table[name] = compensated
        from ..io.atomic import atomic_path

        with atomic_path(out_p) as tmp:
            table.to_parquet(tmp, index=False)
    elif out_kind == "npz":
        from ..io.atomic import atomic_path

        with atomic_path(out_p) as tmp, open(tmp, "wb") as fh:
            arrays: dict[str, Any] = {str(c): _numeric(df[c]) for c in df.columns}
            arrays[name] = compensated
            np.savez(fh, **arrays)
    else:
        raise TrimagInputError(f"cannot write {out_p.suffix!r} files; use .csv, .parquet or .npz")
    return {"n_rows": len(df), "n_uncorrected": n_bad, "units": "nT", "output_columns": [name],
            "out": str(out_p), "column_note": "", "columns": c.vector_columns, "sensor": sensor}


def _write_text_with_column(src: Path, out: Path, df: pd.DataFrame, name: str, values: NDArray[np.float64]) -> None:
    """Copy a delimited text file's preamble, header and cells as read, with one more column appended."""
    layout = detect_csv_layout(src)
    sep = layout.delimiter or ","
    text_df = pd.read_csv(src, skiprows=layout.skip, header=0 if layout.has_header else None, dtype=str,
                          keep_default_na=False, sep=layout.delimiter or r"\s+", skip_blank_lines=True)
    if len(text_df) != len(df):
        raise TrimagInputError(f"{src}: rows changed while reading; try again")
    cells = ["" if not np.isfinite(v) else repr(float(v)) for v in values]
    import io as _io

    buf = _io.StringIO()
    for line in layout.preamble:
        buf.write(line + "\n")
    writer = csv.writer(buf, delimiter=sep, lineterminator="\n")
    if layout.has_header:
        writer.writerow([*map(str, text_df.columns), name])
    rows = text_df.to_numpy(dtype=object)
    writer.writerows([*row, cell] for row, cell in zip(rows.tolist(), cells, strict=True))
    atomic_write_text(out, buf.getvalue())


def evaluate_compensation_file(
    comp_path: str | Path, data: str | Path, *, fmt: str | None = None, var: str | None = None,
    columns: Sequence[str] | None = None, scalar_column: str | None = None, units: str | None = None,
    time_column: str | None = None, rate_hz: float | None = None, segments: str | None = None,
) -> dict[str, Any]:
    """Band-passed std of the scalar before and after compensation, per segment, and the improvement ratio."""
    comp = ScalarCompensation.from_file(comp_path)
    data_p = Path(data)
    c = _compensate(comp, data_p, fmt, var, columns, scalar_column, units,
                    time_column if time_column is not None else comp.sensors.get("time_column"), rate_hz)
    df, vector, scalar, compensated, s_col, t, rate = (c.df, c.vector, c.scalar, c.compensated, c.scalar_column,
                                                       c.time_s, c.rate_hz)
    if abs(rate - comp.bandpass.rate_hz) > 0.01 * comp.bandpass.rate_hz:
        raise TrimagInputError(
            f"the data are sampled at {rate:g} Hz but the compensation was fitted at {comp.bandpass.rate_hz:g} Hz "
            "(its eddy-current terms are per sample): resample the data or refit"
        )
    bp = BandPass(comp.bandpass.low_hz, comp.bandpass.high_hz, rate, comp.bandpass.poles, comp.bandpass.trim)
    ok = c.ok
    segs = split_segments(ok, t, parse_segments(segments), max_gap_s=1.5 / rate)
    before = segment_std(scalar, segs, bp)
    after = segment_std(compensated, segs, bp)
    rows = []
    for (a, b), sb, sa in zip(segs, before, after, strict=True):
        entry: dict[str, Any] = {"t0_s": float(t[a]), "t1_s": float(t[b - 1]), "n": b - a, "std_before_nT": sb,
                                 "std_after_nT": sa, "improvement_ratio": (sb / sa) if sb and sa else None}
        entry.update(manoeuvre_content(vector[a:b]))
        rows.append(entry)
    used = [r for r in rows if r["std_before_nT"] is not None]
    if not used:
        raise TrimagInputError(f"{data_p}: no segment is long enough ({bp.min_length} samples) to band-pass")
    n_tot = sum(r["n"] for r in used)
    pooled_b = float(np.sqrt(sum(r["n"] * r["std_before_nT"] ** 2 for r in used) / n_tot))
    pooled_a = float(np.sqrt(sum(r["n"] * r["std_after_nT"] ** 2 for r in used) / n_tot))
    return {
        "calibration": str(comp_path), "data": str(data_p), "model": comp.model, "method": comp.method,
        "units": "nT", "scalar_column": s_col, "columns": c.vector_columns, "sensor": _sensor_line(comp, data_p, c),
        "rate_hz": rate, "band_hz": [bp.low_hz, bp.high_hz], "n_samples": len(df), "n_dropped": int((~ok).sum()),
        "n_segments": len(segs), "n_segments_too_short": len(rows) - len(used),
        "segments": rows, "std_before_nT": pooled_b, "std_after_nT": pooled_a,
        "improvement_ratio": pooled_b / pooled_a if pooled_a > 0 else None,
    }


def summary(comp: ScalarCompensation) -> dict[str, Any]:
    """The JSON summary ``trimag fit --json`` prints for a compensation."""
    return json.loads(comp.to_json(indent=None))
