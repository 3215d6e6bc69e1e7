"""Checks of a fit before and after it: the data's unit, the acceptance policy, and the refusals of what cannot be
right (a static or unidentified autopilot log, an impossible attitude-based fit)."""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..errors import TrimagError, TrimagInputError
from ..estimators import make_estimator
from ..fields.reference import igrf, parse_igrf_spec
from ..io import Samples
from ..quality.metrics import row_norms
from ..units import normalise_unit, plausible_units, unit_after


def check_unit(
    samples: Samples, units: str | None, reference: str | float | None, igrf_spec: str | None
) -> tuple[str | None, list[str]]:
    """The data's unit, checked against the column headers (issue 22): a unit in the headers that contradicts
    ``units`` is refused (exit 2); without ``units`` it is used. Whether the unit is plausible is judged after the
    fit, on the fitted field (:func:`check_fitted_field`): the raw magnitudes include the hard iron (a phone's is
    ~10 x the Earth's field), so they cannot tell a unit (issue 32). They can tell a reference that is too large:
    a median below 1/5 of the reference is refused before the fit (:func:`refuse_below_reference`, issue 33)."""
    from ..units import header_unit

    messages: list[str] = []
    in_header = header_unit(list(samples.columns))
    said = f"the column headers say {in_header} ({', '.join(samples.columns)})"
    if in_header is None and samples.stated_unit:  # a `trimag live` recording's first line
        in_header, said = normalise_unit(samples.stated_unit), f"the file's first line says unit {samples.stated_unit}"
    if in_header is not None:
        if units is not None and normalise_unit(units) != in_header:
            raise TrimagInputError(f"{said} but `units={units}`; give the data's real unit")
        if units is None:
            units = in_header
            where = "the column headers" if said.startswith("the column") else "the file's first line"
            messages.append(f"unit {in_header} (from {where})")
    if len(samples.field):  # raw magnitudes never fall far below the field, hard iron or not (issue 33)
        # one array of N magnitudes, partitioned in place (norm's (N, 3) squares and median's copy were the peak of
        # a short-row log's fit: issue 41, item 10)
        median = float(np.median(row_norms(samples.field), overwrite_input=True))
        refuse_below_reference(median, normalise_unit(units), reference, igrf_spec, field=samples.field)
    return units, messages


def check_log_unit(units: str | None, log_info: dict[str, Any] | None, columns: Any) -> str | None:
    """The unit of a vehicle log's magnetometer, which the log states: a different ``units`` is refused (exit 2)
    unless ``columns`` picks other columns."""
    if log_info is None or columns is not None:
        return units
    if units is not None and normalise_unit(units) != log_info["unit"]:
        raise TrimagInputError(
            f"the log records {log_info['sensor']} in {log_info['unit']}; drop `units={units}` (it is known)"
        )
    return units or str(log_info["unit"])


#: How far (a factor either way) the data's fitted sphere may be from the reference field in a unit for that unit to be
#: named as the data's likely one (soft iron and the local anomaly move it by a few per cent to some tens).
LIKELY_UNIT_FACTOR = 1.5


#: The mean resultant length of the directions about a fitted sphere's centre above which the data cover too small a
#: cap for its radius to mean anything (a 25 deg cap gives ~0.95; a full turn about one axis ~0.1).
CAP_RESULTANT = 0.8


def sphere_radius(field: NDArray[np.float64]) -> float | None:
    """The radius of the sphere that best fits ``field`` (N, 3) algebraically (centre free); None when none does or
    the directions about its centre cover too small a cap (:data:`CAP_RESULTANT`) for the radius to be defined."""
    if len(field) < 4:
        return None
    design = np.column_stack([2.0 * field, np.ones(len(field))])
    solution, *_ = np.linalg.lstsq(design, np.einsum("ij,ij->i", field, field), rcond=None)
    r2 = float(solution[3] + solution[:3] @ solution[:3])
    if not (np.isfinite(r2) and r2 > 0):
        return None
    about = field - solution[:3]
    norms = np.linalg.norm(about, axis=1, keepdims=True)
    directions = about / np.where(norms > 0, norms, 1.0)
    return float(np.sqrt(r2)) if np.linalg.norm(directions.mean(axis=0)) < CAP_RESULTANT else None


