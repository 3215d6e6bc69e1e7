"""``trimag fit``: read a log, take its reference (and attitudes), fit, check, write (:class:`FitRequest
<trimag.app.requests.FitRequest>` in, :class:`FitResult` out)."""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..errors import IdentifiabilityError, TrimagInputError, TrimagWarning
from ..estimators import make_estimator
from ..fields.reference import ScalarReference, igrf, parse_igrf_spec
from ..io import Samples, column_values, read_samples
from ..io.atomic import check_distinct_outputs
from ..units import normalise_unit, unit_after
from ..validation import check_reference_magnitude
from ._alignment import alignment_lines, dip_check
from ._checks import (
    check_fitted_field,
    check_log_unit,
    check_unit,
    policy_verdict,
    refuse_impossible_vector_fit,
    refuse_static_log,
    refuse_unidentified_log,
    unit_doubt,
    worse_than_raw,
)
from ._gyro import angular_rate, gyro_lines, gyro_requested, log_has_gyro
from ._inputs import (
    accel_values,
    attitudes_of,
    background_field,
    calibration_for,
    drop_rows_without_attitude,
    drop_rows_without_background,
    magnitude_reference,
    parse_regressor_names,
    regressor_columns,
    truthy,
)
from ._large import MODE_OPTIONS, fit_fixed_heading_file, fit_level_turn_file, large_mode
from ._log_advice import log_refusal
from ._outputs import write_fit_outputs
from ._recalibrate import prior_units, refit_prior
from ._sensor import input_for, sensor_record
from ._timesync import attach_attitude_file
from .requests import FitRequest, as_request

__all__ = ["FitResult", "fit_file", "fit_summary"]


@dataclass
class FitResult:
    """What :func:`fit_file` produced."""

    calibration: Calibration
    samples: Samples
    summary: dict[str, Any]
    messages: list[str] = field(default_factory=list)
    written: dict[str, str] = field(default_factory=dict)


def fit_inputs(req: FitRequest) -> dict[str, str | Path | None]:
    """The files a fit reads, by their option's name (what its outputs must not replace)."""
    return {"the input": req.input.path, "the `prior`": req.prior, "the `attitude_file`": req.attitude.attitude_file,
            "the `gyro_file`": req.gyro_file, "the `background_run`": req.reference.background_run,
            "the `policy`": None if req.policy == "default" else req.policy}


def fit_summary(cal: Calibration, samples: Samples | None = None) -> dict[str, Any]:
    """The JSON object ``trimag fit --json`` prints (see docs/cli.md for the keys)."""
    d = cal.as_dict()
    s = d["stats"]
    out: dict[str, Any] = {
        "model": cal.model,
        "method": cal.method,
        "units": cal.units,
        "n_samples": samples.n_rows if samples is not None else s.get("n_samples"),
        "n_used": s.get("n_used"),
        "n_dropped": samples.n_dropped if samples is not None else 0,
        "n_wild": samples.n_wild if samples is not None else 0,
        "n_duplicates": samples.n_duplicates if samples is not None else None,
        "reference": d["reference"],
        "rms_before": s.get("rms_before"),
        "rms_after": s.get("rms_after"),
        "max_abs_before": s.get("max_abs_before"),
        "max_abs_after": s.get("max_abs_after"),
        "converged": s.get("converged"),
        "iterations": s.get("iterations"),
        "params": d["params"],
        "matrix": d["matrix"],
        "offset": d["offset"],
        "uncertainty": d["uncertainty"],
        "diagnostics": d["diagnostics"],
    }
    if cal.regressors is not None:
        out["regressors"] = {**d["regressors"], "ranking": d["diagnostics"].get("regressors", {}).get("ranking")}
        out["rms_after_without_regressors"] = s.get("rms_after_without_regressors")
    if samples is not None:
        out["columns"] = list(samples.columns)
        out["variable"] = samples.variable or None  # an NPZ or MAT file's variable
        out["selection"] = samples.selection
        out["source"] = samples.source
    return out


