"""What a request's text options become: method options, the field reference (magnitude or background vector),
regressor and accelerometer columns, and the rows without an attitude or background dropped and counted."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from ..calibration import Calibration
from ..errors import TrimagInputError
from ..fields.reference import ScalarReference, as_scalar_reference, igrf, igrf_reference, parse_igrf_spec
from ..io import Samples, column_values
from ..io.tables import strict_refusal
from ..units import convert
from ..validation import check_nesting
from .requests import AttitudeSpec, ReferenceSpec

if TYPE_CHECKING:  # scipy.spatial (~0.1 s to import) only for fits with attitudes, which import it themselves
    from scipy.spatial.transform import Rotation


def parse_options(items: list[str] | None) -> dict[str, Any]:
    """Parse ``KEY=VALUE`` method options; values are JSON when they parse as JSON, else strings."""
    out: dict[str, Any] = {}
    for item in items or []:
        if "=" not in item:
            raise TrimagInputError(f"`option` takes KEY=VALUE (e.g. `option form=symmetric`); got {item!r}")
        key, value = item.split("=", 1)
        check_nesting(value, f"`option {key.strip()}`")
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


def refuse_background_vector(given: ReferenceSpec) -> None:
    """A magnitude fit or evaluation has no use for a background vector: refuse one rather than ignore it."""
    for name in ("background_ned", "background_columns", "igrf_columns", "background_run"):
        if getattr(given, name) is not None:
            raise TrimagInputError(
                f"`{name}` is a background vector, for an attitude-based model (interference12, with "
                "`attitude_columns` or `quaternion_columns`); a magnitude takes `reference=F`, "
                "`igrf_spec=LAT,LON,ALT_M,DATE` or `reference_column=NAME`"
            )


def magnitude_reference(samples: Samples, given: ReferenceSpec, unit: str) -> ScalarReference:
    """The field magnitude reference of ``samples`` in ``unit``: ``given.reference`` (a number, or ``"mean"``),
    ``given.igrf_spec`` or ``given.reference_column`` (at most one of them; none: unknown). A background vector
    (``background_ned`` ...) is refused."""
    refuse_background_vector(given)
    reference, igrf_spec, reference_column = given.reference, given.igrf_spec, given.reference_column
    named = [x for x in (reference, igrf_spec, reference_column) if x is not None]
    if len(named) > 1:
        raise TrimagInputError("give only one of `reference`, `igrf_spec`, `reference_column`")
    n = len(samples.field)
    if igrf_spec is not None:
        lat, lon, alt, date = parse_igrf_spec(igrf_spec)
        return igrf_reference(lat, lon, alt, date, n=n, units=unit)
    if reference_column is not None:
        values = column_values(samples, reference_column)
        ref = as_scalar_reference(values, n, units=unit)
        return ScalarReference(ref.values, f"column {reference_column}", ref.unit)
    return as_scalar_reference(reference, n, units=unit)


def background_field(
    given: ReferenceSpec, unit: str, samples: Samples | None = None, **read_kwargs: Any
) -> tuple[NDArray[np.float64], str]:
    """The background field (N, E, D) in ``unit``, shape (3,) or (N, 3) (``background_columns``, ``igrf_columns``:
    one vector per row of ``samples``), and a description of its source: exactly one of ``given.background_ned``,
    ``igrf_spec``, ``background_run`` (read with ``read_kwargs``, :func:`trimag.io.background.background_from_run`),
    ``background_columns`` and ``igrf_columns`` (IGRF-14 at each row's position)."""
    background_ned, igrf_spec = given.background_ned, given.igrf_spec
    background_run, background_columns = given.background_run, given.background_columns
    named = [x for x in (background_ned, igrf_spec, background_run, background_columns, given.igrf_columns)
             if x is not None]
    if len(named) != 1:
        raise TrimagInputError(
            "model interference12 needs exactly one background field: `background_ned=N,E,D`, "
            "`igrf_spec=LAT,LON,ALT_M,DATE`, `background_run=FILE`, `background_columns=N,E,D` or "
            "`igrf_columns=LAT,LON,ALT_M,DATE`"
        )
    if given.igrf_columns is not None:
        from ..io.background import igrf_along_track, parse_igrf_columns

        if samples is None:
            raise TrimagInputError("`igrf_columns` needs the samples' table")
        cols, date = parse_igrf_columns(given.igrf_columns)
        track = [column_values(samples, c) for c in _split_names(",".join(cols), samples, "igrf_columns")]
        return igrf_along_track(track[0], track[1], track[2], date, units=unit)
    if background_columns is not None:
        if samples is None:
            raise TrimagInputError("`background_columns` needs the samples' table")
        names = _split_names(background_columns, samples, "background_columns")
        values = np.column_stack([column_values(samples, c) for c in names])
        F = np.linalg.norm(values, axis=1)
        return values, (f"per sample from columns {', '.join(names)}, |H| {F.min():.6g} to {F.max():.6g} {unit}, "
                        f"mean NED {np.round(values.mean(axis=0), 3).tolist()}")
    if background_ned is not None:
        return _parse_vector(background_ned, "`background_ned`"), "given (NED)"
    if igrf_spec is not None:
        lat, lon, alt, date = parse_igrf_spec(igrf_spec)
        fld = igrf(lat, lon, alt, date)
        vec = fld.ned_nT * convert(1.0, "nT", unit)
        return vec, f"igrf {igrf_spec} (IGRF-14, NED {np.round(fld.ned_nT, 1).tolist()} nT)"

    assert background_run is not None
    from ..io.background import background_from_run

    return background_from_run(background_run, units=unit, **read_kwargs)


def parse_regressor_names(names: Any) -> tuple[str, ...] | None:
    """``FitRequest.regressors`` (a tuple, or a comma-separated string) as a tuple of names; None when none."""
    if names is None:
        return None
    items = names.split(",") if isinstance(names, str) else list(names)
    out = tuple(str(n).strip() for n in items if str(n).strip())
    if not out:
        raise TrimagInputError("`regressors` names no column; give COL[,COL...]")
    if len(set(out)) != len(out):
        from collections import Counter

        from ..validation import listed

        twice = sorted(n for n, k in Counter(out).items() if k > 1)
        raise TrimagInputError(f"`regressors` names a column more than once: {listed(twice)}")
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


def calibration_regressors(
    cal: Calibration, samples: Samples, path: Any, *, time_column: str | None = None, rate_hz: float | None = None
) -> dict[str, NDArray[np.float64]] | None:
    """The values (N,) of a calibration's regressors on the kept rows of ``samples``: logged channels from their
    columns, eddy-current terms (:mod:`trimag.vehicle.eddy`) from the samples' own derivative (from ``time_column``
    or at ``rate_hz`` when given, :func:`trimag.vehicle.eddy.values_from_table`); None without terms."""
    if cal.regressors is None:
        return None
    spec = cal.regressors.get("eddy")
    derived = set(spec["names"]) if spec else set()
    out = regressor_columns(samples, tuple(n for n in cal.regressors["names"] if n not in derived), path)
    if spec:
        from ..vehicle.eddy import values_from_table

        out.update(values_from_table(spec, samples.table, samples.field, path, time_column=time_column,
                                     rate_hz=rate_hz))
    return out


def _split_names(spec: str, samples: Samples, arg: str) -> list[str]:
    """Three column names (or 0-based indices) of ``samples.table`` from ``"A,B,C"``; ``arg`` names the option."""
    items = [c.strip() for c in spec.split(",") if c.strip()]
    if len(items) != 3:
        raise TrimagInputError(f"`{arg}` needs exactly three columns (N, E, D); got {len(items)}")
    from ..fields.attitude import column_names

    names = [str(c) for c in samples.table.columns]
    for item in items:
        if item not in names and item.isdigit() and int(item) >= len(names):
            raise TrimagInputError(f"`{arg}`: index {item} is out of range; the file has {len(names)} columns")
    return column_names(items, names)


def drop_rows_without_background(
    samples: Samples, background_columns: str | None, igrf_columns: str | None = None, *, strict: bool = False
) -> tuple[Samples, int]:
    """Drop (and count) the rows whose per-sample background (or position) cells are missing or non-finite
    (``strict``: refuse them)."""
    if igrf_columns is not None:
        from ..io.background import parse_igrf_columns

        background_columns = ",".join(parse_igrf_columns(igrf_columns)[0])
    if background_columns is None:
        return samples, 0
    names = ",".join(_split_names(background_columns, samples, "background_columns"))
    try:
        return drop_rows_without_attitude(samples, names, None, strict=strict, what="background")
    except TrimagInputError as exc:
        if strict and "`strict`" in str(exc):
            raise
        raise TrimagInputError(f"none of the rows has a finite background in columns {names}") from None


def accel_values(samples: Samples, accel_columns: str, path: Any) -> NDArray[np.float64]:
    """The accelerometer columns ``"AX,AY,AZ"`` of the kept rows of ``samples``, shape (N, 3); one line naming the
    missing column, or the rows with a non-numeric value, when they are not there."""
    from ..fields.attitude import parse_columns

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


def attitudes_of(samples: Samples, att: AttitudeSpec) -> Rotation:
    """The attitude of every kept row of ``samples`` from the columns ``att`` names (Euler angles or quaternions,
    in its order and frame; docs/conventions-attitude.md)."""
    from ..fields.attitude import attitude_from_table

    return attitude_from_table(
        samples.table, euler_columns=att.attitude_columns, quaternion_columns=att.quaternion_columns,
        scalar_first=att.quaternion_order == "wxyz", frame=att.quaternion_frame,
    )


def drop_rows_without_attitude(
    samples: Samples, attitude_columns: str | None, quaternion_columns: str | None, *, strict: bool = False,
    what: str = "attitude",
) -> tuple[Samples, int]:
    """Drop (and count) the rows whose attitude cells are missing or non-finite (``strict``: refuse them)."""
    names = [c.strip() for c in (attitude_columns or quaternion_columns or "").split(",") if c.strip()]
    present = [c for c in names if c in samples.table.columns]
    if not present:
        return samples, 0
    values = np.column_stack([pd.to_numeric(samples.table[c], errors="coerce").to_numpy(dtype=float) for c in present])
    ok = np.isfinite(values).all(axis=1)
    n_bad = int((~ok).sum())
    if n_bad == 0:
        return samples, 0
    if strict:
        raise strict_refusal("", n_bad, f"a missing or non-numeric {what} in columns {', '.join(present)}",
                             f"kept row {int(np.flatnonzero(~ok)[0])}")
    if n_bad == len(ok):
        raise TrimagInputError(f"none of the rows has a finite attitude in columns {', '.join(present)}")
    kept = dataclasses.replace(
        samples,
        field=samples.field[ok],
        table=samples.table[ok],  # the index keeps the original row numbers (trimag.vehicle.eddy's gaps)
        n_dropped=samples.n_dropped + n_bad,
    )
    return kept, n_bad


def truthy(value: Any) -> bool:
    if isinstance(value, str):
        return value.strip().lower() in ("1", "true", "yes", "on")
    return bool(value)



def calibration_for(calibration_path: str | Path, data_path: str | Path | None, command: str) -> Calibration:
    """The calibration file a command (``apply``, ``evaluate``; ``fit --prior`` with ``data_path`` None) was given;
    a data file in its place (not JSON text) is named as such, and two arguments given in the wrong order are said
    to be swapped."""
    from ..errors import CalibrationFormatError

    try:
        return Calibration.from_file(calibration_path)
    except (CalibrationFormatError, UnicodeDecodeError) as exc:
        if isinstance(exc, CalibrationFormatError) and "not valid JSON" not in str(exc):
            raise
        swapped = False
        if data_path is not None:
            try:
                Calibration.from_file(data_path)
                swapped = True
            except (TrimagInputError, UnicodeDecodeError, OSError):
                pass
        if swapped:
            raise TrimagInputError(f"{calibration_path} is a log and {data_path} a calibration: the calibration comes "
                                   f"first: `trimag {command} {data_path} {calibration_path}`") from None
        takes = (f"`trimag {command}` takes the JSON calibration that `trimag fit LOG -o cal.json` writes, then the "
                 "log" if data_path is not None else
                 f"{command} takes the JSON calibration that an earlier `trimag fit LOG -o cal.json` wrote")
        raise TrimagInputError(f"{calibration_path} is not a calibration file (it is not JSON text): {takes}") \
            from None