def likely_unit(field: NDArray[np.float64] | None, reference_nT: float) -> tuple[str, float] | None:
    """The physical unit in which the data's fitted sphere (:func:`sphere_radius`) is closest to the reference field
    ``reference_nT``, within :data:`LIKELY_UNIT_FACTOR`: ``(unit, the radius in it)``, or None (issue 38)."""
    from ..units import UNITS

    radius = sphere_radius(field) if field is not None else None
    if radius is None or not reference_nT > 0:
        return None
    ratios = {u: radius * f / reference_nT for u, f in UNITS.items() if f is not None and u != "1e4nT"}
    unit = min(ratios, key=lambda u: abs(np.log(ratios[u])))
    return (unit, radius) if abs(np.log(ratios[unit])) <= np.log(LIKELY_UNIT_FACTOR) else None


def refuse_below_reference(median: float, unit: str, reference: str | float | None, igrf_spec: str | None,
                           field: NDArray[np.float64] | None = None) -> None:
    """Refuse raw data whose median magnitude is below 1/5 of the reference, whatever the unit and even inside the
    Earth range (issue 33: 6.9x below was accepted). Raw magnitudes do not fall below the field: over the
    directions of a turn ``|F u + h|`` has a median of ``sqrt(F^2 + |h|^2) >= F``; hard iron only adds (which is why
    data far above the reference are not refused here)."""
    from ..units import nT_per_unit

    F: float | None = None
    if reference is not None and str(reference).strip().lower() != "mean":
        try:
            F = float(reference)  # in the data's unit
        except ValueError:
            F = None
    elif igrf_spec is not None and unit not in ("unknown", "counts"):
        F = float(igrf(*parse_igrf_spec(igrf_spec)).total_nT) / nT_per_unit(unit)
    if F is not None and F > 0 and median < 0.2 * F:
        shown = f" {unit}" if unit not in ("unknown", "counts") else ""
        blame = ("the reference or the data's unit is wrong" if (igrf_spec is not None and reference is None)
                 or unit not in plausible_units(median, field=True) else
                 f"the data's field is one in {unit}: give `reference` in the data's unit ({unit})")
        likely = likely_unit(field, F * nT_per_unit(unit)) if unit not in ("unknown", "counts") else None
        if likely is not None and likely[0] != unit:  # a unit in which the data's sphere is the reference field
            blame = (f"the data look like {likely[0]} (their fitted sphere's radius {likely[1]:.4g} is "
                     f"{likely[1] * nT_per_unit(likely[0]) / (F * nT_per_unit(unit)):.2f}x the reference field in "
                     f"{likely[0]}): give `units={likely[0]}`")
        raise TrimagInputError(
            f"the data's median |B| is {median:.6g}{shown}, {median / F:.3g}x the reference field ({F:.6g}{shown}): "
            f"raw magnitudes are never that far below the field; {blame}"
        )