def fit_file(request: FitRequest | str | Path, **arguments: Any) -> FitResult:
    """Read a log, fit a calibration, write the calibration JSON and the report PNG when asked.

    ``request``: a :class:`~trimag.app.requests.FitRequest`, or a path with the request's fields as keyword arguments
    (:meth:`FitRequest.of <trimag.app.requests.FitRequest.of>`). With a ``policy`` (a TOML file or ``"default"``,
    :mod:`trimag.vehicle.policy`) the calibration is checked against its limits; the result is in
    ``summary["acceptance"]`` and in the written file (a rejected calibration is still written, marked so).
    """
    req = as_request(FitRequest, request, (), arguments)
    if str(req.input.sensor).strip().lower() == "all":
        raise TrimagInputError("`sensor=all` fits every compass of a log: call trimag.app.fit_all_sensors (on the "
                               "command line, trimag fit LOG --sensor all)")
    if req.export_to is not None or req.export_out is not None:
        raise TrimagInputError("`export_to` and `export_out` write every compass of a log to one file: give "
                               "`sensor=all` (for one calibration, use trimag export)")
    check_distinct_outputs(fit_inputs(req), {"out": req.out, "report": req.report,
                                             "deviation_card": req.deviation_card})
    from ..vehicle.policy import read_policy

    if req.report is not None and Path(req.report).suffix.lower() in (".html", ".htm"):
        from .._core.extras import require

        require("plotly", "an HTML report (report.html)")  # before the fit: a missing extra is said at once
    _check_reference_number(req.reference.reference)
    if req.rate_hz is not None and not (np.isfinite(float(req.rate_hz)) and float(req.rate_hz) > 0):
        raise TrimagInputError(f"`rate_hz` is the log's sample rate, a positive number of samples per second; got "
                               f"{req.rate_hz}")
    limits = read_policy(req.policy) if req.policy is not None else None
    regressor_names = parse_regressor_names(req.regressors)
    if regressor_names is not None:
        from ..vehicle.regressors import MODELS as REGRESSOR_MODELS

        if req.model not in REGRESSOR_MODELS:
            raise TrimagInputError(
                f"`regressors` works with the models {', '.join(REGRESSOR_MODELS)}; got {req.model!r}"
            )
    req = _rows_as_attitude_stream(req)
    mode = large_mode(req)
    options, sync_options, prior_options = _split_options(req, mode)
    eddy_terms = _eddy_terms(req, options)
    # (a phone export's gyroscope is known once it is read: its gyro fit's own options wait till then)
    # (a gyroscope named implies the gyro-aided method: its options are checked against it, not `ml`'s)
    named_gyro = req.gyro_columns is not None or req.gyro_file is not None
    method = "gyro" if named_gyro and req.method is None and req.model == "ellipsoid" else req.method
    estimator = make_estimator(req.model, method, {k: v for k, v in options.items()
                                                   if not (_phone_export(req) and k in _GYRO_OPTIONS)})
    src, sensor = req.input, req.input.sensor
    if req.prior is not None:  # a quick recalibration reads the prior's sensor by default (issue 39)
        src, sensor = input_for(calibration_for(req.prior, None, "`prior`"), src)
    samples = read_samples(src.path, fmt=src.fmt, columns=src.columns, var=src.var, rows=src.rows, where=src.where,
                           strict=src.strict, sensor=sensor)
    estimator, gyro_messages = _gyro_estimator(req, samples, estimator, options)
    try:
        return _fit_samples(req, samples, estimator, limits, regressor_names, eddy_terms, sync_options,
                            prior_options, mode, gyro_messages)
    except IdentifiabilityError as exc:  # a log: its compasses and the modes that would help (issue 30, item 7)
        if mode is not None or req.prior is not None:
            raise
        if samples.log_info is None:
            return _level_only(req, samples, exc)
        raise log_refusal(exc, samples.log_info, samples.field, target=req.target,
                          igrf_given=req.reference.igrf_spec is not None) from None


def _level_only(req: FitRequest, samples: Samples, exc: IdentifiabilityError) -> FitResult:
    """A table whose samples turned about one axis only (a vehicle that turns level: a boat, a rover): with a field
    reference, the default fit (model ellipsoid, no method, no step the level turn cannot take) is the level-turn
    fit, said; else the refusal names `level_turn` first, never only "record rotations about two more axes"
    (issue 38)."""
    from ..quality.diagnostics import FLAT_RATIO, principal_std

    spread = principal_std(samples.field)[0]
    if not spread[2] < FLAT_RATIO * spread[1]:  # not a turn about one axis
        raise exc
    given = req.reference
    reference = given.igrf_spec is not None or given.reference_column is not None or (
        given.reference is not None and str(given.reference).strip().lower() != "mean")
    # the level turn's vertical offset needs the field's inclination (IGRF's, or given): from a magnitude alone its
    # sign is a guess, so such a log is refused naming the level turn rather than fitted on a guess
    inclination = given.igrf_spec is not None or "inclination_deg" in (req.options or {})
    default = (req.model == "ellipsoid" and req.method is None and req.target is None and not req.regressors
               and req.accel_columns is None and req.attitude.attitude_file is None and not gyro_requested(req))
    if reference and default and inclination:
        try:
            result = fit_file(dataclasses.replace(req, level_turn=True))
        except (IdentifiabilityError, TrimagInputError) as level_exc:
            raise IdentifiabilityError(f"the samples turned about one axis only (a vehicle that turns level): the "
                                       f"level-turn fit (`level_turn`) fails too: {level_exc}") from None
        result.messages.insert(0, "the samples turned about one axis only (a vehicle that turns level) and the "
                                  "field's reference is given: fitted by the level-turn method, as `level_turn` "
                                  "asks (the horizontal offsets and scales from the turn, the vertical offset from "
                                  "the field's magnitude and inclination)")
        return result
    if reference and default:
        raise IdentifiabilityError(f"the samples turned about one axis only (a vehicle that turns level): fit it "
                                   f"with `level_turn` and the site (`igrf_spec=LAT,LON,ALT_M,DATE`) or the field's "
                                   f"inclination (`option inclination_deg=DEG`), which decide the vertical offset's "
                                   f"sign; {exc}") from None
    if reference:
        asked = f"model {req.model}" + (f" with method {req.method}" if req.method else "")
        raise IdentifiabilityError(f"the samples turned about one axis only (a vehicle that turns level): fit it "
                                   f"with `level_turn` (model ellipsoid, the default method), which needs no tilt; "
                                   f"{asked} cannot: {exc}") from None
    raise IdentifiabilityError(f"{exc} (a vehicle that cannot tilt, a boat or a rover: `level_turn` with the "
                               "field's reference, `igrf_spec=LAT,LON,ALT_M,DATE`, fits its level turns)") from None


