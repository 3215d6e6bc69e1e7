"""The fit's outputs (the report figure and the calibration JSON), written together or not at all."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..io import Samples
from .requests import FitRequest


def write_fit_outputs(
    cal: Calibration, samples: Samples, req: FitRequest, regressor_values: dict[str, NDArray[np.float64]] | None = None
) -> tuple[Calibration, dict[str, str]]:
    """Write the report and the calibration when asked: together or not at all (the report first, it can fail)."""
    written: dict[str, str] = {}
    path = req.input.path
    try:
        if req.report is not None and Path(req.report).suffix.lower() in (".html", ".htm"):
            written["report"] = str(_html_report(cal, samples, req))
        elif req.report is not None:
            from ..quality.report import fit_report, save_figure

            notes = [f"{samples.n_dropped} rows dropped"] if samples.n_dropped else []
            title = f"trimag fit of {Path(path).name}: model {cal.model}, method {cal.method}"
            field_, shown = samples.field, cal
            if regressor_values is not None:  # the figure shows the samples with the regressor terms removed
                field_ = samples.field - cal.regressor_shift(regressor_values, samples.field.shape)
                shown = dataclasses.replace(cal, regressors=None)
            time_s = (samples.table["time_s"].to_numpy(dtype=float)
                      if samples.log_info is not None and "time_s" in samples.table.columns
                      and len(samples.table) == len(field_) else None)
            written["report"] = str(save_figure(fit_report(field_, shown, title=title, notes=notes, time_s=time_s),
                                                req.report))
        card = cal.diagnostics.get("deviation_card")
        if req.deviation_card is not None and card is not None:  # a large vehicle's fit (trimag.app._large)
            from ..quality.report import deviation_figure, save_figure

            figure = deviation_figure(card, title=f"deviation card of {Path(path).name} ({cal.method})",
                                      before=f"before ({card['before_label']})")
            written["deviation_card"] = str(save_figure(figure, req.deviation_card))
        if req.out is not None:
            cal = cal.with_stats(source=str(path), columns=list(samples.columns))
            if str(req.out) == "-":  # standard output: last, once every file is written
                _to_standard_output(cal)
                written["calibration"] = "standard output"
            else:
                written["calibration"] = str(cal.to_file(req.out))
    except BaseException:
        for what, done in written.items():
            if what != "calibration" or str(req.out) != "-":
                Path(done).unlink(missing_ok=True)
        raise
    return cal, written


def _html_report(cal: Calibration, samples: Samples, req: FitRequest) -> Path:
    """``report=report.html`` of a flight's firmware fit: the review's figures and tables of this fit
    (:func:`trimag.app.review.report_html`), one self-contained file (Plotly inline; nothing fetched)."""
    from ..errors import TrimagInputError
    from ..io.atomic import atomic_write_text
    from ._flight import CompassResult, FlightLog, report_html

    info = samples.log_info
    if req.target is None or (info is not None and info.get("compass") is None):
        raise TrimagInputError("an HTML report (report.html) shows a flight's firmware fit: give an autopilot log, or "
                               "a table with its attitude columns, and `target`; for other data write report.png")
    review = FlightLog(req.input.path, fmt=req.input.fmt, target=req.target, igrf_spec=req.reference.igrf_spec,
                       units=req.input.units, columns=req.input.columns,
                       attitude_columns=req.attitude.attitude_columns, time_column=req.attitude.time_column)
    number = 1 if info is None else int(info["compass"])
    t = review.log.choose(number).time_s
    n = len(t)
    rows = req.input.rows or ""
    start, stop = (int(x) if x.strip() else None for x in (rows.split(":") if rows else ("", "")))
    first, end = start or 0, min(stop if stop is not None else n, n)
    fitted = f"{first}:{end}"
    if review.table_input is not None:  # the file's data rows -> the kept rows' positions
        kept = review.table_input.rows
        fitted = f"{first}:{stop if stop is not None else int(kept[-1]) + 1}"
        first = int(np.searchsorted(kept, first))
        end = int(np.searchsorted(kept, stop)) if stop is not None else n
    start_s = float(t[min(first, n - 1)]) if n else 0.0
    stop_s = float(t[max(end - 1, 0)]) if n else 0.0
    fw = cal.diagnostics.get("firmware") or {}
    review.results[number] = CompassResult(number, cal, rows=fitted, command="")
    review.choice = {"start_s": start_s, "stop_s": stop_s, "level": fw.get("level", req.level or "auto"),
                     "motor": fw.get("motor_type") or req.motor or "auto", "yaw_source": req.yaw_source or "auto"}
    title = f"trimag fit of {Path(req.input.path).name}: compass {number}, {req.target} level {fw.get('level')}"
    assert req.report is not None
    return atomic_write_text(req.report, report_html(review, [number], title=title))


def _to_standard_output(cal: Calibration) -> None:
    """The calibration's JSON on standard output (``out="-"``), as ``trimag apply`` and ``export`` write theirs."""
    import sys

    text = cal.to_json() + "\n"
    sys.stdout.flush()
    sys.stdout.write(text)
    sys.stdout.flush()