def check_fitted_field(cal: Calibration, unit: str, *, autopilot_log: bool = False) -> list[str]:
    """Is the fit's field an Earth field in the data's unit? (issue 32, items 1 and 4)

    With the magnitude fitted (no reference), ``F`` must lie in :data:`~trimag.units.EARTH_FIELD_RANGE_NT` (the
    range ArduPilot's onboard calibrator accepts). Outside it: a warning naming the unit in which it would be one
    (the unit is wrong); else a refusal (exit 3) when the fit is poorly identified or comes from an autopilot log (the
    fit is wrong: the firmware would refuse it too), a warning otherwise. With a known reference, the correction's
    gain ``|det K|^(1/3)`` gives the field's size in the data's numbers: more than 5 x off the reference is refused
    (exit 2, naming the likely unit). Returns the warning lines.
    """
    from ..errors import IdentifiabilityError
    from ..estimators._finish import COVERAGE_WARN
    from ..units import EARTH_FIELD_RANGE_NT, nT_per_unit

    ref = cal.reference or {}
    value = ref.get("value")
    if unit in ("unknown", "counts") or value is None or not np.isfinite(value) or value <= 0:
        return []
    if ref.get("source") != "mean":  # a known reference: the gain of the correction says the data's scale
        gain = float(abs(np.linalg.det(np.asarray(cal.matrix)))) ** (1.0 / 3.0)
        raw_field = float(value) / gain if gain > 0 else float("inf")
        ratio = raw_field / float(value)
        if not 0.2 <= ratio <= 5.0:
            likely = plausible_units(raw_field, field=True)
            if unit in likely:  # the data's field is an Earth field in their unit: the reference is what is off
                other = [u for u in plausible_units(float(value), field=True) if u != unit]
                in_other = f" (it would be one in {' or '.join(other)})" if other else ""
                raise TrimagInputError(
                    f"the reference field {float(value):.6g} {unit} is not an Earth field in {unit}{in_other}, while "
                    f"the data's field is {raw_field:.6g} {unit}: give `reference` in the data's unit ({unit})"
                )
            guess = f"; the numbers look like {' or '.join(likely)}" if likely else ""
            raise TrimagInputError(
                f"the field in the data is {raw_field:.6g} {unit} (the correction's gain is {gain:.3g}), {ratio:.3g}x "
                f"the reference field ({float(value):.6g} {unit}): the data are not in {unit}{guess}; give the right "
                "unit"
            )
        return []
    F = float(value)
    lo, hi = (v / nT_per_unit(unit) for v in EARTH_FIELD_RANGE_NT)
    if lo <= F <= hi:
        return []
    text = f"the fitted field magnitude F = {F:.4g} {unit} is not a plausible Earth field in {unit} ({lo:.3g}-{hi:.3g})"
    likely = [u for u in plausible_units(F, field=True) if u != unit]
    coverage = (cal.diagnostics.get("coverage") or {}).get("fraction")
    weak = (cal.diagnostics.get("identifiability") or {}).get("warning") is not None or (
        coverage is not None and coverage < COVERAGE_WARN)
    if likely and not weak:  # a well identified fit: its F is right, the unit is not
        return [f"warning: {text}; the numbers look like {' or '.join(likely)}; check the unit"]
    if weak or autopilot_log:  # a poorly identified fit's F says nothing of the unit: the fit is wrong
        seen = f" (the field directions cover {100 * coverage:.0f}% of the sphere)" if coverage is not None else ""
        unit_too = f" (if the data are in {' or '.join(likely)}, give that unit)" if likely else ""
        raise IdentifiabilityError(
            f"{text}: the fit cannot be right; the rotations recorded do not identify the model{seen}{unit_too}. "
            "Record the sensor turning through all attitudes, or give the field's magnitude (`reference`, `igrf`)"
        )
    return [f"warning: {text}: check the unit and the sensor's scale, or give the field's magnitude (`reference`)"]


#: the words of a fit's warning that its numbers look like another unit (:func:`check_fitted_field`)
UNIT_DOUBT = "the numbers look like"


def unit_doubt(messages: list[str]) -> str | None:
    """The fit's warning that its numbers look like another unit (recorded in the calibration as
    ``diagnostics.unit_doubt``, so that ``export`` refuses it: issue 41, item 9), or None."""
    for message in messages:
        if message.startswith("warning:") and UNIT_DOUBT in message:
            return message.removeprefix("warning:").strip()
    return None


def policy_verdict(cal: Calibration, limits: dict[str, float], ref: Any, igrf_spec: str | None) -> dict[str, Any]:
    """The acceptance policy's verdict (:func:`trimag.vehicle.policy.check_policy`) with the site's inclination
    and F."""
    from ..vehicle.policy import check_policy

    inclination = None
    if igrf_spec is not None:
        north, east, down = igrf(*parse_igrf_spec(igrf_spec)).ned_nT
        inclination = float(np.degrees(np.arctan2(down, np.hypot(north, east))))
    values = getattr(ref, "values", None)
    F = float(np.mean(values)) if values is not None else None
    return check_policy(cal, limits, inclination_deg=inclination, reference_F=F)