def _fit_samples(
    req: FitRequest, samples: Samples, estimator: Any, limits: dict[str, float] | None,
    regressor_names: tuple[str, ...] | None, eddy_terms: int | None, sync_options: dict[str, Any],
    prior_options: dict[str, Any], mode: str | None, gyro_messages: list[str] | None = None,
) -> FitResult:
    """:func:`fit_file` after reading the samples (``gyro_messages``: the choice of the gyro-aided fit)."""
    req = _target_of(req, samples)
    src = req.input
    log_unit = samples.log_info is not None and src.units is None
    req, log_messages = _log_defaults(req, samples, estimator, mode)  # a vehicle log states its unit, site, attitudes
    messages = list(gyro_messages or []) + log_messages
    prior = None
    if req.prior is not None:
        if regressor_names is not None:
            raise TrimagInputError("`regressors` cannot be fitted in a quick recalibration (`prior`): it keeps the "
                                   "prior's regressor terms and refits only the offset; drop `regressors`")
        prior = calibration_for(req.prior, None, "`prior`")
        req, prior_messages = prior_units(req, prior, log_unit)
        messages += prior_messages
    units, unit_messages = check_unit(samples, req.input.units, req.reference.reference, req.reference.igrf_spec)
    unit = normalise_unit(units)
    messages += unit_messages + _reading_messages(samples)
    if req.target is not None:  # a firmware-space fit (app/_firmware.py)
        return _fit_target(req, samples, unit, messages, limits)
    sync = None
    if req.attitude.attitude_file is not None:
        samples, req, sync, sync_messages = attach_attitude_file(req, samples, unit, sync_options, estimator)
        messages += sync_messages
    if req.accel_columns is not None:
        from ..vehicle.alignment import check_tilt_variation

        # before the fit: a level log cannot give the alignment (exit 3, saying what to record)
        check_tilt_variation(accel_values(samples, req.accel_columns, src.path))
    warn_texts: list[str] = []
    ref: Any
    regressor_values: dict[str, NDArray[np.float64]] | None
    if mode == "level_turn":
        samples, cal, ref, mode_messages = fit_level_turn_file(req, samples, unit, prior_options)
        messages += mode_messages
        regressor_values = None
    elif mode == "heading":
        samples, cal, ref, mode_messages = fit_fixed_heading_file(req, samples, unit, prior, prior_options)
        messages += mode_messages
        regressor_values = None
    elif prior is not None:
        samples, cal, regressor_values, prior_messages = refit_prior(req, samples, unit, prior, prior_options)
        ref = ScalarReference(np.full(len(samples.field), float((cal.reference or {})["value"])), "prior", unit)
        messages += prior_messages
    else:
        samples, cal, ref, regressor_values, warn_texts, fit_messages = _fit_model(req, samples, estimator, unit,
                                                                                   regressor_names, eddy_terms)
        messages += fit_messages
        cal = _input_orientation(cal, samples)
    cal, summary, finish_messages = _finish(req, cal, samples, ref, regressor_values, warn_texts, limits, sync,
                                            prior is not None and mode is None)
    if samples.log_info is not None:
        summary["log"] = {"compass": samples.log_info.get("compass"), "name": samples.log_info.get("sensor"),
                          "format": samples.log_info.get("format")}
    cal = _record_unit_doubt(cal, messages)
    cal, written = write_fit_outputs(cal, samples, req, regressor_values)
    summary["outputs"] = written
    return FitResult(cal, samples, summary, messages + finish_messages + [f"warning: {w}" for w in warn_texts],
                     written)


def _rows_as_attitude_stream(req: FitRequest) -> FitRequest:
    """``estimate_lag`` (or ``max_lag``) with the attitudes in the data's own rows and no ``attitude_file``: the data
    file is also the attitude stream (its attitude columns on its time column), so the lag between the two sets of
    columns (a filter's delay) is searched as between two files (issue 42)."""
    att = req.attitude
    sync = any(k in req.options for k in ("estimate_lag", "max_lag"))
    in_rows = att.attitude_columns is not None or att.quaternion_columns is not None
    if not sync or not in_rows or att.attitude_file is not None or gyro_requested(req) or _phone_export(req):
        return req
    return dataclasses.replace(req, attitude=dataclasses.replace(att, attitude_file=req.input.path))


