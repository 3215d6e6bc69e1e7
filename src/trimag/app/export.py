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
    from ..io.atomic import check_distinct_outputs
    from ..io.export import export_calibration, write_export

    req = request if request is not None else ExportRequest(**arguments)
    if request is not None and arguments:
        raise TrimagInputError("give either an ExportRequest or its arguments, not both")
    if req.instance is not None and not 1 <= req.instance <= 8:  # counted from 1, as the firmware's names do
        raise TrimagInputError(f"`instance` must be 1..8 (COMPASS_OFS, COMPASS_OFS2 ...; CAL_MAG0 is 1); got "
                               f"{req.instance}")
    check_distinct_outputs({"the calibration": req.calibration}, {"out": req.out})
    cal = _read_calibration(req.calibration, req.target)
    instance, note = _instance(cal, req.instance)
    exp = export_calibration(cal, req.target, instance=instance - 1)
    exp.notes[:0] = note
    if str(req.out) == "-":  # standard output
        import sys

        sys.stdout.write(exp.text)
        sys.stdout.flush()
        path: Any = "-"
    else:
        path = write_export(exp, req.out)
    return {"target": exp.target, "out": str(path), "parameters": exp.parameters, "notes": exp.notes,
            "violations": exp.violations}


def _instance(cal: Calibration, given: int | None) -> tuple[int, list[str]]:
    """The compass number to write: ``given``, else the compass of the log the calibration was fitted to (recorded
    by fit as ``diagnostics.log_compass``), else 1; a given number that differs from the fitted compass is said."""
    fitted = (cal.diagnostics.get("log_compass") or {}).get("compass")
    fitted = int(fitted) if isinstance(fitted, int | float) and 1 <= int(fitted) <= 8 else None
    if given is None:
        return fitted or 1, []
    if fitted is not None and fitted != given:
        return given, [f"fitted to compass {fitted} of its log, written as compass {given} (`instance`)"]
    return given, []


def _read_calibration(path: Any, target: str) -> Calibration:
    """The calibration file ``path``; a log or a data file given instead is refused saying which command makes a
    calibration (a newcomer's ``trimag export flight.bin`` said "not UTF-8 text")."""
    from pathlib import Path

    from ..io.logs import log_format

    make = (f"make one with `trimag fit {path} -o cal.json`, then `trimag export cal.json --to {target} -o FILE`")
    if Path(path).exists() and log_format(path) is not None:
        raise TrimagInputError(f"{path} is an autopilot log, not a calibration: export writes the parameters of a "
                               f"calibration file (JSON); {make}")
    try:
        return Calibration.from_file(path)
    except UnicodeDecodeError:
        raise TrimagInputError(f"{path} is not a calibration file (it is not JSON text): export takes the JSON "
                               f"calibration that `trimag fit` writes; {make}") from None
    except TrimagInputError as exc:
        if "JSON" in str(exc) or "not a trimag calibration" in str(exc):
            raise TrimagInputError(f"{path} is not a calibration file ({exc}): export takes the JSON calibration that "
                                   f"`trimag fit` writes; {make}") from None
        raise
