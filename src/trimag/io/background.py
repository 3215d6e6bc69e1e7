"""Background fields of the vector model: the mean of an iron-free run stored in a file (``--background-run FILE``;
paper C), and IGRF along the track from position columns (``--igrf-columns LAT,LON,ALT_M,YYYY-MM-DD``)."""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from ..errors import TrimagInputError
from ..fields.attitude import attitude_from_table, background_from_samples, parse_columns
from ..units import normalise_unit
from .tables import read_samples

__all__ = ["background_from_run", "igrf_along_track", "parse_igrf_columns"]


def background_from_run(
    path: str | os.PathLike[str],
    *,
    units: str = "unknown",
    attitude: Rotation | None = None,
    attitude_columns: str | Sequence[str] | None = None,
    quaternion_columns: str | Sequence[str] | None = None,
    quaternion_order: str = "wxyz",
    quaternion_frame: str = "ned",
    degrees: bool = True,
    fmt: str | None = None,
    columns: str | None = None,
    var: str | None = None,
) -> tuple[NDArray[np.float64], str]:
    """Background field (NED) from an iron-free run stored in a file (``--background-run FILE``).

    The file is read like the data (same ``fmt``, ``columns``, ``var``, unit ``units``). Attitudes come from
    the file's own attitude columns when it has the named ones; otherwise the run must have been recorded
    at the same attitudes as the data, row for row, and ``attitude`` (the data's) is used.

    Returns
    -------
    H_n : ndarray, shape (3,)
        :func:`background_from_samples` of the run, in ``units``.
    source : str
        A description for messages and the calibration file (file name, rows, spread).
    """
    run = read_samples(os.fspath(path), fmt=fmt, columns=columns, var=var)
    wanted = parse_columns(attitude_columns, 3, option="`attitude_columns`") or parse_columns(
        quaternion_columns, 4, option="`quaternion_columns`"
    )
    has_own = wanted is not None and all(c in [str(x) for x in run.table.columns] for c in wanted)
    if has_own:
        att = attitude_from_table(
            run.table, euler_columns=attitude_columns, quaternion_columns=quaternion_columns,
            scalar_first=quaternion_order == "wxyz", frame=quaternion_frame, degrees=degrees,
        )
        how = "its own attitude columns"
    elif attitude is not None:
        n_att = 1 if attitude.single else len(attitude)
        if n_att != len(run.field):
            raise TrimagInputError(
                f"`background_run` {path}: the file has no attitude columns {wanted} and {len(run.field)} "
                f"valid rows, but the data have {n_att} attitudes; record the iron-free run at the same "
                "attitudes (one row each) or add the attitude columns to it"
            )
        att = attitude
        how = "the data's attitudes, row for row"
    else:
        raise TrimagInputError(
            f"`background_run` {path}: no attitudes for the iron-free run; add attitude columns to it"
        )
    H_n, spread = background_from_samples(run.field, att)
    unit = normalise_unit(units)
    source = (
        f"mean of iron-free run {os.path.basename(os.fspath(path))} ({len(run.field)} rows, {how}; "
        f"rotated readings scatter {spread:.4g} {unit} RMS)"
    )
    return H_n, source


def parse_igrf_columns(spec: str) -> tuple[list[str], str]:
    """``"LAT,LON,ALT_M,YYYY-MM-DD"`` (``--igrf-columns``) -> the three position columns and the date."""
    parts = [p.strip() for p in str(spec).split(",")]
    if len(parts) != 4 or not all(parts):
        raise TrimagInputError(
            f"`igrf_columns` takes LAT,LON,ALT_M,YYYY-MM-DD: the latitude, longitude (degrees) and altitude (m above "
            f"the WGS84 ellipsoid) columns and the date, e.g. lat,lon,alt,2020-06-29; got {spec!r}"
        )
    return parts[:3], parts[3]


def igrf_along_track(
    latitude_deg: NDArray[np.float64], longitude_deg: NDArray[np.float64], altitude_m: NDArray[np.float64], date: str,
    *, units: str = "nT",
) -> tuple[NDArray[np.float64], str]:
    """IGRF-14 (N, E, D) at every sample's position (:func:`trimag.fields.reference.igrf_ned`), in ``units``, shape
    (N, 3), and a description of it for messages and the calibration file."""
    from ..fields.reference import igrf_ned
    from ..units import convert

    H = igrf_ned(latitude_deg, longitude_deg, altitude_m, date) * convert(1.0, "nT", units)
    F = np.linalg.norm(H, axis=1)
    unit = normalise_unit(units)
    return H, (f"IGRF-14 along the track ({len(H)} positions, {date}): |H| {F.min():.6g} to {F.max():.6g} {unit}, "
               f"mean NED {np.round(H.mean(axis=0), 3).tolist()}")
