"""Writers of a calibration in a firmware's or tool's own parameters (``trimag export``; docs/autopilot.md).

trimag's calibration is ``c = W (r - b)`` (docs/conventions.md). Each target has its own convention:

- ArduPilot (``AP_Compass_Backend::correct_field``): ``m = M (s (r + ofs))``; ``COMPASS_OFSn_* = -b`` in mGauss,
  added; symmetric ``M`` from ``COMPASS_DIAn``/``ODIn``; ``COMPASS_SCALEn``.
- PX4 (``sensor_calibration::Magnetometer``): ``m = R (S ((r + p c) - off))``; ``CAL_MAGn_xOFF = b`` in gauss,
  subtracted; symmetric ``S`` from ``CAL_MAGn_xSCALE``/``xODIAG``.
- MATLAB ``magcal``: ``C = (D - b) A`` on rows ``D``: ``A = W'``, ``b``, in the data's unit.
- C header, JSON, ROS YAML: ``c = W (r - b)`` as trimag, in the data's unit.

Both autopilots take a *symmetric* matrix after the offset. Where ``W`` is not symmetric, its polar decomposition
``W = R P`` (``R`` a rotation, ``P`` symmetric positive definite) gives ``P``: the same corrected magnitude, without
the rotation ``R``. That is exact for magnitude-only (reference-free or scalar) calibrations, whose rotation is
arbitrary; a calibration fitted with attitudes (``interference12``) aligns axes, and dropping its rotation would
change the heading, so it is refused unless the rotation is below 0.1 degree.
"""

from __future__ import annotations

import datetime as _dt
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..errors import TrimagInputError
from ..units import convert

__all__ = ["EXPORT_TARGETS", "Export", "export_calibration", "symmetric_polar"]

EXPORT_TARGETS = ("ardupilot", "px4", "c-header", "json", "ros-yaml", "matlab")

#: ArduPilot's acceptance limits (libraries/AP_Compass/CompassCalibrator.cpp fit_acceptable, AP_Compass.h)
ARDUPILOT_LIMITS = {"offset_max_mG": 1800.0, "diag_min": 0.2, "diag_max": 5.0, "offdiag_max": 1.0,
                    "scale_min": 1 / 1.5, "scale_max": 1.5}
_ROTATION_TOLERANCE_DEG = 0.1


def symmetric_polar(W: NDArray[np.float64]) -> tuple[NDArray[np.float64], float]:
    """``P`` of the polar decomposition ``W = R P`` and the angle of ``R`` in degrees."""
    U, s, Vt = np.linalg.svd(W)
    P = Vt.T @ np.diag(s) @ Vt
    R = U @ Vt
    angle = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))
    return (P + P.T) / 2.0, angle


@dataclass
class Export:
    """A rendered export: the file text, the parameters, and notes for the user (limits, what was changed)."""

    target: str
    text: str
    parameters: dict[str, float] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    violations: list[str] = field(default_factory=list)


def _provenance(cal: Calibration) -> str:
    return (f"trimag {cal.trimag_version} calibration: model {cal.model}, method {cal.method}, unit {cal.units}, "
            f"created {cal.created or _dt.datetime.now(_dt.UTC).isoformat(timespec='seconds')}")


def _symmetric(cal: Calibration, target: str) -> tuple[NDArray[np.float64], list[str]]:
    W = np.asarray(cal.matrix)
    if np.linalg.det(W) <= 0:
        raise TrimagInputError("the calibration matrix has det <= 0 (a reflection): it cannot be exported")
    P, angle = symmetric_polar(W)
    notes = []
    if angle > 1e-9:
        if cal.model == "interference12" and angle > _ROTATION_TOLERANCE_DEG:
            raise TrimagInputError(
                f"{target} takes a symmetric matrix, but this {cal.model} calibration rotates the axes by "
                f"{angle:.2f} deg (it was fitted with attitudes): dropping the rotation would change the heading. "
                "Export it to c-header, json, ros-yaml or matlab, which keep the full matrix"
            )
        notes.append(f"the matrix is not symmetric: exported its symmetric polar factor (same corrected magnitude; "
                     f"drops a {angle:.3f} deg rotation that a magnitude calibration does not determine)")
    return P, notes


