"""``fit --target ardupilot|px4`` (issue 30): the firmware-space fit of a log or table (:mod:`trimag.vehicle.firmware`).

What this layer decides from the data and the log:

- the **residual**: a vector one (the IGRF vector, or ``background_ned``, rotated into the body frame by the
  attitude of every sample) when the data have attitudes and a field vector, else a magnitude one (IGRF's total
  field, or ``reference``);
- the **attitude source** (named in the report): a moving-baseline GPS heading, else the EKF-GSF yaw (ArduPilot
  ``XKY0``, where its sigma is within :data:`GSF_MAX_SIGMA_DEG`), else the log's attitude (``ATT``,
  ``vehicle_attitude``), whose yaw the EKF estimated with this very compass when it fused it: that circularity is
  stated;
- the **held** values and the orientation in force (the log's parameters: ``COMPASS_*`` / ``CAL_MAGn_*``), whether
  the compass is external, ``COMPASS_OFFS_MAX``;
- the **motor channels**: the battery current (A) and the throttle (0..1; not on ArduPlane and Rover, which never
  give the compass a throttle: ``Copter::update_batt_compass``).
"""

from __future__ import annotations

import dataclasses
import re
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from ..calibration import Calibration
from ..errors import TrimagInputError
from ..fields.attitude import body_field, from_euler
from ..fields.reference import igrf, parse_igrf_spec
from ..io import Samples
from ..models.firmware import ArduPilotCompass, FirmwareCompass, PX4Magnetometer, firmware_class
from ..units import convert, normalise_unit
from ._inputs import attitudes_of
from .requests import FitRequest

#: The EKF-GSF yaw is used where its own sigma (``XKY0.YCS``) is within this (ArduPilot's CompassLearn waits for 5 deg).
GSF_MAX_SIGMA_DEG = 5.0
#: A GSF yaw further than this from the EKF's yaw has not converged (its sigma alone does not say so in the first
#: seconds of a flight: 90 deg apart at a sigma of 0.6 deg in a real ArduCopter 4.3 log).
GSF_MAX_APART_DEG = 15.0
#: The share of samples with a usable GSF yaw below which the log's attitude is used instead.
GSF_MIN_SHARE = 0.8


def _log_firmware(log_info: dict[str, Any] | None) -> str | None:
    fmt = (log_info or {}).get("format", "")
    if fmt.startswith(("ArduPilot", "MAVLink")):
        return "ardupilot"
    if fmt.startswith("PX4"):
        return "px4"
    return None


_FIRMWARE_NAMES = {"ardupilot": "ArduPilot", "px4": "PX4"}


def _check_log_firmware(target: str, log_info: dict[str, Any] | None) -> None:
    """Refuse (exit 2) a log of one firmware fitted for the other's parameters: the vehicle that wrote it loads its
    own firmware's parameters, so the file would name parameters it does not have."""
    firmware = _log_firmware(log_info)
    if firmware is None or firmware == target:
        return
    raise TrimagInputError(
        f"this log is {_FIRMWARE_NAMES[firmware]}'s ({(log_info or {}).get('format', firmware)}): its vehicle loads "
        f"{_FIRMWARE_NAMES[firmware]}'s parameters, not {_FIRMWARE_NAMES.get(target, target)}'s: give "
        f"`--target {firmware}`"
    )


def _instance(target: str, log_info: dict[str, Any] | None) -> int:
    """The 0-based instance whose parameter names the fit uses: the log's compass of ``target``'s firmware (its
    slot), else 0 (a table, or another firmware's log: ``export --instance`` names it later)."""
    if log_info is None or _log_firmware(log_info) != target:
        return 0
    return int(log_info.get("instance") or 0)


def _held(target: str, log_info: dict[str, Any] | None) -> tuple[FirmwareCompass | None, int | None, bool,
                                                                  float | None, list[str]]:
    """``(held, applied orientation, external, offsets_max, messages)`` from a log of ``target``'s firmware."""
    if log_info is None or _log_firmware(log_info) != target:
        if log_info is not None:
            return None, None, True, None, [f"the log is not {target}'s: nothing of its calibration is held"]
        return None, None, True, None, []
    params = log_info.get("parameters") or {}
    instance = int(log_info.get("instance") or 0)
    if target == "ardupilot":
        held: FirmwareCompass = ArduPilotCompass.from_parameters(params, instance)
        n = "" if instance == 0 else str(instance + 1)
        external = bool(params.get(f"COMPASS_EXTERN{n}" if n else "COMPASS_EXTERNAL", 1.0))
        applied: int | None = int(held.orientation)  # the log's readings are rotated by it
        offsets_max = params.get("COMPASS_OFFS_MAX")
        what = f"COMPASS_ORIENT{n}" if external else "AHRS_ORIENTATION (an internal compass)"
    else:
        held = PX4Magnetometer.from_parameters(params, instance)
        external = params.get(f"CAL_MAG{instance}_ROT", -1.0) >= 0
        rotated = str(log_info.get("sensor", "")).startswith("vehicle_magnetometer")
        applied = int(held.orientation) if rotated else None
        offsets_max = None
        what = f"CAL_MAG{instance}_ROT" if external else "SENS_BOARD_ROT (an internal magnetometer)"
    msg = (f"the log's calibration is held where a level does not fit it; orientation in force: {what} = "
           f"{held.orientation} ({held.rotation_name})")
    return held, applied, external, offsets_max, [msg]