def _record_unit_doubt(cal: Calibration, messages: list[str]) -> Calibration:
    """The fit's doubt of the data's unit kept in the calibration (``diagnostics.unit_doubt``): export refuses it
    unless forced (issue 41, item 9: µT data declared nT exported offsets 1000x too small)."""
    doubt = unit_doubt(messages)
    return cal if doubt is None else cal.with_diagnostics(unit_doubt=doubt)


def _split_options(req: FitRequest, mode: str | None = None) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
    """The request's options split into the estimator's, the time synchronisation's (``estimate_lag``,
    ``max_lag``) and the quick recalibration's (or a large vehicle's ``mode``'s); an option of a step the request
    does not take is refused."""
    options = dict(req.options)
    # the gyro-aided fit's own lag options (a phone export with a gyroscope is fitted so by default)
    gyro = (gyro_requested(req) or _phone_export(req)) and req.attitude.attitude_file is None
    sync_options: dict[str, Any] = {} if gyro else {k: options.pop(k) for k in ("estimate_lag", "max_lag")
                                                    if k in options}
    prior_options: dict[str, Any] = {k: options.pop(k) for k in ("prior_offset_sigma", "scale_sigma", "inclination_deg",
                                                                 "inclination_sigma_deg", *MODE_OPTIONS)
                                     if k in options}
    if mode is not None:
        return options, sync_options, prior_options
    if set(prior_options) & set(MODE_OPTIONS):
        key = next(k for k in prior_options if k in MODE_OPTIONS)
        raise TrimagInputError(f"`option {key}` belongs to a large vehicle's fit; give `level_turn` or `heading`")
    if prior_options and req.prior is None:
        raise TrimagInputError(f"`option {next(iter(prior_options))}` belongs to a quick recalibration; give `prior`")
    if sync_options and req.attitude.attitude_file is None:
        raise TrimagInputError(f"`option {next(iter(sync_options))}` needs attitudes from a second file; give "
                               "`attitude_file`")
    return options, sync_options, prior_options


def _finish(
    req: FitRequest, cal: Calibration, samples: Samples, ref: Any,
    regressor_values: dict[str, NDArray[np.float64]] | None, warn_texts: list[str], limits: dict[str, float] | None,
    sync: dict[str, Any] | None, quick: bool,
) -> tuple[Calibration, dict[str, Any], list[str]]:
    """After the fit: the time synchronisation, the alignment (``accel_columns``), the counts, the warnings and the
    acceptance (``limits``) recorded in the calibration; ``(calibration, summary, messages)``. ``quick``: a quick
    recalibration (no predicted heading error)."""
    messages: list[str] = []
    # the sensor it belongs to: what evaluate, apply, export (its default instance), live and batch read
    cal = cal.with_sensor(sensor_record(samples, req.input, cal.units))
    if sync is not None:
        cal = cal.with_diagnostics(time_sync=sync)
    if cal.method == "gyro" and "gyro_alignment" in cal.diagnostics:
        cal, lines = gyro_lines(cal)
        messages += lines
    alignment_messages: list[str] = []
    if req.accel_columns is not None:
        from ..vehicle.alignment import fit_alignment

        accel = accel_values(samples, req.accel_columns, req.input.path)  # the rows the fit kept
        alignment = fit_alignment(cal, samples.field, accel, regressors=regressor_values)
        cal = cal.with_diagnostics(alignment={**alignment, "accel_columns": req.accel_columns})
        alignment_messages = alignment_lines(alignment)
    cal = cal.with_stats(n_samples=samples.n_rows, n_dropped=samples.n_dropped)
    if warn_texts:
        cal = cal.with_diagnostics(warnings=warn_texts)
    igrf_spec = req.reference.igrf_spec
    if limits is not None:
        cal = cal.with_diagnostics(acceptance=policy_verdict(cal, limits, ref, igrf_spec))
    summary = fit_summary(cal, samples)
    summary["warnings"] = warn_texts
    if limits is not None:
        summary["acceptance"] = cal.diagnostics["acceptance"]
    if sync is not None:
        summary["time_sync"] = sync
    if quick:
        summary["prior"] = cal.diagnostics["prior"]
    if req.accel_columns is not None:
        summary["alignment"] = cal.diagnostics["alignment"]
        messages += alignment_messages
        if igrf_spec is not None:
            messages.append(dip_check(float(cal.diagnostics["alignment"]["dip_deg"]), igrf_spec))
    if (not quick and igrf_spec is not None and (cal.uncertainty or {}).get("covariance") is not None
            and req.model == "ellipsoid" and req.target is None):
        messages.append(_heading_message(cal, igrf_spec, summary))
    return cal, summary, messages


def _eddy_terms(req: FitRequest, options: dict[str, Any]) -> int | None:
    """``option eddy=9|3`` (popped from ``options``): eddy-current terms of ``interference12``
    (:mod:`trimag.vehicle.eddy`)."""
    if "eddy" not in options:
        return None
    from ..vehicle.eddy import parse_terms

    terms = parse_terms(options.pop("eddy"))
    if req.model != "interference12":
        raise TrimagInputError(f"`option eddy` is for the model interference12; got {req.model!r}")
    if req.prior is not None:
        raise TrimagInputError("`option eddy` cannot be fitted in a quick recalibration (`prior`)")
    return terms


