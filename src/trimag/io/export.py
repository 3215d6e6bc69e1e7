"""Writers of a calibration in a firmware's or tool's own parameters (``trimag export``; docs/autopilot.md).

trimag's calibration is ``c = W (r - b - sum_j k_j (u_j - mean_j))`` (docs/conventions.md). Each target has its own
convention:

- ArduPilot (``AP_Compass_Backend::rotate_field``, ``correct_field``): ``m = M (s (R r + ofs)) + MOT x``;
  ``COMPASS_ORIENTn``, ``COMPASS_OFSn_*`` in mGauss (added), symmetric ``M`` from ``COMPASS_DIAn``/``ODIn``,
  ``COMPASS_SCALEn``, ``COMPASS_MOTn_*`` with ``COMPASS_MOTCT`` (1 throttle, 2 current).
- PX4 (``sensor_calibration::Magnetometer::Correct``): ``m = R (S ((r + p COMP) - off))``; ``CAL_MAGn_ROT``,
  ``CAL_MAGn_xOFF`` in gauss (subtracted), symmetric ``S`` from ``CAL_MAGn_xSCALE``/``xODIAG``, ``CAL_MAGn_xCOMP``
  with ``CAL_MAG_COMP_TYP`` (1 thrust, 2 current in kA).
- QGroundControl (``qgc``): PX4's parameters in the file QGroundControl's "Load from file" reads
  (``ParameterManager::loadFromStream``): ``# Vehicle-Id Component-Id Name Value Type`` then one tab-separated line
  per parameter, vehicle 1, component 1, the ``MAV_PARAM_TYPE`` (6 INT32, 9 REAL32), with ``CAL_MAGn_ID`` the
  device id of the log's magnetometer the calibration was fitted to (PX4 applies a slot only to the device it names).
- MATLAB ``magcal``: ``C = (D - b) A`` on rows ``D``: ``A = W'``, ``b``, in the data's unit (a ``.m`` text, or a MAT
  file when the output ends in ``.mat``).
- C header, JSON, ROS YAML: ``c = W (r - b)`` as trimag, in the data's unit.

The autopilot parameters are those of :mod:`trimag.models.firmware`: a firmware-space fit (``fit --target``) is
written exactly as fitted; any other calibration is converted (:func:`~trimag.models.firmware.compass_from_affine`):
a calibration fitted with attitudes determines its rotation (written as the nearest standard orientation, the rest
left to the symmetric matrix up to 5 degrees, refused beyond), a magnitude-only one does not (its symmetric polar
factor is written: the same corrected magnitude); current and throttle regressor terms become the motor term. The
exact writers are checked by putting their parameters through the firmware's formula against ``Calibration.apply``
before anything is written. What the firmware cannot load (its limits, a rotation, a term or a unit it does not
have) is refused (:class:`~trimag.errors.TrimagInputError`, exit 2), naming the parameter and the limit.

Outputs carry numbers, not text from the calibration file: the provenance line is built from validated fields
only (the registered model, a method and version of the expected form, the ISO date), so nothing in a calibration
file can add a line, a parameter or a comment terminator to an output.
"""

from __future__ import annotations

import datetime as _dt
import json
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..errors import TrimagInputError
from ..models.firmware import (
    FirmwareCompass,
    compass_from_affine,
    firmware_class,
    nearest_rotation,
    rotation_matrix,
    without_features,
)
from ..units import convert

__all__ = ["EXPORT_TARGETS", "Export", "export_calibration", "export_calibrations", "firmware_compass",
           "keep_firmware_record", "symmetric_polar", "write_export"]

EXPORT_TARGETS = ("ardupilot", "px4", "qgc", "c-header", "json", "ros-yaml", "matlab")

#: ArduPilot's acceptance limits (libraries/AP_Compass/CompassCalibrator.cpp fit_acceptable, AP_Compass.h);
#: the checks themselves are :meth:`trimag.models.firmware.ArduPilotCompass.violations`.
ARDUPILOT_LIMITS = {"offset_max_mG": 1800.0, "diag_min": 0.2, "diag_max": 5.0, "offdiag_max": 1.0,
                    "scale_min": 1 / 1.5, "scale_max": 1.5}