def _absent(target: str, log_info: dict[str, Any] | None) -> tuple[tuple[str, ...], list[str]]:
    """The parts of ``target``'s calibration the log's firmware lacks (its parameter list has none of their
    parameters: an older version), never fitted nor written, and the message saying so."""
    from ..models.firmware import FEATURE_NAMES, absent_features

    if log_info is None or _log_firmware(log_info) != target:
        return (), []
    absent = absent_features(target, log_info.get("parameters") or {})
    if not absent:
        return (), []
    parts = ", ".join(FEATURE_NAMES[a] for a in absent)
    return absent, [f"the log's firmware has no {parts} (not among its parameters): not fitted, not written"]


#: The yaw sources a firmware fit of a log may be told to take (``fit --yaw-source``).
YAW_SOURCES = ("auto", "attitude", "dcm", "gsf", "gps")


def _yaw_source(samples: Samples, choice: str | None = None) -> tuple[Samples, str, str | None, list[str]]:
    """The yaw column to use (``yaw_gps_deg``, ``yaw_gsf_deg`` or ``yaw_deg``), the rows kept, its name and a note;
    ``choice`` (:data:`YAW_SOURCES`; None: ``"auto"``) forces one, refused where the log has none usable."""
    table = samples.table
    info = samples.log_info or {}
    source = info.get("attitude_source") or "the attitude columns"
    choice = choice or "auto"
    if choice not in YAW_SOURCES:
        raise TrimagInputError(f"`yaw_source` must be one of {', '.join(YAW_SOURCES)}; got {choice!r}")
    if choice == "attitude":
        return samples, "yaw_deg", None, [f"attitude: {source}, as asked (`yaw_source=attitude`)"]
    if choice == "dcm":  # the whole attitude from ArduPilot's DCM (AHR2), whose yaw fuses the compass too
        dcm = ["yaw_dcm_deg", "pitch_dcm_deg", "roll_dcm_deg"]
        if not set(dcm) <= set(table.columns):
            raise TrimagInputError("`yaw_source=dcm`: the log has no DCM attitude (AHR2 of an ArduPilot DataFlash log, "
                                   "AHRS2 of a telemetry log); choose auto, attitude, gsf or gps")
        ok = np.isfinite(table[dcm].to_numpy(dtype=float)).all(axis=1)
        if not ok.any():
            raise TrimagInputError("`yaw_source=dcm`: the DCM attitude (AHR2) covers none of this compass's samples; "
                                   "choose auto or attitude")
        kept = _keep(samples, ok)
        swapped = kept.table.drop(columns=["yaw_deg", "pitch_deg", "roll_deg"], errors="ignore").rename(
            columns=dict(zip(dcm, ["yaw_deg", "pitch_deg", "roll_deg"], strict=True)))
        name = (info.get("attitude_sources") or {}).get("AHR2", "AHR2 (DCM)")
        more = f"; {int((~ok).sum())} samples outside it dropped" if not ok.all() else ""
        return (dataclasses.replace(kept, table=swapped, log_info={**info, "attitude_source": name}), "yaw_deg", None,
                [f"attitude: roll, pitch and yaw from {name}, as asked (`yaw_source=dcm`){more}"])
    if choice == "gps" and not ("yaw_gps_deg" in table.columns and np.isfinite(table["yaw_gps_deg"]).any()):
        raise TrimagInputError("`yaw_source=gps`: the log has no GPS heading (GPS.Yaw of a moving-baseline GPS); "
                               "choose auto, attitude or gsf")
    if choice == "gsf" and "yaw_gsf_deg" not in table.columns:
        raise TrimagInputError("`yaw_source=gsf`: the log has no EKF-GSF yaw (XKY0, ArduPilot 4.1+); choose auto, "
                               "attitude or gps")
    if choice == "gps" or (choice == "auto" and "yaw_gps_deg" in table.columns
                           and np.isfinite(table["yaw_gps_deg"]).mean() >= GSF_MIN_SHARE):
        ok = np.isfinite(table["yaw_gps_deg"].to_numpy(dtype=float))
        return _keep(samples, ok), "yaw_gps_deg", "GPS.Yaw", [f"attitude: roll and pitch from {source}, yaw from the "
                                                             "GPS heading (GPS.Yaw): independent of the compass"]
    if "yaw_gsf_deg" in table.columns:
        sigma = table["yaw_gsf_sigma_deg"].to_numpy(dtype=float)
        gsf = table["yaw_gsf_deg"].to_numpy(dtype=float)
        apart = np.abs((gsf - table["yaw_deg"].to_numpy(dtype=float) + 180.0) % 360.0 - 180.0)
        ok = np.isfinite(gsf) & (sigma <= GSF_MAX_SIGMA_DEG) & (apart <= GSF_MAX_APART_DEG)
        if choice == "gsf" and not ok.any():
            raise TrimagInputError(f"`yaw_source=gsf`: the EKF-GSF yaw never converged in this log (sigma <= "
                                   f"{GSF_MAX_SIGMA_DEG:g} deg within {GSF_MAX_APART_DEG:g} deg of the EKF's yaw); "
                                   "choose auto or attitude")
        if ok.mean() >= GSF_MIN_SHARE or choice == "gsf":
            note = (f"attitude: roll and pitch from {source}, yaw from the EKF-GSF estimator (XKY0.YC, where its sigma "
                    f"is <= {GSF_MAX_SIGMA_DEG:g} deg and it has converged to within {GSF_MAX_APART_DEG:g} deg of the "
                    f"EKF's yaw; {int((~ok).sum())} samples without it dropped): independent of the compass")
            return _keep(samples, ok), "yaw_gsf_deg", "XKY0.YC", [note]
    return samples, "yaw_deg", None, []


