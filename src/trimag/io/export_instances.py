"""One firmware parameter file for several compasses (``trimag fit LOG --sensor all``; docs/autopilot.md).

The compasses are numbered from 1 as the firmware's parameter names count them (``COMPASS_OFS`` = 1, ``OFS2`` = 2;
PX4 ``CAL_MAG0`` = 1) and written by :func:`trimag.io.export.export_calibrations`: each compass's parameters as
its own export writes them (orientation, offsets, scale and symmetric matrix, motor term), checked through the
firmware's formula. A parameter every compass shares (``COMPASS_MOTCT``, ``CAL_MAG_COMP_TYP``) must have one
value, or the file is refused.
"""

from __future__ import annotations

from collections.abc import Sequence

from ..calibration import Calibration
from ..errors import TrimagInputError
from .export import Export, export_calibrations

__all__ = ["PARAMETER_TARGETS", "export_instances"]

#: The targets whose files hold several compasses' parameters.
PARAMETER_TARGETS = ("ardupilot", "px4", "qgc")


def export_instances(calibrations: Sequence[tuple[Calibration, int]], target: str) -> Export:
    """The parameters of every ``(calibration, compass number)`` (numbers from 1, as ``export --instance``) in one
    file of ``target`` (``"ardupilot"`` or ``"px4"``).

    Returns
    -------
    Export
        The joined text and parameters; the notes of each compass, prefixed with its number.

    Raises
    ------
    TrimagInputError
        Another target, no calibration, a compass number twice, a shared parameter with two values, or what a
        compass's own writer refuses (the firmware's limits).
    """
    if target not in PARAMETER_TARGETS:
        raise TrimagInputError("one file for several compasses is written for ardupilot or px4 (or qgc: PX4's in "
                               "QGroundControl's file); "
                               f"got {target!r}")
    if not calibrations:
        raise TrimagInputError("no calibration to write")
    numbers = [n for _, n in calibrations]
    if len(set(numbers)) != len(numbers):
        raise TrimagInputError(f"compass numbers given twice: {numbers}")
    return export_calibrations([(cal, number - 1) for cal, number in sorted(calibrations, key=lambda c: c[1])],
                               target)