def _fit_model(
    req: FitRequest, samples: Samples, estimator: Any, unit: str, regressor_names: tuple[str, ...] | None,
    eddy_terms: int | None = None,
) -> tuple[Samples, Calibration, Any, dict[str, NDArray[np.float64]] | None, list[str], list[str]]:
    """The estimator's fit (and the regressor terms' joint refit): ``(samples, calibration, reference, regressor
    values, warnings, messages)``; refuses what cannot be right (an unidentified log, an impossible vector fit)."""
    src = req.input
    samples, ref, attitude, messages = _fit_reference(req, samples, estimator, unit)
    regressor_values = None if regressor_names is None else regressor_columns(
        samples, regressor_names, src.path, "named by `regressors`"
    )
    accel = None
    if req.accel_columns is not None:
        from ..vehicle.alignment import check_tilt_variation

        accel = accel_values(samples, req.accel_columns, src.path)
        check_tilt_variation(accel)  # before the fit: a level log cannot give the alignment (exit 3)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", TrimagWarning)
        estimator.fit(samples.field, ref, units=unit, attitude=attitude)
    cal = estimator.calibration_
    if samples.log_info is not None and src.columns is None:
        refuse_unidentified_log(cal, samples, samples.log_info)
    if estimator.reference_kind != "vector":
        messages += check_fitted_field(cal, unit, autopilot_log=samples.log_info is not None)
    if estimator.reference_kind == "vector":
        att = req.attitude
        refuse_impossible_vector_fit(cal, samples, ref, unit, req.model, req.method, dict(req.options),
                                      att.attitude_columns, att.quaternion_columns, att.quaternion_order,
                                      att.quaternion_frame)
    elif worse_than_raw(cal):
        messages.append(f"warning: the corrected data fit the reference worse than the raw data (RMS "
                        f"{cal.stats['rms_after']:.4g} against {cal.stats['rms_before']:.4g} {unit_after(unit)}): "
                        "check the reference and the unit")
    free, record = None, None
    if eddy_terms is not None:
        from ..vehicle.eddy import fit_values, free_mask

        values, spec, eddy_messages = fit_values(samples, eddy_terms, req.attitude.time_column, req.rate_hz,
                                                 req.input.path)
        regressor_values, free, record = {**(regressor_values or {}), **values}, free_mask(eddy_terms), {"eddy": spec}
        messages += eddy_messages
    if regressor_values is not None:
        from ..vehicle.regressors import fit_regressors

        cal = fit_regressors(cal, samples.field, regressor_values, ref, attitude=attitude, free=free, record=record)
    if req.position_columns is not None:
        cal, gradient_message = _background_gradient(req, cal, samples, attitude, regressor_values)
        messages.append(gradient_message)
    if estimator.reference_kind == "vector" and req.reference.reference_column is not None:
        cal, joint_message = _joint_scalar(req, cal, samples, ref, attitude, regressor_values, unit)
        messages.append(joint_message)
    warn_texts = [str(w.message) for w in caught if issubclass(w.category, TrimagWarning)]
    # what the fit's honesty checks found (halves that disagree, too few samples) is said too (issue 32)
    warn_texts += [w for w in estimator.calibration_.diagnostics.get("warnings", []) if w not in warn_texts]
    return samples, cal, ref, regressor_values, warn_texts, messages


def _background_gradient(
    req: FitRequest, cal: Calibration, samples: Samples, attitude: Any,
    regressor_values: dict[str, NDArray[np.float64]] | None,
) -> tuple[Calibration, str]:
    """``position_columns``: the background's gradient across the room (:mod:`trimag.vehicle.gradient`), and its
    line."""
    from ..vehicle.gradient import fit_background_gradient

    if req.model != "interference12" or attitude is None:
        raise TrimagInputError("`position_columns` fits the background's gradient of the model interference12 (with "
                               "attitudes); drop it, or give `model=interference12`")
    if regressor_values is not None or req.reference.reference_column is not None:
        raise TrimagInputError("`position_columns` cannot be combined with `regressors`, eddy terms or "
                               "`reference_column`: fit the background's gradient alone")
    assert req.position_columns is not None
    names = [c.strip() for c in req.position_columns.split(",") if c.strip()]
    positions = regressor_columns(samples, tuple(names), req.input.path, "named by `position_columns`")
    if len(names) != 3:
        raise TrimagInputError(f"`position_columns` needs three columns X,Y,Z; got {req.position_columns!r}")
    cal = fit_background_gradient(cal, samples.field, attitude, np.column_stack([positions[n] for n in names]),
                                  position_columns=",".join(names))
    g = cal.diagnostics["background_gradient"]
    terms = ", ".join(f"{k} {v:.4g} +- {g['terms_std'][k]:.2g}" for k, v in g["terms"].items())
    return cal, (f"background gradient ({g['unit']}): {terms}; vector RMS {g['vector_rms_without']:.4g} -> "
                 f"{g['vector_rms_with']:.4g} {cal.units} over positions spanning "
                 f"{np.round(g['position_span_m'], 3).tolist()} m")