def _keep(samples: Samples, ok: NDArray[np.bool_]) -> Samples:
    if ok.all():
        return samples
    return dataclasses.replace(samples, field=samples.field[ok], table=samples.table[ok],
                               n_dropped=samples.n_dropped + int((~ok).sum()))


@dataclasses.dataclass(frozen=True)
class FlightAttitude:
    """The attitude a firmware fit takes of a log or table (:func:`flight_attitude`): the one the fit's expected
    field is rotated by, and the review's figures too (:mod:`trimag.app._flight`)."""

    #: the rows that have it (a table's index keeps the rows' labels), their ``yaw_deg``/``pitch_deg``/``roll_deg``
    #: the DCM's where it is chosen
    samples: Samples
    #: body -> NED of each row: the chosen yaw with the logged roll and pitch, an ArduPilot log's board trim added back
    rotation: Any
    #: the yaw source taken (``"attitude"``, ``"dcm"``, ``"gsf"`` or ``"gps"``; ``auto`` resolved), what
    #: ``yaw_source`` names to take it again on other rows
    yaw_source: str
    #: a compass-free yaw's name (``"XKY0.YC"``, ``"GPS.Yaw"``) or None
    yaw_name: str | None
    #: the attitude in words (the page and the report say it)
    source: str
    #: whether the attitude is a log's own (its ``yaw_deg,pitch_deg,roll_deg``), not columns the user named
    from_log: bool
    #: the yaw source's lines and the board trim's
    messages: list[str]
    notes: list[str]


def flight_attitude(samples: Samples, att: Any, yaw_source: str | None = None) -> FlightAttitude:
    """The attitude of the rows of ``samples`` a firmware fit takes (``att``: the
    :class:`~trimag.app.requests.AttitudeSpec`): for a log's own attitude columns, the yaw of ``yaw_source``
    (:data:`YAW_SOURCES`; :func:`_yaw_source`) with the logged roll and pitch and the board trim (:func:`_attitudes`);
    else the columns ``att`` names. Raises :class:`~trimag.errors.TrimagInputError` where the log has no such yaw."""
    info = samples.log_info or {}
    from_log = bool(info) and att.attitude_columns == "yaw_deg,pitch_deg,roll_deg"
    yaw_column: str | None = None
    yaw_name: str | None = None
    messages: list[str] = []
    if from_log:
        samples, yaw_column, yaw_name, messages = _yaw_source(samples, yaw_source)
    samples, rotation, notes = _attitudes(samples, att, yaw_column)
    attitude = (samples.log_info or {}).get("attitude_source") or "the attitude columns"
    if not from_log:
        source, resolved = f"the columns {att.attitude_columns or att.quaternion_columns}", "attitude"
    elif yaw_name == "XKY0.YC":
        source, resolved = f"roll and pitch from {attitude}, yaw from the EKF-GSF estimator (XKY0.YC)", "gsf"
    elif yaw_name == "GPS.Yaw":
        source, resolved = f"roll and pitch from {attitude}, yaw from the GPS heading (GPS.Yaw)", "gps"
    else:
        source, resolved = str(attitude), "dcm" if yaw_source == "dcm" else "attitude"
    if notes:
        source += ", the board trim AHRS_TRIM added back"
    return FlightAttitude(samples, rotation, resolved, yaw_name, source, from_log, messages, notes)


