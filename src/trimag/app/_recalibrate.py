"""``trimag fit --prior``: the quick recalibration (keep an earlier calibration's matrix, refit its offset)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..errors import TrimagInputError
from ..fields.reference import igrf, parse_igrf_spec
from ..io import Samples
from ..units import normalise_unit, unit_after
from ._inputs import (
    attitudes_of,
    calibration_regressors,
    drop_rows_without_attitude,
    magnitude_reference,
    regressor_columns,
)
from .requests import FitRequest


def prior_units(req: FitRequest, prior: Calibration, log_unit: bool = False) -> tuple[FitRequest, list[str]]:
    """The data's unit against the prior calibration's: a clash is refused, an unstated unit is the prior's
    (``log_unit``: the unit is the one an autopilot log records)."""
    given = req.input.units
    if given is not None:
        unit = normalise_unit(given)
        if "unknown" not in (unit, prior.units) and unit != prior.units:
            data = f"the log records {unit}" if log_unit else f"`units={given}`"
            raise TrimagInputError(
                f"the prior calibration {req.prior} is for data in {prior.units}, but {data}: its matrix is kept, so "
                "the data must be in its unit (fit the prior from data in the same unit)"
            )
        return req, []
    if prior.units == "unknown":
        return req, []
    return (dataclasses.replace(req, input=dataclasses.replace(req.input, units=prior.units)),
            [f"unit {prior.units} (from the prior calibration)"])


def _inclination(igrf_spec: str | None) -> float | None:
    """The IGRF inclination (degrees, positive down) at a site ``LAT,LON,ALT_M,DATE``; None without a site."""
    if igrf_spec is None:
        return None
    north, east, down = igrf(*parse_igrf_spec(igrf_spec)).ned_nT
    return float(np.degrees(np.arctan2(down, np.hypot(north, east))))


def refit_prior(
    req: FitRequest, samples: Samples, unit: str, prior: Calibration, options: dict[str, Any]
) -> tuple[Samples, Calibration, dict[str, NDArray[np.float64]] | None, list[str]]:
    """Quick recalibration (:func:`trimag.vehicle.prior.refit_offset`): ``(samples, calibration, regressor values,
    messages)``."""
    from ..vehicle.prior import file_digest, refit_offset

    given, att = req.reference, req.attitude
    messages = [f"quick recalibration: the matrix{' and regressor terms' if prior.regressors else ''} of "
                f"{req.prior} (model {prior.model}, method {prior.method}) kept; the offset refitted"]
    if given.background_ned is not None or given.background_run is not None:
        raise TrimagInputError("a quick recalibration (`prior`) uses the field magnitude (and the inclination), not "
                               "a background vector: give `reference=F` or `igrf_spec=LAT,LON,ALT_M,DATE`")
    attitude = None
    if att.attitude_columns is not None or att.quaternion_columns is not None:
        samples, n_no_attitude = drop_rows_without_attitude(samples, att.attitude_columns, att.quaternion_columns,
                                                            strict=req.input.strict)
        if n_no_attitude:
            messages.append(f"dropped {n_no_attitude} rows whose attitude is missing or non-numeric")
        attitude = attitudes_of(samples, att)
    ref = magnitude_reference(samples, given, unit)
    F: Any = ref.values
    if F is None:
        value = (prior.reference or {}).get("value")
        if value is None:
            raise TrimagInputError("a quick recalibration (`prior`) needs the field magnitude: give `reference=F`, "
                                   "`igrf_spec=LAT,LON,ALT_M,DATE` or `reference_column=NAME` (the prior states none)")
        F = float(value)
        messages.append(f"field magnitude F = {F:.6g} {unit_after(unit)} (the prior calibration's reference)")
    elif ref.source.startswith("igrf"):
        messages.append(f"reference from {ref.source}: F = {float(np.asarray(F).ravel()[0]):.6g} {unit_after(unit)}")
    inclination = options.get("inclination_deg")
    inclination = float(inclination) if inclination is not None else _inclination(given.igrf_spec)
    if attitude is not None and inclination is None:
        messages.append("warning: attitudes given without an inclination (`igrf_spec` or `option inclination_deg`): "
                        "only the magnitude is used")
    if attitude is None:
        inclination = None
    regressor_values = None
    if prior.regressors is not None and prior.regressors.get("eddy"):  # derived from the data (trimag.vehicle.eddy)
        regressor_values = calibration_regressors(prior, samples, req.input.path,
                                                  time_column=req.attitude.time_column, rate_hz=req.rate_hz)
    elif prior.regressors is not None:
        regressor_values = regressor_columns(samples, tuple(prior.regressors["names"]), req.input.path,
                                             "a regressor of the prior calibration")
    sigma = options.get("prior_offset_sigma")
    cal = refit_offset(
        prior, samples.field, F, regressors=regressor_values, attitude=attitude, inclination_deg=inclination,
        prior_offset_sigma=None if sigma is None else float(sigma),
        scale_sigma=float(options.get("scale_sigma", 0.005)),
        inclination_sigma_deg=float(options.get("inclination_sigma_deg", 0.2)),
        prior_source={"path": str(req.prior), "sha256": file_digest(str(req.prior))},
    )
    cal = dataclasses.replace(cal, reference={"value": float(np.mean(F)), "source": ref.source if ref.known else
                                              "prior", "unit": unit})
    from ..io.export import keep_firmware_record  # the firmware models: only a --prior fit imports them

    cal = keep_firmware_record(prior, cal)  # the orientation, firmware level and motor term of a firmware fit
    fw = cal.diagnostics.get("firmware")
    if isinstance(fw, dict) and fw.get("target"):
        messages.append(f"kept from {req.prior}: the {fw['target']} fit's {fw.get('level')} level, orientation "
                        f"{fw.get('orientation_name') or fw.get('orientation')}"
                        + (f" and {fw['motor_type']} motor term" if fw.get("motor_type") else "")
                        + "; its offsets recomputed for the firmware's formula")
    d = cal.diagnostics["prior"]
    by_reference = []
    for name, c in d["components"].items():
        if c["identified_by_data"]:
            state = "identified"
        elif c["identified"]:
            by_reference.append(name)
            matrix = c.get("std_from_prior_matrix") or 0.0
            state = (f"from {c['identified_by']} (sigma from the reference {c['std_from_reference']:.3g}, "
                     + (f"from the prior's matrix {matrix:.3g}, " if matrix >= 0.05 * c["std"] else "")
                     + f"from the data {c['std_from_data']:.3g})")
        else:
            state = "NOT identified by these data (value and sigma from the priors)"
        messages.append(f"  {name} = {c['value']:.6g} +- {c['std']:.3g} {unit_after(unit)} "
                        f"(prior {c['prior_value']:.6g}): {state}")
    if by_reference:
        scale = d["field_scale"]["prior_std"]
        messages.append(f"{', '.join(by_reference)}: the data alone cannot tell it from the field's magnitude (the "
                        f"vehicle barely tilted); the known magnitude fixes it, to the reference's {100 * scale:.2g} % "
                        "(`option scale_sigma`): tilt the vehicle while it turns, or give a better reference, to "
                        "shrink its sigma")
    if d["unidentified"]:
        messages.append(f"unidentified: {', '.join(d['unidentified'])}: these data do not fix it beyond the prior "
                        "(turn the vehicle through more headings and tilt it), or keep the prior's value")
    return samples, cal, regressor_values, messages