def _to_unit(cal: Calibration, value: NDArray[np.float64], unit: str) -> NDArray[np.float64]:
    if cal.units in ("unknown", "counts"):
        raise TrimagInputError(
            f"this calibration is in {cal.units!r}; the firmware needs {unit}: refit with the data's unit "
            "(units=nT, uT, G or mG)"
        )
    return np.asarray(value, dtype=np.float64) * convert(1.0, cal.units, unit)


def _param_file(params: dict[str, float], header: list[str]) -> str:
    lines = [f"# {h}" for h in header]
    lines += [f"{name},{value:.9g}" for name, value in sorted(params.items())]  # sorted, as MAGFit's files
    return "\n".join(lines) + "\n"


def _ardupilot(cal: Calibration, instance: int) -> Export:
    P, notes = _symmetric(cal, "ardupilot")
    b_mG = _to_unit(cal, cal.offset, "mG")
    n = "" if instance == 0 else str(instance + 1)
    scale = 1.0
    params = {f"COMPASS_OFS{n}_{a}": float(-v) for a, v in zip("XYZ", b_mG, strict=True)}
    params.update({f"COMPASS_DIA{n}_X": P[0, 0], f"COMPASS_DIA{n}_Y": P[1, 1], f"COMPASS_DIA{n}_Z": P[2, 2],
                   f"COMPASS_ODI{n}_X": P[0, 1], f"COMPASS_ODI{n}_Y": P[0, 2], f"COMPASS_ODI{n}_Z": P[1, 2],
                   f"COMPASS_SCALE{n}": scale})
    lim = ARDUPILOT_LIMITS
    violations = []
    if np.abs(b_mG).max() > lim["offset_max_mG"]:
        violations.append(f"offset {np.abs(b_mG).max():.0f} mG exceeds COMPASS_OFFS_MAX's default "
                          f"{lim['offset_max_mG']:.0f} mG: raise COMPASS_OFFS_MAX or move the compass away from iron")
    if np.any(np.diag(P) < lim["diag_min"]) or np.any(np.diag(P) > lim["diag_max"]):
        violations.append(f"a diagonal entry {np.round(np.diag(P), 3).tolist()} is outside ArduPilot's "
                          f"[{lim['diag_min']}, {lim['diag_max']}]")
    off = np.abs([P[0, 1], P[0, 2], P[1, 2]])
    if np.any(off >= lim["offdiag_max"]):
        violations.append(f"an off-diagonal entry {np.round(off, 3).tolist()} is not below {lim['offdiag_max']}")
    header = [_provenance(cal), f"ArduPilot compass {instance + 1}: m = M * (SCALE * (raw + OFS)), OFS in mGauss "
              "(AP_Compass_Backend::correct_field)"]
    return Export("ardupilot", _param_file(params, header), params, notes, violations)


def _px4(cal: Calibration, instance: int) -> Export:
    P, notes = _symmetric(cal, "px4")
    b_G = _to_unit(cal, cal.offset, "G")
    n = instance
    params = {f"CAL_MAG{n}_{a}OFF": float(v) for a, v in zip("XYZ", b_G, strict=True)}
    params.update({f"CAL_MAG{n}_XSCALE": P[0, 0], f"CAL_MAG{n}_YSCALE": P[1, 1], f"CAL_MAG{n}_ZSCALE": P[2, 2],
                   f"CAL_MAG{n}_XODIAG": P[0, 1], f"CAL_MAG{n}_YODIAG": P[0, 2], f"CAL_MAG{n}_ZODIAG": P[1, 2]})
    violations = []
    if np.any(np.diag(P) <= 0):
        violations.append("a scale is not positive")
    header = [_provenance(cal), f"PX4 magnetometer {n}: m = S * (raw - OFF), OFF in gauss "
              "(src/lib/sensor_calibration/Magnetometer.cpp); set CAL_MAG{n}_ID to the sensor's device id"]
    text = "\n".join(f"# {h}" for h in header) + "\n" + "".join(
        f"param set {k} {v:.9g}\n" for k, v in params.items())
    return Export("px4", text, params, notes, violations)


def _matrix_c(name: str, M: NDArray[np.float64]) -> str:
    rows = ",\n    ".join("{" + ", ".join(f"{v:.12g}f" for v in row) + "}" for row in M)
    return f"static const float {name}[3][3] = {{\n    {rows}\n}};\n"