_MAX_INSTANCE = {"ardupilot": 2, "px4": 3}  # COMPASS_OFS..OFS3; CAL_MAG0..3 (max_num_sensor_instances)
_CURRENT = re.compile(r"(^|[^a-z])(current|curr|amps?)([^a-z]|$)", re.IGNORECASE)
_THROTTLE = re.compile(r"(^|[^a-z])(throttle|thr|tho|thrust)([^a-z]|$)", re.IGNORECASE)


def symmetric_polar(W: NDArray[np.float64]) -> tuple[NDArray[np.float64], float]:
    """``P`` of the polar decomposition ``W = R P`` and the angle of ``R`` in degrees."""
    U, s, Vt = np.linalg.svd(W)
    P = Vt.T @ np.diag(s) @ Vt
    R = U @ Vt
    angle = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))
    return (P + P.T) / 2.0, angle


@dataclass
class Export:
    """A rendered export: the file text, the parameters, and notes for the user (what the conversion did).

    ``violations`` is kept for compatibility and is always empty: what the firmware cannot load is refused.
    ``arrays`` holds what a binary output (a MAT file) stores.
    """

    target: str
    text: str
    parameters: dict[str, float] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    violations: list[str] = field(default_factory=list)
    arrays: dict[str, Any] = field(default_factory=dict)


# ------------------------------------------------------------------ numbers only (issue 33 item 3)
_VERSION = re.compile(r"^[0-9]+(\.[0-9A-Za-z+]+){0,4}$")
_METHOD = re.compile(r"^[A-Za-z0-9_.:+-]{1,40}( [A-Za-z0-9_.:+-]{1,40}){0,4}$")


def _provenance(cal: Calibration) -> str:
    """One line from validated fields only (never free text of the file)."""
    version = cal.trimag_version if _VERSION.fullmatch(cal.trimag_version or "") else "(unknown version)"
    method = cal.method if _METHOD.fullmatch(cal.method or "") else "(not shown)"
    try:
        created = _dt.datetime.fromisoformat(cal.created).isoformat(timespec="seconds")
    except (TypeError, ValueError):
        created = "(date not shown)"
    return (f"trimag {version} calibration: model {cal.model}, method {method}, unit {cal.units}, "
            f"created {created}")


def _comment_lines(lines: Sequence[str], mark: str) -> str:
    """Comment lines of printable ASCII only (a stray line break, escape or comment terminator cannot get out)."""
    out = []
    for line in lines:
        clean = re.sub(r"[^\x20-\x7e]", " ", line).replace("*/", "* /").replace("/*", "/ *")
        out.append(f"{mark} {clean}".rstrip())
    return "\n".join(out) + "\n"


# ------------------------------------------------------------------ the autopilots
def _unit_factor(cal: Calibration, unit: str) -> float:
    if cal.units in ("unknown", "counts"):
        held = "is in counts" if cal.units == "counts" else "has no unit (it was fitted without `units`)"
        raise TrimagInputError(
            f"this calibration {held}; the firmware needs {unit}: refit with the data's unit "
            "(`units=nT`, uT, G or mG)"
        )
    return float(convert(1.0, cal.units, unit))


