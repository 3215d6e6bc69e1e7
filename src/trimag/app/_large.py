"""``trimag fit --level-turn`` and ``--heading`` / ``--heading-column``: the calibration of a vehicle that cannot
be tumbled (issue 30, item 5; :mod:`trimag.vehicle.level_turn`, :mod:`trimag.vehicle.fixed_yaw`,
docs/autopilot.md "Large vehicles")."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from ..calibration import Calibration
from ..errors import TrimagInputError
from ..fields.reference import ScalarReference, igrf, parse_igrf_spec
from ..io import Samples
from ..units import convert, unit_after
from ._inputs import attitudes_of, drop_rows_without_attitude, magnitude_reference
from .requests import FitRequest

#: ``option`` keys of the two modes (besides the quick recalibration's ``scale_sigma``, ``inclination_deg``,
#: ``inclination_sigma_deg``, which they share)
MODE_OPTIONS = ("vertical_scale_sigma", "gain_sigma", "heading_sigma_deg", "attitude_sigma_deg",
                "declination_sigma_deg")
_LEVEL_KEYS = ("vertical_scale_sigma", "gain_sigma", "scale_sigma", "inclination_sigma_deg")
_HEADING_KEYS = ("scale_sigma", "inclination_sigma_deg", "declination_sigma_deg", "heading_sigma_deg",
                 "attitude_sigma_deg")


def large_mode(req: FitRequest) -> str | None:
    """``"level_turn"``, ``"heading"`` or None; a combination that cannot work is refused."""
    heading = req.heading is not None or req.heading_column is not None
    if req.heading is not None and not (np.isfinite(float(req.heading)) and -360.0 <= float(req.heading) <= 360.0):
        raise TrimagInputError(f"`heading` is the vehicle's true heading in degrees, -360 to 360; got {req.heading}")
    if req.heading is not None and req.heading_column is not None:
        raise TrimagInputError("give the heading once: `heading=DEG` (one, for the whole log) or "
                               "`heading_column=NAME` (one per sample)")
    if req.level_turn and heading:
        raise TrimagInputError("give one mode: `level_turn` (the vehicle turns; no heading needed) or `heading` "
                               "(the vehicle's known heading)")
    if req.level_turn and req.prior is not None:
        raise TrimagInputError("`prior` already refits an earlier calibration's offset from a level turn; drop "
                               "`level_turn`")
    mode = "level_turn" if req.level_turn else ("heading" if heading else None)
    if mode is not None and (req.target is not None or req.level is not None or req.motor is not None):
        raise TrimagInputError(f"`{mode}` does not combine with a firmware fit (`target`, `level`, `motor`: they "
                               "choose the orientation and levels from a log that tilts); its offsets and symmetric "
                               "matrix are already the firmware's form: drop `target` and write the calibration with "
                               "trimag export CAL.json --to ardupilot|px4")
    if req.deviation_card is not None and mode is None:
        raise TrimagInputError("`deviation_card` is drawn by a large vehicle's fit: give `level_turn` or `heading`")
    if mode is not None and req.model != "ellipsoid":
        raise TrimagInputError(f"`{mode}` fits the firmware's offsets and matrix (model ellipsoid); drop "
                               f"`model={req.model}`")
    if mode is not None and req.regressors:
        raise TrimagInputError(f"`regressors` cannot be fitted with `{mode}`; drop one of them")
    return mode


def _options(options: dict[str, Any], keys: tuple[str, ...], mode: str) -> dict[str, float]:
    """The mode's options as floats; another mode's option is refused."""
    out: dict[str, float] = {}
    for key, value in options.items():
        if key == "inclination_deg":
            continue
        if key not in keys:
            raise TrimagInputError(f"`option {key}` is not an option of `{mode}`; its options: {', '.join(keys)}")
        try:
            out[key] = float(value)
        except (TypeError, ValueError):
            raise TrimagInputError(f"`option {key}` takes a number; got {value!r}") from None
    return out


def _attitude(req: FitRequest, samples: Samples) -> tuple[Samples, Any, list[str]]:
    """The attitudes (the request's columns, or the log's), rows without one dropped and counted: ``(samples,
    Rotation or None, messages)``."""
    att = req.attitude
    log_info = samples.log_info
    if att.attitude_columns is None and att.quaternion_columns is None and log_info and log_info.get("has_attitude"):
        att = dataclasses.replace(att, attitude_columns="yaw_deg,pitch_deg,roll_deg")
    if att.attitude_columns is None and att.quaternion_columns is None:
        return samples, None, ["no attitudes: the vehicle is taken as level (give `attitude_columns` for its roll "
                               "and pitch)"]
    samples, n_bad = drop_rows_without_attitude(samples, att.attitude_columns, att.quaternion_columns,
                                                strict=req.input.strict)
    messages = [f"dropped {n_bad} rows without an attitude"] if n_bad else []
    rotation = attitudes_of(samples, att)
    tilt = np.degrees(np.arccos(np.clip(rotation.inv().apply([0.0, 0.0, 1.0])[:, 2], -1.0, 1.0)))
    source = "the log's" if log_info and att.attitude_columns == "yaw_deg,pitch_deg,roll_deg" else "the given"
    messages.append(f"roll and pitch from {source} attitudes: tilt {float(np.sqrt(np.mean(tilt**2))):.2g} deg RMS, "
                    f"{float(tilt.max()):.2g} deg at most")
    return samples, rotation, messages


def _inclination(req: FitRequest, options: dict[str, Any]) -> tuple[float | None, str]:
    if options.get("inclination_deg") is not None:
        return float(options["inclination_deg"]), "`option inclination_deg`"
    if req.reference.igrf_spec is not None:
        north, east, down = igrf(*parse_igrf_spec(req.reference.igrf_spec)).ned_nT
        return float(np.degrees(np.arctan2(down, np.hypot(north, east)))), "IGRF"
    return None, ""


def fit_level_turn_file(req: FitRequest, samples: Samples, unit: str, options: dict[str, Any]
                        ) -> tuple[Samples, Calibration, ScalarReference, list[str]]:
    """``level_turn``: :func:`trimag.vehicle.level_turn.fit_level_turn` on the request's samples."""
    from ..vehicle.level_turn import fit_level_turn

    sigmas = _options(options, _LEVEL_KEYS, "level_turn")
    samples, rotation, messages = _attitude(req, samples)
    ref = magnitude_reference(samples, req.reference, unit)
    if not ref.known or ref.values is None:
        raise TrimagInputError("`level_turn` needs the field's magnitude (and, best, its inclination): give "
                               "`igrf_spec=LAT,LON,ALT_M,DATE` (a log with a GPS fix has it) or `reference=F`")
    inclination, source = _inclination(req, options)
    from ..vehicle.level_turn import DEFAULTS

    s = {**DEFAULTS, **sigmas}
    cal = fit_level_turn(samples.field, ref.values, inclination_deg=inclination, attitude=rotation, units=unit,
                         vertical_scale_sigma=s["vertical_scale_sigma"], gain_sigma=s["gain_sigma"],
                         scale_sigma=s["scale_sigma"], inclination_sigma_deg=s["inclination_sigma_deg"])
    messages.insert(0, f"level turn: reference F = {float(np.mean(ref.values)):.6g} {unit_after(unit)} ({ref.source})"
                    + (f", inclination {inclination:.3f} deg ({source})" if inclination is not None else
                       ", inclination unknown (the horizontal gain held at the data's unit)"))
    declination = _declination(req)
    cal, card_lines = attach_deviation_card(cal, samples, rotation, declination,
                                            cal.diagnostics["level_turn"]["fitted_inclination_deg"])
    return samples, cal, ref, messages + level_turn_lines(cal) + card_lines