def _c_header(cal: Calibration) -> Export:
    b = np.asarray(cal.offset)
    text = (
        f"/* {_provenance(cal)}\n * corrected = MAG_CAL_MATRIX * (raw - MAG_CAL_OFFSET), unit {cal.units} */\n"
        "#ifndef TRIMAG_MAG_CAL_H\n#define TRIMAG_MAG_CAL_H\n"
        f"#define MAG_CAL_UNIT \"{cal.units}\"\n"
        f"static const float MAG_CAL_OFFSET[3] = {{{', '.join(f'{v:.12g}f' for v in b)}}};\n"
        + _matrix_c("MAG_CAL_MATRIX", np.asarray(cal.matrix))
        + "#endif /* TRIMAG_MAG_CAL_H */\n"
    )
    return Export("c-header", text)


def _plain(cal: Calibration) -> dict[str, Any]:
    return {"convention": "corrected = matrix @ (raw - offset)", "unit": cal.units,
            "offset": np.asarray(cal.offset).tolist(), "matrix": np.asarray(cal.matrix).tolist(),
            "provenance": _provenance(cal)}


def _json(cal: Calibration) -> Export:
    return Export("json", json.dumps(_plain(cal), indent=2) + "\n")


def _ros_yaml(cal: Calibration) -> Export:
    d = _plain(cal)
    M = d["matrix"]
    text = (
        f"# {d['provenance']}\n# corrected = matrix * (raw - offset); ROS sensor_msgs/MagneticField is in tesla\n"
        "magnetometer_calibration:\n"
        f"  unit: {cal.units}\n"
        f"  offset: [{', '.join(f'{v:.12g}' for v in d['offset'])}]\n"
        f"  matrix: [{', '.join(f'{v:.12g}' for row in M for v in row)}]  # row-major 3x3\n"
    )
    return Export("ros-yaml", text)


def _matlab(cal: Calibration) -> Export:
    A = np.asarray(cal.matrix).T
    b = np.asarray(cal.offset)
    fmt = ";\n     ".join(" ".join(f"{v:.15g}" for v in row) for row in A)
    text = (f"% {_provenance(cal)}\n% MATLAB magcal convention: C = (D - b) * A, D an N x 3 array of rows\n"
            f"A = [{fmt}];\nb = [{' '.join(f'{v:.15g}' for v in b)}];\n")
    return Export("matlab", text)


def export_calibration(cal: Calibration, target: str, *, instance: int = 0) -> Export:
    """Render ``cal`` for ``target`` (one of :data:`EXPORT_TARGETS`); ``instance`` is 0-based."""
    if target not in EXPORT_TARGETS:
        raise TrimagInputError(f"unknown export target {target!r}; choose one of {', '.join(EXPORT_TARGETS)}")
    if instance < 0 or instance > 7:
        raise TrimagInputError(f"instance must be 0..7; got {instance}")
    if cal.regressors is not None:
        eddy = cal.regressors.get("eddy")
        logged = len(cal.regressors["names"]) - (len(eddy["names"]) if eddy else 0)
        fix = " and ".join(x for x in ("`regressors`" if logged else "", "`option eddy`" if eddy else "") if x)
        raise TrimagInputError(
            f"this calibration has regressor terms ({', '.join(cal.regressors['names'])}) that the {target} format "
            f"cannot hold (a constant offset only); export a fit without {fix}"
        )
    if target == "ardupilot":
        if instance > 2:
            raise TrimagInputError("ArduPilot calibrates compasses 0..2 (COMPASS_OFS, OFS2, OFS3)")
        exp = _ardupilot(cal, instance)
        board = (cal.diagnostics.get("alignment") or {}).get("board_rotation")
        if board is not None:  # the alignment of fit --accel-columns: said, not written (docs/vehicle.md)
            exp.notes.append(
                f"the calibration's alignment is nearest to {board['name']} (COMPASS_ORIENT = {board['number']}) "
                f"with {board['remaining_angle_deg']:.2f} deg remaining; COMPASS_ORIENT is not written: set it "
                "yourself for an external compass"
            )
        return exp
    if target == "px4":
        return _px4(cal, instance)
    return {"c-header": _c_header, "json": _json, "ros-yaml": _ros_yaml, "matlab": _matlab}[target](cal)


def write_export(exp: Export, out: str | Path) -> Path:
    """Write the export atomically (``.mat`` for the MATLAB target writes a MAT file with A and b)."""
    from .atomic import atomic_write_text

    return atomic_write_text(out, exp.text)
