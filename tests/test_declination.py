"""Magnetic declination from the World Magnetic Model (napari_imgreg.geo).

Known answers: NOAA/NCEI's published test values of each edition, the
table printed in the WMM report and distributed with its coefficients
(``WMM2025_TEST_VALUES.txt``, ``WMM2020_TEST_VALUES.txt``; pygeomag's own
tests use the same files, ``test/test_values/``). Each row gives the decimal
year, the height above the WGS84 ellipsoid (km), geodetic latitude and
longitude (degrees) and the declination D (degrees, east positive, rounded
to 0.01°).
"""

from __future__ import annotations

import math
from datetime import date, datetime, timedelta, timezone

import pytest

from napari_imgreg.geo import (
    DeclinationError,
    GeoError,
    Georef,
    WMM_GRACE_YEARS,
    declination_deg,
    magnetic_declination,
    site_latitude_longitude,
)

# (decimal year, height km, lat, lon, D) — WMM2025_TEST_VALUES.txt (NOAA NCEI,
# WMM2025 report, test values for 2025.0–2029.5). The polar rows (lat ≥ 80°,
# horizontal field < 2000 nT) are in the next test.
WMM2025_ROWS = [
    (2025.0, 65, 43, 93, 0.50),
    (2025.0, 51, -33, 109, -5.49),
    (2025.0, 39, -59, -8, -15.75),
    (2025.0, 3, -50, -103, 27.96),
    (2025.0, 18, 0, 21, 1.29),
    (2025.5, 6, -36, -137, 20.28),
    (2025.5, 69, 38, -144, 12.93),
    (2025.5, 44, 33, -118, 11.10),
    (2026.0, 46, -24, -122, 14.01),
    (2026.0, 62, -14, 99, -1.43),
    (2026.5, 43, 17, 52, 1.19),
    (2026.5, 12, 33, -145, 11.96),
    (2027.0, 67, 72, -115, 13.73),
    (2027.0, 61, 59, -77, -16.48),
    (2027.5, 0, -13, -59, -17.49),
    (2027.5, 8, 62, 53, 19.39),
    (2028.0, 71, 5, -13, -6.47),
    (2028.0, 30, -36, -64, -4.65),
    (2028.5, 11, 34, 0, 1.57),
    (2028.5, 28, 54, -120, 15.43),
    (2029.0, 41, 42, -19, -4.13),
    (2029.0, 19, 46, -22, -5.65),
    (2029.5, 31, 13, -132, 9.04),
    (2029.5, 33, 17, 5, 0.89),
]

# WMM2020_TEST_VALUES.txt (NOAA NCEI, WMM2020 report, 2020.0–2024.5).
WMM2020_ROWS = [
    (2020.0, 65, 43, 93, 0.71),
    (2020.0, 51, -33, 109, -5.78),
    (2020.0, 39, -59, -8, -15.79),
    (2020.5, 6, -36, -137, 20.16),
    (2020.5, 63, 26, 81, 0.43),
    (2021.5, 12, 33, -145, 12.36),
    (2022.0, 38, 27, -169, 8.76),
    (2023.5, 95, 30, 28, 4.49),
    (2024.0, 58, 32, 19, 3.94),
    (2024.5, 77, -18, 138, 4.63),
]

#: The published values are rounded to 0.01°; the brief's bar is 0.05°.
TOLERANCE_DEG = 0.05


def _instant(decimal_year: float) -> datetime:
    """The UTC instant of a decimal year (2025.5 = 2 July 2025, 12:00)."""
    year = int(decimal_year)
    start = datetime(year, 1, 1, tzinfo=timezone.utc)
    length = datetime(year + 1, 1, 1, tzinfo=timezone.utc) - start
    return start + (decimal_year - year) * length


@pytest.mark.parametrize("year, height_km, lat, lon, expected", WMM2025_ROWS + WMM2020_ROWS)
def test_declination_matches_noaa_test_values(year, height_km, lat, lon, expected):
    result = magnetic_declination(lat, lon, height_km * 1000.0, _instant(year))
    assert result.declination_deg == pytest.approx(expected, abs=TOLERANCE_DEG)
    assert declination_deg(lat, lon, height_km * 1000.0, _instant(year)) \
        == result.declination_deg
    assert result.model == ("WMM2025" if year >= 2025 else "WMM2020")
    assert not result.extrapolated


