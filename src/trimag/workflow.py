"""File-level operations behind the ``trimag`` command: read -> reference -> fit -> write.

Each function takes plain values (paths, strings), does the work through the public API, writes outputs
atomically, and returns a result the CLI prints. Keeping this here leaves ``cli.py`` with parsing and printing
only, and makes every command usable and testable from Python.
"""

from __future__ import annotations

import dataclasses
import json
import warnings
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from .calibration import Calibration
from .errors import TrimagError, TrimagInputError, TrimagWarning
from .estimators import make_estimator
from .io import MagnitudeAccumulator, Samples, apply_file, column_values, open_chunks, read_samples
from .io.atomic import atomic_write_text
from .io.stream import chunk_columns
from .io.tables import where_mask
from .reference import ScalarReference, as_scalar_reference, igrf, igrf_reference, parse_igrf_spec
from .requests import FitRequest, InputSpec
from .units import convert, normalise_unit

__all__ = [
    "DEMO_DATA",
    "FitResult",
    "apply_to_file",
    "evaluate_file",
    "evaluate_heading_file",
    "fit_file",
    "fit_summary",
    "parse_options",
    "run_demo",
    "simulate_to_file",
]

#: The bundled real log used by ``trimag demo`` (see ``trimag/data/README.md`` for its source and licence).
DEMO_DATA = "qmc5883l_noisy_raw_data.csv"


@dataclass
class FitResult:
    """What :func:`fit_file` produced."""

    calibration: Calibration
    samples: Samples
    summary: dict[str, Any]
    messages: list[str] = field(default_factory=list)
    written: dict[str, str] = field(default_factory=dict)


def parse_options(items: list[str] | None) -> dict[str, Any]:
    """Parse ``KEY=VALUE`` method options; values are JSON when they parse as JSON, else strings."""
    out: dict[str, Any] = {}
    for item in items or []:
        if "=" not in item:
            raise TrimagInputError(f"`option` takes KEY=VALUE (e.g. `option form=symmetric`); got {item!r}")
        key, value = item.split("=", 1)
        try:
            out[key.strip()] = json.loads(value)
        except json.JSONDecodeError:
            out[key.strip()] = value
    return out


def _parse_vector(text: str, name: str) -> NDArray[np.float64]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise TrimagInputError(f"{name} takes three numbers N,E,D; got {text!r}") from None
    if len(values) != 3:
        raise TrimagInputError(f"{name} takes three numbers N,E,D; got {text!r}")
    return np.array(values)


def scalar_reference_from_options(
    samples: Samples,
    *,
    units: str,
    reference: str | float | None = None,
    igrf_spec: str | None = None,
    reference_column: str | None = None,
) -> ScalarReference:
    """Build the magnitude reference from the command-line choices (at most one of them)."""
    given = [x for x in (reference, igrf_spec, reference_column) if x is not None]
    if len(given) > 1:
        raise TrimagInputError("give only one of `reference`, `igrf_spec`, `reference_column`")
    n = len(samples.field)
    if igrf_spec is not None:
        lat, lon, alt, date = parse_igrf_spec(igrf_spec)
        return igrf_reference(lat, lon, alt, date, n=n, units=units)
    if reference_column is not None:
        values = column_values(samples, reference_column)
        ref = as_scalar_reference(values, n, units=units)
        return ScalarReference(ref.values, f"column {reference_column}", ref.unit)
    return as_scalar_reference(reference, n, units=units)


def vector_reference_from_options(
    *, units: str, background_ned: str | None = None, igrf_spec: str | None = None,
    background_run: str | None = None, background_columns: str | None = None, samples: Samples | None = None,
    igrf_columns: str | None = None, **read_kwargs: Any,
) -> tuple[NDArray[np.float64], str]:
    """The background field (N, E, D) in the data's unit, shape (3,) or (N, 3) (``background_columns``,
    ``igrf_columns``: one vector per row of ``samples``), and a description of its source."""
    given = [x for x in (background_ned, igrf_spec, background_run, background_columns, igrf_columns) if x is not None]
    if len(given) != 1:
        raise TrimagInputError(
            "model interference12 needs exactly one background field: `background_ned=N,E,D`, "
            "`igrf_spec=LAT,LON,ALT_M,DATE`, `background_run=FILE`, `background_columns=N,E,D` or "
            "`igrf_columns=LAT,LON,ALT_M,DATE`"
        )
    if igrf_columns is not None:
        from .io.background import igrf_along_track, parse_igrf_columns

        if samples is None:
            raise TrimagInputError("`igrf_columns` needs the samples' table")
        cols, date = parse_igrf_columns(igrf_columns)
        track = [column_values(samples, c) for c in _split_names(",".join(cols), samples, "igrf_columns")]
        return igrf_along_track(track[0], track[1], track[2], date, units=units)
    if background_columns is not None:
        if samples is None:
            raise TrimagInputError("`background_columns` needs the samples' table")
        names = _split_names(background_columns, samples, "background_columns")
        values = np.column_stack([column_values(samples, c) for c in names])
        F = np.linalg.norm(values, axis=1)
        return values, (f"per sample from columns {', '.join(names)}, |H| {F.min():.6g} to {F.max():.6g} {units}, "
                        f"mean NED {np.round(values.mean(axis=0), 3).tolist()}")
    if background_ned is not None:
        return _parse_vector(background_ned, "`background_ned`"), "given (NED)"
    if igrf_spec is not None:
        lat, lon, alt, date = parse_igrf_spec(igrf_spec)
        fld = igrf(lat, lon, alt, date)
        vec = fld.ned_nT * convert(1.0, "nT", units)
        return vec, f"igrf {igrf_spec} (IGRF-14, NED {np.round(fld.ned_nT, 1).tolist()} nT)"

    assert background_run is not None
    from .io.background import background_from_run

    return background_from_run(background_run, units=units, **read_kwargs)


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
        out["selection"] = samples.selection
        out["source"] = samples.source
    return out


def _regressor_names(names: Any) -> tuple[str, ...] | None:
    """``FitRequest.regressors`` (a tuple, or a comma-separated string) as a tuple of names; None when none."""
    if names is None:
        return None
    items = names.split(",") if isinstance(names, str) else list(names)
    out = tuple(str(n).strip() for n in items if str(n).strip())
    if not out:
        raise TrimagInputError("`regressors` names no column; give COL[,COL...]")
    if len(set(out)) != len(out):
        raise TrimagInputError(f"`regressors` names a column twice: {', '.join(out)}")
    return out


def regressor_columns(
    samples: Samples, names: tuple[str, ...], path: Any, what: str = "a regressor of the calibration"
) -> dict[str, NDArray[np.float64]]:
    """The values (N,) of the regressor columns ``names`` in the kept rows of ``samples``; one line naming the
    missing column and the file when one is not there."""
    missing = [n for n in names if n not in samples.table.columns]
    if missing:
        raise TrimagInputError(
            f"{path}: no column {missing[0]!r} ({what}); the columns are "
            f"{', '.join(map(str, samples.table.columns))}"
        )
    return {n: column_values(samples, n) for n in names}


def calibration_regressors(cal: Calibration, samples: Samples, path: Any) -> dict[str, NDArray[np.float64]] | None:
    """The values (N,) of a calibration's regressors on the kept rows of ``samples``: logged channels from their
    columns, eddy-current terms (:mod:`trimag.eddy`) from the samples' own derivative; None without terms."""
    if cal.regressors is None:
        return None
    spec = cal.regressors.get("eddy")
    derived = set(spec["names"]) if spec else set()
    out = regressor_columns(samples, tuple(n for n in cal.regressors["names"] if n not in derived), path)
    if spec:
        from .eddy import values_from_table

        out.update(values_from_table(spec, samples.table, samples.field, path))
    return out


