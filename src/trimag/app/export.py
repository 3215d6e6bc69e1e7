"""``trimag export``: a calibration written as firmware or tool parameters (docs/autopilot.md)."""

from __future__ import annotations

from pathlib import Path
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
        ``target``, ``out`` (the path written), ``parameters``, ``notes`` (what the conversion did),
        ``violations`` (values outside the firmware's limits) and ``warnings`` (what ``force`` let through).
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
    forced = refuse_rejected(cal, str(req.calibration), req.force)
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
            "violations": exp.violations, "warnings": forced}


def refuse_rejected(cal: Calibration, name: str, force: bool) -> list[str]:
    """Refuse to export a calibration its own fit rejected (issue 41, item 9), unless ``force``: one the acceptance
    policy rejected (:class:`~trimag.vehicle.policy.PolicyRejected`, exit 4) or one whose numbers the fit said look
    like another unit (``diagnostics.unit_doubt``; :class:`TrimagInputError`, exit 2). ``name`` names it in the
    message. Returns the warnings of what ``force`` let through (empty when nothing was doubted)."""
    from ..vehicle.policy import PolicyRejected, failed_rules

    verdict = cal.diagnostics.get("acceptance")
    rejected = isinstance(verdict, dict) and verdict.get("accepted") is False
    doubt = cal.diagnostics.get("unit_doubt")
    notes: list[str] = []
    if rejected:
        rules = "; ".join(failed_rules(verdict or {})) or "no rule could be evaluated"
        if not force:
            raise PolicyRejected(f"{name} was rejected by the acceptance policy when it was fitted ({rules}): its "
                                 "parameters are not written; record and fit again, or give `force` to write them "
                                 "anyway")
        notes.append(f"written although the acceptance policy rejected it ({rules}; `force`)")
    if isinstance(doubt, str) and doubt:
        if not force:
            raise TrimagInputError(f"{name}'s fit doubted the data's unit ({doubt}): its parameters are not written; "
                                   "fit again with the right unit, or give `force` to write them anyway")
        notes.append(f"written although its fit doubted the data's unit ({doubt}; `force`)")
    return notes


def _instance(cal: Calibration, given: int | None) -> tuple[int, list[str]]:
    """The compass number to write: ``given``, else the compass of the log the calibration was fitted to (its
    sensor record, ``sensor.compass``; ``diagnostics.log_compass`` in a file of an earlier trimag), else 1; a given
    number that differs from the fitted compass is said."""
    fitted = cal.sensor.compass if cal.sensor is not None and cal.sensor.kind == "log" else \
        (cal.diagnostics.get("log_compass") or {}).get("compass")
    fitted = int(fitted) if isinstance(fitted, int | float) and 1 <= int(fitted) <= 8 else None
    if given is None:
        return fitted or 1, []
    if fitted is not None and fitted != given:
        return given, [f"fitted to compass {fitted} of its log, written as compass {given} (`instance`)"]
    return given, []


def _read_calibration(path: Any, target: str) -> Calibration:
    """The calibration file ``path``; a log or a data file given instead is refused saying which command makes a
    calibration (a newcomer's ``trimag export flight.bin`` said "not UTF-8 text")."""
    from ..io.logs import log_format

    make = (f"make one with `trimag fit {path} -o cal.json`, then `trimag export cal.json --to {target} -o FILE`")
    from .tolles_lawson import is_compensation_file

    if is_compensation_file(path):  # never "make one with trimag fit" (which points back here: issue 39)
        name = Path(path).name
        raise TrimagInputError(f"{path} is a Tolles-Lawson compensation (the terms of a scalar magnetometer, not a "
                               f"vector calibration): no firmware or tool takes it as parameters; use it with `trimag "
                               f"apply {name} LOG -o OUT.csv` or `trimag evaluate {name} LOG` (its coefficients are "
                               "in the file's \"coefficients\")")
    if Path(path).exists() and log_format(path) is not None:
        raise TrimagInputError(f"{path} is an autopilot log, not a calibration: export writes the parameters of a "
                               f"calibration file (JSON); {make}")
    try:
        return Calibration.from_file(path)
    except UnicodeDecodeError:
        raise TrimagInputError(f"{path} is not a calibration file (it is not JSON text): export takes the JSON "
                               f"calibration that `trimag fit` writes; {make}") from None
    except TrimagInputError as exc:
        said = str(exc).removeprefix(f"{path}: ")  # Calibration.from_file names the file; said once here
        if "not a trimag calibration" in said:  # JSON, but another program's (settings, a parameter dump): no data
            raise TrimagInputError(f"{path} is not a calibration file (a JSON file without \"format\": \"trimag-"
                                   f"calibration\"): export takes the JSON calibration that `trimag fit LOG -o "
                                   "cal.json` writes") from None
        if "JSON" in said:
            raise TrimagInputError(f"{path} is not a calibration file ({said}): export takes the JSON calibration that "
                                   f"`trimag fit` writes; {make}") from None
        raise