def _declination(req: FitRequest) -> float:
    """IGRF's declination at the request's site (degrees east), 0 without one (magnetic headings)."""
    if req.reference.igrf_spec is None:
        return 0.0
    north, east, _ = igrf(*parse_igrf_spec(req.reference.igrf_spec)).ned_nT
    return float(np.degrees(np.arctan2(east, north)))


def level_turn_lines(cal: Calibration) -> list[str]:
    """What a level turn fitted and held, for the user."""
    d = cal.diagnostics["level_turn"]
    std = (cal.uncertainty or {})["param_std"]
    unit = unit_after(cal.units)  # after a number: "(unit not given)" for a fit without a unit
    parts = d["offset_z_sigma_parts"]
    lines = [f"  turned through {d['turn_covered_deg']:.0f} deg of heading; tilt {d['tilt_rms_deg']:.2g} deg RMS"]
    for k, axis in enumerate("xyz"):
        lines.append(f"  offset_{axis} = {cal.offset[k]:.6g} +- {std[f'hard_iron_{axis}']:.3g} {unit}"
                     + (f" (from {d['offset_z_from']}; sigma from the data {parts['data']:.3g}, the held vertical "
                        f"scale {parts['vertical_scale']:.3g}, the reference {parts['reference']:.3g})"
                        if axis == "z" else " (the turn's centre)"))
    if d["held"]:
        lines.append(f"held, not identified by a level turn: {'; '.join(d['held'])} (tilt the vehicle while it "
                     "turns to fit it, or widen `option vertical_scale_sigma`)")
    else:
        lines.append(f"the vertical scale is fitted (the tilt identifies it: sigma {d['vertical_scale_std']:.3g})")
    halves = d.get("halves")
    if halves is not None and not halves["agree"]:
        diff = np.subtract(*halves["offsets"])
        lines.append(f"warning: the log's two halves give offsets that differ by {np.round(diff, 3).tolist()} {unit} "
                     f"({max(halves['z']):.1f} times their combined sigma): the field or the vehicle's iron changed "
                     "during the log (nearby iron, a moved battery or cable), and the sigmas above understate the "
                     "uncertainty; record the turns again, away from iron")
    if d["offset_z_alternative"] is not None:
        lines.append(f"warning: without the inclination a level turn cannot tell the vertical field's sign: the "
                     f"vertical offset {cal.offset[2]:.6g} {unit} was chosen (the smaller); the other solution is "
                     f"{d['offset_z_alternative']:.6g} {unit}; give `igrf_spec` or `option inclination_deg` to decide")
    return lines