def _joint_scalar(
    req: FitRequest, cal: Calibration, samples: Samples, ref: Any, attitude: Any,
    regressor_values: dict[str, NDArray[np.float64]] | None, unit: str,
) -> tuple[Calibration, str]:
    """A compensated scalar magnetometer beside the vector one (``reference_column``): the joint fit
    (:mod:`trimag.vehicle.joint`) and its message."""
    from ..vehicle.joint import fit_joint_scalar

    column = req.reference.reference_column
    assert column is not None
    cal = fit_joint_scalar(cal, samples.field, column_values(samples, column), attitude=attitude,
                           background=ref if cal.diagnostics.get("background_per_sample")
                           else cal.diagnostics["background_ned"], regressors=regressor_values,
                           scalar_source=f"column {column}")
    joint = cal.diagnostics["joint_scalar"]
    return cal, (f"joint fit with the scalar magnetometer {column}: vector RMS per axis "
                 f"{joint['vector_rms_axis_after']:.4g}, magnitude RMS {joint['scalar_rms_after']:.4g} {unit}")


def _log_defaults(req: FitRequest, samples: Samples, estimator: Any, mode: str | None = None
                  ) -> tuple[FitRequest, list[str]]:
    """What a vehicle log states itself (unit, the IGRF site of its GPS fix, its attitude columns) filled into the
    request, the log reader's messages, and the refusal of a log that cannot be fitted (static, too short)."""
    log_info = samples.log_info
    if log_info is None:
        return req, []
    messages = [m for m in log_info["messages"] if not m.startswith("warning:")]
    messages += [m for m in log_info["messages"] if m.startswith("warning:")]
    src, given, att = req.input, req.reference, req.attitude
    src = dataclasses.replace(src, units=check_log_unit(src.units, log_info, src.columns) or log_info["unit"])
    gps = log_info.get("gps")
    if not given.given and gps and gps.get("date"):
        from ..fields.reference import check_site

        try:  # a GPS fix no place on Earth has is named as the log's (issue 41, item 17)
            check_site(float(gps["lat_deg"]), float(gps["lon_deg"]), float(gps["alt_m"]), "the log's GPS fix")
        except TrimagInputError as exc:
            raise TrimagInputError(f"{exc}: the GPS position logged is wrong, so the field expected there is unknown; "
                                   "give the site yourself (`igrf_spec=LAT,LON,ALT_M,DATE`) or the field's magnitude "
                                   "(`reference`)") from None
        igrf_spec = f"{gps['lat_deg']:.6f},{gps['lon_deg']:.6f},{gps['alt_m']:.1f},{gps['date']}"
        given = dataclasses.replace(given, igrf_spec=igrf_spec)
        messages.append(f"field reference: IGRF at the log's GPS fix {igrf_spec}")
    if req.target is not None and att.attitude_columns is None and att.quaternion_columns is None:
        if log_info.get("has_attitude"):
            att = dataclasses.replace(att, attitude_columns="yaw_deg,pitch_deg,roll_deg")
    elif estimator.reference_kind == "vector" and att.attitude_columns is None and att.quaternion_columns is None:
        if not log_info.get("has_attitude"):
            raise TrimagInputError(f"model {req.model!r} needs attitudes, and this log has none (ATT/ATTITUDE)")
        att = dataclasses.replace(att, attitude_columns="yaw_deg,pitch_deg,roll_deg")
    if src.columns is None and req.prior is None and mode is None and req.target is None \
            and estimator.reference_kind != "gyro":
        # (a quick recalibration, a large vehicle's mode and a firmware fit, whose levels say what the log identifies,
        # are made for logs that barely tilt; the gyroscope says itself whether the sensor turned)
        refuse_static_log(samples, log_info)
        refuse_unidentified_log(None, samples, log_info)  # the data's coverage, before any method (issue 32)
    return dataclasses.replace(req, input=src, reference=given, attitude=att), messages


def _reading_messages(samples: Samples) -> list[str]:
    """What reading the samples chose, selected, dropped and found repeated (never silently)."""
    messages = []
    if samples.column_note:
        messages.append(samples.column_note)
    if samples.format_note:
        messages.append(samples.format_note)
    if samples.selection:
        messages.append(f"selected {samples.n_rows} of {samples.n_total_rows} rows ({samples.selection})")
    if samples.n_dropped - samples.n_wild:
        messages.append(
            f"dropped {samples.n_dropped - samples.n_wild} of {samples.n_rows} rows with missing, non-numeric, NaN or "
            f"inf x/y/z values (first at data row {samples.dropped_index[0]}; use `strict` to refuse them)"
        )
    if samples.n_wild:
        messages.append(f"dropped {samples.wild_note}; use `strict` to refuse them")
    if samples.n_duplicates:
        messages.append(f"{samples.n_duplicates} rows repeat an earlier x/y/z exactly (kept)")
    return messages