def _circularity(target: str, info: dict[str, Any]) -> tuple[bool, str]:
    """Whether the log's EKF yaw used this compass, and what that means, in one line."""
    params = info.get("parameters") or {}
    source = info.get("attitude_source") or "the log's attitude"
    if str(source).startswith(("AHR2", "AHRS2")):  # AP_AHRS_DCM::drift_correction_yaw: the compass, whatever the EKF
        return True, (f"attitude: {source}; its yaw is the DCM's, which fuses the primary compass (the GPS course "
                      "only without one): a fit to it would partly see its own heading, so the levels are fitted "
                      "heading-free (the field's horizontal and vertical components under the DCM's roll and "
                      "pitch) and the orientation only among the standard rotations")
    if target == "ardupilot":
        instance = int(info.get("instance") or 0)
        use_name = "COMPASS_USE" if instance == 0 else f"COMPASS_USE{instance + 1}"
        use = params.get(use_name, 1.0)
        yaw_src = params.get("EK3_SRC1_YAW")
        src_text = f"EK3_SRC1_YAW = {yaw_src if yaw_src is not None else 'n/a'}"
        if yaw_src in (2.0, 8.0):  # a GPS heading or the GSF yaw: no compass in it
            return False, (f"attitude: {source} (the EKF's yaw did not use this compass: {use_name} = {use:g}, "
                           f"{src_text})")
        if not use:  # the EKF's yaw is the compass it did use (issue 38: held-out logs that never turned)
            return False, (f"attitude: {source}: the EKF's yaw did not use this compass ({use_name} = {use:g}, "
                           f"{src_text}) but is another compass's heading, taken here as the truth: this compass's "
                           "offsets and orientation are only as good as that compass's calibration, and on a log that "
                           "barely turned they rest on its heading alone")
        why = f"{use_name} = {use:g}" + (f", EK3_SRC1_YAW = {yaw_src:g}" if yaw_src is not None else "")
    else:
        fused, device = info.get("ekf_mag_device_ids"), info.get("device_id")
        if params.get("EKF2_MAG_TYPE") == 5.0:  # PX4's EKF2_MAG_TYPE 5: none
            return False, f"attitude: {source} (the EKF's yaw used no magnetometer: EKF2_MAG_TYPE = 5, none)"
        if fused and device is not None and int(device) not in fused:
            return False, (f"attitude: {source}: the EKF's yaw did not use this compass (its estimators fused "
                           f"device id {', '.join(map(str, fused))}, estimator_status.mag_device_id; this compass is "
                           f"{device}) but is another compass's heading, taken here as the truth: this compass's "
                           "offsets and orientation are only as good as that compass's calibration, and on a log that "
                           "barely turned they rest on its heading alone")
        why = "EKF2 fuses the magnetometers unless EKF2_MAG_TYPE is none" + (
            f"; its estimators fused device id {', '.join(map(str, fused))}" if fused else "")
    advice = ("Log XKY0 (EKF3's GSF yaw, ArduPilot 4.1+) or fly with a GPS heading to fit the full vector"
              if target == "ardupilot" else
              "trimag reads no compass-free yaw from PX4 logs: the full vector needs a calibration turn through all "
              "headings, pitched and rolled")
    return True, (f"attitude: {source}; its yaw is the EKF's, which fused this compass ({why}): a fit to it would "
                  "partly see its own heading, so the levels are fitted heading-free (the field's horizontal and "
                  "vertical components under the logged roll and pitch, MAGFit's cost as least squares) and the "
                  f"orientation only among the standard rotations. {advice}")


