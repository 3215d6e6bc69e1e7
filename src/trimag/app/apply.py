"""``trimag apply``: correct every row of a file with a calibration (streamed)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..io import apply_file
from ..io.atomic import check_distinct_outputs
from ._inputs import calibration_for
from ._sensor import input_for, sensor_line
from .requests import ApplyRequest, as_request

__all__ = ["apply_to_file"]


def apply_to_file(
    request: ApplyRequest | str | Path, *paths: str | Path, progress: Callable[[int], None] | None = None,
    **arguments: Any,
) -> dict[str, Any]:
    """Correct a whole file with a calibration (streamed; see :func:`trimag.io.apply_file`).

    ``request``: an :class:`~trimag.app.requests.ApplyRequest`, or the calibration's, the data's and the output's paths
    with the request's fields as keyword arguments (:meth:`ApplyRequest.of <trimag.app.requests.ApplyRequest.of>`).
    ``progress`` is called with the rows written so far. A calibration with regressor terms reads its regressors
    from the columns of the same names; a missing column raises :class:`TrimagInputError`, and a row whose
    regressor value is missing is left uncorrected.
    """
    req = as_request(ApplyRequest, request, paths, arguments)
    src = req.input
    check_distinct_outputs({"the calibration": req.calibration, "the input": src.path}, {"out": req.out})
    cal = calibration_for(req.calibration, src.path, "apply")
    if src.units is not None:
        cal.check_units(src.units)
    src, sensor = input_for(cal, src)  # the calibration's sensor by default (issue 39)
    names = tuple(cal.regressors["names"]) if cal.regressors is not None else ()
    spec = cal.regressors.get("eddy") if cal.regressors is not None else None
    if spec:  # eddy-current terms: the derivative of the samples themselves, streamed (trimag.vehicle.eddy)
        from ..vehicle.eddy import streamed_calibrate

        calibrate, names = streamed_calibrate(cal, spec, src.path, fmt=src.fmt, columns=src.columns, var=src.var,
                                              chunk_rows=req.chunk_rows, sensor=sensor)
    else:
        def calibrate(xyz: NDArray[np.float64], *u: NDArray[np.float64]) -> NDArray[np.float64]:
            return cal.apply(xyz, regressors=u[0] if u else None)

    def write(out: str | Path) -> dict[str, Any]:
        return apply_file(calibrate, src.path, out, fmt=src.fmt, columns=src.columns, var=src.var,
                          chunk_rows=req.chunk_rows, progress=progress, regressor_columns=names, sensor=sensor,
                          strict=src.strict)

    result = _to_standard_output(write) if str(req.out) == "-" else write(req.out)
    result["units"] = cal.units
    result["sensor"] = sensor_line(cal, req.input, result.pop("log_info", None), result.get("columns"),
                                   result.pop("variable", None))
    return result


def _to_standard_output(write: Callable[[Path], dict[str, Any]]) -> dict[str, Any]:
    """``write`` to a CSV file in a temporary folder, then copied to standard output (``out="-"``): nothing is
    printed when the correction fails half-way, as with a file."""
    import shutil
    import sys
    import tempfile

    with tempfile.TemporaryDirectory(prefix="trimag-") as folder:
        path = Path(folder) / "corrected.csv"
        result = write(path)
        sys.stdout.flush()
        with path.open("rb") as fh:
            shutil.copyfileobj(fh, sys.stdout.buffer)
        sys.stdout.buffer.flush()
    result["out"] = "-"
    return result
