"""A magnetic heading in the sensor prior: WMM declination, then grid convergence.

The hand-computed case is a camera in Mato Grosso, Brazil (13° S, 59° W),
on 2 July 2027, in a model georeferenced to UTM zone 21S (EPSG:32721,
central meridian 57° W):

* declination D = −17.49° — NOAA's WMM2025 test value for 2027.5, 0 km,
  13° S, 59° W (WMM2025_TEST_VALUES.txt, see tests/test_declination.py);
* meridian convergence γ = atan(tan(λ − λ0) · sin φ) = atan(tan(−2°) ·
  sin(−13°)) = +0.4501° (the spherical formula; the ellipsoid's correction
  here is 0.0004 % of it);
* a phone heading of 100.00° from magnetic north is 100 − 17.49 = 82.51°
  from true north, and 82.51 − 0.45 = 82.06° from the grid north (+Y):
  grid = magnetic + D − γ.
"""

from __future__ import annotations

import json
import math
from datetime import date
from types import SimpleNamespace

import numpy as np
import pytest
from PIL import ExifTags, Image
from PIL.TiffImagePlugin import IFDRational

from napari_imgreg.errors import InputError
from napari_imgreg.geo import Georef
from napari_imgreg.io.exif import capture_date, record_from_exif
from napari_imgreg.io.photos import load_photo
from napari_imgreg.io.records import parse_sensor_record
from napari_imgreg.prior import prior_for_photo, prior_from_record

SITE = (-13.0, -59.0)
GEOREF = Georef("EPSG:32721", [283_077.0, 8_562_012.0, 0.0])
DECLINATION = -17.49            # NOAA test value (2027.5, 0 km, 13° S, 59° W)
CONVERGENCE = math.degrees(math.atan(math.tan(math.radians(-2.0))
                                     * math.sin(math.radians(-13.0))))  # +0.4501°
MAGNETIC = 100.0
TRUE = MAGNETIC + DECLINATION   # 82.51
GRID = TRUE - CONVERGENCE       # 82.06
TOLERANCE = 0.05


def _dms(deg: float):
    deg = abs(deg)
    d, m = int(deg), int((deg - int(deg)) * 60)
    s = (deg - d - m / 60) * 3600
    return (IFDRational(d, 1), IFDRational(m, 1), IFDRational(int(round(s * 10000)), 10000))


def _photo(path, *, direction=None, direction_ref="M", taken="2027:07:02 09:30:00",
           gps=True):
    """A small JPEG with a 26 mm-equivalent lens, GPS at SITE and the given tags."""
    im = Image.fromarray(np.full((120, 160, 3), 90, np.uint8))
    exif = Image.Exif()
    sub = exif.get_ifd(ExifTags.IFD.Exif)
    sub[ExifTags.Base.FocalLengthIn35mmFilm] = 26
    if taken is not None:
        sub[ExifTags.Base.DateTimeOriginal] = taken
    if gps:
        tags = exif.get_ifd(ExifTags.IFD.GPSInfo)
        tags[ExifTags.GPS.GPSLatitudeRef] = "S"
        tags[ExifTags.GPS.GPSLatitude] = _dms(SITE[0])
        tags[ExifTags.GPS.GPSLongitudeRef] = "W"
        tags[ExifTags.GPS.GPSLongitude] = _dms(SITE[1])
        tags[ExifTags.GPS.GPSAltitude] = IFDRational(0, 1)
        if direction is not None:
            tags[ExifTags.GPS.GPSImgDirectionRef] = direction_ref
            tags[ExifTags.GPS.GPSImgDirection] = IFDRational(int(round(direction * 100)), 100)
    im.save(path, exif=exif)
    return load_photo(path)


def _scene(georef=GEOREF):
    return SimpleNamespace(georef=georef, dem=None, terrain_height=lambda x, y: 0.0)


def _trend(prior) -> float:
    return float(prior.pose.attitude[0])


def _notes(prior) -> str:
    return " | ".join(prior.assumptions)


# ------------------------------------------------------------ hand-computed case
def test_hand_computed_case_from_a_sensor_record(tmp_path):
    photo = _photo(tmp_path / "IMG_0001.jpg", taken=None)
    (tmp_path / "IMG_0001.json").write_text(json.dumps({
        "position": {"lat": SITE[0], "lon": SITE[1], "alt": 0.0},
        "orientation": {"trend_deg": MAGNETIC, "plunge_deg": 5.0, "roll_deg": 0.0,
                        "heading_reference": "magnetic"},
        "time": "2027-07-02T12:00:00+00:00",
    }))
    prior = prior_for_photo(photo, scene=_scene())
    assert _trend(prior) == pytest.approx(GRID, abs=TOLERANCE)
    assert abs(GRID - 82.06) < 0.005  # the docstring's arithmetic
    notes = _notes(prior)
    assert "magnetic heading: declination -17.5° (WMM2025, 2027-07-02) applied" in notes
    assert "meridian convergence +0.45° at the camera" in notes
    # Declination first, then convergence: the notes say it in that order.
    assert notes.index("declination") < notes.index("meridian convergence")


