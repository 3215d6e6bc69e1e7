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
        if req.report is not None:
            from ..quality.report import fit_report, save_figure

            notes = [f"{samples.n_dropped} rows dropped"] if samples.n_dropped else []
            title = f"trimag fit of {Path(path).name}: model {cal.model}, method {cal.method}"
            field_, shown = samples.field, cal
            if regressor_values is not None:  # the figure shows the samples with the regressor terms removed
                field_ = samples.field - cal.regressor_shift(regressor_values, samples.field.shape)
                shown = dataclasses.replace(cal, regressors=None)
            written["report"] = str(save_figure(fit_report(field_, shown, title=title, notes=notes), req.report))
        card = cal.diagnostics.get("deviation_card")
        if req.deviation_card is not None and card is not None:  # a large vehicle's fit (trimag.app._large)
            from ..quality.report import deviation_figure, save_figure

            figure = deviation_figure(card, title=f"deviation card of {Path(path).name} ({cal.method})",
                                      before=f"before ({card['before_label']})")
            written["deviation_card"] = str(save_figure(figure, req.deviation_card))
        if req.out is not None:
            cal = cal.with_stats(source=str(path), columns=list(samples.columns))
            written["calibration"] = str(cal.to_file(req.out))
    except BaseException:
        for done in written.values():
            Path(done).unlink(missing_ok=True)
        raise
    return cal, written