#: The names under which a table holds a motor channel (compared in lower case, spaces as underscores, a unit in
#: brackets dropped: ``Current (A)`` is ``current``); the first one the table has is used. A vehicle log's reader
#: names them ``current_A`` and ``throttle`` (the first of each).
MOTOR_COLUMN_NAMES: dict[str, tuple[str, ...]] = {
    "current": ("current_a", "current", "curr", "battery_current", "battery_current_a", "batt_current", "batt_curr",
                "bat_current", "bat_curr", "current_amps", "curr_a", "ibatt", "i_batt", "amps"),
    "throttle": ("throttle", "thr", "thr_out", "throttle_out", "throut", "thrust"),
}


def parse_motor(text: str | None) -> tuple[str, str | None]:
    """``motor`` as given (``auto``, ``none``, ``current``, ``throttle``, or ``current=COLUMN`` /
    ``throttle=COLUMN``: the table's column of that channel; ``auto=current`` / ``auto=throttle``: the motor term
    fitted when it helps, on that channel only, as ``--sensor all`` asks for one channel for every compass)
    -> ``(kind, column or None)`` (for ``auto=KIND``: ``("auto", KIND)``)."""
    kind, sep, column = str(text or "auto").partition("=")
    kind, column = kind.strip().lower(), column.strip()
    restricted = kind == "auto" and column.lower() in MOTOR_COLUMN_NAMES
    if kind not in ("auto", "none", *MOTOR_COLUMN_NAMES) or (
            sep and not restricted and (kind not in MOTOR_COLUMN_NAMES or not column)):
        raise TrimagInputError(f"`motor` is auto, none, current, throttle, current=COLUMN or throttle=COLUMN; got "
                               f"{text!r}")
    return kind, (column.lower() if restricted else column) or None


def _plain_name(name: Any) -> str:
    return re.sub(r"\s*[\(\[][^\)\]]*[\)\]]\s*$", "", str(name)).strip().lower().replace(" ", "_")


def _motor_column(table: Any, kind: str, named: tuple[str, str | None], log: bool) -> str | None:
    """The column of the motor channel ``kind``: the one ``named`` (``motor=KIND=COLUMN``; a missing one is
    refused, naming the table's columns), else a log's own (``current_A``, ``throttle``), else the first of a
    table's columns with one of :data:`MOTOR_COLUMN_NAMES`."""
    if named[0] == "auto" and named[1] is not None and named[1] != kind:  # auto=KIND: that channel only
        return None
    if named[0] == kind and named[1] is not None:
        if named[1] not in table.columns:
            raise TrimagInputError(f"no column {named[1]!r} (named by `motor={kind}={named[1]}`); the columns are "
                                   f"{', '.join(map(str, table.columns))}")
        return named[1]
    if log:
        own = "current_A" if kind == "current" else "throttle"
        return own if own in table.columns else None
    plain = {_plain_name(c): c for c in reversed(list(table.columns))}  # the first of equal names wins
    return next((plain[n] for n in MOTOR_COLUMN_NAMES[kind] if n in plain), None)


#: A motor channel empty on at most this share of the rows (a battery logged from a little after the compass) is
#: kept and those rows dropped (counted); emptier, the channel is not used.
MOTOR_MAX_EMPTY = 0.05


def _motor_channels(target: str, samples: Samples, info: dict[str, Any] | None,
                    named: tuple[str, str | None] = ("auto", None),
                    ) -> tuple[Samples, dict[str, Any], dict[str, str], list[str]]:
    """``(samples, {"current": values, "throttle": values}, {kind: column}, messages)`` from the logged channels
    (``named``: :func:`parse_motor` of the request's ``motor``); the rows a used channel leaves empty are dropped
    and counted."""
    table = samples.table
    columns: dict[str, str] = {}
    messages: list[str] = []
    keep = np.ones(len(table), dtype=bool)
    for kind in MOTOR_COLUMN_NAMES:
        column = _motor_column(table, kind, named, info is not None)
        if column is not None:
            v = pd.to_numeric(table[column], errors="coerce").to_numpy(dtype=float)
            finite = np.isfinite(v)
            if finite.mean() >= 1.0 - MOTOR_MAX_EMPTY and finite.any() and np.ptp(v[finite]) > 0:
                columns[kind] = column
                if not finite.all():
                    messages.append(f"{int((keep & ~finite).sum())} samples without a {column} value dropped (the "
                                    "channel's log starts later or ends earlier than the compass's)")
                keep &= finite
    samples = _keep(samples, keep)
    if info is None and columns:
        messages.append("motor channel(s): " + ", ".join(f"{kind} from column {column}"
                                                         for kind, column in columns.items()))
    kind = named[0]
    if info is None and kind in MOTOR_COLUMN_NAMES and kind not in columns:
        column = _motor_column(table, kind, named, False)
        why = (f"column {column} does not vary (or is empty on more than {MOTOR_MAX_EMPTY:.0%} of the rows)"
               if column is not None else f"no column named {', '.join(MOTOR_COLUMN_NAMES[kind])}")
        raise TrimagInputError(f"`motor={kind}` needs a {kind} channel that varies: {why}; the table's columns are "
                               f"{', '.join(map(str, table.columns))}: name one with `motor={kind}=COLUMN`")
    values: dict[str, Any] = {kind: pd.to_numeric(samples.table[column], errors="coerce").to_numpy(dtype=float)
                              for kind, column in columns.items()}
    vehicle = str((info or {}).get("vehicle") or "")
    if target == "ardupilot" and "throttle" in values and any(k in vehicle for k in ("Plane", "Rover")):
        del values["throttle"], columns["throttle"]
        messages.append(f"{vehicle} never gives the compass a throttle (only Copter and Sub do): no throttle term "
                        "(COMPASS_MOTCT = 1 would multiply by 0)")
    return samples, values, columns, messages


