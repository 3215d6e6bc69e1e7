"""The heading check of a heading-free firmware fit (:mod:`trimag.vehicle.firmware`): what the new parameters do to
the compass's heading against the attitude's own yaw.

A heading-free fit (``fit_firmware(..., heading_free=tilt)``: the logged yaw is an EKF's that fused this very
compass) is fitted to the field's horizontal magnitude and vertical component under the logged roll and pitch; the
direction of the horizontal field, the heading, does not enter it. On a log that barely turned, the offsets can
then move the corrected field around the horizontal circle without changing that residual: a real ArduCopter log
(yaw only 347-355 deg) got 680 mGauss of offsets that turned its second compass's heading 53 deg from the first's,
written without a word. The logged yaw is not the truth (the EKF took it partly from this compass, with the log's
calibration), but it is the vehicle's own estimate: a fit that turns the heading far from it, when the log's
calibration stays close, is not shown to be right.

Both calibrations' corrected fields (the firmware's formula,
:meth:`~trimag.models.firmware.FirmwareCompass.correct`) and the reference field ``h`` (the Earth's field rotated
into the body frame by the logged attitude, yaw included) are turned into the level frame by each sample's roll and
pitch; the heading error is the angle from ``h``'s horizontal component to the corrected field's, as a compass
heading (clockwise from north: ``atan2(-y, x)`` of the level-frame field, the tilt-compensated heading of
:func:`trimag.vehicle.heading.tilt_compensated_heading`), wrapped into [-180, 180).

The rule (:func:`heading_decision`): the fit's RMS heading error more than :data:`WARN_EXCESS_DEG` above the log's
calibration's (and above :data:`WARN_MIN_DEG`) is a warning; more than :data:`REFUSE_EXCESS_DEG` above it is
refused under ``level="auto"`` (keep the log's calibration, exit 3) and a warning for a level asked for; a log that
barely turned (the field within ``MIN_CONE_DEG`` of :mod:`trimag.vehicle.firmware`) is refused from the warning on.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..models.firmware import FirmwareCompass, rotation_matrix
from .heading import heading_difference

__all__ = ["REFUSE_EXCESS_DEG", "WARN_EXCESS_DEG", "WARN_MIN_DEG", "heading_check", "heading_decision"]

#: The fit's RMS heading error above the log's calibration's by more than this (degrees): a warning.
WARN_EXCESS_DEG = 10.0
#: ... and only when the fit's RMS heading error exceeds this (degrees): a few degrees apart is the EKF's own spread.
WARN_MIN_DEG = 15.0
#: The fit's RMS heading error above the log's calibration's by more than this (degrees): refused (level auto).
REFUSE_EXCESS_DEG = 30.0


def _heading_error_deg(compass: FirmwareCompass, sensor: NDArray[np.float64], field: NDArray[np.float64],
                       motors: Mapping[str, NDArray[np.float64]], tilt: NDArray[np.float64]) -> NDArray[np.float64]:
    """Heading (degrees, compass convention) of ``compass``'s corrected field minus that of ``field``, per sample,
    both in the level frame of ``tilt`` (N, 3, 3, body -> level)."""
    x = motors.get(compass.motor_type) if compass.motor_type else None
    B = compass.correct(sensor, x)
    L = np.einsum("nij,nj->ni", tilt, B)
    H = np.einsum("nij,nj->ni", tilt, field)
    return heading_difference(np.degrees(np.arctan2(-L[:, 1], L[:, 0])), np.degrees(np.arctan2(-H[:, 1], H[:, 0])))


def heading_check(fitted: FirmwareCompass, held: FirmwareCompass, raw: NDArray[np.float64],
                  field: NDArray[np.float64], motors: Mapping[str, NDArray[np.float64]], tilt: NDArray[np.float64],
                  applied: int | None) -> dict[str, Any]:
    """The heading error against the logged yaw of the log's calibration and of the fit, on the samples fitted.

    Parameters
    ----------
    fitted, held : FirmwareCompass
        The fit's parameters and the calibration in force in the log.
    raw : ndarray, shape (N, 3)
        The readings as the fit received them (rotated by ``applied``), firmware unit.
    field : ndarray, shape (N, 3)
        The body-frame reference field (rotated by the logged attitude, yaw included), firmware unit.
    motors : mapping
        The motor channels (``"current"``, ``"throttle"``: (N,)).
    tilt : ndarray, shape (N, 3, 3)
        Each sample's roll-and-pitch rotation (body -> level frame).
    applied : int or None
        The rotation already applied to ``raw`` (the firmware's enum value), None for the sensor's frame.

    Returns
    -------
    dict
        ``rms_before_deg``/``mean_before_deg`` (the log's calibration), ``rms_after_deg``/``mean_after_deg`` (the
        fit), ``change_deg`` (after minus before, RMS), ``n_samples``, ``against`` (what the yaw is).
    """
    R0 = np.eye(3) if applied is None else rotation_matrix(held.target, applied)
    sensor = raw @ R0  # the raw readings in the sensor's own frame (the firmware's formula rotates them)
    before = _heading_error_deg(held, sensor, field, motors, tilt)
    after = _heading_error_deg(fitted, sensor, field, motors, tilt)
    out: dict[str, Any] = {"against": "the logged yaw (an EKF's, which used this compass)", "n_samples": len(raw)}
    for name, e in (("before", before), ("after", after)):
        out[f"rms_{name}_deg"] = float(np.sqrt(np.mean(e**2)))
        out[f"mean_{name}_deg"] = float(np.mean(e))
    out["change_deg"] = out["rms_after_deg"] - out["rms_before_deg"]
    out.update(warn_excess_deg=WARN_EXCESS_DEG, warn_min_deg=WARN_MIN_DEG, refuse_excess_deg=REFUSE_EXCESS_DEG)
    return out


def heading_decision(check: dict[str, Any], level: str, barely_turned: bool = False
                     ) -> tuple[list[str], str | None]:
    """``(messages, refusal)``: the info line (always), a warning where the fit turns the heading (module
    docstring's rule), and the refusal text under ``level="auto"`` beyond :data:`REFUSE_EXCESS_DEG` (else None);
    beyond the warning already when the log ``barely_turned`` (the field's direction within a narrow cone: the
    heading-free fit then has no information on the heading at all).
    ``check["decision"]`` is set to ``"ok"``, ``"warned"`` or ``"refused"``."""
    b, a = check["rms_before_deg"], check["rms_after_deg"]
    info = (f"heading against the logged yaw (EKF, which used this compass): RMS {b:.1f} deg (mean "
            f"{check['mean_before_deg']:+.1f}) with the log's calibration -> RMS {a:.1f} (mean "
            f"{check['mean_after_deg']:+.1f}) with this fit")
    excess = a - b
    if excess <= WARN_EXCESS_DEG or a <= WARN_MIN_DEG:
        check["decision"] = "ok"
        return [info], None
    text = (f"the heading-free fit cannot see the heading (the logged yaw is the EKF's, which used this compass): "
            f"this fit turns the compass's heading {abs(check['mean_after_deg']):.0f} deg (mean; RMS {a:.1f}) from "
            f"the vehicle's own estimate, against {abs(check['mean_before_deg']):.0f} (RMS {b:.1f}) with the log's "
            "calibration; fit a flight with a yaw independent of this compass (a GPS "
            "heading, or ArduPilot 4.1+ with XKY0 logged: the EKF-GSF yaw) so the vector can be fitted, or record a "
            "calibration turn through all headings")
    if (excess > REFUSE_EXCESS_DEG or barely_turned) and level == "auto":
        check["decision"] = "refused"
        why = "; the vehicle barely turned, so nothing in the log supports the change" if barely_turned else ""
        return [info], f"{text}{why}; keep the log's calibration"
    check["decision"] = "warned"
    return [info, f"warning: {text}"], None
