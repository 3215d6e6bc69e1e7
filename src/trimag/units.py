"""Field units known to trimag and conversions between them.

=========  ==================  =========================================================
unit       nT per unit         note
=========  ==================  =========================================================
``nT``     1                   nanotesla
``uT``     1e3                 microtesla (also accepted: ``µT``)
``G``      1e5                 gauss (also accepted: ``gauss``)
``mG``     1e2                 milligauss
``1e4nT``  1e4                 the unit of paper A's fluxgate experiment
``counts`` --                  raw sensor output; no conversion to physical units exists
``unknown`` --                 not stated by the user; no conversion exists
=========  ==================  =========================================================
"""

from __future__ import annotations

from .errors import TrimagInputError

__all__ = ["UNITS", "convert", "nT_per_unit", "normalise_unit"]

UNITS: dict[str, float | None] = {
    "nT": 1.0,
    "uT": 1e3,
    "G": 1e5,
    "mG": 1e2,
    "1e4nT": 1e4,
    "counts": None,
    "unknown": None,
}

_ALIASES = {
    "nt": "nT",
    "ut": "uT",
    "µt": "uT",
    "μt": "uT",
    "microtesla": "uT",
    "nanotesla": "nT",
    "g": "G",
    "gauss": "G",
    "mg": "mG",
    "milligauss": "mG",
    "1e4nt": "1e4nT",
    "counts": "counts",
    "count": "counts",
    "lsb": "counts",
    "raw": "counts",
    "unknown": "unknown",
}


def normalise_unit(unit: str | None) -> str:
    """Return the canonical spelling of ``unit`` (``None`` gives ``"unknown"``).

    Raises
    ------
    TrimagInputError
        If the unit is not one of :data:`UNITS` or an alias of one.
    """
    if unit is None:
        return "unknown"
    key = str(unit).strip()
    if key in UNITS:
        return key
    canonical = _ALIASES.get(key.lower())
    if canonical is None:
        raise TrimagInputError(
            f"unknown unit {unit!r}; use one of {', '.join(UNITS)} (e.g. `units=uT`)"
        )
    return canonical


def unit_words(unit: str | None) -> str:
    """``unit`` as a reader names it: ``"unit not given"`` for ``unknown`` (a fit without ``units``), else the unit
    (``"nT"``, ``"counts"``); e.g. a table's heading ``[unit not given]``."""
    return "unit not given" if unit is None or unit == "unknown" else str(unit)


def unit_after(unit: str | None) -> str:
    """``unit`` written after a number: ``"nT"``, or ``"(unit not given)"`` for ``unknown`` (never ``"37 unknown"``,
    as if "unknown" were a unit)."""
    words = unit_words(unit)
    return f"({words})" if words == "unit not given" else words


def nT_per_unit(unit: str) -> float:
    """Nanotesla per one ``unit``; raises for ``counts`` and ``unknown``, which have no physical scale."""
    canonical = normalise_unit(unit)
    factor = UNITS[canonical]
    if factor is None:
        raise TrimagInputError(
            f"unit {canonical!r} has no conversion to nT; state the data's physical unit with `units` "
            "(nT, uT, G, mG) or give the reference in the data's own unit"
        )
    return factor


def convert(value: float, from_unit: str, to_unit: str) -> float:
    """Convert a field value between physical units, e.g. ``convert(48193, "nT", "uT") == 48.193``."""
    if normalise_unit(from_unit) == normalise_unit(to_unit):
        return float(value)
    return float(value) * nT_per_unit(from_unit) / nT_per_unit(to_unit)


#: magnitudes of a raw Earth-field reading that a calibration can start from, nT: the weakest main field (~22 uT)
#: with a strong hard iron against it, up to the strongest (~67 uT) with a strong hard iron adding to it
EARTH_RAW_RANGE_NT = (5_000.0, 300_000.0)



#: magnitudes of the Earth's field itself (what a calibration's fitted F must be), nT: ArduPilot's onboard calibrator
#: accepts a fitted radius of 150-950 mGauss (``FIELD_RADIUS_MIN``/``MAX``, libraries/AP_Compass/CompassCalibrator.h,
#: ``fit_acceptable``); the main field is 22-67 uT at the surface (IGRF-14), the rest is room for scale errors
EARTH_FIELD_RANGE_NT = (15_000.0, 95_000.0)


def plausible_units(median_norm: float, *, field: bool = False) -> list[str]:
    """Physical units in which a raw magnitude of ``median_norm`` is a plausible Earth-field reading
    (:data:`EARTH_RAW_RANGE_NT`), or with ``field`` a plausible Earth field itself (:data:`EARTH_FIELD_RANGE_NT`)."""
    lo, hi = EARTH_FIELD_RANGE_NT if field else EARTH_RAW_RANGE_NT
    return [u for u, f in UNITS.items() if f is not None and u != "1e4nT" and lo <= median_norm * f <= hi]


def header_unit(names: list[str]) -> str | None:
    """The unit written in the x, y, z column headers (``Mx (uT)``, ``mag_x_nT``, ``Bx[G]``, ``x_counts``), if one
    and the same."""
    import re

    pattern = re.compile(r"(?:[\(\[]\s*|[_\s])(nT|uT|µT|μT|mG|mGauss|G|gauss|Gauss|counts)\s*[\)\]]?\s*$")
    found = set()
    for name in names:
        m = pattern.search(str(name))
        if m is None:
            return None
        token = m.group(1)
        found.add(normalise_unit("mG" if token.lower() == "mgauss" else token))
    return found.pop() if len(found) == 1 else None


__all__ += ["EARTH_FIELD_RANGE_NT", "EARTH_RAW_RANGE_NT", "header_unit", "plausible_units"]