def _split_names(spec: str, samples: Samples, arg: str) -> list[str]:
    """Three column names (or 0-based indices) of ``samples.table`` from ``"A,B,C"``; ``arg`` names the option."""
    items = [c.strip() for c in spec.split(",") if c.strip()]
    if len(items) != 3:
        raise TrimagInputError(f"`{arg}` needs exactly three columns (N, E, D); got {len(items)}")
    from .attitude import column_names

    names = [str(c) for c in samples.table.columns]
    for item in items:
        if item not in names and item.isdigit() and int(item) >= len(names):
            raise TrimagInputError(f"`{arg}`: index {item} is out of range; the file has {len(names)} columns")
    return column_names(items, names)


def _drop_rows_without_background(
    samples: Samples, background_columns: str | None, igrf_columns: str | None = None
) -> tuple[Samples, int]:
    """Drop (and count) the rows whose per-sample background (or position) cells are missing or non-finite."""
    if igrf_columns is not None:
        from .io.background import parse_igrf_columns

        background_columns = ",".join(parse_igrf_columns(igrf_columns)[0])
    if background_columns is None:
        return samples, 0
    names = ",".join(_split_names(background_columns, samples, "background_columns"))
    try:
        return _drop_rows_without_attitude(samples, names, None)
    except TrimagInputError:
        raise TrimagInputError(f"none of the rows has a finite background in columns {names}") from None


def accel_values(samples: Samples, accel_columns: str, path: Any) -> NDArray[np.float64]:
    """The accelerometer columns ``"AX,AY,AZ"`` of the kept rows of ``samples``, shape (N, 3); one line naming the
    missing column, or the rows with a non-numeric value, when they are not there."""
    from .attitude import parse_columns

    names = parse_columns(accel_columns, 3, option="`accel_columns`")
    assert names is not None
    missing = [n for n in names if n not in samples.table.columns]
    if missing:
        raise TrimagInputError(
            f"{path}: no column {missing[0]!r} (named by `accel_columns`); the columns are "
            f"{', '.join(map(str, samples.table.columns))}"
        )
    values = np.column_stack([pd.to_numeric(samples.table[n], errors="coerce").to_numpy(dtype=float) for n in names])
    bad = ~np.isfinite(values).all(axis=1)
    if bad.any():
        raise TrimagInputError(
            f"{path}: {int(bad.sum())} rows have a missing or non-numeric accelerometer value in {accel_columns} "
            f"(first at kept row {int(np.flatnonzero(bad)[0])}); drop them first (e.g. with `where`)"
        )
    return values


def _dip_check(dip_deg: float, igrf_spec: str) -> str:
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


def _drop_rows_without_attitude(
    samples: Samples, attitude_columns: str | None, quaternion_columns: str | None
) -> tuple[Samples, int]:
    """Drop (and count) the rows whose attitude cells are missing or non-finite."""
    names = [c.strip() for c in (attitude_columns or quaternion_columns or "").split(",") if c.strip()]
    present = [c for c in names if c in samples.table.columns]
    if not present:
        return samples, 0
    values = np.column_stack([pd.to_numeric(samples.table[c], errors="coerce").to_numpy(dtype=float) for c in present])
    ok = np.isfinite(values).all(axis=1)
    n_bad = int((~ok).sum())
    if n_bad == 0:
        return samples, 0
    if n_bad == len(ok):
        raise TrimagInputError(f"none of the rows has a finite attitude in columns {', '.join(present)}")
    kept = dataclasses.replace(
        samples,
        field=samples.field[ok],
        table=samples.table[ok].reset_index(drop=True),
        n_dropped=samples.n_dropped + n_bad,
    )
    return kept, n_bad


def _check_unit(
    samples: Samples, units: str | None, reference: str | float | None, igrf_spec: str | None
) -> tuple[str | None, list[str]]:
    """The data's unit, checked against the column headers, Earth-field ranges and the reference (issue 22).

    A unit in the headers that contradicts ``units`` is refused (exit 2); without ``units`` it is used. A median
    magnitude that is not a plausible Earth field in the declared unit is a warning naming the likely unit, and
    an error when a reference (a number or IGRF) makes the contradiction certain.
    """
    from .units import EARTH_RAW_RANGE_NT, header_unit, nT_per_unit, plausible_units

    messages: list[str] = []
    in_header = header_unit(list(samples.columns))
    if in_header is not None:
        if units is not None and normalise_unit(units) != in_header:
            raise TrimagInputError(
                f"the column headers say {in_header} ({', '.join(samples.columns)}) but units={units!r}; "
                "give the data's real unit"
            )
        if units is None:
            units = in_header
            messages.append(f"unit {in_header} (from the column headers)")
    unit = normalise_unit(units)
    if unit in ("unknown", "counts") or not len(samples.field):
        return units, messages
    median = float(np.median(np.linalg.norm(samples.field, axis=1)))
    lo, hi = (v / nT_per_unit(unit) for v in EARTH_RAW_RANGE_NT)
    if lo <= median <= hi:
        return units, messages
    likely = plausible_units(median)
    guess = f"; the numbers look like {' or '.join(likely)}" if likely else ""
    F_nT: float | None = None
    if igrf_spec is not None:
        F_nT = float(igrf(*parse_igrf_spec(igrf_spec)).total_nT)
    elif reference is not None and str(reference).strip().lower() != "mean":
        try:
            F_nT = float(reference) * nT_per_unit(unit)
        except ValueError:
            F_nT = None
    if F_nT is not None:
        ratio = median * nT_per_unit(unit) / F_nT
        if not 0.2 <= ratio <= 5.0:
            raise TrimagInputError(
                f"the data's median |B| is {median:.6g} {unit}, {ratio:.3g}x the reference field "
                f"({F_nT / nT_per_unit(unit):.6g} {unit}): the data are not in {unit}{guess}; give the right unit"
            )
    messages.append(
        f"warning: the data's median |B| = {median:.6g} {unit} is not a plausible Earth field in {unit} "
        f"({lo:.3g}-{hi:.3g}){guess}; check the unit"
    )
    return units, messages


def _acceptance(cal: Calibration, limits: dict[str, float], ref: Any, igrf_spec: str | None) -> dict[str, Any]:
    """The acceptance policy's verdict (:func:`trimag.policy.check_policy`) with the site's inclination and F."""
    from .policy import check_policy

    inclination = None
    if igrf_spec is not None:
        north, east, down = igrf(*parse_igrf_spec(igrf_spec)).ned_nT
        inclination = float(np.degrees(np.arctan2(down, np.hypot(north, east))))
    values = getattr(ref, "values", None)
    F = float(np.mean(values)) if values is not None else None
    return check_policy(cal, limits, inclination_deg=inclination, reference_F=F)


def _worse_than_raw(cal: Calibration) -> bool:
    before, after = cal.stats.get("rms_before"), cal.stats.get("rms_after")
    return before is not None and after is not None and float(after) > float(before)


def _attitude_alternatives(
    samples: Samples, attitude_columns: str | None, quaternion_columns: str | None, quaternion_order: str,
    quaternion_frame: str,
) -> list[tuple[str, Any]]:
    """The usual mistakes of an attitude convention, each as (what to give instead, attitudes)."""
    from itertools import permutations

    from . import attitude as _attitude

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


def _refuse_impossible_vector_fit(
    cal: Calibration, samples: Samples, ref: Any, unit: str, model: str, method: str | None,
    options: dict[str, Any] | None, attitude_columns: str | None, quaternion_columns: str | None,
    quaternion_order: str, quaternion_frame: str,
) -> None:
    """Refuse an attitude-based fit that cannot be right: worse than the raw data, or a reflection (det < 0).

    The usual convention mistakes (Euler column order, an inverted rotation, quaternion scalar first/last, ENU
    for NED) are tried; a much better one is named (exit 2), else the fit is refused as unidentified (exit 3).
    """
    from .errors import IdentifiabilityError

    det = float(np.linalg.det(np.asarray(cal.matrix)))
    if not (_worse_than_raw(cal) or det <= 0):
        return
    before, after = float(cal.stats["rms_before"]), float(cal.stats["rms_after"])
    what = f"RMS {after:.4g} {unit} after against {before:.4g} before" + ("; det(K) < 0, a reflection" if det <= 0
                                                                         else "")
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