def _field_reference(req: FitRequest, samples: Samples, unit_fw: str, target: str
                     ) -> tuple[Samples, Any, Any, Any, dict[str, Any], list[str], FlightAttitude | None]:
    """``(samples, field_body or None, magnitude or None, heading-free tilts or None, reference info, messages,
    the attitude or None)`` in the firmware's unit: a log whose only yaw is an EKF's that fused this compass is fitted
    heading-free."""
    given = req.reference
    messages: list[str] = []
    ned = None
    if given.background_ned is not None:
        from ._inputs import _parse_vector

        data_unit = normalise_unit(req.input.units)
        ned = _parse_vector(given.background_ned, "background_ned") * convert(1.0, data_unit, unit_fw)
        what = f"background_ned {given.background_ned}"
    elif given.igrf_spec is not None:
        ned = np.asarray(igrf(*parse_igrf_spec(given.igrf_spec)).ned_nT, dtype=np.float64) * convert(1.0, "nT",
                                                                                                     unit_fw)
        what = f"IGRF at {given.igrf_spec}"
    att = req.attitude
    has_attitude = att.attitude_columns is not None or att.quaternion_columns is not None
    if ned is not None and has_attitude:
        info = samples.log_info or {}
        chosen = flight_attitude(samples, att, req.yaw_source)
        samples, rotation = chosen.samples, chosen.rotation
        messages = list(chosen.messages)
        circular = False
        if chosen.from_log and chosen.yaw_name is None:
            circular, line = _circularity(target, samples.log_info or info)
            messages.append(line)
        messages += chosen.notes
        tilt = None
        if circular:
            euler = rotation.as_euler("ZYX", degrees=True)
            tilt = from_euler(np.zeros(len(euler)), euler[:, 1], euler[:, 2]).as_matrix()
        reference = {"value": float(np.linalg.norm(ned)), "source": f"{what}: vector NED {np.round(ned, 4).tolist()} "
                     f"{unit_fw}, rotated into the body frame", "unit": unit_fw}
        return samples, body_field(rotation, ned), None, tilt, reference, messages, chosen
    if ned is not None:
        F = float(np.linalg.norm(ned))
        messages.append(f"no attitudes: the fit uses the field's magnitude {F:.6g} {unit_fw} ({what}) and keeps the "
                        "orientation (a magnitude cannot see it)")
        return samples, None, F, None, {"value": F, "source": what, "unit": unit_fw}, messages, None
    if given.reference is not None and str(given.reference).strip().lower() != "mean":
        F = float(given.reference) * convert(1.0, normalise_unit(req.input.units), unit_fw)
        return samples, None, F, None, {"value": F, "source": "reference", "unit": unit_fw}, messages, None
    raise TrimagInputError(
        f"`target={target}` needs the Earth's field: the log has no GPS fix; give `igrf_spec=LAT,LON,ALT_M,DATE` or "
        "`reference=F`",
        details=["`igrf_spec`: the site's field (with attitudes: the vector, rotated into the body frame)",
                 "`reference=F`: the field's magnitude, in the data's unit"])