def worse_than_raw(cal: Calibration) -> bool:
    """Whether the fit's corrected data miss the reference by more than the raw data, beyond round-off
    (:data:`~trimag.validation.ROUNDOFF_FRACTION` of the field)."""
    from ..validation import ROUNDOFF_FRACTION

    before, after = cal.stats.get("rms_before"), cal.stats.get("rms_after")
    field = (cal.reference or {}).get("value") or cal.stats.get("mean_norm_after") or 0.0
    return before is not None and after is not None and float(after) > float(before) and \
        float(after) > ROUNDOFF_FRACTION * abs(float(field))


def _attitude_alternatives(
    samples: Samples, attitude_columns: str | None, quaternion_columns: str | None, quaternion_order: str,
    quaternion_frame: str,
) -> list[tuple[str, Any]]:
    """The usual mistakes of an attitude convention, each as (what to give instead, attitudes)."""
    from itertools import permutations

    from ..fields import attitude as _attitude

    out: list[tuple[str, Any]] = []

    def build(label: str, **kwargs: Any) -> None:
        try:
            rot = _attitude.attitude_from_table(samples.table, **kwargs)
        except TrimagInputError:
            return
        out.append((label, rot))
        out.append((f"{label} with the rotation inverted (navigation -> body)", rot.inv()))

    if attitude_columns is not None:
        names = [c.strip() for c in attitude_columns.split(",")]
        for perm in permutations(names):
            build(f"attitude columns {','.join(perm)}", euler_columns=",".join(perm))
    if quaternion_columns is not None:
        for order in ("wxyz", "xyzw"):
            for frame in ("ned", "enu"):
                build(f"quaternion order {order}, frame {frame}", quaternion_columns=quaternion_columns,
                      scalar_first=order == "wxyz", frame=frame)
    return out


def refuse_impossible_vector_fit(
    cal: Calibration, samples: Samples, ref: Any, unit: str, model: str, method: str | None,
    options: dict[str, Any] | None, attitude_columns: str | None, quaternion_columns: str | None,
    quaternion_order: str, quaternion_frame: str,
) -> None:
    """Refuse an attitude-based fit that cannot be right: worse than the raw data, or a reflection (det < 0).

    The usual convention mistakes (Euler column order, an inverted rotation, quaternion scalar first/last, ENU
    for NED) are tried; a much better one is named (exit 2), else the fit is refused as unidentified (exit 3).
    """
    from ..errors import IdentifiabilityError

    det = float(np.linalg.det(np.asarray(cal.matrix)))
    if not (worse_than_raw(cal) or det <= 0):
        return
    before, after = float(cal.stats["rms_before"]), float(cal.stats["rms_after"])
    what = f"RMS {after:.4g} {unit_after(unit)} after against {before:.4g} before" + (
        "; det(K) < 0, a reflection" if det <= 0 else "")
    best: tuple[float, str] | None = None
    for label, rot in _attitude_alternatives(samples, attitude_columns, quaternion_columns, quaternion_order,
                                             quaternion_frame):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                alt = make_estimator(model, method, options).fit(samples.field, ref, units=unit, attitude=rot)
        except TrimagError:
            continue
        alt_cal = alt.calibration_
        alt_after = float(alt_cal.stats["rms_after"])
        if np.linalg.det(np.asarray(alt_cal.matrix)) > 0 and (best is None or alt_after < best[0]):
            best = (alt_after, label)
    if best is not None and best[0] < 0.5 * min(before, after):
        raise TrimagInputError(
            f"the correction fitted with these attitudes cannot be right ({what}); with {best[1]} it reaches "
            f"RMS {best[0]:.4g} {unit}: the attitudes are probably in that convention (docs/conventions-attitude.md)"
        )
    raise IdentifiabilityError(
        f"the correction fitted with these attitudes cannot be right ({what}), and no usual convention mistake "
        "explains it: check the attitudes (Z-Y-X yaw, pitch, roll in degrees, body -> NED), the background field "
        "and the unit"
    )


