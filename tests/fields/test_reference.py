"""Field references: IGRF known values against the NOAA calculator, unit conversion, parsing.

Known values (the source, stated once):
    NOAA NCEI Magnetic Field Calculator, https://www.ngdc.noaa.gov/geomag/calculators/magcalc.shtml ,
    model IGRF (IGRF-14, labelled "IGRF2025" by NOAA), sea level (elevation 0 km), yearly time series,
    total field F in nT. The values below are copied from the calculator's JSON output as transcribed in the
    PmagPy project's IGRF test file ("NOAA IGRF14 reference values calculated with the magnetic field
    calculator ... on Feb 28, 2026"); I did not query the calculator myself. The time series is on 1 January
    of each year (at these points ppigrf agrees with it within 1 nT, while mid-year would differ by the
    secular variation, ~17 nT per half year here).

Tolerance: 5 nT (issue 4). The calculator prints F to 0.1 nT; the remaining differences come from the
geodetic-to-geocentric conversion and the date convention of the two implementations, well under 5 nT at
these latitudes.
"""

from __future__ import annotations

import numpy as np
import pytest

from trimag.errors import TrimagInputError
from trimag.fields.reference import as_scalar_reference, igrf, igrf_reference, parse_igrf_spec

NOAA_IGRF14_F = [
    # (latitude, longitude, date, F [nT])
    pytest.param(20.0, 50.0, "2020-01-01", 41232.3, id="20N-50E-2020"),
    pytest.param(20.0, 50.0, "2025-01-01", 41406.0, id="20N-50E-2025"),
    pytest.param(-20.0, 50.0, "2020-01-01", 35870.0, id="20S-50E-2020"),
    pytest.param(20.0, -50.0, "2022-01-01", 35164.9, id="20N-50W-2022"),
    pytest.param(20.0, 50.0, "2000-01-01", 40484.5, id="20N-50E-2000"),
]


@pytest.mark.parametrize(("lat", "lon", "date", "F_noaa"), NOAA_IGRF14_F)
def test_igrf_total_field_matches_the_noaa_calculator(
    lat: float, lon: float, date: str, F_noaa: float
) -> None:
    field = igrf(lat, lon, 0.0, date)
    assert abs(field.total_nT - F_noaa) < 5.0


def test_igrf_components_are_consistent() -> None:
    f = igrf(20.0, 50.0, 0.0, "2020-01-01")
    # NOAA, same source: X = 35747.8, Y = 1220.6, Z = 20511.3 nT (north, east, down), inclination 29.83 deg
    np.testing.assert_allclose(f.ned_nT, [35747.8, 1220.6, 20511.3], atol=5.0)
    assert f.inclination_deg == pytest.approx(29.832, abs=0.02)
    assert f.declination_deg == pytest.approx(1.956, abs=0.02)


def test_igrf_reference_is_converted_to_the_data_unit() -> None:
    ref_nT = igrf_reference(20.0, 50.0, 0.0, "2020-01-01", n=4, units="nT")
    ref_uT = igrf_reference(20.0, 50.0, 0.0, "2020-01-01", n=4, units="uT")
    ref_G = igrf_reference(20.0, 50.0, 0.0, "2020-01-01", n=4, units="G")
    assert ref_nT.values is not None and ref_uT.values is not None and ref_G.values is not None
    assert ref_nT.values.shape == (4,)
    np.testing.assert_allclose(ref_uT.values * 1e3, ref_nT.values)
    np.testing.assert_allclose(ref_G.values * 1e5, ref_nT.values)
    assert "41231" in ref_nT.source or "41232" in ref_nT.source  # the value used is printed in the source


def test_parse_igrf_spec_and_its_errors() -> None:
    assert parse_igrf_spec("52.51, 13.33, 40, 2021-01-01") == (52.51, 13.33, 40.0, "2021-01-01")
    with pytest.raises(TrimagInputError, match="LAT,LON,ALT_M"):
        parse_igrf_spec("52.5,13.3,2021-01-01")
    with pytest.raises(TrimagInputError, match="ISO date"):
        parse_igrf_spec("52.5,13.3,40,1st of May")
    with pytest.raises(TrimagInputError, match="1900-2029"):
        igrf(0.0, 0.0, 0.0, "2035-01-01")


def test_scalar_reference_forms() -> None:
    assert as_scalar_reference("mean", 3).values is None
    assert as_scalar_reference(None, 3).source == "mean"
    np.testing.assert_array_equal(as_scalar_reference("48193", 2, units="nT").values, [48193.0, 48193.0])
    with pytest.raises(TrimagInputError, match="neither a number nor 'mean'"):
        as_scalar_reference("median", 3)
    with pytest.raises(TrimagInputError, match="finite and positive"):
        as_scalar_reference([1.0, -1.0], 2)