def _motor_term(cal: Calibration, target: str, factor: float) -> tuple[NDArray[np.float64], tuple[Any, str] | None]:
    """The offset at zero motor power and the motor term ``(m_body, kind)`` of the calibration's regressors (firmware
    unit); a regressor the firmware has no term for is refused."""
    b = np.asarray(cal.offset, dtype=np.float64)
    terms = cal.regressors
    if terms is None:
        return b * factor, None
    names = list(terms["names"])
    units = list(terms.get("units") or [""] * len(names))
    eddy = set((terms.get("eddy") or {}).get("names", []))
    kinds = ["current" if _CURRENT.search(n) else ("throttle" if _THROTTLE.search(n) else None) for n in names]
    other = [n for n, k in zip(names, kinds, strict=True) if k is None or n in eddy]
    if other:
        fix = "`option eddy`" if set(other) & eddy else "`regressors`"
        raise TrimagInputError(
            f"this calibration has regressor terms ({', '.join(names)}) that {target} cannot hold (one motor term on "
            f"the battery current or the throttle, no {', '.join(other)} term); export a fit without {fix}"
        )
    if len(names) > 1:
        raise TrimagInputError(f"this calibration has {len(names)} motor terms ({', '.join(names)}); {target} holds "
                               "one (COMPASS_MOTCT / CAL_MAG_COMP_TYP picks current or throttle): fit with one")
    k = np.asarray(terms["coefficients"], dtype=np.float64)[0]
    mean = float(terms["means"][0])
    W = np.asarray(cal.matrix)
    per_unit = 1.0
    if kinds[0] == "throttle":
        if "%" in str(units[0]):
            per_unit = 100.0  # per percent -> per unit throttle
        elif abs(mean) > 1.5:
            raise TrimagInputError(
                f"the throttle term's channel {names[0]!r} has no stated unit and a mean of {mean:.3g}: the firmware's "
                "throttle runs 0..1; refit with a 0..1 throttle column"
            )
    b_zero = b - k * mean  # W (v - b - k (x - mean)) = W (v - b_zero) - W k x
    return b_zero * factor, (-(W @ k) * factor * per_unit, str(kinds[0]))


def _input_orientation(cal: Calibration, target: str) -> int | None:
    """The rotation the calibration's input readings carry, in ``target``'s enum: the same rotation when the log
    was the other firmware's (the enums share 0..40 but for 38; one ``target`` lacks is refused)."""
    given = cal.diagnostics.get("input_orientation") or {}
    fw = cal.diagnostics.get("firmware") or {}
    source, value = None, None
    if isinstance(given, dict) and given.get("value") is not None:
        source, value = given.get("target"), int(given["value"])
    elif isinstance(fw, dict) and fw.get("input_orientation") is not None:
        source, value = fw.get("target"), int(fw["input_orientation"])
    if value is None or source not in ("ardupilot", "px4"):
        return None
    if source == target:
        return value
    same, angle = nearest_rotation(target, rotation_matrix(str(source), value))
    if angle > 1e-3:
        raise TrimagInputError(f"the readings this calibration was fitted to carry {source}'s sensor rotation "
                               f"{value}, which {target} has not (nearest: {same}, {angle:.2f} deg off): export it "
                               f"--to {source}")
    return same


def firmware_compass(cal: Calibration, target: str) -> tuple[FirmwareCompass, list[str], bool, float | None]:
    """The parameters ``target`` loads for ``cal``: ``(compass, notes, write_orientation, offsets_max)``."""
    klass = firmware_class(target)
    factor = _unit_factor(cal, klass.unit)
    fw = cal.diagnostics.get("firmware")
    rotated = cal.diagnostics.get("readings_rotated")
    if rotated:  # an old PX4 log's readings carry CAL_MAGn_ROT already (app._firmware)
        raise TrimagInputError(f"cannot write {target}'s parameters: {rotated}")
    if isinstance(fw, dict) and fw.get("target") == target:
        compass = FirmwareCompass.from_dict(fw)
        _check_formula(cal, compass, _input_orientation(cal, target), factor)
        note = f"the {fw.get('level')} level of the {target} fit (fit --target), written as fitted"
        if fw.get("offsets_refitted"):
            note += f", its offsets refitted by a {fw['offsets_refitted']}"
        return compass, [note], True, fw.get("offsets_max")
    b, motor = _motor_term(cal, target, factor)
    applied = _input_orientation(cal, target)
    # the rotation is determined by a fit with attitudes: a vector model, or the other firmware's fit whose
    # orientation was decided against the attitudes (vector or heading-free residual)
    determined = cal.model == "interference12" or (isinstance(fw, dict) and (
        fw.get("residual") == "vector" or (fw.get("target") in ("ardupilot", "px4")
                                           and fw.get("residual") in ("vector", "heading-free"))))
    compass, notes = compass_from_affine(target, cal.matrix, b, motor=motor, input_orientation=applied,
                                         rotation_determined=determined)
    if determined or applied is not None:
        if not notes:
            _check_formula(cal, compass, applied, factor)
        return compass, notes, True, None
    board = (cal.diagnostics.get("alignment") or {}).get("board_rotation")
    if board is not None and target == "ardupilot":  # the alignment of fit --accel-columns: said, not written
        notes.append(
            f"the calibration's alignment is nearest to {board['name']} (COMPASS_ORIENT = {board['number']}) "
            f"with {board['remaining_angle_deg']:.2f} deg remaining; COMPASS_ORIENT is not written: set it "
            "yourself for an external compass"
        )
    return compass, notes, False, None