def fit_fixed_heading_file(req: FitRequest, samples: Samples, unit: str, prior: Calibration | None,
                           options: dict[str, Any]) -> tuple[Samples, Calibration, ScalarReference, list[str]]:
    """``heading`` / ``heading_column``: :func:`trimag.vehicle.fixed_yaw.fit_fixed_heading` on the request's samples
    (the matrix of ``prior`` held when given, else the identity)."""
    from ..vehicle.fixed_yaw import fit_fixed_heading, heading_misfit_message

    sigmas = _options(options, _HEADING_KEYS, "heading")
    if prior is not None and prior.regressors is not None:
        raise TrimagInputError(f"the prior calibration {req.prior} has regressor terms, which a fixed heading does "
                               "not refit: give a prior without them (or refit its offset with `prior` alone)")
    messages: list[str] = []
    if req.heading_column is not None:
        samples, n_bad = drop_rows_without_attitude(samples, req.heading_column, None, strict=req.input.strict,
                                                    what="heading")
        if n_bad:
            messages.append(f"dropped {n_bad} rows without a heading in {req.heading_column} (e.g. a GPS course "
                            "while the vehicle stood still)")
    samples, rotation, att_messages = _attitude(req, samples)
    messages += att_messages
    if req.heading_column is not None:
        from ..io import column_values

        yaw = column_values(samples, req.heading_column)
    else:
        yaw = np.full(len(samples.field), float(req.heading))  # type: ignore[arg-type]
    pitch = roll = np.zeros(len(samples.field))
    if rotation is not None:
        _, pitch, roll = rotation.as_euler("ZYX", degrees=True).T
    F, incl, decl, source = _field_vector(req, unit)
    if req.heading_column is None and options.get("heading_sigma_deg") is None:
        messages.append("the heading given is taken as known to 1 deg (`option heading_sigma_deg`)")
    matrix = None if prior is None else np.asarray(prior.matrix)
    cal = fit_fixed_heading(samples.field, (F, incl, decl), yaw, pitch_deg=pitch, roll_deg=roll, matrix=matrix,
                            units=unit, sigmas=sigmas, model="ellipsoid" if prior is None else prior.model)
    std = (cal.uncertainty or {})["param_std"]
    shown = unit_after(unit)  # after a number: "(unit not given)" for a fit without a unit
    messages.insert(0, f"fixed heading (as ArduPilot's MAG_CAL_YAW): field {F:.6g} {shown}, inclination {incl:.3f} "
                       f"deg, declination {decl:.3f} deg ({source}); true heading "
                       + (f"{float(req.heading):.2f} deg" if req.heading is not None else
                          f"from column {req.heading_column}")
                       + f"; matrix held: {cal.diagnostics['fixed_heading']['matrix_held']}")
    for k, axis in enumerate("xyz"):
        messages.append(f"  offset_{axis} = {cal.offset[k]:.6g} +- {std[f'hard_iron_{axis}']:.3g} {shown}")
    misfit = heading_misfit_message(cal)
    if misfit:
        messages.append(f"warning: {misfit}")
    cal, card_lines = attach_deviation_card(cal, samples, rotation, decl, incl, yaw,
                                            "the heading column" if req.heading_column else "the heading given")
    ref = ScalarReference(np.full(len(samples.field), F), source, unit)
    return samples, cal, ref, messages + card_lines