def _refuse_static_log(samples: Samples, log_info: dict[str, Any]) -> None:
    """Refuse (exit 3) a log whose magnetometer barely turned, saying what to fly or log instead."""
    from .errors import IdentifiabilityError

    B = samples.field
    n = len(B)
    name = log_info["sensor"]
    if n < 30:
        raise IdentifiabilityError(
            f"{name} has only {n} samples in this log: too few to calibrate. Log the magnetometer faster or longer "
            "and turn the vehicle through all headings and attitudes"
        )
    u = B / np.linalg.norm(B, axis=1, keepdims=True)
    mean = u.mean(axis=0)
    mean /= np.linalg.norm(mean)
    cone = float(np.degrees(np.arccos(np.clip(u @ mean, -1.0, 1.0))).max())
    if cone < 30.0:
        raise IdentifiabilityError(
            f"{name}: the field direction stayed within {cone:.0f} deg of its mean over {n} samples: the vehicle "
            "barely turned. Record a calibration: rotate the vehicle through all headings, nose up and down and on "
            "each side (on the ground or in flight), then fit that log"
        )


def _refuse_unidentified_log(cal: Calibration, samples: Samples, log_info: dict[str, Any]) -> None:
    """Refuse (exit 3) a fit of an autopilot log that the rotation recorded cannot identify.

    A vehicle that turns about its vertical axis with little tilt (a rover, a boat, a level flight) leaves the
    field directions in a narrow band: the full 3-D calibration is then not identified, and an autopilot would be
    given parameters that are wrong in the unseen directions.
    """
    from .errors import IdentifiabilityError

    ident = cal.diagnostics.get("identifiability") or {}
    inflation = ident.get("std_inflation_vs_full_sphere")
    coverage = (cal.diagnostics.get("coverage") or {}).get("fraction")
    converged = cal.stats.get("converged", True)
    if converged and (inflation is None or inflation <= 100.0):
        return
    B = samples.field
    u = B / np.linalg.norm(B, axis=1, keepdims=True)
    axis = u.mean(axis=0)
    axis /= np.linalg.norm(axis)
    angle = np.degrees(np.arccos(np.clip(u @ axis, -1.0, 1.0)))
    detail = [f"the field directions cover {100 * coverage:.0f}% of the sphere" if coverage is not None else "",
              f"they stay {angle.min():.0f}..{angle.max():.0f} deg from their mean direction "
              f"{np.round(axis, 2).tolist()} (body frame)",
              "the fit did not converge" if not converged else
              f"its parameters would be {inflation:.3g}x less certain than from a full tumble"]
    raise IdentifiabilityError(
        f"{log_info['sensor']}: this log turned the vehicle mostly about one axis "
        f"({'; '.join(d for d in detail if d)}): "
        "a 3-D calibration cannot be identified from it. Record a calibration with the vehicle also pitched "
        "nose up and down and rolled on each side; a vehicle that cannot tilt needs an earlier full calibration "
        "whose offsets are refitted"
    )


def fit_file(request: FitRequest | str | Path, **arguments: Any) -> FitResult:
    """Read a log, fit a calibration, write the calibration JSON and the report PNG when asked.

    ``request``: a :class:`~trimag.requests.FitRequest`, or a path with the request's fields as keyword arguments
    (:meth:`FitRequest.of <trimag.requests.FitRequest.of>`). With a ``policy`` (a TOML file or ``"default"``,
    :mod:`trimag.policy`) the calibration is checked against its limits; the result is in
    ``summary["acceptance"]`` and in the written file (a rejected calibration is still written, marked so).
    """
    req = request if isinstance(request, FitRequest) else FitRequest.of(request, **arguments)
    if arguments and isinstance(request, FitRequest):
        raise TrimagInputError("give either a FitRequest or a path with keyword arguments, not both")
    from .policy import read_policy

    limits = read_policy(req.policy) if req.policy is not None else None
    regressor_names = _regressor_names(req.regressors)
    if regressor_names is not None:
        from .regressors import MODELS as REGRESSOR_MODELS

        if req.model not in REGRESSOR_MODELS:
            raise TrimagInputError(
                f"`regressors` works with the models {', '.join(REGRESSOR_MODELS)}; got {req.model!r}"
            )
    options = dict(req.options)
    eddy_terms = _eddy_terms(req, options)
    sync_options: dict[str, Any] = {k: options.pop(k) for k in ("estimate_lag", "max_lag") if k in options}
    prior_options: dict[str, Any] = {k: options.pop(k) for k in ("prior_offset_sigma", "scale_sigma", "inclination_deg",
                                                                 "inclination_sigma_deg") if k in options}
    if prior_options and req.prior is None:
        raise TrimagInputError(f"`option {next(iter(prior_options))}` belongs to a quick recalibration; give `prior`")
    if sync_options and req.attitude.attitude_file is None:
        raise TrimagInputError(f"`option {next(iter(sync_options))}` needs attitudes from a second file; give "
                               "`attitude_file`")
    estimator = make_estimator(req.model, req.method, options)
    src = req.input
    samples = read_samples(src.path, fmt=src.fmt, columns=src.columns, var=src.var, rows=src.rows, where=src.where,
                           strict=src.strict, sensor=src.sensor)
    req, messages = _log_defaults(req, samples, estimator)  # a vehicle log states its unit, site and attitudes
    prior = None
    if req.prior is not None:
        if regressor_names is not None:
            raise TrimagInputError("`regressors` cannot be fitted in a quick recalibration (`prior`): it keeps the "
                                   "prior's regressor terms and refits only the offset; drop `regressors`")
        prior = Calibration.from_file(req.prior)
        req, prior_messages = _prior_units(req, prior)
        messages += prior_messages
    units, unit_messages = _check_unit(samples, req.input.units, req.reference.reference, req.reference.igrf_spec)
    unit = normalise_unit(units)
    messages += unit_messages + _reading_messages(samples)
    sync = None
    if req.attitude.attitude_file is not None:
        samples, req, sync, sync_messages = _attach_attitude_file(req, samples, unit, sync_options, estimator)
        messages += sync_messages
    if req.accel_columns is not None:
        from .alignment import check_tilt_variation

        # before the fit: a level log cannot give the alignment (exit 3, saying what to record)
        check_tilt_variation(accel_values(samples, req.accel_columns, src.path))
    if prior is not None:
        samples, cal, regressor_values, prior_messages = _refit_prior(req, samples, unit, prior, prior_options)
        ref: Any = ScalarReference(np.full(len(samples.field), float((cal.reference or {})["value"])), "prior", unit)
        messages += prior_messages
        warn_texts: list[str] = []
    else:
        samples, cal, ref, regressor_values, warn_texts, fit_messages = _fit_model(req, samples, estimator, unit,
                                                                                   regressor_names, eddy_terms)
        messages += fit_messages
    if sync is not None:
        cal = cal.with_diagnostics(time_sync=sync)
    alignment_messages: list[str] = []
    if req.accel_columns is not None:
        from .alignment import fit_alignment

        accel = accel_values(samples, req.accel_columns, src.path)  # the rows the fit kept
        alignment = fit_alignment(cal, samples.field, accel, regressors=regressor_values)
        cal = cal.with_diagnostics(alignment={**alignment, "accel_columns": req.accel_columns})
        alignment_messages = alignment_lines(alignment)
    cal = cal.with_stats(n_samples=samples.n_rows, n_dropped=samples.n_dropped)
    if warn_texts:
        cal = cal.with_diagnostics(warnings=warn_texts)
    igrf_spec = req.reference.igrf_spec
    if limits is not None:
        cal = cal.with_diagnostics(acceptance=_acceptance(cal, limits, ref, igrf_spec))
    summary = fit_summary(cal, samples)
    summary["warnings"] = warn_texts
    if limits is not None:
        summary["acceptance"] = cal.diagnostics["acceptance"]
    if sync is not None:
        summary["time_sync"] = sync
    if prior is not None:
        summary["prior"] = cal.diagnostics["prior"]
    if req.accel_columns is not None:
        summary["alignment"] = cal.diagnostics["alignment"]
        messages += alignment_messages
        if igrf_spec is not None:
            messages.append(_dip_check(float(cal.diagnostics["alignment"]["dip_deg"]), igrf_spec))
    if (prior is None and igrf_spec is not None and (cal.uncertainty or {}).get("covariance") is not None
            and req.model == "ellipsoid"):
        messages.append(_heading_message(cal, igrf_spec, summary))
    cal, written = _write_fit_outputs(cal, samples, req, regressor_values)
    summary["outputs"] = written
    return FitResult(cal, samples, summary, messages + [f"warning: {w}" for w in warn_texts], written)


