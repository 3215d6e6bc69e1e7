"""``trimag evaluate`` of a magnitude calibration: statistics of ``|B| - F`` before and after, streamed in one pass."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..errors import TrimagError, TrimagInputError
from ..fields.reference import as_scalar_reference, igrf, parse_igrf_spec
from ..io import MagnitudeAccumulator, open_chunks
from ..io.stream import Chunk, _parse_rows, chunk_columns
from ..io.tables import strict_refusal, where_mask
from ..units import convert, normalise_unit, unit_after
from ..validation import ROUNDOFF_FRACTION
from ._inputs import calibration_for, refuse_background_vector
from ._sensor import input_for, sensor_line
from .requests import EvaluateRequest, as_request

__all__ = ["evaluate_file"]


def evaluate_file(
    request: EvaluateRequest | str | Path, *paths: str | Path, progress: Callable[[int], None] | None = None,
    **arguments: Any,
) -> dict[str, Any]:
    """Statistics of ``|B| - F`` before and after applying a calibration to a file (streamed, one pass).

    ``request``: an :class:`~trimag.app.requests.EvaluateRequest`, or the calibration's and the data's paths with the
    request's fields as keyword arguments (:meth:`EvaluateRequest.of <trimag.app.requests.EvaluateRequest.of>`).
    Without a reference, ``F`` is the mean corrected magnitude (as in ``trimag fit``). ``progress`` is called with
    the rows read so far.
    """
    req = as_request(EvaluateRequest, request, paths, arguments)
    src, given = req.input, req.reference
    cal = calibration_for(req.calibration, src.path, "evaluate")
    unit = cal.units if src.units is None else normalise_unit(src.units)
    if src.units is not None:
        cal.check_units(unit)
    F, source = _reference_value(req, unit)
    src, sensor = input_for(cal, src)  # the calibration's sensor by default (issue 39)
    columns, chunks = open_chunks(src.path, fmt=src.fmt, columns=src.columns, var=src.var, chunk_rows=req.chunk_rows,
                                  sensor=sensor)
    sensor_read = sensor_line(cal, req.input, columns.log_info, columns.columns, columns.variable)
    rows = _parse_rows(src.rows)
    regressor_names = tuple(cal.regressors["names"]) if cal.regressors is not None else ()
    spec = cal.regressors.get("eddy") if cal.regressors is not None else None
    read_names = regressor_names
    if spec:  # the derivative needs neighbouring rows: the selected rows are collected, then corrected at once
        from ..vehicle.eddy import evaluate_columns, with_row_numbers

        read_names = evaluate_columns(cal, spec, req.attitude.time_column, req.rate_hz)
    kept: list[tuple[Any, ...]] = []
    before, after = MagnitudeAccumulator(), MagnitudeAccumulator()
    n_rows = n_bad = 0
    first_bad: int | None = None
    for chunk in chunks:
        if spec:  # each row's number: the derivative's gaps without a time column
            chunk = with_row_numbers(chunk)
        xyz, u, ref_values, n_chunk, first = _chunk_rows(chunk, req, rows, read_names, F)
        n_rows += n_chunk
        n_bad += n_chunk - len(xyz)
        first_bad = first if first_bad is None else first_bad
        before.add(np.linalg.norm(xyz, axis=1), ref_values)
        if spec:
            kept.append((xyz, u, ref_values))
        else:
            after.add(np.linalg.norm(cal.apply(xyz, regressors=u), axis=1), ref_values)
        if progress:
            progress(chunk.start + len(chunk.xyz))
    if spec and kept:
        from ..vehicle.eddy import corrected_magnitudes

        after.add(*corrected_magnitudes(cal, spec, kept, req.attitude.time_column, req.rate_hz))
    if n_bad and src.strict:
        raise strict_refusal(f"{src.path}: ", n_bad, "missing, non-numeric, NaN or inf field (or regressor or "
                             "reference) values", f"data row {first_bad}")
    if after.n == 0:
        raise TrimagInputError(f"{src.path}: no rows with finite x, y, z values to evaluate")
    if F is None and not given.reference_column and after.n < MIN_ROWS_AGAINST_OWN_MEAN:
        raise TooFewRowsError(
            f"{src.path}: {after.n} row{'s' if after.n != 1 else ''} with x, y, z: without a reference the field F "
            f"is the corrected rows' own mean, so the RMS after correction says nothing about the calibration (one "
            f"row's is 0); evaluate at least {MIN_ROWS_AGAINST_OWN_MEAN} rows, or give the field: `reference=F` (or "
            "`igrf_spec=LAT,LON,ALT_M,DATE`)")
    stats_after = after.result()
    F_used = F if F is not None else (None if given.reference_column else stats_after["mean_norm"])
    stats_before = before.result(F_used)
    selection = (f"rows {src.rows}" if src.rows else "", f"where {src.where}" if src.where else "")
    # worse than raw: like with like. Against a reference, RMS(|B| - F) before and after. Against the corrected data's
    # own mean (no reference) the raw |B| is judged about its own mean too, and relative to it: a calibration's
    # gain scales the spread with the field (a scale-only change is not worse: issue 38)
    if F is not None or given.reference_column:
        judged_after, judged_before, what, unit = stats_after["rms"], stats_before["rms"], "RMS of |B| - F", cal.units
    else:
        field_after = _fitted_field(cal) or stats_after["mean_norm"]  # the field the calibration maps the data to
        judged_after = 100.0 * stats_after["std_norm"] / field_after if field_after > 0 else np.inf
        judged_before = 100.0 * stats_before["std_norm"] / stats_before["mean_norm"] \
            if stats_before["mean_norm"] > 0 else np.inf
        what, unit = "spread of |B| relative to the field (std / |B|)", "%"
    roundoff = ROUNDOFF_FRACTION * (100.0 if unit == "%" else abs(F if F is not None else stats_after["mean_norm"]))
    worse = bool(judged_after > judged_before * (1.0 + RELATIVE_SPREAD_TOLERANCE)
                 if unit == "%" else judged_after > judged_before) and bool(judged_after > roundoff)
    fitted, fitted_warning = (None, None) if F is not None or given.reference_column else \
        _against_fitted_reference(cal, after, before)
    return {
        "calibration": str(req.calibration), "data": str(src.path), "model": cal.model, "method": cal.method,
        "sensor": sensor_read, "units": cal.units,
        "columns": list(columns.columns), "n_samples": n_rows, "n_used": after.n,
        "n_dropped": n_bad, "selection": "; ".join(x for x in selection if x), "regressors": list(regressor_names),
        "reference": {"value": F_used, "source": source, "unit": cal.units},
        "rms_before": stats_before["rms"], "rms_after": stats_after["rms"],
        "max_abs_before": stats_before["max_abs"], "max_abs_after": stats_after["max_abs"],
        "p2p_before": stats_before["peak_to_peak"], "p2p_after": stats_after["peak_to_peak"],
        "mean_norm_before": stats_before["mean_norm"], "mean_norm_after": stats_after["mean_norm"],
        "std_norm_before": stats_before["std_norm"], "std_norm_after": stats_after["std_norm"],
        "worse_than_raw": worse, "fitted_reference": fitted,
        "warnings": ([worse_than_raw_warning(what, judged_after, judged_before, unit)] if worse else [])
        + ([fitted_warning] if fitted_warning else []),
    }


class TooFewRowsError(TrimagError, ValueError):
    """An evaluation the rows cannot support (exit 3, as a fit the data cannot support)."""

    exit_code = 3


#: Fewest rows an evaluation against the corrected rows' own mean |B| accepts: one row's RMS(|B| - F) is 0 and two
#: rows' is half their difference, whatever the calibration
MIN_ROWS_AGAINST_OWN_MEAN = 3

#: Share by which the relative spread of |B| may grow before an evaluation without a reference calls the calibration
#: worse than the raw data: on a static pose the raw spread is the noise, which a gain scales with the field, and the
#: field the calibration maps to differs from the corrected mean by the local anomaly (issue 38).
RELATIVE_SPREAD_TOLERANCE = 0.05


def _fitted_field(cal: Calibration) -> float | None:
    """The field magnitude the calibration was fitted to (its reference's value, the fitted mean included), if any."""
    value = (cal.reference or {}).get("value")
    return float(value) if isinstance(value, (int, float)) and np.isfinite(value) and value > 0 else None


#: Share by which the corrected mean magnitude may differ from the magnitude the calibration was fitted to before an
#: evaluation against the corrected mean names it (the local anomaly and IGRF's error are well under 1 %).
FITTED_REFERENCE_TOLERANCE = 0.02


def _against_fitted_reference(cal: Calibration, after: Any, before: Any) -> tuple[dict[str, Any] | None, str | None]:
    """An evaluation against the corrected mean, of a calibration fitted to a known magnitude: the statistics
    against that magnitude, and a warning when the corrected mean is more than :data:`FITTED_REFERENCE_TOLERANCE`
    from it (a scale error that the corrected data's own mean hides)."""
    ref = cal.reference or {}
    value = ref.get("value")
    if str(ref.get("source", "mean")) == "mean" or not isinstance(value, (int, float)) or not value > 0:
        return None, None
    a, b = after.result(float(value)), before.result(float(value))
    fitted = {"value": float(value), "source": ref.get("source"), "rms_after": a["rms"], "rms_before": b["rms"],
              "max_abs_after": a["max_abs"]}
    off = a["mean_norm"] / float(value) - 1.0
    if abs(off) <= FITTED_REFERENCE_TOLERANCE:
        return fitted, None
    return fitted, (
        f"the corrected field's mean |B| here is {a['mean_norm']:.4g} {cal.units}, {100 * off:+.1f} % from the "
        f"{float(value):.4g} {cal.units} the calibration was fitted to ({ref.get('source')}); against that, RMS(|B| - "
        f"F) is {a['rms']:.4g} {cal.units}: where the field is {float(value):.4g} {cal.units}, the calibration's scale "
        "does not hold for these data; give `reference=F` (or `igrf_spec=LAT,LON,ALT_M,DATE`) to measure against the "
        "field you expect")


def worse_than_raw_warning(what: str, after: float, before: float, unit: str) -> str:
    """The warning of an evaluation in which the calibration makes the data worse than the raw data (issue 32)."""
    sep, unit = ("", unit) if unit == "%" else (" ", unit_after(unit))
    return (f"the calibration makes these data worse than the raw data ({what} {after:.4g}{sep}{unit} after against "
            f"{before:.4g}{sep}{unit} before): it does not hold for this log (fitted on too little rotation, on "
            "another sensor or mounting, or the vehicle changed); fit this log, or check the calibration and the unit")


def _reference_value(req: EvaluateRequest, unit: str) -> tuple[float | None, str]:
    """The one field magnitude ``F`` in ``unit`` (None: per sample from a column, or the mean) and its source."""
    given = req.reference
    refuse_background_vector(given)
    named = [x for x in (given.reference, given.igrf_spec, given.reference_column) if x is not None]
    if len(named) > 1:
        raise TrimagInputError("give only one of `reference`, `igrf_spec`, `reference_column`")
    if given.igrf_spec is not None:
        lat, lon, alt, date = parse_igrf_spec(given.igrf_spec)
        return convert(igrf(lat, lon, alt, date).total_nT, "nT", unit), f"igrf {given.igrf_spec}"
    if given.reference is not None and str(given.reference).strip().lower() != "mean":
        return float(as_scalar_reference(given.reference, 1, units=unit).values[0]), "given"  # type: ignore[index]
    if given.reference_column is not None:
        return None, f"column {given.reference_column}"
    return None, "mean"


def _chunk_rows(
    chunk: Chunk, req: EvaluateRequest, rows: tuple[int, int | None], regressor_names: tuple[str, ...],
    F: float | None,
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None, Any, int, int | None]:
    """The selected rows of one chunk with finite x, y, z (and regressors): ``(xyz (n, 3), regressors (n, m) or
    None, reference (float, (n,) or None), number of selected rows before the finite check, the first selected
    data row that is not finite or None)``; ``rows``: the selected data rows START, STOP (None: to the end)."""
    src, column = req.input, req.reference.reference_column
    start, stop = rows
    idx = chunk.start + np.arange(len(chunk.xyz))
    mask = idx >= start
    if stop is not None:
        mask &= idx < stop
    if src.where:
        mask &= where_mask(chunk.table, src.where)
    xyz = chunk.xyz[mask]
    ok = np.isfinite(xyz).all(axis=1)
    u = chunk_columns(chunk, regressor_names, src.path)[mask] if regressor_names else None
    if u is not None:
        ok &= np.isfinite(u).all(axis=1)
    ref_values: Any = F
    if column is not None:  # a missing, non-numeric or non-finite reference: the row is dropped (and counted)
        if column not in chunk.table.columns:
            raise TrimagInputError(f"no column {column!r} in {src.path}")
        ref_values = chunk_columns(chunk, (column,), src.path)[mask, 0]
        ok &= np.isfinite(ref_values)
        ref_values = ref_values[ok]
    if u is not None:
        u = u[ok]
    first = int(idx[mask][np.flatnonzero(~ok)[0]]) if not ok.all() else None
    return xyz[ok], u, ref_values, len(xyz), first