#: What a calibration records of the firmware and frame it was fitted in, kept by a quick recalibration (``--prior``).
FRAME_RECORDS = ("firmware", "input_orientation", "readings_rotated", "alignment")


def keep_firmware_record(prior: Calibration, cal: Calibration) -> Calibration:
    """``cal``, a quick recalibration of ``prior`` (its matrix and regressor terms kept, its offset refitted), with
    what ``prior`` records of its firmware and frame (:data:`FRAME_RECORDS`): the orientation, the firmware fit's
    level and motor term, with the firmware's offsets recomputed so that its formula gives ``cal.apply``; the
    parameters named in ``cal.params`` follow. Refused (:class:`TrimagInputError`) when the firmware's parameters
    cannot hold the new calibration."""
    import dataclasses

    kept = {k: prior.diagnostics[k] for k in FRAME_RECORDS if k in prior.diagnostics and k not in cal.diagnostics}
    fw = kept.get("firmware")
    params = dict(cal.params)
    if isinstance(fw, dict) and fw.get("target") in ("ardupilot", "px4"):
        target = str(fw["target"])
        compass = FirmwareCompass.from_dict(fw)
        factor = _unit_factor(cal, compass.unit)
        applied = _input_orientation(prior, target)
        R0 = np.eye(3) if applied is None else rotation_matrix(target, applied)
        v = np.zeros((1, 3))
        x = np.zeros(1)
        terms = {cal.regressors["names"][0]: x} if cal.regressors is not None else None
        wanted = cal.apply(v, regressors=terms)[0] * factor

        def corrected(offsets: NDArray[np.float64]) -> NDArray[np.float64]:
            moved = dataclasses.replace(compass, offsets=offsets)
            return moved.correct((v * factor) @ R0, x if compass.motor_type else None)[0]

        c0 = corrected(np.zeros(3))  # the formula is affine in the offsets
        J = np.column_stack([corrected(e) - c0 for e in np.eye(3)])
        compass = dataclasses.replace(compass, offsets=np.linalg.solve(J, wanted - c0))
        shown = dataclasses.replace(cal, diagnostics={**cal.diagnostics, **kept})
        try:
            _check_formula(shown, compass, applied, factor)
        except RuntimeError:
            raise TrimagInputError(
                f"the prior calibration's {target} parameters cannot hold the refitted offset (its matrix or motor "
                "term is not the one kept): refit the full calibration instead of `prior`") from None
        kept["firmware"] = {**fw, **compass.as_dict(), "offsets_refitted": "quick recalibration (prior)"}
        params.update({k: v for k, v in compass.parameters(0).items() if k in params})
    return dataclasses.replace(cal, diagnostics={**cal.diagnostics, **kept}, params=params)