def _eddy_terms(req: FitRequest, options: dict[str, Any]) -> int | None:
    """``option eddy=9|3`` (popped from ``options``): eddy-current terms of ``interference12`` (:mod:`trimag.eddy`)."""
    if "eddy" not in options:
        return None
    from .eddy import parse_terms

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
        from .alignment import check_tilt_variation

        accel = accel_values(samples, req.accel_columns, src.path)
        check_tilt_variation(accel)  # before the fit: a level log cannot give the alignment (exit 3)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", TrimagWarning)
        estimator.fit(samples.field, ref, units=unit, attitude=attitude)
    cal = estimator.calibration_
    if samples.log_info is not None and src.columns is None:
        _refuse_unidentified_log(cal, samples, samples.log_info)
    if estimator.reference_kind == "vector":
        att = req.attitude
        _refuse_impossible_vector_fit(cal, samples, ref, unit, req.model, req.method, dict(req.options),
                                      att.attitude_columns, att.quaternion_columns, att.quaternion_order,
                                      att.quaternion_frame)
    elif _worse_than_raw(cal):
        messages.append(f"warning: the corrected data fit the reference worse than the raw data (RMS "
                        f"{cal.stats['rms_after']:.4g} against {cal.stats['rms_before']:.4g} {unit}): check the "
                        "reference and the unit")
    free, record = None, None
    if eddy_terms is not None:
        from .eddy import fit_values, free_mask

        values, spec, eddy_messages = fit_values(samples, eddy_terms, req.attitude.time_column, req.rate_hz,
                                                 req.input.path)
        regressor_values, free, record = {**(regressor_values or {}), **values}, free_mask(eddy_terms), {"eddy": spec}
        messages += eddy_messages
    if regressor_values is not None:
        from .regressors import fit_regressors

        cal = fit_regressors(cal, samples.field, regressor_values, ref, attitude=attitude, free=free, record=record)
    if estimator.reference_kind == "vector" and req.reference.reference_column is not None:
        from .joint import fit_joint_scalar  # a compensated scalar magnetometer alongside: joint fit (trimag.joint)

        column = req.reference.reference_column
        cal = fit_joint_scalar(cal, samples.field, column_values(samples, column), attitude=attitude,
                               background=ref if cal.diagnostics.get("background_per_sample")
                               else cal.diagnostics["background_ned"], regressors=regressor_values,
                               scalar_source=f"column {column}")
        messages.append(f"joint fit with the scalar magnetometer {column}: vector RMS per axis "
                        f"{cal.diagnostics['joint_scalar']['vector_rms_axis_after']:.4g}, magnitude RMS "
                        f"{cal.diagnostics['joint_scalar']['scalar_rms_after']:.4g} {unit}")
    warn_texts = [str(w.message) for w in caught if issubclass(w.category, TrimagWarning)]
    return samples, cal, ref, regressor_values, warn_texts, messages