def _fit_reference(
    req: FitRequest, samples: Samples, estimator: Any, unit: str
) -> tuple[Samples, Any, Any, list[str]]:
    """The reference the estimator takes (a background vector and the attitudes for a vector model, a magnitude
    otherwise): ``(samples without the rows that lack an attitude, reference, attitude or None, messages)``."""
    given, att, src = req.reference, req.attitude, req.input
    messages: list[str] = []
    gyro = None
    if estimator.reference_kind == "gyro":
        lag = estimator.estimate_lag
        samples, gyro, messages = angular_rate(req, samples, float(estimator.max_lag),
                                               None if lag is None else truthy(lag))
    if estimator.reference_kind != "vector":
        ref = magnitude_reference(samples, given, unit)
        if ref.source.startswith("igrf"):
            assert ref.values is not None
            messages.append(f"reference from {ref.source}: F = {float(ref.values[0]):.6g} {unit_after(unit)}")
        if estimator.requires_reference and not ref.known:
            raise TrimagInputError(
                f"method {estimator.name!r} needs a known field magnitude: give `reference=F`, "
                "`igrf_spec=LAT,LON,ALT_M,DATE` or `reference_column=NAME`"
            )
        return samples, ref, gyro, messages

    samples, n_no_attitude = drop_rows_without_attitude(samples, att.attitude_columns, att.quaternion_columns,
                                                        strict=src.strict)
    if n_no_attitude:
        messages.append(
            f"dropped {n_no_attitude} rows whose attitude is missing or non-numeric (e.g. optical tracking lost)"
        )
    samples, n_no_background = drop_rows_without_background(samples, given.background_columns, given.igrf_columns,
                                                            strict=src.strict)
    if n_no_background:
        messages.append(f"dropped {n_no_background} rows whose background is missing or non-numeric")
    if req.position_columns is not None:
        samples, n_no_position = drop_rows_without_attitude(samples, req.position_columns, None, strict=src.strict,
                                                            what="position")
        if n_no_position:
            messages.append(f"dropped {n_no_position} rows whose position is missing or non-numeric")
    attitude = attitudes_of(samples, att)
    if _fits_background(estimator) and not _names_background(given):
        scale = _background_scale(given)  # a magnitude, or None: det(K) = 1
        messages.append("background field: fitted (`estimate_background`), |H_n| " + (
            f"= {scale:.6g} {unit_after(unit)} (given)" if scale is not None
            else "from det(K) = 1 (the mean corrected magnitude)"))
        return samples, scale, attitude, messages
    background, source = background_field(
        given, unit, samples, fmt=src.fmt, columns=src.columns, var=src.var,
        **({"attitude": attitude, "attitude_columns": att.attitude_columns,
            "quaternion_columns": att.quaternion_columns, "quaternion_order": att.quaternion_order,
            "quaternion_frame": att.quaternion_frame} if given.background_run is not None else {}),
    )
    if background.ndim == 1:
        messages.append(f"background field {np.round(background, 6).tolist()} {unit} ({source})")
    else:
        messages.append(f"background field {source}")
    return samples, background, attitude, messages


#: Options of the gyro-aided fit alone (a phone export's default fit takes them once its gyroscope is found).
_GYRO_OPTIONS = ("estimate_lag", "max_lag", "segment_s", "estimate_bias")


def _phone_export(req: FitRequest) -> bool:
    """Whether the input is a phone's sensor-logger export (whose gyroscope the fit takes by default)."""
    from ..io.logs import log_format

    return req.method is None and log_format(req.input.path, req.input.fmt) == "phone"


def _gyro_estimator(
    req: FitRequest, samples: Samples, estimator: Any, options: dict[str, Any]
) -> tuple[Any, list[str]]:
    """The gyro-aided estimator when the request names a gyroscope, or a phone export has one and no method is
    named (the ellipsoid model); a gyroscope given to another method is refused."""
    if estimator.name == "gyro":
        return estimator, []
    named = req.gyro_columns is not None or req.gyro_file is not None
    if named and (req.method is not None or req.model != "ellipsoid"):
        raise TrimagInputError(f"`gyro_columns` / `gyro_file` are for the gyro-aided fit of the ellipsoid model "
                               f"(`method=gyro`); model {req.model!r}, method {req.method!r} does not use a gyroscope")
    phone = bool(samples.log_info and samples.log_info.get("format") == "phone sensor logger" and log_has_gyro(samples))
    if not (named or (phone and req.method is None)) or req.model != "ellipsoid":
        if any(k in options for k in _GYRO_OPTIONS) and estimator.name != "gyro":
            make_estimator(req.model, req.method, options)  # refuses the gyro fit's options, naming the method's
        return estimator, []
    note = [] if named else [f"the export has a gyroscope ({samples.log_info['gyro']}): gyro-aided fit "  # type: ignore[index]
                             "(`method=ml` fits the magnitude alone; docs/method-gyro.md)"]
    return make_estimator(req.model, "gyro", options), note


