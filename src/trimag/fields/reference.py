"""Field references: a known scalar magnitude, one per sample, IGRF from position and date, or none.

A scalar reference ``F`` is what magnitude-based calibration fits ``|B_corrected| = F`` against. Sources:

* a number (a proton/Overhauser magnetometer reading, or a value you trust), in the data's unit;
* one value per sample (a scalar magnetometer logged alongside);
* IGRF at a position and date (:func:`igrf`, via ``ppigrf``, offline), converted to the data's unit;
* ``"mean"`` / ``None``: no reference; the magnitude is a free parameter and the calibration preserves the
  mean field magnitude (the result is then relative: shape and offsets, not absolute scale).
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._core.chunks import row_blocks
from ..errors import TrimagInputError
from ..units import convert, normalise_unit
from ..validation import check_reference_values

__all__ = [
    "IGRFField",
    "ScalarReference",
    "as_scalar_reference",
    "igrf",
    "igrf_ned",
    "igrf_reference",
    "parse_igrf_spec",
]


@dataclass(frozen=True)
class IGRFField:
    """IGRF main field at one place and time (geodetic), components in nT."""

    north_nT: float
    east_nT: float
    down_nT: float
    latitude_deg: float
    longitude_deg: float
    altitude_m: float
    date: str

    @property
    def total_nT(self) -> float:
        """Total intensity F (nT)."""
        return float(np.sqrt(self.north_nT**2 + self.east_nT**2 + self.down_nT**2))

    @property
    def ned_nT(self) -> NDArray[np.float64]:
        """Field vector in the local north-east-down frame, shape (3,), nT."""
        return np.array([self.north_nT, self.east_nT, self.down_nT])

    @property
    def inclination_deg(self) -> float:
        """Inclination (dip), positive down, degrees."""
        return float(np.degrees(np.arctan2(self.down_nT, np.hypot(self.north_nT, self.east_nT))))

    @property
    def declination_deg(self) -> float:
        """Declination, positive east of true north, degrees."""
        return float(np.degrees(np.arctan2(self.east_nT, self.north_nT)))


def _parse_date(date: str | _dt.date | _dt.datetime) -> _dt.datetime:
    if isinstance(date, _dt.datetime):
        return date
    if isinstance(date, _dt.date):
        return _dt.datetime(date.year, date.month, date.day)
    try:
        return _dt.datetime.fromisoformat(str(date))
    except ValueError:
        raise TrimagInputError(f"date {date!r} is not an ISO date; write it as YYYY-MM-DD") from None


def igrf(
    latitude_deg: float,
    longitude_deg: float,
    altitude_m: float,
    date: str | _dt.date | _dt.datetime,
) -> IGRFField:
    """IGRF-14 main field at a geodetic position and date (via ``ppigrf``; no network needed).

    Parameters
    ----------
    latitude_deg, longitude_deg : float
        Geodetic latitude (-90..90) and longitude (degrees east).
    altitude_m : float
        Height above the WGS84 ellipsoid, metres.
    date : str or date
        ``YYYY-MM-DD``; IGRF-14 covers 1900-2030 (dates outside are refused).
    """
    import ppigrf

    if not -90.0 <= latitude_deg <= 90.0:
        raise TrimagInputError(f"latitude must be within -90..90 degrees; got {latitude_deg}")
    when = _parse_date(date)
    if not 1900 <= when.year < 2030:
        raise TrimagInputError(f"IGRF-14 covers 1900-2029; got the date {when.date().isoformat()}")
    be, bn, bu = ppigrf.igrf(longitude_deg, latitude_deg, altitude_m / 1000.0, when)
    return IGRFField(
        north_nT=float(np.ravel(bn)[0]),
        east_nT=float(np.ravel(be)[0]),
        down_nT=-float(np.ravel(bu)[0]),
        latitude_deg=float(latitude_deg),
        longitude_deg=float(longitude_deg),
        altitude_m=float(altitude_m),
        date=when.date().isoformat(),
    )


#: Working memory per position of :func:`igrf_ned`'s blocks, in doubles (983 positions per ``ppigrf`` call at the
#: default working memory; the measured optimum is near 1000).
IGRF_DOUBLES_PER_POSITION = 200


def igrf_ned(
    latitude_deg: ArrayLike, longitude_deg: ArrayLike, altitude_m: ArrayLike, date: str | _dt.date | _dt.datetime
) -> NDArray[np.float64]:
    """IGRF-14 main field (N, E, D), nT, at many geodetic positions and one date, vectorised (``ppigrf`` on blocks
    of positions, :func:`trimag._core.chunks.row_blocks`: its temporaries take about 10 KB per position, so one call
    on every position of a long flight would take gigabytes; blocks of ~1000 positions are also the fastest,
    0.43 s per 20 000 positions against 1.04 s in one call and 2.1 s in blocks of 150).

    Parameters
    ----------
    latitude_deg, longitude_deg : array_like, shape (N,)
        Geodetic latitude (-90..90) and longitude (degrees east).
    altitude_m : array_like, shape (N,)
        Height above the WGS84 ellipsoid, metres.
    date : str or date
        ``YYYY-MM-DD`` (IGRF-14: 1900-2029). One date for all positions: the secular variation is tens of nT per
        year, below 0.1 nT over a day's flight.

    Returns
    -------
    ndarray, shape (N, 3)
        North, east, down components, nT.
    """
    import ppigrf

    lat, lon, alt = (np.atleast_1d(np.asarray(v, dtype=np.float64)) for v in (latitude_deg, longitude_deg, altitude_m))
    if not (lat.shape == lon.shape == alt.shape and lat.ndim == 1):
        raise TrimagInputError(f"latitude, longitude and altitude need the same shape (N,); got {lat.shape}, "
                               f"{lon.shape}, {alt.shape}")
    if not (np.isfinite(lat).all() and np.isfinite(lon).all() and np.isfinite(alt).all()):
        raise TrimagInputError("latitude, longitude and altitude must be finite in every row")
    if np.any(np.abs(lat) > 90.0):
        raise TrimagInputError(f"latitude must be within -90..90 degrees; got {float(lat[np.abs(lat) > 90][0])}")
    when = _parse_date(date)
    if not 1900 <= when.year < 2030:
        raise TrimagInputError(f"IGRF-14 covers 1900-2029; got the date {when.date().isoformat()}")
    out = np.empty((len(lat), 3))
    for rows in row_blocks(len(lat), IGRF_DOUBLES_PER_POSITION):
        be, bn, bu = ppigrf.igrf(lon[rows], lat[rows], alt[rows] / 1000.0, when)
        out[rows] = np.column_stack([np.ravel(bn), np.ravel(be), -np.ravel(bu)])
    return out


def parse_igrf_spec(spec: str) -> tuple[float, float, float, str]:
    """Parse ``"LAT,LON,ALT_M,YYYY-MM-DD"`` (the ``--igrf`` option)."""
    parts = [p.strip() for p in str(spec).split(",")]
    if len(parts) != 4:
        raise TrimagInputError(
            f"`igrf_spec` takes LAT,LON,ALT_M,YYYY-MM-DD (e.g. 52.51,13.33,40,2021-01-01); got {spec!r}"
        )
    try:
        lat, lon, alt = (float(p) for p in parts[:3])
    except ValueError:
        raise TrimagInputError(f"`igrf_spec`: latitude, longitude and altitude must be numbers; got {spec!r}") from None
    _parse_date(parts[3])
    check_site(lat, lon, alt)
    return lat, lon, alt, parts[3]


#: the altitudes a site may have, m: the Dead Sea's shore (-430 m) less a margin, to a low orbit (IGRF's model holds
#: above the surface; 1000 km is well beyond any vehicle trimag calibrates)
ALTITUDE_RANGE_M = (-12_000.0, 1_000_000.0)


def check_site(latitude_deg: float, longitude_deg: float, altitude_m: float, what: str = "`igrf_spec`") -> None:
    """Refuse a site no place on Earth has (issue 41, item 14: a longitude of 1e308 was accepted): latitude -90..90,
    longitude -360..360 degrees, altitude within :data:`ALTITUDE_RANGE_M`; ``what`` names where it came from."""
    lo, hi = ALTITUDE_RANGE_M
    if not -90.0 <= latitude_deg <= 90.0:
        raise TrimagInputError(f"{what}: the latitude {latitude_deg:g} is not within -90..90 degrees")
    if not -360.0 <= longitude_deg <= 360.0:
        raise TrimagInputError(f"{what}: the longitude {longitude_deg:g} is not within -360..360 degrees (east)")
    if not lo <= altitude_m <= hi:
        raise TrimagInputError(f"{what}: the altitude {altitude_m:g} m is not within {lo:g} to {hi:g} m (metres "
                               "above sea level)")


@dataclass(frozen=True)
class ScalarReference:
    """A field-magnitude reference, in the data's unit.

    Attributes
    ----------
    values : ndarray, shape (N,), or None
        The magnitude each sample should have after correction; ``None`` means unknown (fitted).
    source : str
        Where it came from: ``"given"``, ``"column NAME"``, ``"igrf LAT,LON,ALT,DATE"``, ``"mean"``.
    unit : str
    """

    values: NDArray[np.float64] | None
    source: str
    unit: str = "unknown"

    @property
    def known(self) -> bool:
        """True when the magnitude is given, not fitted."""
        return self.values is not None

    def info(self, fitted_value: float | None = None) -> dict[str, Any]:
        """``{"value", "source", "unit"}`` for files and JSON output (per-sample values give their mean)."""
        value = float(np.mean(self.values)) if self.values is not None else fitted_value
        out: dict[str, Any] = {"value": value, "source": self.source, "unit": self.unit}
        if self.values is not None and np.ptp(self.values) > 0:
            out["per_sample"] = True
        return out


def igrf_reference(
    latitude_deg: float, longitude_deg: float, altitude_m: float, date: str, *, n: int, units: str
) -> ScalarReference:
    """IGRF total intensity as a constant reference for ``n`` samples, in ``units``."""
    field = igrf(latitude_deg, longitude_deg, altitude_m, date)
    value = convert(field.total_nT, "nT", units)
    return ScalarReference(
        np.full(n, value),
        f"igrf {latitude_deg},{longitude_deg},{altitude_m},{field.date} (IGRF-14, {field.total_nT:.1f} nT)",
        normalise_unit(units),
    )


def as_scalar_reference(reference: Any, n: int, *, units: str = "unknown") -> ScalarReference:
    """Normalise what a user passes as ``reference`` into a :class:`ScalarReference` for ``n`` samples.

    Accepts ``None`` or ``"mean"`` (unknown magnitude), a positive number, an array of shape (N,), or a
    :class:`ScalarReference` (checked against ``n``).
    """
    unit = normalise_unit(units)
    if isinstance(reference, ScalarReference):
        if reference.values is not None:
            check_reference_values(reference.values, n)
        return reference
    if reference is None or (isinstance(reference, str) and reference.strip().lower() == "mean"):
        return ScalarReference(None, "mean", unit)
    if isinstance(reference, str):
        try:
            reference = float(reference)
        except ValueError:
            raise TrimagInputError(
                f"reference {reference!r} is neither a number nor 'mean'; give the field magnitude in the "
                "data's unit, e.g. `reference=48193`"
            ) from None
    values = check_reference_values(reference, n)
    source = "given" if np.ndim(reference) == 0 else "per-sample"
    return ScalarReference(values, source, unit)


def as_vector(value: ArrayLike, *, name: str = "background") -> NDArray[np.float64]:
    """Validate a field vector of shape (3,)."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (3,) or not np.isfinite(arr).all():
        got = np.asarray(value).tolist() if arr.size <= 3 else f"an array of shape {arr.shape}"
        hint = ("; a per-sample background (one vector per row) is given as `background_columns` (or as an (N, 3) "
                "array to `fit`)" if arr.ndim == 2 and arr.shape[-1] == 3 else "")
        raise TrimagInputError(f"`{name}` must be 3 finite numbers (N, E, D); got {got}{hint}")
    return arr


def as_background(value: ArrayLike, n: int, *, name: str = "background") -> NDArray[np.float64]:
    """Validate a background field: one vector (3,) or one per sample (``n``, 3), NED, finite.

    Parameters
    ----------
    value : array_like, shape (3,) or (n, 3)
        The background field in the navigation frame (NED), in the data's unit.
    n : int
        Number of samples.

    Returns
    -------
    ndarray, shape (3,) or (n, 3)
    """
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != 2:
        return as_vector(arr, name=name)
    if arr.shape[1] != 3 or arr.shape[0] != n:
        raise TrimagInputError(
            f"`{name}` per sample needs one row per sample (N, E, D): {n} rows of 3; got {arr.shape[0]} rows of "
            f"{arr.shape[1]}"
        )
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        raise TrimagInputError(
            f"`{name}` has {int(bad.sum())} row(s) with missing or non-finite values (first at row "
            f"{int(np.argmax(bad))})"
        )
    return arr