def _check_formula(cal: Calibration, compass: FirmwareCompass, applied: int | None, factor: float) -> None:
    """The parameters through the firmware's own formula give ``Calibration.apply`` (a writer's bug otherwise)."""
    rng = np.random.default_rng(0)
    v = rng.normal(size=(20, 3)) * 500.0 / factor
    x = rng.uniform(0.0, 1.0, 20)
    terms = {cal.regressors["names"][0]: x} if cal.regressors is not None else None
    expected = cal.apply(v, regressors=terms) * factor
    R0 = np.eye(3) if applied is None else rotation_matrix(compass.target, applied)
    got = compass.correct((v * factor) @ R0, x if compass.motor_type else None)
    if not np.allclose(got, expected, rtol=1e-6, atol=1e-6 * float(np.abs(expected).max())):
        raise RuntimeError(f"the {compass.target} parameters do not reproduce the calibration through the firmware's "
                           "formula: please report this bug")


def export_calibrations(items: Sequence[tuple[Calibration, int]], target: str) -> Export:
    """One autopilot parameter file for several magnetometers: ``items`` are ``(calibration, instance)`` pairs
    (instance 0-based). The firmware-wide motor-term type (``COMPASS_MOTCT``, ``CAL_MAG_COMP_TYP``) must agree."""
    if target == "qgc":
        return _qgc(items)
    if target not in ("ardupilot", "px4"):
        raise TrimagInputError(f"several magnetometers go into one file for ardupilot, px4 or qgc only; got "
                               f"{target!r}")
    if not items:
        raise TrimagInputError("give at least one calibration to export")
    params: dict[str, float] = {}
    notes: list[str] = []
    header: list[str] = []
    seen: set[int] = set()
    global_name = "COMPASS_MOTCT" if target == "ardupilot" else "CAL_MAG_COMP_TYP"
    for cal, instance in items:
        if instance in seen:
            raise TrimagInputError(f"instance {instance + 1} twice in one export: give each magnetometer once")
        seen.add(instance)
        if not 0 <= instance <= _MAX_INSTANCE[target]:
            raise TrimagInputError("ArduPilot calibrates compasses 1..3 (COMPASS_OFS, OFS2, OFS3)" if target ==
                                   "ardupilot" else "PX4 calibrates magnetometers CAL_MAG0..3 (instance 1..4)")
        compass, more, write_orientation, offsets_max = firmware_compass(cal, target)
        bad = compass.violations(instance=instance, offsets_max=offsets_max)
        if bad:
            raise TrimagInputError(f"{target} cannot load this calibration (nothing written): "
                                   + "; ".join(str(v) for v in bad))
        p = _present(compass.parameters(instance), cal, target)
        p, dropped = _without_absent(p, cal, target, instance, compass)
        more = [*more, *dropped]
        if not write_orientation:
            p = {k: v for k, v in p.items() if not k.endswith(("ORIENT", "_ROT")) and "ORIENT" not in k}
        elif _internal(cal):
            p, note = _internal_orientation(p, compass, instance)
            more = [*more, note]
        if global_name in p and global_name in params and params[global_name] != p[global_name]:
            raise TrimagInputError(f"{global_name} is one for all magnetometers: these calibrations have a current "
                                   "term and a throttle term; fit them with the same motor channel")
        params.update(p)
        notes += [f"instance {instance + 1}: {n}" if len(items) > 1 else n for n in more]
        header += [_provenance(cal), _formula_line(compass, instance)]
        if compass.motor_type is not None:
            note = (f"{global_name} = {p[global_name]:g} applies to every magnetometer: the others keep their motor "
                    f"terms, now read as {compass.motor_type}" if len(items) == 1 else
                    f"{global_name} = {p[global_name]:g} applies to every magnetometer: each motor term in this file "
                    f"is per {compass.motor_type}, and any magnetometer not in it keeps its own, now read so")
            if note not in notes:
                notes.append(note)
        elif not write_orientation and cal.method == "gyro":  # (its alignment is the gyroscope's, not the matrix's)
            notes.append("the orientation is not written (the gyro-aided fit's rotation to the gyroscope, "
                         "diagnostics.gyro_alignment, with its nearest board rotation printed by trimag fit, is not "
                         "exported): the firmware keeps its own")
        elif not write_orientation:
            notes.append("the orientation is not written (a magnitude-only calibration does not determine it): "
                         "the firmware keeps its own")
    text = (_param_file(params, header) if target == "ardupilot" else
            _comment_lines(header, "#") + "".join(f"param set {k} {v:.9g}\n" for k, v in params.items()))
    return Export(target, text, params, notes)