def test_east_positive_and_the_label_names_model_and_date():
    # Seattle's declination is east (~15°, NOAA's calculator), the Cape's west.
    seattle = magnetic_declination(47.6205, -122.3493, 0.0, date(2026, 6, 1))
    assert seattle.declination_deg == pytest.approx(15.0, abs=0.3)
    assert seattle.label() == f"{seattle.declination_deg:+.1f}° (WMM2025, 2026-06-01)"
    assert seattle.to_dict()["model"] == "WMM2025"
    assert seattle.to_dict()["date"] == "2026-06-01"
    assert 0.2 < seattle.uncertainty_deg < 1.0
    assert magnetic_declination(-34.0, 18.5, 0.0, date(2026, 6, 1)).declination_deg < -20.0


def test_an_aware_time_is_taken_in_utc():
    # 00:30 on 1 January 2026 in UTC+02 is still 2025 in UTC: WMM2025 either way,
    # but the date recorded is the UTC one.
    local = datetime(2026, 1, 1, 0, 30, tzinfo=timezone(timedelta(hours=2)))
    assert magnetic_declination(45.0, 7.0, 0.0, local).date == date(2025, 12, 31)


def test_older_editions_cover_2010_to_2020():
    assert magnetic_declination(45.0, 7.0, 0.0, date(2016, 5, 1)).model == "WMM2015v2"
    old = magnetic_declination(45.0, 7.0, 0.0, date(2012, 5, 1))
    assert old.model == "WMM2010" and math.isnan(old.uncertainty_deg)
    assert old.to_dict()["uncertainty_deg"] is None


def test_dates_outside_the_models_are_refused_in_one_line():
    with pytest.raises(DeclinationError, match="2009-12-31 is before 2010.0.*as a number"):
        magnetic_declination(45.0, 7.0, 0.0, date(2009, 12, 31))
    # The grace year past 2030.0: used, and said to be an extrapolation.
    late = magnetic_declination(45.0, 7.0, 0.0, date(2030, 7, 1))
    assert late.model == "WMM2025" and late.extrapolated
    assert WMM_GRACE_YEARS == 1.0
    with pytest.raises(DeclinationError, match="past the newest World Magnetic Model.*update "
                                               "pygeomag"):
        magnetic_declination(45.0, 7.0, 0.0, date(2031, 1, 2))


def test_the_magnetic_pole_blackout_zone_is_refused():
    # NOAA's 2025.0 row at 89° N, 121° W: H = 1504 nT, D = -99.77°.
    with pytest.raises(DeclinationError, match="1504 nT.*blackout"):
        magnetic_declination(89.0, -121.0, 28_000.0, _instant(2025.0))
    # NOAA's 2026.0 row at 86° N, 46° W: H = 3000 nT, a caution zone: computed, flagged.
    near_pole = magnetic_declination(86.0, -46.0, 83_000.0, _instant(2026.0))
    assert near_pole.declination_deg == pytest.approx(-30.61, abs=TOLERANCE_DEG)
    assert near_pole.caution


@pytest.mark.parametrize("lat, lon, height, needle", [
    (95.0, 0.0, 0.0, "latitude 95 is outside"),
    (math.nan, 0.0, 0.0, "latitude must be a finite number"),
    (45.0, 0.0, 2e6, "height 2000000 m is outside"),
])
def test_bad_places_are_refused(lat, lon, height, needle):
    with pytest.raises(GeoError, match=needle):
        magnetic_declination(lat, lon, height, date(2026, 1, 1))


def test_longitudes_past_180_are_wrapped():
    a = magnetic_declination(40.0, -111.9, 0.0, date(2026, 1, 1)).declination_deg
    b = magnetic_declination(40.0, 248.1, 0.0, date(2026, 1, 1)).declination_deg
    assert a == pytest.approx(b, abs=1e-9)


def test_site_of_a_georef_origin():
    # UTM 30N origin at E 500000 (the central meridian, 3° W), N 5,900,000.
    georef = Georef("EPSG:32630", [500_000.0, 5_900_000.0, 120.0])
    lat, lon, height = site_latitude_longitude(georef)
    assert lon == pytest.approx(-3.0, abs=1e-9)
    assert 53.2 < lat < 53.3 and height == 120.0