def _attitudes(samples: Samples, att: Any, yaw_column: str | None) -> tuple[Samples, Any, list[str]]:
    """The attitude of every kept row (yaw from ``yaw_column``) and a note; an ArduPilot log's ``ATT`` is given back
    the board trim ``AHRS_TRIM_X/Y/Z`` (as ``magfit_WMM.py`` does): the compass is rotated into the IMU's frame, the
    one the EKF works in, and ``ATT`` is the vehicle's, the trim removed (``AP_AHRS``)."""
    from ._inputs import drop_rows_without_attitude

    samples, _ = drop_rows_without_attitude(samples, att.attitude_columns, att.quaternion_columns)
    info = samples.log_info or {}
    params = info.get("parameters") or {}
    from_log = bool(info) and att.attitude_columns == "yaw_deg,pitch_deg,roll_deg"
    if not from_log:
        return samples, attitudes_of(samples, att), []
    trim = np.degrees([params.get("AHRS_TRIM_Z", 0.0), params.get("AHRS_TRIM_Y", 0.0), params.get("AHRS_TRIM_X", 0.0)])
    t = samples.table
    yaw = t[yaw_column or "yaw_deg"].to_numpy(dtype=float)
    rotation = from_euler(yaw + trim[0], t["pitch_deg"].to_numpy(dtype=float) + trim[1],
                          t["roll_deg"].to_numpy(dtype=float) + trim[2])
    note = ([f"attitude: the board trim AHRS_TRIM (roll {trim[2]:.2f}, pitch {trim[1]:.2f}, yaw {trim[0]:.2f} deg) "
             "added back to ATT: the compass is in the IMU's frame"] if np.any(trim) else [])
    return samples, rotation, note


def fit_target(req: FitRequest, samples: Samples, unit: str
               ) -> tuple[Samples, Calibration, dict[str, Any] | None, list[str]]:
    """The firmware-space fit of ``samples`` (in ``unit``): ``(samples kept, calibration, regressor values,
    messages)``."""
    from ..vehicle.firmware import firmware_calibration, fit_firmware, level_table

    target = str(req.target)
    klass = firmware_class(target)
    if unit in ("unknown", "counts"):
        raise TrimagInputError(f"`target={target}` needs the data's unit (`units=mG`, G, uT or nT); got {unit!r}")
    info = samples.log_info
    _check_log_firmware(target, info)
    held, applied, external, offsets_max, messages = _held(target, info)
    absent, more = _absent(target, info)
    messages += more
    named = parse_motor(req.motor)
    samples, _, columns, more = _motor_channels(target, samples, info, named)  # first: the rows a channel leaves empty
    messages += more
    samples, field_body, magnitude, tilt, reference, more, attitude = _field_reference(req, samples, klass.unit,
                                                                                        target)
    messages += more
    motors = {kind: pd.to_numeric(samples.table[column], errors="coerce").to_numpy(dtype=float)
              for kind, column in columns.items()}
    factor = convert(1.0, unit, klass.unit)
    unfitted = _unfitted_rows(req, samples, target, factor)
    fit = fit_firmware(target, samples.field * factor, field_body=field_body, magnitude=magnitude,
                       motor_values=motors, held=held, applied_orientation=applied, external=external,
                       level=req.level or "auto", motor=named[0],
                       offsets_max=offsets_max, heading_free=tilt, absent=absent,
                       instance=_instance(target, info), unfitted=unfitted)
    messages += [m for m in fit.messages if not m.startswith("warning:")]
    kind = fit.compass.motor_type
    channel = columns.get(kind) if kind else None
    cal = firmware_calibration(fit, units=unit, motor_channel=channel, reference={**reference, "unit": unit,
                                                                                    "value": reference["value"]
                                                                                    / factor},
                               input_orientation=applied)
    messages.append(f"{target} levels ({fit.residual_kind} residual; held-out RMS over {5} contiguous folds):\n"
                    + level_table(fit.table, klass.unit))
    held_names = "; ".join(f"{k} = {h['value']:.4g}" + (f" ({h['why']})" if "not identified" in h["why"] else "")
                           for k, h in fit.held.items()) or "nothing"
    messages.append(f"level {fit.level}: held {held_names}; orientation {fit.orientation['decision']}: "
                    f"{fit.compass.rotation_name} ({fit.compass.orientation}); field RMS {fit.rms_before:.4g} -> "
                    f"{fit.rms_after:.4g} {klass.unit}")
    regressor_values = {channel: motors[kind]} if channel and kind else None
    if attitude is not None:  # the attitude the figures draw the expected field with (trimag review, --report)
        cal = cal.with_diagnostics(firmware={**cal.diagnostics["firmware"], "attitude": {
            "yaw_source": attitude.yaw_source, "source": attitude.source}})
    old = _old_px4_rotation(info, applied)
    if old is not None:
        messages.append(f"warning: {old}")
        cal = cal.with_diagnostics(readings_rotated=old)
    return samples, _magnitude_stats(cal, samples, regressor_values), regressor_values, messages