#: PX4's integer parameters among those written (``MAV_PARAM_TYPE_INT32``); every other one is a float (REAL32).
_PX4_INTEGERS = re.compile(r"^CAL_MAG([0-9]_(ID|ROT|PRIO)|_COMP_TYP)$")
#: MAVLink's MAV_PARAM_TYPE of a QGroundControl parameter file's last column.
_MAV_PARAM_TYPE_INT32, _MAV_PARAM_TYPE_REAL32 = 6, 9


def device_id(cal: Calibration) -> int | None:
    """The device id of the log's magnetometer ``cal`` was fitted to (its sensor record; ``diagnostics["log_compass"]``
    in a file of an earlier trimag), or None."""
    if cal.sensor is not None and cal.sensor.device_id is not None:
        value: Any = cal.sensor.device_id
    else:
        record = cal.diagnostics.get("log_compass")
        value = record.get("device_id") if isinstance(record, dict) else None
    return int(value) if isinstance(value, int | float) and not isinstance(value, bool) and value > 0 else None


def _qgc(items: Sequence[tuple[Calibration, int]]) -> Export:
    """PX4's parameters of ``items`` as QGroundControl's parameter file, each slot's ``CAL_MAGn_ID`` the device id
    of the magnetometer it was fitted to (a calibration without one is written without it, and said)."""
    px4 = export_calibrations(items, "px4")
    params = dict(px4.parameters)
    notes = list(px4.notes)
    for cal, instance in items:
        dev = device_id(cal)
        if dev is not None:
            params[f"CAL_MAG{instance}_ID"] = float(dev)
        else:
            notes.append(f"CAL_MAG{instance}_ID not written: the calibration does not record its magnetometer's "
                         "device id (fitted to a table, or to a log without it); PX4 applies the slot only to the "
                         "device it names: set it yourself")
    written = [instance for cal, instance in items if device_id(cal) is not None]
    comments = [line[2:] for line in px4.text.splitlines() if line.startswith("# ")]
    comments = [re.sub(r"; set CAL_MAG(\d)_ID to the sensor's device id$",
                       lambda m: "" if int(m.group(1)) in written else m.group(0), line) for line in comments]
    header = ["Onboard parameters for Vehicle 1", "", *comments, "", "Vehicle-Id Component-Id Name Value Type"]
    lines = []
    for name, value in sorted(params.items()):
        integer = bool(_PX4_INTEGERS.match(name))
        text = f"{int(value)}" if integer else f"{value:.9g}"
        kind = _MAV_PARAM_TYPE_INT32 if integer else _MAV_PARAM_TYPE_REAL32
        lines.append(f"1\t1\t{name}\t{text}\t{kind}")
    return Export("qgc", _comment_lines(header, "#") + "\n".join(lines) + "\n", params, notes)


def _present(p: dict[str, float], cal: Calibration, target: str) -> dict[str, float]:
    """``p`` without the parameters the log's firmware lacks (``diagnostics["firmware"]["absent"]``: the fit held
    them at the firmware's neutral values, so the correction is the same without them)."""
    fw = cal.diagnostics.get("firmware")
    absent = fw.get("absent") if isinstance(fw, dict) and fw.get("target") == target else None
    return without_features(target, p, absent) if absent else p


#: The value of each kind of parameter that changes nothing (a firmware without the parameter behaves so).
_NEUTRAL = ((re.compile(r"COMPASS_DIA\d?_|CAL_MAG\d_[XYZ]SCALE"), 1.0),
            (re.compile(r"COMPASS_(ODI|MOT)\d?_|CAL_MAG\d_[XYZ](ODIAG|COMP)"), 0.0),
            (re.compile(r"COMPASS_SCALE\d?$"), None))