def _field_vector(req: FitRequest, unit: str) -> tuple[float, float, float, str]:
    """The field's magnitude (``unit``), inclination and declination (degrees) for a fixed heading."""
    given = req.reference
    if given.background_ned is not None:
        from ._inputs import _parse_vector

        n, e, d = _parse_vector(given.background_ned, "`background_ned`")
        return float(np.linalg.norm([n, e, d])), float(np.degrees(np.arctan2(d, np.hypot(n, e)))), \
            float(np.degrees(np.arctan2(e, n))), "`background_ned`"
    if given.igrf_spec is None:
        raise TrimagInputError("a fixed heading needs the field's vector at the site: give "
                               "`igrf_spec=LAT,LON,ALT_M,DATE` (a log with a GPS fix has it) or `background_ned=N,E,D`")
    north, east, down = (convert(v, "nT", unit) for v in igrf(*parse_igrf_spec(given.igrf_spec)).ned_nT)
    return (float(np.linalg.norm([north, east, down])), float(np.degrees(np.arctan2(down, np.hypot(north, east)))),
            float(np.degrees(np.arctan2(east, north))), f"IGRF at {given.igrf_spec}")


def attach_deviation_card(cal: Calibration, samples: Samples, rotation: Any, declination_deg: float,
                          inclination_deg: float | None, reference_deg: Any = None,
                          reference_label: str = "the heading column") -> tuple[Calibration, list[str]]:
    """The deviation card of the fit (:func:`trimag.vehicle.heading.deviation_card`) into the calibration's
    diagnostics, and its table for the user. Before: the log's onboard calibration (what the autopilot used), or
    the raw reading; the reference: ``reference_deg`` (a heading column), else the new calibration's own heading
    (then the card is the old compass's deviation, and the new one's predicted sigma)."""
    from ..vehicle.heading import deviation_card, deviation_table, predicted_heading_sigma, tilt_compensated_heading

    n = len(samples.field)
    down = np.tile([0.0, 0.0, 1.0], (n, 1)) if rotation is None else rotation.inv().apply([0.0, 0.0, 1.0])
    logged = [f"mag_logged_{a}" for a in "xyz"]
    if samples.log_info is not None and all(c in samples.table.columns for c in logged):
        before_field, before = samples.table[logged].to_numpy(dtype=np.float64), "the onboard calibration"
    else:
        before_field, before = samples.field, "raw"
    ok = np.isfinite(before_field).all(axis=1)
    after_deg = tilt_compensated_heading(cal.apply(samples.field), -down, declination_deg=declination_deg)
    before_deg = np.where(ok, 0.0, np.nan)
    before_deg[ok] = tilt_compensated_heading(before_field[ok], -down[ok], declination_deg=declination_deg)
    reference = after_deg if reference_deg is None else np.asarray(reference_deg, dtype=np.float64)
    sigma = None
    if inclination_deg is not None:
        def sigma(h: Any) -> Any:
            return predicted_heading_sigma(cal, inclination_deg, h)["sigma_deg"]
    card = deviation_card(reference[ok], before_deg[ok], None if reference_deg is None else after_deg[ok],
                          after_sigma=sigma)
    card.update({"before_label": before, "reference": reference_label if reference_deg is not None else
                 "the new calibration's heading", "declination_deg": declination_deg,
                 "level": rotation is None})
    heading = "true" if declination_deg else "magnetic"
    lines = [f"deviation card ({heading} heading; before: {before}; reference: {card['reference']}"
             + ("; the vehicle taken as level" if rotation is None else "") + "):", deviation_table(card)]
    return cal.with_diagnostics(deviation_card=card), lines