def _unfitted_rows(req: FitRequest, samples: Samples, target: str, factor: float) -> dict[str, Any] | None:
    """The log's rows that ``rows``/``where`` left out of the fit, prepared as the fit's own (firmware unit, the
    field reference, the motor channels, the heading-free tilts) to judge the parameters on (issue 38, item 3); None
    without a selection or when fewer than :data:`~trimag.vehicle._firmware_trust.UNFITTED_MIN_ROWS` remain."""
    import pandas as pd

    from ..errors import TrimagError
    from ..io import read_samples
    from ..io.tables import select_rows, where_mask
    from ..vehicle._firmware_trust import UNFITTED_MIN_ROWS

    src = req.input
    if not (src.rows or src.where) or samples.log_info is None:
        return None
    try:
        full = read_samples(src.path, fmt=src.fmt, columns=src.columns, var=src.var, sensor=src.sensor)
        chosen, _ = select_rows(pd.DataFrame(index=pd.RangeIndex(full.n_total_rows)), src.rows, None)
        left = ~full.table.index.isin(chosen.index)
        if src.where:
            left |= ~where_mask(full.table, src.where)
        if left.sum() < UNFITTED_MIN_ROWS:
            return None
        rest = _keep(full, left)
        rest, _, columns, _ = _motor_channels(target, rest, rest.log_info)
        rest, field_body, magnitude, tilt, _, _, _ = _field_reference(req, rest, firmware_class(target).unit, target)
    except TrimagError:
        return None
    if len(rest.field) < UNFITTED_MIN_ROWS:
        return None
    field = field_body if field_body is not None else np.full(len(rest.field), float(magnitude))
    what = "; ".join(x for x in (f"--rows {src.rows}" if src.rows else "", f"--where {src.where}" if src.where
                                  else "") if x)
    return {"raw": rest.field * factor, "field": field, "tilt": tilt, "what": f"left out by {what}",
            "motors": {kind: rest.table[column].to_numpy(dtype=float) for kind, column in columns.items()}}


def _old_px4_rotation(info: dict[str, Any] | None, applied: int | None) -> str | None:
    """Why an orientation found on this log cannot be written, or None: a PX4 log from before v1.12 (sdlog2's
    ``IMU.Mag``, an older ULog's calibrated ``sensor_mag``) holds readings its drivers had already rotated by
    ``CAL_MAGn_ROT`` (rotation first, then offsets and scales), so the orientation the fit finds is relative to
    the logged readings, not the sensor's; the v1.12+ formula export writes would rotate them again."""
    if info is None or applied is not None:
        return None
    fmt = str(info.get("format", ""))
    raw = "sensor_mag is the raw reading" in " ".join(str(m) for m in info.get("messages") or [])
    if "sdlog2" not in fmt and ("ULog" not in fmt or raw):
        return None
    instance = int(info.get("instance") or 0)
    rotation = int((info.get("parameters") or {}).get(f"CAL_MAG{instance}_ROT", -1))
    in_force = f"CAL_MAG{instance}_ROT = {rotation}" if rotation >= 0 else "SENS_BOARD_ROT (an internal compass)"
    # 2016's sensor_combined: sensors.cpp rotated the driver's calibrated report (mag_poll), after its calibration
    by = ("its sensors module", "after") if info.get("sensor") == "sensor_combined" else ("the drivers", "before")
    return (f"this log's readings were rotated by {by[0]} of PX4 before v1.12 ({in_force}, {by[1]} their "
            "offsets and scales): the orientation and offsets found are relative "
            "to the logged readings, not the sensor's own frame, so `trimag export` will not write them as a "
            "firmware's parameters; fit a log of PX4 v1.12 or later (raw sensor_mag) for the firmware's parameters")


def _magnitude_stats(cal: Calibration, samples: Samples, regressors: dict[str, Any] | None) -> Calibration:
    """The |B| statistics every calibration carries (before: the raw readings), beside the firmware fit's own field
    RMS (``field_rms_before``, ``field_rms_after``: the vector or magnitude residual the levels were judged by)."""
    from ..quality.metrics import norm_stats

    F = float((cal.reference or {})["value"])
    before = norm_stats(np.linalg.norm(samples.field, axis=1), F)
    after = norm_stats(np.linalg.norm(cal.apply(samples.field, regressors=regressors), axis=1), F)
    stats = {f"{k}_{when}": v for when, d in (("before", before), ("after", after)) for k, v in d.items()
             if k in ("mean_norm", "std_norm", "rms", "max_abs")}
    stats.update(p2p_before=before["peak_to_peak"], p2p_after=after["peak_to_peak"],
                 field_rms_before=cal.stats["rms_before"], field_rms_after=cal.stats["rms_after"])
    return cal.with_stats(**stats)