def _without_absent(p: dict[str, float], cal: Calibration, target: str, instance: int, compass: FirmwareCompass
                    ) -> tuple[dict[str, float], list[str]]:
    """``p`` without the parameters the log's firmware lacks for this compass (its sensor record's
    ``absent_parameters``, when written as the same slot of the same firmware) and the note saying so; one that
    would change the correction (a matrix, scale or motor value the firmware cannot load) is refused."""
    record = cal.sensor
    if record is None or record.firmware != target or record.slot != instance or not record.absent_parameters:
        return p, []
    gone = [k for k in record.absent_parameters if k in p]
    if not gone:
        return p, []
    for name in gone:
        for pattern, neutral in _NEUTRAL:
            value = p[name]
            if pattern.match(name) and not (value in (0.0, 1.0) if neutral is None else value == neutral):
                raise TrimagInputError(
                    f"the log's firmware has no {name} (not among its parameters), and this calibration needs "
                    f"{name} = {value:.6g}: it cannot load it; fit with --target {target} (which fits only what the "
                    "firmware has) or update the firmware")
    kept = {k: v for k, v in p.items() if k not in gone}
    orient = [k for k in gone if "ORIENT" in k or k.endswith("_ROT")]
    why = (f" (its orientation stays the firmware's own; fitted: {compass.rotation_name}, {compass.orientation})"
           if orient else "")
    return kept, [f"not written: {', '.join(gone)}: the log's firmware has no such parameter{why}"]


def _internal(cal: Calibration) -> bool:
    """The firmware fit was of an internal compass (its orientation follows the board's)."""
    fw = cal.diagnostics.get("firmware")
    decision = fw.get("orientation_decision") if isinstance(fw, dict) else None
    return isinstance(decision, dict) and decision.get("external") is False


def _internal_orientation(p: dict[str, float], compass: FirmwareCompass, instance: int
                          ) -> tuple[dict[str, float], str]:
    """An internal compass's orientation as its firmware stores it: ArduPilot ignores ``COMPASS_ORIENTn`` of an
    internal compass (``AP_Compass_Backend::rotate_field`` rotates it by ``AHRS_ORIENTATION``), so it is not
    written; PX4 stores ``CAL_MAGn_ROT = -1`` and rotates it by ``SENS_BOARD_ROT`` (``Magnetometer::ParametersSave``
    / ``ParametersLoad``). The board's rotation also turns the IMU: it is never written from a compass fit."""
    name = compass.rotation_name
    if compass.target == "ardupilot":
        p = {k: v for k, v in p.items() if not k.startswith("COMPASS_ORIENT")}
        return p, (f"an internal compass: its orientation is the board's (AHRS_ORIENTATION = {compass.orientation}, "
                   f"{name}), so COMPASS_ORIENT is not written")
    p = {**p, f"CAL_MAG{instance}_ROT": -1.0}
    return p, (f"an internal magnetometer: CAL_MAG{instance}_ROT = -1 as PX4 stores it; its orientation is the "
               f"board's (SENS_BOARD_ROT = {compass.orientation}, {name})")


def _formula_line(compass: FirmwareCompass, instance: int) -> str:
    if compass.target == "ardupilot":
        return (f"ArduPilot compass {instance + 1}: m = M * (SCALE * (R(ORIENT) * raw + OFS)) + MOT * x, OFS in "
                "mGauss (AP_Compass_Backend::correct_field)")
    return (f"PX4 magnetometer {instance}: m = R(ROT) * S * ((raw + p * COMP) - OFF), OFF in gauss "
            f"(src/lib/sensor_calibration/Magnetometer.cpp); set CAL_MAG{instance}_ID to the sensor's device id")


def _param_file(params: dict[str, float], header: list[str]) -> str:
    lines = [f"{name},{value:.9g}" for name, value in sorted(params.items())]  # sorted, as MAGFit's files
    return _comment_lines(header, "#") + "\n".join(lines) + "\n"