def _field_directions(B: Any) -> Any:
    """Unit field directions (N, 3) of raw samples: about the centre of the sphere they lie on when they do lie on one
    (its residuals below 10 % of its radius: a phone's ~10 x hard iron would otherwise hide a whole tumble in a few
    degrees, issue 32), else the raw vectors themselves (a static or barely turned sensor)."""
    from ..quality.diagnostics import sphere_centre

    centre = sphere_centre(B)
    if centre is not None:
        d = B - centre
        radius = np.linalg.norm(d, axis=1)
        if np.all(radius > 0) and float(np.std(radius)) < 0.1 * float(np.mean(radius)):
            return d / radius[:, None]
    return B / np.linalg.norm(B, axis=1, keepdims=True)


def refuse_static_log(samples: Samples, log_info: dict[str, Any]) -> None:
    """Refuse (exit 3) a log whose magnetometer barely turned, saying what to fly or log instead."""
    from ..errors import IdentifiabilityError

    B = samples.field
    n = len(B)
    name = log_info["sensor"]
    if n < 30:
        raise IdentifiabilityError(
            f"{name} has only {n} samples in this log: too few to calibrate. Log the magnetometer faster or longer "
            "and turn the vehicle through all headings and attitudes"
        )
    u = _field_directions(B)
    mean = u.mean(axis=0)
    mean /= np.linalg.norm(mean)
    cone = float(np.degrees(np.arccos(np.clip(u @ mean, -1.0, 1.0))).max())
    if cone < 30.0:
        raise IdentifiabilityError(
            f"{name}: the field direction stayed within {cone:.0f} deg of its mean over {n} samples: the vehicle "
            "barely turned. Record a calibration: rotate the vehicle through all headings, nose up and down and on "
            "each side (on the ground or in flight), then fit that log"
        )


def refuse_unidentified_log(cal: Calibration | None, samples: Samples, log_info: dict[str, Any]) -> None:
    """Refuse (exit 3) an autopilot log that the rotation recorded cannot identify.

    A vehicle that turns about its vertical axis with little tilt (a rover, a boat, a level flight) leaves the
    field directions in a narrow band: the full 3-D calibration is then not identified, and an autopilot would be
    given parameters that are wrong in the unseen directions. The verdict is the data's, taken before the fit with
    ``cal`` None (issue 32): the covered share of the sphere of directions
    (:func:`~trimag.quality.diagnostics.data_coverage`) below :data:`~trimag.estimators._finish.COVERAGE_WARN`, so
    that a log and the parts of it are judged alike, in the same words whatever the method. After the fit (``cal``),
    a fit that did not converge is refused the same way.
    """
    from ..errors import IdentifiabilityError
    from ..estimators._finish import COVERAGE_WARN
    from ..quality.diagnostics import data_coverage

    if cal is None:
        coverage, converged = data_coverage(samples.field)["fraction"], True
    else:
        coverage = (cal.diagnostics.get("coverage") or {}).get("fraction")
        converged = cal.stats.get("converged", True)
    if converged and (coverage is None or coverage >= COVERAGE_WARN):
        return
    B = samples.field
    u = B / np.linalg.norm(B, axis=1, keepdims=True)
    axis = u.mean(axis=0)
    axis /= np.linalg.norm(axis)
    angle = np.degrees(np.arccos(np.clip(u @ axis, -1.0, 1.0)))
    detail = [f"the field directions cover {100 * coverage:.0f}% of the sphere" if coverage is not None else "",
              f"they stay {angle.min():.0f}..{angle.max():.0f} deg from their mean direction "
              f"{np.round(axis, 2).tolist()} (body frame)",
              "the fit did not converge" if not converged else ""]
    raise IdentifiabilityError(
        f"{log_info['sensor']}: this log turned the vehicle mostly about one axis "
        f"({'; '.join(d for d in detail if d)}): "
        "a 3-D calibration cannot be identified from it. Record a calibration with the vehicle also pitched "
        "nose up and down and rolled on each side; a vehicle that cannot tilt needs an earlier full calibration "
        "whose offsets are refitted"
    )