def _prior_units(req: FitRequest, prior: Calibration) -> tuple[FitRequest, list[str]]:
    """The data's unit against the prior calibration's: a clash is refused, an unstated unit is the prior's."""
    given = req.input.units
    if given is not None:
        unit = normalise_unit(given)
        if "unknown" not in (unit, prior.units) and unit != prior.units:
            raise TrimagInputError(
                f"the prior calibration {req.prior} is for data in {prior.units}, but `units={given}`: a quick "
                "recalibration keeps the prior's matrix, so the data must be in its unit"
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


def _refit_prior(
    req: FitRequest, samples: Samples, unit: str, prior: Calibration, options: dict[str, Any]
) -> tuple[Samples, Calibration, dict[str, NDArray[np.float64]] | None, list[str]]:
    """Quick recalibration (:func:`trimag.prior.refit_offset`): ``(samples, calibration, regressor values,
    messages)``."""
    from . import attitude as _attitude
    from .prior import file_digest, refit_offset

    given, att = req.reference, req.attitude
    messages = [f"quick recalibration: the matrix{' and regressor terms' if prior.regressors else ''} of "
                f"{req.prior} (model {prior.model}, method {prior.method}) kept; the offset refitted"]
    if given.background_ned is not None or given.background_run is not None:
        raise TrimagInputError("a quick recalibration (`prior`) uses the field magnitude (and the inclination), not "
                               "a background vector: give `reference=F` or `igrf_spec=LAT,LON,ALT_M,DATE`")
    attitude = None
    if att.attitude_columns is not None or att.quaternion_columns is not None:
        samples, n_no_attitude = _drop_rows_without_attitude(samples, att.attitude_columns, att.quaternion_columns)
        if n_no_attitude:
            messages.append(f"dropped {n_no_attitude} rows whose attitude is missing or non-numeric")
        attitude = _attitude.attitude_from_table(
            samples.table, euler_columns=att.attitude_columns, quaternion_columns=att.quaternion_columns,
            scalar_first=att.quaternion_order == "wxyz", frame=att.quaternion_frame,
        )
    ref = scalar_reference_from_options(samples, units=unit, reference=given.reference, igrf_spec=given.igrf_spec,
                                        reference_column=given.reference_column)
    F: Any = ref.values
    if F is None:
        value = (prior.reference or {}).get("value")
        if value is None:
            raise TrimagInputError("a quick recalibration (`prior`) needs the field magnitude: give `reference=F`, "
                                   "`igrf_spec=LAT,LON,ALT_M,DATE` or `reference_column=NAME` (the prior states none)")
        F = float(value)
        messages.append(f"field magnitude F = {F:.6g} {unit} (the prior calibration's reference)")
    elif ref.source.startswith("igrf"):
        messages.append(f"reference from {ref.source}: F = {float(np.asarray(F).ravel()[0]):.6g} {unit}")
    inclination = options.get("inclination_deg")
    inclination = float(inclination) if inclination is not None else _inclination(given.igrf_spec)
    if attitude is not None and inclination is None:
        messages.append("warning: attitudes given without an inclination (`igrf_spec` or `option inclination_deg`): "
                        "only the magnitude is used")
    if attitude is None:
        inclination = None
    regressor_values = None
    if prior.regressors is not None and prior.regressors.get("eddy"):  # derived from the data (trimag.eddy)
        regressor_values = calibration_regressors(prior, samples, req.input.path)
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
    d = cal.diagnostics["prior"]
    for name, c in d["components"].items():
        state = ("identified" if c["identified_by_data"] else
                 "NOT identified by these data (value and sigma from the priors)")
        messages.append(f"  {name} = {c['value']:.6g} +- {c['std']:.3g} {unit} (prior {c['prior_value']:.6g}): "
                        f"{state}")
    if d["unidentified"]:
        messages.append(f"unidentified: {', '.join(d['unidentified'])}: a level turn cannot tell a vertical offset "
                        "from the field's magnitude and inclination: tilt the vehicle (roll and pitch it while it "
                        "turns) to fit it, or keep the prior's value")
    return samples, cal, regressor_values, messages


def _truthy(value: Any) -> bool:
    if isinstance(value, str):
        return value.strip().lower() in ("1", "true", "yes", "on")
    return bool(value)


def _attach_attitude_file(
    req: FitRequest, samples: Samples, unit: str, options: dict[str, Any], estimator: Any
) -> tuple[Samples, FitRequest, dict[str, Any], list[str]]:
    """Attitudes from ``attitude_file`` interpolated (slerp) to the samples' time stamps, after the lag when
    ``estimate_lag`` (:mod:`trimag.timesync`): the samples outside the stream's span dropped, the attitudes put in
    the table as quaternion columns and the request pointed at them."""
    from .requests import AttitudeSpec
    from .timesync import estimate_lag, interpolate_attitude, read_attitude_stream, time_values

    att = req.attitude
    if att.time_column is None:
        raise TrimagInputError("`attitude_file` needs the time stamps of the magnetometer's samples: give "
                               "`time_column=NAME` (and `attitude_time_column=NAME` if the attitude file's differs)")
    if att.attitude_columns is None and att.quaternion_columns is None:
        raise TrimagInputError("name the attitude file's columns: `attitude_columns=YAW,PITCH,ROLL` or "
                               "`quaternion_columns=W,X,Y,Z`")
    stream = read_attitude_stream(
        att.attitude_file, time_column=att.attitude_time_column or att.time_column,  # type: ignore[arg-type]
        attitude_columns=att.attitude_columns, quaternion_columns=att.quaternion_columns,
        scalar_first=att.quaternion_order == "wxyz", frame=att.quaternion_frame,
    )
    t = time_values(samples.table, att.time_column, str(req.input.path))
    t0, t1 = stream.span
    sync: dict[str, Any] = {
        "attitude_file": str(att.attitude_file), "time_column": att.time_column,
        "attitude_time_column": att.attitude_time_column or att.time_column, "n_attitudes": len(stream.times),
        "attitude_span_s": [t0, t1], "attitude_interval_s": stream.median_interval,
        "n_attitude_rows_dropped": stream.n_dropped, "interpolation": "slerp",
        "lag_convention": "lag = attitude clock - magnetometer clock: the sample stamped t takes the attitude at "
                          "t + lag", "lag_s": 0.0, "lag_estimated": False,
    }
    messages = [f"attitudes from {att.attitude_file}: {len(stream.times)} rows over {t0:.6g}..{t1:.6g} s "
                f"(every {stream.median_interval:.4g} s), interpolated (slerp) to the magnetometer's time stamps"]
    lag = float(options.get("lag_s", 0.0))  # a known lag (evaluate: the calibration's)
    if _truthy(options.get("estimate_lag", False)):
        if estimator.reference_kind != "vector" or req.reference.background_run is not None:
            raise TrimagInputError("`option estimate_lag=true` maximises the quality of the vector fit: it needs "
                                   "`model=interference12` with `background_ned=N,E,D` or `igrf_spec=...`")
        background, _ = vector_reference_from_options(units=unit, background_ned=req.reference.background_ned,
                                                      igrf_spec=req.reference.igrf_spec)
        ok = np.isfinite(t)
        result = estimate_lag(samples.field[ok], t[ok], stream, background,
                              max_lag=float(options.get("max_lag", 1.0)))
        lag = float(result["lag_s"])
        sync.update(result, lag_estimated=True)
        messages.append(
            f"lag between the streams (attitude clock - magnetometer clock): {lag:+.5f} +- {result['lag_std_s']:.2g} "
            f"s; vector RMS of the interference12 fit {result['rms_at_lag']:.4g} {unit} at that lag against "
            f"{result['rms_at_zero']:.4g} at zero lag"
        )
    rot, inside = interpolate_attitude(stream, t, lag)
    n_out = int((~inside).sum())
    sync["n_outside"] = n_out
    if rot is None:
        raise TrimagInputError(
            f"none of the {len(t)} magnetometer samples (time {np.nanmin(t):.6g}..{np.nanmax(t):.6g} s) lies inside "
            f"the attitude stream's span {t0:.6g}..{t1:.6g} s: check the time columns and their units"
        )
    if n_out:
        messages.append(f"dropped {n_out} of {len(t)} magnetometer samples outside the attitude stream's span "
                        f"({t0:.6g}..{t1:.6g} s{f', lag {lag:+.4g} s' if lag else ''}) or without a time stamp")
    table = samples.table[inside].reset_index(drop=True)
    names = ("_attitude_qw", "_attitude_qx", "_attitude_qy", "_attitude_qz")
    q = rot.as_quat(scalar_first=True)
    table = table.assign(**{name: q[:, k] for k, name in enumerate(names)})
    samples = dataclasses.replace(samples, field=samples.field[inside], table=table,
                                  n_dropped=samples.n_dropped + n_out)
    req = dataclasses.replace(req, attitude=AttitudeSpec(quaternion_columns=",".join(names)))
    return samples, req, sync, messages


def _log_defaults(req: FitRequest, samples: Samples, estimator: Any) -> tuple[FitRequest, list[str]]:
    """What a vehicle log states itself (unit, the IGRF site of its GPS fix, its attitude columns) filled into the
    request, the log reader's messages, and the refusal of a log that cannot be fitted (static, too short)."""
    log_info = samples.log_info
    if log_info is None:
        return req, []
    messages = [m for m in log_info["messages"] if not m.startswith("warning:")]
    messages += [m for m in log_info["messages"] if m.startswith("warning:")]
    src, given, att = req.input, req.reference, req.attitude
    if src.units is not None and normalise_unit(src.units) != log_info["unit"] and src.columns is None:
        raise TrimagInputError(
            f"the log records {log_info['sensor']} in {log_info['unit']}; drop units={src.units!r} (it is known)"
        )
    src = dataclasses.replace(src, units=src.units or log_info["unit"])
    gps = log_info.get("gps")
    if not given.given and gps and gps.get("date"):
        igrf_spec = f"{gps['lat_deg']:.6f},{gps['lon_deg']:.6f},{gps['alt_m']:.1f},{gps['date']}"
        given = dataclasses.replace(given, igrf_spec=igrf_spec)
        messages.append(f"field reference: IGRF at the log's GPS fix {igrf_spec}")
    if estimator.reference_kind == "vector" and att.attitude_columns is None and att.quaternion_columns is None:
        if not log_info.get("has_attitude"):
            raise TrimagInputError(f"model {req.model!r} needs attitudes, and this log has none (ATT/ATTITUDE)")
        att = dataclasses.replace(att, attitude_columns="yaw_deg,pitch_deg,roll_deg")
    if src.columns is None and req.prior is None:  # a quick recalibration is made for logs that barely tilt
        _refuse_static_log(samples, log_info)
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
    if samples.n_dropped:
        messages.append(
            f"dropped {samples.n_dropped} of {samples.n_rows} rows with missing, non-numeric, NaN or inf "
            f"x/y/z values (first at data row {samples.dropped_index[0]}; use `strict` to refuse them)"
        )
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
    if estimator.reference_kind != "vector":
        ref = scalar_reference_from_options(samples, units=unit, reference=given.reference,
                                            igrf_spec=given.igrf_spec, reference_column=given.reference_column)
        if ref.source.startswith("igrf"):
            assert ref.values is not None
            messages.append(f"reference from {ref.source}: F = {float(ref.values[0]):.6g} {unit}")
        if estimator.requires_reference and not ref.known:
            raise TrimagInputError(
                f"method {estimator.name!r} needs a known field magnitude: give `reference=F`, "
                "`igrf_spec=LAT,LON,ALT_M,DATE` or `reference_column=NAME`"
            )
        return samples, ref, None, messages
    from . import attitude as _attitude

    samples, n_no_attitude = _drop_rows_without_attitude(samples, att.attitude_columns, att.quaternion_columns)
    if n_no_attitude:
        messages.append(
            f"dropped {n_no_attitude} rows whose attitude is missing or non-numeric (e.g. optical tracking lost)"
        )
    samples, n_no_background = _drop_rows_without_background(samples, given.background_columns, given.igrf_columns)
    if n_no_background:
        messages.append(f"dropped {n_no_background} rows whose background is missing or non-numeric")
    attitude = _attitude.attitude_from_table(
        samples.table, euler_columns=att.attitude_columns, quaternion_columns=att.quaternion_columns,
        scalar_first=att.quaternion_order == "wxyz", frame=att.quaternion_frame,
    )
    background, source = vector_reference_from_options(
        units=unit, background_ned=given.background_ned, igrf_spec=given.igrf_spec,
        background_run=given.background_run, background_columns=given.background_columns, samples=samples,
        igrf_columns=given.igrf_columns, fmt=src.fmt, columns=src.columns, var=src.var,
        **({"attitude": attitude, "attitude_columns": att.attitude_columns,
            "quaternion_columns": att.quaternion_columns, "quaternion_order": att.quaternion_order,
            "quaternion_frame": att.quaternion_frame} if given.background_run is not None else {}),
    )
    if background.ndim == 1:
        messages.append(f"background field {np.round(background, 6).tolist()} {unit} ({source})")
    else:
        messages.append(f"background field {source}")
    return samples, background, attitude, messages


def _heading_message(cal: Calibration, igrf_spec: str, summary: dict[str, Any]) -> str:
    """The heading error the calibration predicts at the IGRF site's inclination (into ``summary``), as a line."""
    from .heading import predicted_heading_sigma

    north, east, down = igrf(*parse_igrf_spec(igrf_spec)).ned_nT
    heading = predicted_heading_sigma(cal, float(np.degrees(np.arctan2(down, np.hypot(north, east)))))
    summary["predicted_heading_sigma_deg"] = {k: heading[k] for k in ("rms_deg", "max_deg", "inclination_deg")}
    return (f"predicted heading error of a level sensor here (inclination {heading['inclination_deg']:.1f} deg): "
            f"{heading['rms_deg']:.3g} deg RMS over headings, {heading['max_deg']:.3g} deg at worst (1 sigma)")


def _write_fit_outputs(
    cal: Calibration, samples: Samples, req: FitRequest, regressor_values: dict[str, NDArray[np.float64]] | None = None
) -> tuple[Calibration, dict[str, str]]:
    """Write the report and the calibration when asked: together or not at all (the report first, it can fail)."""
    written: dict[str, str] = {}
    path = req.input.path
    try:
        if req.report is not None:
            from .report import fit_report, save_figure

            notes = [f"{samples.n_dropped} rows dropped"] if samples.n_dropped else []
            title = f"trimag fit of {Path(path).name}: model {cal.model}, method {cal.method}"
            field_, shown = samples.field, cal
            if regressor_values is not None:  # the figure shows the samples with the regressor terms removed
                field_ = samples.field - cal.regressor_shift(regressor_values, samples.field.shape)
                shown = dataclasses.replace(cal, regressors=None)
            written["report"] = str(save_figure(fit_report(field_, shown, title=title, notes=notes), req.report))
        if req.out is not None:
            cal = cal.with_stats(source=str(path), columns=list(samples.columns))
            written["calibration"] = str(cal.to_file(req.out))
    except BaseException:
        for done in written.values():
            Path(done).unlink(missing_ok=True)
        raise
    return cal, written


def apply_to_file(
    cal_path: str | Path,
    data_path: str | Path,
    out: str | Path,
    *,
    fmt: str | None = None,
    columns: str | None = None,
    var: str | None = None,
    units: str | None = None,
    chunk_rows: int = 200_000,
    progress: Any = None,
) -> dict[str, Any]:
    """Correct a whole file with a calibration (streamed; see :func:`trimag.io.apply_file`).

    A calibration with regressor terms reads its regressors from the columns of the same names; a missing column
    raises :class:`TrimagInputError`, and a row whose regressor value is missing is left uncorrected.
    """
    cal = Calibration.from_file(cal_path)
    if units is not None:
        cal.apply(np.zeros(3), units=units)  # raises UnitMismatchError on a unit clash
    names = tuple(cal.regressors["names"]) if cal.regressors is not None else ()
    spec = cal.regressors.get("eddy") if cal.regressors is not None else None
    if spec:
        from .eddy import streamed_calibrate

        calibrate, names = streamed_calibrate(cal, spec, data_path, fmt=fmt, columns=columns, var=var,
                                              chunk_rows=chunk_rows)
    else:
        def calibrate(xyz: NDArray[np.float64], *u: NDArray[np.float64]) -> NDArray[np.float64]:
            return cal.apply(xyz, regressors=u[0] if u else None)

    result = apply_file(
        calibrate, data_path, out, fmt=fmt, columns=columns, var=var, chunk_rows=chunk_rows, progress=progress,
        regressor_columns=names,
    )
    result["units"] = cal.units
    return result


def evaluate_file(
    cal_path: str | Path,
    data_path: str | Path,
    *,
    fmt: str | None = None,
    columns: str | None = None,
    var: str | None = None,
    units: str | None = None,
    rows: str | None = None,
    where: str | None = None,
    reference: str | float | None = None,
    igrf_spec: str | None = None,
    reference_column: str | None = None,
    chunk_rows: int = 200_000,
    progress: Any = None,
) -> dict[str, Any]:
    """Statistics of ``|B| - F`` before and after applying a calibration to a file (streamed, one pass).

    Without a reference, ``F`` is the mean corrected magnitude (as in ``trimag fit``).
    """
    cal = Calibration.from_file(cal_path)
    unit = cal.units if units is None else normalise_unit(units)
    if units is not None:
        cal.apply(np.zeros(3), units=unit)
    given = [x for x in (reference, igrf_spec, reference_column) if x is not None]
    if len(given) > 1:
        raise TrimagInputError("give only one of `reference`, `igrf_spec`, `reference_column`")
    F: float | None = None
    source = "mean"
    if igrf_spec is not None:
        lat, lon, alt, date = parse_igrf_spec(igrf_spec)
        F = convert(igrf(lat, lon, alt, date).total_nT, "nT", unit)
        source = f"igrf {igrf_spec}"
    elif reference is not None and str(reference).strip().lower() != "mean":
        F = float(as_scalar_reference(reference, 1, units=unit).values[0])  # type: ignore[index]
        source = "given"
    elif reference_column is not None:
        source = f"column {reference_column}"
    src, chunks = open_chunks(data_path, fmt=fmt, columns=columns, var=var, chunk_rows=chunk_rows)
    start, stop = _row_range(rows)
    regressor_names = tuple(cal.regressors["names"]) if cal.regressors is not None else ()
    spec = cal.regressors.get("eddy") if cal.regressors is not None else None
    read_names = regressor_names
    if spec:  # the derivative needs neighbouring rows: the selected rows are collected, then corrected at once
        from .eddy import evaluate_columns

        read_names = evaluate_columns(cal, spec)
    kept: list[tuple[Any, ...]] = []
    before, after = MagnitudeAccumulator(), MagnitudeAccumulator()
    n_rows = n_bad = 0
    for chunk in chunks:
        mask = np.ones(len(chunk.xyz), dtype=bool)
        idx = chunk.start + np.arange(len(chunk.xyz))
        mask &= idx >= start
        if stop is not None:
            mask &= idx < stop
        if where:
            mask &= where_mask(chunk.table, where)
        xyz = chunk.xyz[mask]
        n_rows += len(xyz)
        ok = np.isfinite(xyz).all(axis=1)
        u = chunk_columns(chunk, read_names, data_path)[mask] if read_names else None
        if u is not None:
            ok &= np.isfinite(u).all(axis=1)
            u = u[ok]
        n_bad += int((~ok).sum())
        xyz = xyz[ok]
        ref_values: Any = F
        if reference_column is not None:
            if reference_column not in chunk.table.columns:
                raise TrimagInputError(f"no column {reference_column!r} in {data_path}")
            col = chunk.table[reference_column]
            vals = np.asarray(col if col.dtype.kind in "fiu" else col.astype(str).str.strip(), dtype=object)
            ref_values = np.asarray(vals.astype(float))[mask][ok]
        before.add(np.linalg.norm(xyz, axis=1), ref_values)
        if spec:
            kept.append((xyz, u, ref_values))
        else:
            after.add(np.linalg.norm(cal.apply(xyz, regressors=u), axis=1), ref_values)
        if progress:
            progress(chunk.start + len(chunk.xyz))
    if spec and kept:
        from .eddy import corrected_magnitudes

        after.add(*corrected_magnitudes(cal, spec, kept))
    if after.n == 0:
        raise TrimagInputError(f"{data_path}: no rows with finite x, y, z values to evaluate")
    stats_after = after.result()
    F_used = F if F is not None else (None if reference_column else stats_after["mean_norm"])
    stats_before = before.result(F_used)
    return {
        "calibration": str(cal_path),
        "data": str(data_path),
        "model": cal.model,
        "method": cal.method,
        "units": cal.units,
        "columns": list(src.columns),
        "n_samples": n_rows,
        "n_used": after.n,
        "n_dropped": n_bad,
        "selection": "; ".join(x for x in (f"rows {rows}" if rows else "", f"where {where}" if where else "") if x),
        "regressors": list(regressor_names),
        "reference": {"value": F_used, "source": source, "unit": cal.units},
        "rms_before": stats_before["rms"],
        "rms_after": stats_after["rms"],
        "max_abs_before": stats_before["max_abs"],
        "max_abs_after": stats_after["max_abs"],
        "p2p_before": stats_before["peak_to_peak"],
        "p2p_after": stats_after["peak_to_peak"],
        "mean_norm_before": stats_before["mean_norm"],
        "mean_norm_after": stats_after["mean_norm"],
        "std_norm_before": stats_before["std_norm"],
        "std_norm_after": stats_after["std_norm"],
    }


def evaluate_vector_file(
    cal_path: str | Path,
    data_path: str | Path,
    *,
    fmt: str | None = None,
    columns: str | None = None,
    var: str | None = None,
    rows: str | None = None,
    where: str | None = None,
    attitude_columns: str | None = None,
    quaternion_columns: str | None = None,
    quaternion_order: str = "wxyz",
    quaternion_frame: str = "ned",
    background_ned: str | None = None,
    igrf_spec: str | None = None,
    background_columns: str | None = None,
    attitude_file: str | Path | None = None,
    time_column: str | None = None,
    attitude_time_column: str | None = None,
    igrf_columns: str | None = None,
) -> dict[str, Any]:
    """Vector errors of an attitude-based calibration (``interference12``) on a log with attitudes.

    The background field (N, E, D) -- one vector, or one per row from ``background_columns`` -- is rotated into
    the body frame at every sample (docs/conventions-attitude.md) and compared with the raw and the corrected
    vector: per-axis RMS, vector RMS, and the angle between the corrected field and the background in degrees
    (RMS and maximum). With ``attitude_file`` the attitudes come from that file (its own ``attitude_time_column``),
    interpolated (slerp) to the data's ``time_column`` after the lag the calibration stores
    (``diagnostics.time_sync.lag_s``, 0 when none); samples outside its span are dropped.
    """
    from . import attitude as _attitude
    from .requests import AttitudeSpec

    cal = Calibration.from_file(cal_path)
    samples = read_samples(data_path, fmt=fmt, columns=columns, var=var, rows=rows, where=where)
    lag = None
    if attitude_file is not None:
        lag = float((cal.diagnostics.get("time_sync") or {}).get("lag_s", 0.0))
        req = FitRequest(InputSpec(data_path), attitude=AttitudeSpec(
            attitude_columns=attitude_columns, quaternion_columns=quaternion_columns, quaternion_order=quaternion_order,
            quaternion_frame=quaternion_frame, attitude_file=attitude_file, time_column=time_column,
            attitude_time_column=attitude_time_column))
        samples, req, _, _ = _attach_attitude_file(req, samples, cal.units, {"lag_s": lag}, None)
        attitude_columns, quaternion_columns = None, req.attitude.quaternion_columns
        quaternion_order, quaternion_frame = "wxyz", "ned"
    samples, n_no_attitude = _drop_rows_without_attitude(samples, attitude_columns, quaternion_columns)
    samples, n_no_background = _drop_rows_without_background(samples, background_columns, igrf_columns)
    rot = _attitude.attitude_from_table(
        samples.table, euler_columns=attitude_columns, quaternion_columns=quaternion_columns,
        scalar_first=quaternion_order == "wxyz", frame=quaternion_frame,
    )
    background, source = vector_reference_from_options(units=cal.units, background_ned=background_ned,
                                                       igrf_spec=igrf_spec, background_columns=background_columns,
                                                       samples=samples, igrf_columns=igrf_columns)
    expected = _attitude.body_field(rot, background)
    u = calibration_regressors(cal, samples, data_path)
    raw, corrected = samples.field, cal.apply(samples.field, regressors=u)

    def errors(B: NDArray[np.float64]) -> dict[str, Any]:
        e = B - expected
        cos = np.einsum("ij,ij->i", B, expected) / (np.linalg.norm(B, axis=1) * np.linalg.norm(expected, axis=1))
        angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
        return {"rms_axis": np.sqrt(np.mean(e**2, axis=0)).tolist(),
                "rms_vector": float(np.sqrt(np.mean(np.sum(e**2, axis=1)))),
                "angular_error_rms_deg": float(np.sqrt(np.mean(angle**2))),
                "angular_error_max_deg": float(angle.max())}

    before, after = errors(raw), errors(corrected)
    return {
        "calibration": str(cal_path), "data": str(data_path), "model": cal.model, "method": cal.method,
        "units": cal.units, "columns": list(samples.columns), "n_samples": samples.n_rows,
        "n_used": len(raw), "n_dropped": samples.n_dropped + n_no_attitude + n_no_background,
        "background": {"ned": (background.mean(axis=0) if background.ndim == 2 else background).tolist(),
                       "source": source, "per_sample": background.ndim == 2},
        **({"attitude_file": str(attitude_file), "lag_s": lag} if attitude_file is not None else {}),
        "before": before, "after": after,
        "rms_before": before["rms_vector"], "rms_after": after["rms_vector"],
        "angular_error_rms_deg": after["angular_error_rms_deg"],
    }


def evaluate_heading_file(
    cal_path: str | Path,
    data_path: str | Path,
    *,
    accel_columns: str,
    heading_column: str | None = None,
    attitude_columns: str | None = None,
    igrf_spec: str | None = None,
    declination: float | str | None = None,
    fmt: str | None = None,
    columns: str | None = None,
    var: str | None = None,
    units: str | None = None,
    rows: str | None = None,
    where: str | None = None,
) -> dict[str, Any]:
    """Tilt-compensated true heading of a calibrated log against a reference heading (issue 20, item 3).

    The corrected field is rotated into the accelerometer frame by the calibration's alignment
    (``diagnostics.alignment``, from ``fit --accel-columns``; without one the frames are taken as the same), the
    heading computed with the accelerometer (:func:`trimag.heading.tilt_compensated_heading`) plus the declination
    (IGRF at ``igrf_spec``, or ``declination`` in degrees east; 0 when neither: magnetic heading), and compared with
    ``heading_column`` (degrees clockwise from true north) or the yaw of ``attitude_columns`` (yaw, pitch, roll).

    Returns
    -------
    dict
        ``heading_error_rms_deg``, ``heading_error_max_deg``, ``heading_error_mean_deg``, ``heading_error_std_deg``
        (wrapped into -180..180), ``n_used``, ``declination_deg`` and its ``declination_source``, ``alignment``
        (``"calibration"`` or ``"none"``), ``reference_heading`` and the usual ``calibration``, ``data``,
        ``units``, ``columns``, ``n_samples``, ``n_dropped``.
    """
    from .heading import heading_error_stats, tilt_compensated_heading

    cal = Calibration.from_file(cal_path)
    if units is not None:
        cal.apply(np.zeros(3), units=normalise_unit(units))
    if (heading_column is None) == (attitude_columns is None):
        raise TrimagInputError("a heading evaluation needs exactly one reference: `heading_column=H` (degrees "
                               "clockwise from true north) or `attitude_columns=yaw,pitch,roll`")
    if igrf_spec is not None and declination is not None:
        raise TrimagInputError("give only one of `igrf_spec` and `declination`")
    if igrf_spec is not None:
        decl, decl_source = igrf(*parse_igrf_spec(igrf_spec)).declination_deg, f"igrf {igrf_spec}"
    elif declination is not None:
        try:
            decl, decl_source = float(declination), "given"
        except ValueError:
            raise TrimagInputError(f"`declination` takes degrees east of north; got {declination!r}") from None
        if not -180.0 <= decl <= 180.0:
            raise TrimagInputError(f"`declination` must be within -180..180 degrees; got {decl}")
    else:
        decl, decl_source = 0.0, "none (magnetic heading compared)"
    samples = read_samples(data_path, fmt=fmt, columns=columns, var=var, rows=rows, where=where)
    ref_col = heading_column if heading_column is not None else (attitude_columns or "").split(",")[0].strip()
    from .attitude import parse_columns

    if attitude_columns is not None:
        parse_columns(attitude_columns, 3, option="`attitude_columns`")
    if ref_col not in samples.table.columns:
        raise TrimagInputError(f"{data_path}: no column {ref_col!r} (the reference heading); the columns are "
                               f"{', '.join(map(str, samples.table.columns))}")
    reference = pd.to_numeric(samples.table[ref_col], errors="coerce").to_numpy(dtype=float)
    names = parse_columns(accel_columns, 3, option="`accel_columns`")
    assert names is not None
    missing = [n for n in names if n not in samples.table.columns]
    if missing:
        raise TrimagInputError(f"{data_path}: no column {missing[0]!r} (named by `accel_columns`); the columns are "
                               f"{', '.join(map(str, samples.table.columns))}")
    accel = np.column_stack([pd.to_numeric(samples.table[n], errors="coerce").to_numpy(dtype=float) for n in names])
    u = None
    if cal.regressors is not None:
        values = calibration_regressors(cal, samples, data_path)
        assert values is not None
        u = np.column_stack([values[n] for n in cal.regressors["names"]])
    ok = np.isfinite(reference) & np.isfinite(accel).all(axis=1) & (np.linalg.norm(accel, axis=1) > 0)
    if u is not None:
        ok &= np.isfinite(u).all(axis=1)
    if not ok.any():
        raise TrimagInputError(f"{data_path}: no row has a finite reference heading and accelerometer")
    corrected = cal.apply(samples.field[ok], regressors=None if u is None else u[ok])
    alignment = cal.diagnostics.get("alignment")
    if alignment is not None:
        corrected = corrected @ np.asarray(alignment["matrix"], dtype=np.float64).T
    heading = tilt_compensated_heading(corrected, accel[ok], declination_deg=decl)
    stats = heading_error_stats(heading, reference[ok])
    return {
        "calibration": str(cal_path), "data": str(data_path), "model": cal.model, "method": cal.method,
        "units": cal.units, "columns": list(samples.columns), "n_samples": samples.n_rows,
        "n_used": int(ok.sum()), "n_dropped": samples.n_dropped + int((~ok).sum()),
        "accel_columns": accel_columns,
        "reference_heading": f"column {heading_column}" if heading_column is not None
        else f"yaw of attitude columns {attitude_columns}",
        "declination_deg": float(decl), "declination_source": decl_source,
        "alignment": "calibration" if alignment is not None else "none",
        "board_rotation": None if alignment is None else alignment["board_rotation"]["name"],
        **stats,
    }


def _row_range(rows: str | None) -> tuple[int, int | None]:
    from .io.stream import _parse_rows

    return _parse_rows(rows)


def simulate_to_file(
    *,
    model: str,
    params_path: str | Path,
    n: int,
    noise: float,
    out: str | Path,
    attitudes: str = "random",
    seed: int = 0,
    field: float = 1.0,
    units: str | None = None,
    truth: str | Path | None = None,
) -> dict[str, Any]:
    """Simulate a sensor with the parameters in ``params_path`` (JSON ``{name: value}``) and write a CSV log with
    columns ``x, y, z`` (raw), ``qw, qx, qy, qz`` (attitude, scalar first, body -> navigation NED) and, with
    ``truth``, a JSON file with the true parameters and settings."""
    from .models import get_model
    from .simulate import simulate

    p = Path(params_path)
    if not p.is_file():
        raise TrimagInputError(f"{p}: no such parameter file (JSON object of model parameters)")
    try:
        params = json.loads(p.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise TrimagInputError(f"{p}: not valid JSON ({exc})") from None
    if isinstance(params, dict) and "params" in params and isinstance(params["params"], dict):
        params = params["params"]
    if n < 1:
        raise TrimagInputError(f"`n` must be a positive number of samples; got {n}")
    if noise < 0 or not np.isfinite(noise):
        raise TrimagInputError(f"`noise` must be a non-negative standard deviation; got {noise}")
    truth_model = get_model(model).from_dict(params)
    sim = simulate(truth_model, n=n, field_nav=(field, 0.0, 0.0), noise=noise, attitudes=attitudes, seed=seed)
    q = sim.attitude.as_quat(scalar_first=True)
    table = np.column_stack([sim.raw, q])
    header = "x,y,z,qw,qx,qy,qz"
    import io as _stdio

    buf = _stdio.StringIO()
    np.savetxt(buf, table, delimiter=",", header=header, comments="", fmt="%.17g")
    written = {"data": str(atomic_write_text(out, buf.getvalue()))}
    if truth is not None:
        doc = {
            "model": model,
            "params": truth_model.as_dict(),
            "n": len(sim.raw),
            "noise": noise,
            "seed": seed,
            "attitudes": attitudes,
            "field_nav": [field, 0.0, 0.0],
            "units": normalise_unit(units),
        }
        written["truth"] = str(atomic_write_text(truth, json.dumps(doc, indent=2) + "\n"))
    return {"n": len(sim.raw), "outputs": written}


def run_demo(out_dir: str | Path = ".") -> FitResult:
    """Fit the bundled real log (QMC5883L, raw counts) and write the calibration and report into ``out_dir``."""
    out = Path(out_dir)
    data = resources.files("trimag") / "data" / DEMO_DATA
    with resources.as_file(data) as path:
        return fit_file(
            path,
            units="counts",
            model="ellipsoid",
            out=out / "trimag-demo-calibration.json",
            report=out / "trimag-demo-report.png",
        )