def test_hand_computed_case_from_exif_magnetic_heading(tmp_path):
    # No record: EXIF GPS, GPSImgDirectionRef M and a DateTimeOriginal without
    # a time zone (a day is all a declination needs).
    photo = _photo(tmp_path / "IMG_0002.jpg", direction=MAGNETIC)
    prior = prior_for_photo(photo, scene=_scene())
    assert _trend(prior) == pytest.approx(GRID, abs=TOLERANCE)
    assert "magnetic heading: declination -17.5° (WMM2025, 2027-07-02) applied" in _notes(prior)


def test_a_true_north_exif_heading_gets_the_convergence_only(tmp_path):
    photo = _photo(tmp_path / "IMG_0003.jpg", direction=MAGNETIC, direction_ref="T")
    prior = prior_for_photo(photo, scene=_scene())
    assert _trend(prior) == pytest.approx(MAGNETIC - CONVERGENCE, abs=0.01)
    assert "declination" not in _notes(prior)


def test_magnetic_heading_without_a_date_keeps_todays_note(tmp_path):
    photo = _photo(tmp_path / "IMG_0004.jpg", direction=MAGNETIC, taken=None)
    prior = prior_for_photo(photo, scene=_scene())
    # Used as if from true north (then turned to grid north, as before).
    assert _trend(prior) == pytest.approx(MAGNETIC - CONVERGENCE, abs=0.01)
    assert "magnetic heading: declination not applied (no capture date" in _notes(prior)


def test_magnetic_heading_on_a_date_no_model_covers(tmp_path):
    photo = _photo(tmp_path / "IMG_0005.jpg", direction=MAGNETIC, taken="2008:05:01 10:00:00")
    notes = _notes(prior_for_photo(photo, scene=_scene()))
    assert "declination not applied (2008-05-01 is before 2010.0" in notes


# ------------------------------------------------------------- record field
def _record(tmp_path, orientation, position=None, **extra):
    path = tmp_path / "PHOTO.json"
    data = {"camera": {"width": 160, "height": 120, "fx": 150.0},
            "position": position or {"x": 0.0, "y": 0.0, "z": 2.0},
            "orientation": orientation, **extra}
    path.write_text(json.dumps(data))
    return parse_sensor_record(data, path)


def test_a_record_without_heading_reference_is_from_grid_north_as_before(tmp_path):
    record = _record(tmp_path, {"trend_deg": MAGNETIC})
    prior = prior_from_record(record, georef=GEOREF)
    assert _trend(prior) == pytest.approx(MAGNETIC, abs=1e-9)
    assert "declination" not in _notes(prior) and "convergence" not in _notes(prior)


def test_a_record_from_true_north_gets_the_convergence(tmp_path):
    record = _record(tmp_path, {"trend_deg": MAGNETIC, "heading_reference": "true"})
    prior = prior_from_record(record, georef=GEOREF)
    assert _trend(prior) == pytest.approx(MAGNETIC - CONVERGENCE, abs=0.01)


def test_a_magnetic_record_in_local_coordinates_is_placed_by_the_georef(tmp_path):
    record = _record(tmp_path, {"trend_deg": MAGNETIC, "heading_reference": "magnetic"},
                     time="2027-07-02T12:00:00-04:00")
    prior = prior_from_record(record, georef=GEOREF)
    assert _trend(prior) == pytest.approx(GRID, abs=TOLERANCE)
    # Without a georeference the place is unknown: today's note.
    prior = prior_from_record(record, georef=None)
    assert _trend(prior) == pytest.approx(MAGNETIC, abs=1e-9)
    assert "declination not applied (the camera's latitude and longitude are unknown" \
        in _notes(prior)


def test_a_bad_heading_reference_is_refused_naming_the_file(tmp_path):
    record = _record(tmp_path, {"trend_deg": MAGNETIC, "heading_reference": "compass"})
    with pytest.raises(InputError, match=r"PHOTO.json: field 'orientation.heading_reference' "
                                         r"must be one of 'grid', 'true', 'magnetic', got "
                                         r"'compass'"):
        prior_from_record(record, georef=GEOREF)


def test_the_record_given_is_not_changed(tmp_path):
    record = _record(tmp_path, {"trend_deg": MAGNETIC, "heading_reference": "magnetic"},
                     time="2027-07-02T12:00:00+00:00")
    prior_from_record(record, georef=GEOREF)
    assert record.orientation == {"trend_deg": MAGNETIC, "heading_reference": "magnetic"}


# ------------------------------------------------------------- EXIF readers
def test_exif_marks_what_the_heading_is_from(tmp_path):
    magnetic, notes = record_from_exif(_photo(tmp_path / "m.jpg", direction=10.0))
    assert magnetic.orientation["heading_reference"] == "magnetic"
    assert "trend from EXIF GPSImgDirection (magnetic north)" in notes
    true, _ = record_from_exif(_photo(tmp_path / "t.jpg", direction=10.0, direction_ref="T"))
    assert true.orientation["heading_reference"] == "true"


def test_capture_date_needs_no_time_zone():
    assert capture_date({"DateTimeOriginal": "2027:07:02 23:59:00"}) == date(2027, 7, 2)
    assert capture_date({"GPSInfo": {"GPSDateStamp": "2027:07:03"}}) == date(2027, 7, 3)
    assert capture_date({"DateTimeOriginal": "0000:00:00 00:00:00"}) is None
    assert capture_date({}) is None
