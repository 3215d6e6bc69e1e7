"""``trimag export``: a calibration written as firmware or tool parameters (docs/autopilot.md)."""

from __future__ import annotations

from typing import Any

from ..calibration import Calibration
from ..errors import TrimagInputError
from .requests import ExportRequest

__all__ = ["export_to_file"]


def export_to_file(request: ExportRequest | None = None, **arguments: Any) -> dict[str, Any]:
    """Write the calibration in ``target``'s convention (:func:`trimag.io.export.export_calibration`).

    ``request``: an :class:`~trimag.app.requests.ExportRequest`, or its fields as keyword arguments.

    Returns
    -------
    dict
        ``target``, ``out`` (the path written), ``parameters``, ``notes`` (what the conversion did) and
        ``violations`` (values outside the firmware's limits).
    """
    from ..io.export import export_calibration, write_export

    req = request if request is not None else ExportRequest(**arguments)
    if request is not None and arguments:
        raise TrimagInputError("give either an ExportRequest or its arguments, not both")
    if not 1 <= req.instance <= 8:  # the request's instance counts from 1, as the firmware's parameter names do
        raise TrimagInputError(f"`instance` must be 1..8 (COMPASS_OFS, COMPASS_OFS2 ...; CAL_MAG0 is 1); got "
                               f"{req.instance}")
    cal = Calibration.from_file(req.calibration)
    exp = export_calibration(cal, req.target, instance=req.instance - 1)
    if str(req.out) == "-":  # standard output
        import sys

        sys.stdout.write(exp.text)
        sys.stdout.flush()
        path: Any = "-"
    else:
        path = write_export(exp, req.out)
    return {"target": exp.target, "out": str(path), "parameters": exp.parameters, "notes": exp.notes,
            "violations": exp.violations}
