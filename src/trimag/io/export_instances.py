"""One firmware parameter file for several compasses (``trimag fit LOG --sensor all``; docs/autopilot.md).

Each compass is written by the target's own writer (:func:`trimag.io.export.export_calibration`, once per
instance, whatever parameters it writes), and the parameters are joined: ArduPilot's ``.param`` as sorted
``NAME,VALUE`` lines, PX4's as ``param set NAME VALUE`` lines. A parameter two compasses both write (a global one,
e.g. ``COMPASS_MOTCT`` or ``CAL_MAG_COMP_TYP``) must have the same value in both, or the file is refused.
"""

from __future__ import annotations

from collections.abc import Sequence

from ..calibration import Calibration
from ..errors import TrimagInputError
from .export import Export, export_calibration

__all__ = ["PARAMETER_TARGETS", "export_instances"]

#: The targets whose files hold several compasses' parameters.
PARAMETER_TARGETS = ("ardupilot", "px4")


def export_instances(calibrations: Sequence[tuple[Calibration, int]], target: str) -> Export:
    """The parameters of every ``(calibration, compass number)`` (numbers from 1, as ``export --instance``) in one
    file of ``target`` (``"ardupilot"`` or ``"px4"``).

    Returns
    -------
    Export
        The joined text and parameters; the notes and violations of each compass, prefixed with its number.

    Raises
    ------
    TrimagInputError
        Another target, no calibration, a compass number twice, a shared parameter with two values, or what a
        compass's own writer refuses.
    """
    if target not in PARAMETER_TARGETS:
        raise TrimagInputError(f"one file for several compasses is written for {' or '.join(PARAMETER_TARGETS)}; "
                               f"got {target!r}")
    if not calibrations:
        raise TrimagInputError("no calibration to write")
    numbers = [n for _, n in calibrations]
    if len(set(numbers)) != len(numbers):
        raise TrimagInputError(f"compass numbers given twice: {numbers}")
    params: dict[str, float] = {}
    notes: list[str] = []
    violations: list[str] = []
    headers: list[str] = []
    for cal, number in sorted(calibrations, key=lambda item: item[1]):
        exp = export_calibration(cal, target, instance=number - 1)
        for name, value in exp.parameters.items():
            if name in params and params[name] != value:
                raise TrimagInputError(f"compasses disagree on the shared parameter {name} ({params[name]} and "
                                       f"{value}): write them to separate files")
            params[name] = value
        notes += [f"compass {number}: {note}" for note in exp.notes]
        violations += [f"compass {number}: {v}" for v in exp.violations]
        headers += [line[2:] for line in exp.text.splitlines() if line.startswith("# ")]
    lines = [f"# {h}" for h in dict.fromkeys(headers)]  # each compass's provenance, once
    if target == "ardupilot":
        lines += [f"{name},{value:.9g}" for name, value in sorted(params.items())]  # sorted, as MAGFit's files
    else:
        lines += [f"param set {name} {value:.9g}" for name, value in params.items()]
    return Export(target, "\n".join(lines) + "\n", params, notes, violations)