# ------------------------------------------------------------------ the full-matrix targets
def _c_float(value: float) -> str:
    """A C float literal (``12.0f``, not the invalid ``12f``)."""
    text = f"{float(value):.12g}"
    if not any(c in text for c in ".en"):
        text += ".0"
    return text + "f"


def _matrix_c(name: str, M: NDArray[np.float64]) -> str:
    rows = ",\n    ".join("{" + ", ".join(_c_float(v) for v in row) + "}" for row in M)
    return f"static const float {name}[3][3] = {{\n    {rows}\n}};\n"


def _no_regressors(cal: Calibration, target: str) -> None:
    if cal.regressors is not None:
        raise TrimagInputError(
            f"this calibration has regressor terms ({', '.join(cal.regressors['names'])}) that the {target} format "
            "cannot hold (a constant offset only); export it to ardupilot or px4 (current or throttle terms), or "
            "fit without them"
        )


def _c_header(cal: Calibration) -> Export:
    b = np.asarray(cal.offset)
    text = (
        "/* " + _provenance(cal).replace("*/", "* /") + " */\n"
        f"/* corrected = MAG_CAL_MATRIX * (raw - MAG_CAL_OFFSET), unit {cal.units} */\n"
        "#ifndef TRIMAG_MAG_CAL_H\n#define TRIMAG_MAG_CAL_H\n"
        f"#define MAG_CAL_UNIT \"{cal.units}\"\n"
        f"static const float MAG_CAL_OFFSET[3] = {{{', '.join(_c_float(v) for v in b)}}};\n"
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
        _comment_lines([d["provenance"], "corrected = matrix * (raw - offset); ROS sensor_msgs/MagneticField is in "
                        "tesla"], "#")
        + "magnetometer_calibration:\n"
        f"  unit: {cal.units}\n"
        f"  offset: [{', '.join(f'{v:.12g}' for v in d['offset'])}]\n"
        f"  matrix: [{', '.join(f'{v:.12g}' for row in M for v in row)}]  # row-major 3x3\n"
    )
    return Export("ros-yaml", text)


def _matlab(cal: Calibration) -> Export:
    A = np.asarray(cal.matrix).T
    b = np.asarray(cal.offset)
    fmt = ";\n     ".join(" ".join(f"{v:.15g}" for v in row) for row in A)
    text = (_comment_lines([_provenance(cal), "MATLAB magcal convention: C = (D - b) * A, D an N x 3 array of rows"],
                           "%")
            + f"A = [{fmt}];\nb = [{' '.join(f'{v:.15g}' for v in b)}];\n")
    return Export("matlab", text, arrays={"A": A, "b": b.reshape(1, 3), "unit": cal.units,
                                          "provenance": _provenance(cal)})


def export_calibration(cal: Calibration, target: str, *, instance: int = 0) -> Export:
    """Render ``cal`` for ``target`` (one of :data:`EXPORT_TARGETS`); ``instance`` is 0-based."""
    if target not in EXPORT_TARGETS:
        raise TrimagInputError(f"unknown export target {target!r}; choose one of {', '.join(EXPORT_TARGETS)}")
    if instance < 0 or instance > 7:
        raise TrimagInputError(f"instance must be 0..7; got {instance}")
    if target in ("ardupilot", "px4", "qgc"):
        return export_calibrations([(cal, instance)], target)
    _no_regressors(cal, target)
    return {"c-header": _c_header, "json": _json, "ros-yaml": _ros_yaml, "matlab": _matlab}[target](cal)


def write_export(exp: Export, out: str | Path) -> Path:
    """Write the export atomically; the MATLAB target writes a MAT file (``A``, ``b``, ``unit``, ``provenance``)
    when ``out`` ends in ``.mat``, its ``.m`` text otherwise."""
    from .atomic import atomic_path, atomic_write_text

    if exp.target == "matlab" and Path(out).suffix.lower() == ".mat":
        from scipy.io import savemat

        with atomic_path(out) as tmp:
            with open(tmp, "wb") as fh:
                savemat(fh, exp.arrays)
        return Path(out)
    return atomic_write_text(out, exp.text)