def _fits_background(estimator: Any) -> bool:
    """Whether the estimator fits the background vector itself (``linear-vector`` with ``estimate_background``)."""
    return truthy(getattr(estimator, "estimate_background", False))


def _names_background(given: Any) -> bool:
    """Whether the request names a background vector (or an iron-free run, or a per-sample background)."""
    return any(getattr(given, name) is not None for name in
               ("background_ned", "igrf_spec", "background_run", "background_columns", "igrf_columns"))


def _check_reference_number(reference: Any) -> None:
    """A field magnitude given as a number is finite and positive, whatever fit uses it (issue 41, item 14: ``-5``
    with ``target`` reached a numpy warning); other forms are read (and checked) where they are used."""
    if isinstance(reference, bool) or not isinstance(reference, str | int | float):
        return
    try:
        float(reference)
    except ValueError:
        return
    check_reference_magnitude(reference)


def _background_scale(given: Any) -> float | None:
    """The magnitude ``reference=F`` gives a fitted background (None: not given, or ``"mean"``)."""
    if given.reference_column is not None:
        raise TrimagInputError("`reference_column` is a per-sample magnitude; a fitted background takes one "
                               "magnitude (`reference=F`) or none")
    if given.reference is None or str(given.reference).strip().lower() == "mean":
        return None
    try:
        float(given.reference)
    except ValueError:
        raise TrimagInputError(f"`reference` takes a number or 'mean'; got {given.reference!r}") from None
    return check_reference_magnitude(given.reference)


def _heading_message(cal: Calibration, igrf_spec: str, summary: dict[str, Any]) -> str:
    """The heading error the calibration predicts at the IGRF site's inclination (into ``summary``), as a line."""
    from ..vehicle.heading import predicted_heading_sigma

    north, east, down = igrf(*parse_igrf_spec(igrf_spec)).ned_nT
    heading = predicted_heading_sigma(cal, float(np.degrees(np.arctan2(down, np.hypot(north, east)))))
    summary["predicted_heading_sigma_deg"] = {k: heading[k] for k in ("rms_deg", "max_deg", "inclination_deg")}
    return (f"predicted heading error of a level sensor here (inclination {heading['inclination_deg']:.1f} deg): "
            f"{heading['rms_deg']:.3g} deg RMS over headings, {heading['max_deg']:.3g} deg at worst (1 sigma)")



def _target_of(req: FitRequest, samples: Samples) -> FitRequest:
    """``level``/``motor`` without ``target``: the log's own firmware (refused for other data)."""
    if req.target is not None or (req.level is None and req.motor is None and req.yaw_source is None):
        return req
    from ._firmware import _log_firmware

    target = _log_firmware(samples.log_info)
    if target is None:
        raise TrimagInputError("`level`, `motor` and `yaw_source` belong to a firmware fit: give `target=ardupilot` "
                               "or `target=px4`")
    return dataclasses.replace(req, target=target)


def _fit_target(req: FitRequest, samples: Samples, unit: str, messages: list[str],
                limits: dict[str, float] | None) -> FitResult:
    """``fit --target``: the firmware-space fit (:mod:`trimag.app._firmware`), checked and written as any fit."""
    from ._firmware import fit_target

    for name in ("prior", "regressors", "accel_columns"):
        if getattr(req, name) is not None:
            raise TrimagInputError(f"`{name}` does not combine with a firmware fit (`target`): drop one of them")
    if req.attitude.attitude_file is not None:
        raise TrimagInputError("a firmware fit takes the attitudes of the data or the log; drop `attitude_file`")
    samples, cal, regressor_values, target_messages = fit_target(req, samples, unit)
    messages += target_messages
    ref = ScalarReference(np.full(len(samples.field), float((cal.reference or {})["value"])), "firmware fit", unit)
    warn_texts = list(cal.diagnostics.get("warnings", []))
    cal, summary, finish_messages = _finish(req, cal, samples, ref, regressor_values, [], limits, None, False)
    summary["warnings"] = warn_texts
    summary["firmware"] = cal.diagnostics["firmware"]
    cal = _record_unit_doubt(cal, messages)
    cal, written = write_fit_outputs(cal, samples, req, regressor_values)
    summary["outputs"] = written
    return FitResult(cal, samples, summary, messages + finish_messages + [f"warning: {w}" for w in warn_texts],
                     written)


def _input_orientation(cal: Calibration, samples: Samples) -> Calibration:
    """An autopilot log's fit records the sensor rotation its readings carry (what ``export`` writes from)."""
    if not samples.log_info:  # a table: nothing to record (and the firmware models are not imported for it)
        return cal
    from ._firmware import _held, _log_firmware

    target = _log_firmware(samples.log_info)
    if target is None:
        return cal
    _, applied, _, _, _ = _held(target, samples.log_info)
    return cal.with_diagnostics(input_orientation={"target": target, "value": applied})
