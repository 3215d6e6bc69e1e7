"""The lines ``trimag fit --accel-columns`` prints about the magnetometer-to-accelerometer alignment."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..fields.reference import igrf, parse_igrf_spec


def dip_check(dip_deg: float, igrf_spec: str) -> str:
    """The fitted dip against IGRF's at the site, as a line; a warning when the signs differ (an accelerometer
    that reads gravity instead of specific force, or a flipped axis)."""
    expected = igrf(*parse_igrf_spec(igrf_spec)).inclination_deg
    if dip_deg * expected < 0 and abs(expected) > 5.0:
        return (f"warning: the fitted dip {dip_deg:.2f} deg has the opposite sign of IGRF's {expected:.2f} deg here: "
                "the accelerometer columns may read gravity (+g down at rest) instead of specific force (-g), or "
                "have a flipped axis; negate them (the heading would be mirrored)")
    return f"dip {dip_deg:.3f} deg against IGRF's {expected:.3f} deg here (difference {dip_deg - expected:+.3f} deg)"


def alignment_lines(alignment: dict[str, Any]) -> list[str]:
    """The text lines ``trimag fit --accel-columns`` prints about the alignment."""
    board = alignment["board_rotation"]
    yaw, pitch, roll = alignment["euler_zyx_deg"]
    sensor = alignment["sensor_euler_zyx_deg"]
    sx, sy, sz = alignment["rotation_std_deg"]
    note = ("" if alignment["calibration_uncertainty_propagated"]
            else " (the calibration's own uncertainty not included)")
    lines = [
        f"alignment, corrected magnetometer -> accelerometer, from {alignment['n_used']} samples"
        + (f" ({alignment['n_dropped_accelerating']} accelerating samples dropped)"
           if alignment["n_dropped_accelerating"] else "")
        + f": yaw {yaw:.3f}, pitch {pitch:.3f}, roll {roll:.3f} deg (Z-Y-X); 1 sigma about x, y, z "
          f"{sx:.2g}, {sy:.2g}, {sz:.2g} deg{note}",
        f"dip (inclination) {alignment['dip_deg']:.3f} +- {alignment['dip_std_deg']:.2g} deg; RMS of the "
        f"field-gravity angle residual {alignment['rms_residual_deg']:.3g} deg; heading error of a level vehicle "
        f"from the alignment's uncertainty {alignment['heading_sigma_deg']['rms_deg']:.2g} deg RMS over headings "
        "(1 sigma)",
        f"sensor axes -> accelerometer (symmetric soft iron): yaw {sensor[0]:.3f}, pitch {sensor[1]:.3f}, roll "
        f"{sensor[2]:.3f} deg; nearest board rotation {board['name']} (COMPASS_ORIENT = {board['number']}), "
        "remaining rotation "
        f"{board['remaining_angle_deg']:.3f} deg (rotation vector {np.round(board['remaining_rotvec_deg'], 3).tolist()}"
        " deg, body frame)",
    ]
    if alignment.get("warning"):
        lines.append(f"warning: alignment: {alignment['warning']}")
    return lines

