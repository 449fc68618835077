"""Priors of phone photos checked against known answers: the frame of a logged
roll under an EXIF orientation, true-north headings in a grid CRS, and the
altitude of a GPS fix over a DEM (prior.py)."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
from PIL import ExifTags, Image

from napari_imgreg.camera import Intrinsics, Pose
from napari_imgreg.geo import DEM, Georef
from napari_imgreg.io.photos import load_photo
from napari_imgreg.io.records import parse_sensor_record
from napari_imgreg.prior import prior_for_photo, prior_from_record

from test_prior_exif import GEOREF, MAM_TOR, dji_xmp, grid_azimuth, utm_local, write_photo


# ------------------------------------------- a logged roll under EXIF orientation
def _record_without_camera(roll, plunge=10.0):
    return parse_sensor_record({"position": {"x": 0.0, "y": 0.0, "z": 0.0},
                                "orientation": {"trend_deg": 30.0, "plunge_deg": plunge,
                                                "roll_deg": roll}}, "IMG_0001.json")


@pytest.mark.parametrize("orientation, size, sensor_roll, shown_roll", [
    (6, (120, 160), 95.0, 5.0),     # phone upright, sensor x axis pointing down
    (8, (120, 160), -85.0, 5.0),
    (3, (160, 120), 178.0, -2.0),   # phone upside down
])
def test_a_sensor_roll_without_camera_size_is_turned_with_the_pixels(orientation, size,
                                                                     sensor_roll, shown_roll):
    """No camera block: the phone chose the EXIF orientation so that the shown
    photo is within 45° of level, so a roll level only once turned is the sensor's."""
    prior = prior_from_record(_record_without_camera(sensor_roll), image_size=size,
                              exif_orientation=orientation)
    assert prior.pose.attitude == pytest.approx((30.0, 10.0, shown_roll), abs=1e-6)
    assert any("is the sensor's" in note for note in prior.assumptions)


@pytest.mark.parametrize("orientation, size", [(6, (120, 160)), (3, (160, 120))])
def test_a_level_roll_without_camera_size_is_the_shown_photos(orientation, size):
    prior = prior_from_record(_record_without_camera(4.0), image_size=size,
                              exif_orientation=orientation)
    assert prior.pose.attitude == pytest.approx((30.0, 10.0, 4.0), abs=1e-6)


def test_a_steep_view_keeps_the_default_frame():
    """Looking nearly straight down, the phone's orientation says nothing of the roll."""
    prior = prior_from_record(_record_without_camera(95.0, plunge=75.0),
                              image_size=(120, 160), exif_orientation=6)
    assert prior.pose.attitude[2] == pytest.approx(95.0, abs=1e-6)


def test_portrait_phone_photo_with_a_sensor_record_and_exif_focal_projects_true(tmp_path):
    """End to end: a landscape sensor image stored with EXIF orientation 6, its
    focal length in EXIF, and a record of position and sensor attitude only.
    Points of the world land in the loaded (shown) photo where the prior puts them."""
    w, h, f35 = 320, 240, 28
    sensor = Intrinsics.from_35mm_equivalent(w, h, f35)
    pose = Pose.from_attitude(30.0, 10.0, 95.0, np.zeros(3))  # phone upright, tilted 5°
    pixels = np.array([[sensor.cx, sensor.cy], [sensor.cx + 90, sensor.cy - 60],
                       [sensor.cx - 100, sensor.cy + 70]])
    rays = np.column_stack([(pixels - [sensor.cx, sensor.cy]) / sensor.fx, np.ones(3)])
    world = pose.inverse_transform(rays * 40.0)
    stored = np.zeros((h, w, 3), np.uint8)
    for channel, (u, v) in enumerate(np.round(pose.project(sensor, world)).astype(int)):
        stored[v - 2:v + 3, u - 2:u + 3, channel] = 255
    exif = Image.Exif()
    exif[ExifTags.Base.Orientation] = 6
    exif.get_ifd(ExifTags.IFD.Exif)[ExifTags.Base.FocalLengthIn35mmFilm] = f35
    Image.fromarray(stored).save(tmp_path / "IMG_0001.png", exif=exif)
    (tmp_path / "IMG_0001.json").write_text(json.dumps(
        {"position": {"x": 0.0, "y": 0.0, "z": 0.0},
         "orientation": {"trend_deg": 30.0, "plunge_deg": 10.0, "roll_deg": 95.0}}))
    photo = load_photo(tmp_path / "IMG_0001.png")
    prior = prior_for_photo(photo)
    assert photo.size == (h, w)
    assert prior.pose.attitude == pytest.approx((30.0, 10.0, 5.0), abs=1e-6)
    seen = [np.argwhere(photo.image[..., c] > 128).mean(axis=0)[::-1] for c in range(3)]
    assert np.abs(prior.pose.project(prior.intrinsics, world) - seen).max() < 0.6


# ------------------------------------------------- true north to grid north
def test_exif_true_heading_becomes_a_grid_trend(tmp_path):
    """33.86° S, 70.51° W in UTM 19S (central meridian 69° W): a true heading of
    10° is 10° − 0.84° from grid north; the known answer from pyproj's geodesic."""
    lat, lon = -33.8568, -70.5125
    georef = Georef(crs="EPSG:32719", origin=np.array([350_000.0, 6_250_000.0, 2000.0]))
    scene = SimpleNamespace(georef=georef, dem=None, terrain_height=None)
    expected = grid_azimuth(lat, lon, 10.0, crs="EPSG:32719")
    assert expected == pytest.approx(10.0 - 0.84, abs=0.01)
    photo = write_photo(tmp_path / "IMG_0002.jpg", lat=lat, lon=lon, alt=2500.0,
                        direction=10.0, focal35=26)
    prior = prior_for_photo(photo, scene=scene)
    assert prior.pose.attitude[0] == pytest.approx(expected, abs=2e-3)
    assert any("meridian convergence +0.84°" in note for note in prior.assumptions)


def test_a_record_trend_is_already_from_grid_north(tmp_path):
    """Contract §2: a record's trend is from +Y; only metadata headings are turned."""
    photo = write_photo(tmp_path / "IMG_0003.jpg", lat=MAM_TOR[0], lon=MAM_TOR[1], alt=400.0,
                        direction=10.0, focal35=26)
    (tmp_path / "IMG_0003.json").write_text(json.dumps({"orientation": {"trend_deg": 10.0}}))
    prior = prior_for_photo(photo, scene=SimpleNamespace(georef=GEOREF, dem=None,
                                                         terrain_height=None))
    assert prior.pose.attitude[0] == pytest.approx(10.0)
    assert not any("convergence" in note for note in prior.assumptions)


# ------------------------------------------------------ GPS altitude over a DEM
def _dem_scene(height=350.0):
    """A flat DEM at ``height`` m around Mam Tor, 100 m cells, 4 km square."""
    e, n, _ = GEOREF.origin + utm_local(*MAM_TOR, 0.0)
    heights = np.full((41, 41), height)
    dem = DEM.from_array(heights, e - 2000.0, n + 2000.0, 100.0, 100.0, crs="EPSG:32630",
                         source="dem.tif")
    return SimpleNamespace(georef=GEOREF, dem=dem, terrain_height=None)


def test_a_phone_gps_altitude_of_zero_gives_way_to_the_dem(tmp_path):
    """A network fix writes GPSAltitude 0: 300 m underground at Mam Tor. The
    method takes the altitude from the DEM, and says what the GPS claimed."""
    photo = write_photo(tmp_path / "IMG_0004.jpg", lat=MAM_TOR[0], lon=MAM_TOR[1], alt=0.0,
                        direction=10.0, focal35=26)
    prior = prior_for_photo(photo, scene=_dem_scene(350.0))
    expected = utm_local(*MAM_TOR, 350.0 + 1.6)
    np.testing.assert_allclose(prior.pose.center, expected, atol=1e-3)
    assert any(n.startswith("EXIF GPS altitude 0 m not used (-351.6 m from the DEM's")
               for n in prior.assumptions), prior.assumptions
    assert "altitude from DEM + 1.6 m" in prior.assumptions


def test_a_drone_keeps_its_gps_altitude_over_a_dem(tmp_path):
    photo = write_photo(tmp_path / "DJI_0001.jpg", lat=MAM_TOR[0], lon=MAM_TOR[1], alt=452.3,
                        focal35=24, xmp=dji_xmp(123.4, -30.5, 1.2))
    prior = prior_for_photo(photo, scene=_dem_scene(350.0))
    assert prior.pose.center[2] == pytest.approx(452.3 - GEOREF.origin[2])


def test_a_phone_outside_the_dem_keeps_its_gps_altitude_and_says_so(tmp_path):
    photo = write_photo(tmp_path / "IMG_0005.jpg", lat=MAM_TOR[0] + 0.1, lon=MAM_TOR[1],
                        alt=410.0, direction=10.0, focal35=26)
    prior = prior_for_photo(photo, scene=_dem_scene(350.0))
    assert prior.pose.center[2] == pytest.approx(410.0 - GEOREF.origin[2])
    assert any("outside the DEM" in note for note in prior.assumptions)


def test_a_sidecar_altitude_is_kept_over_the_dem(tmp_path):
    """An altitude the record gives is the user's: only the EXIF's gives way."""
    photo = write_photo(tmp_path / "IMG_0006.jpg", direction=10.0, focal35=26)
    (tmp_path / "IMG_0006.json").write_text(json.dumps(
        {"position": {"lat": MAM_TOR[0], "lon": MAM_TOR[1], "alt": 420.0}}))
    prior = prior_for_photo(photo, scene=_dem_scene(350.0))
    assert prior.pose.center[2] == pytest.approx(420.0 - GEOREF.origin[2])


# ------------------------------------------------------------ EXIF variations
def _exif_photo(path, gps=None, sub=None):
    """A JPEG with raw GPS and Exif sub-IFD tags by name, read back."""
    exif = Image.Exif()
    for name, value in (sub or {}).items():
        exif.get_ifd(ExifTags.IFD.Exif)[getattr(ExifTags.Base, name)] = value
    for name, value in (gps or {}).items():
        exif.get_ifd(ExifTags.IFD.GPSInfo)[getattr(ExifTags.GPS, name)] = value
    Image.fromarray(np.full((120, 160, 3), 90, np.uint8)).save(path, exif=exif)
    return load_photo(path)


def _rational(value):
    from PIL.TiffImagePlugin import IFDRational

    return IFDRational(*value) if isinstance(value, tuple) else IFDRational(value, 1)


def test_seconds_of_sixty_carry_into_the_minute(tmp_path):
    from napari_imgreg.io.exif import record_from_exif

    photo = _exif_photo(tmp_path / "a.jpg", gps={
        "GPSLatitudeRef": "S", "GPSLatitude": tuple(map(_rational, (33, 59, 60))),
        "GPSLongitudeRef": "W", "GPSLongitude": tuple(map(_rational, (70, 30, (4500, 100))))})
    record, _ = record_from_exif(photo)
    assert record.position == pytest.approx({"lat": -34.0, "lon": -(70.5 + 45 / 3600)})


def test_a_missing_hemisphere_reference_is_said(tmp_path):
    from napari_imgreg.io.exif import record_from_exif

    photo = _exif_photo(tmp_path / "a.jpg", gps={
        "GPSLatitudeRef": "N", "GPSLatitude": tuple(map(_rational, (53, 20, 0))),
        "GPSLongitude": tuple(map(_rational, (1, 48, 0)))})
    record, notes = record_from_exif(photo)
    assert record.position == pytest.approx({"lat": 53 + 1 / 3, "lon": 1.8})
    assert "position from EXIF GPS: GPSLongitudeRef missing, taken as E" in notes


def test_an_unknown_compass_reading_is_refused_with_the_fix(tmp_path):
    from napari_imgreg.errors import InputError
    from napari_imgreg.io.exif import record_from_exif

    photo = _exif_photo(tmp_path / "IMG_0008.jpg", gps={
        "GPSImgDirectionRef": "M", "GPSImgDirection": _rational((0, 0))})
    with pytest.raises(InputError) as err:
        record_from_exif(photo)
    message = str(err.value)
    assert message.startswith(str(tmp_path / "IMG_0008.jpg")) and "\n" not in message
    assert "got 0/0 (no compass reading): give 'orientation.trend_deg'" in message


def test_no_record_names_what_the_exif_lacks(tmp_path):
    from napari_imgreg.errors import InputError

    photo = _exif_photo(tmp_path / "IMG_0009.jpg", gps={
        "GPSLatitudeRef": "N", "GPSLatitude": tuple(map(_rational, (53, 20, 0))),
        "GPSLongitudeRef": "W", "GPSLongitude": tuple(map(_rational, (1, 48, 0)))})
    with pytest.raises(InputError) as err:
        prior_for_photo(photo, scene=SimpleNamespace(georef=GEOREF, dem=None,
                                                     terrain_height=None))
    assert str(err.value).endswith("no sensor record (.json beside the photo) and no compass "
                                   "heading in its EXIF/XMP")


def test_digital_zoom_is_said(tmp_path):
    from napari_imgreg.io.exif import record_from_exif

    photo = _exif_photo(tmp_path / "a.jpg", sub={"FocalLengthIn35mmFilm": 26,
                                                  "DigitalZoomRatio": _rational((20, 10))})
    record, notes = record_from_exif(photo)
    assert record.camera["fx"] == pytest.approx(26 * math.hypot(160, 120) / math.hypot(36, 24))
    assert any(n.startswith("camera from EXIF may be 2× too wide") for n in notes)


def test_a_camera_outside_the_dem_without_altitude_is_one_line_with_the_fix():
    from napari_imgreg.errors import InputError

    record = parse_sensor_record({"position": {"x": 9000.0, "y": 0.0},
                                  "orientation": {"trend_deg": 10.0}}, "/data/IMG_0001.json")
    with pytest.raises(InputError) as err:
        prior_from_record(record, georef=GEOREF, dem=_dem_scene().dem, image_size=(160, 120))
    message = str(err.value)
    assert "\n" not in message and message.startswith("/data/IMG_0001.json: ")
    assert "is outside the DEM" in message and "give the camera's 'z'" in message


def test_a_camera_in_the_wrong_hemisphere_is_said(tmp_path):
    """A southern photo with the northern zone's CRS: 10 000 km of false northing off."""
    photo = write_photo(tmp_path / "IMG_0010.jpg", lat=-MAM_TOR[0], lon=MAM_TOR[1], alt=300.0,
                        direction=10.0, focal35=26)
    bounds = np.array([[-100.0, -100.0, 0.0], [100.0, 100.0, 50.0]])
    scene = SimpleNamespace(georef=GEOREF, dem=None, terrain_height=None, bounds=bounds)
    prior = prior_for_photo(photo, scene=scene)
    assert any(n.startswith("camera is 11,8") and "km from the model" in n
               for n in prior.assumptions), prior.assumptions
    near = write_photo(tmp_path / "IMG_0011.jpg", lat=MAM_TOR[0], lon=MAM_TOR[1], alt=300.0,
                       direction=10.0, focal35=26)
    assert not any("from the model" in n
                   for n in prior_for_photo(near, scene=scene).assumptions)


# ------------------------------------------------------- units of the camera block
@pytest.mark.parametrize("camera, view", [
    ({"focal_length_mm": 4250.0, "sensor_width_mm": 5.6, "sensor_height_mm": 4.2}, "so little"),
    ({"focal_length_mm": 4.25, "sensor_width_mm": 0.0056, "sensor_height_mm": 0.0042},
     "so little"),
    ({"fx": 1.2e6, "fy": 1.2e6, "cx": 800.0, "cy": 600.0}, "so little"),  # fx in µm?
])
def test_a_camera_block_in_the_wrong_units_is_refused_naming_the_file(camera, view):
    """A 4.25 mm phone lens on a 5.6 mm sensor sees 67°; written as 4250 mm, or the
    sensor in metres, it would see 0.08° and the prior was made with it unsaid."""
    record = parse_sensor_record({"camera": {"width": 1600, "height": 1200, **camera},
                                  "position": {"x": 0.0, "y": 0.0, "z": 0.0},
                                  "orientation": {"trend_deg": 0.0}}, "IMG_0001.json")
    with pytest.raises(Exception, match=rf"IMG_0001.json: field 'camera'.*{view}.*units"):
        prior_from_record(record, image_size=(1600, 1200))
    good = parse_sensor_record({"camera": {"width": 1600, "height": 1200, "focal_length_mm": 4.25,
                                           "sensor_width_mm": 5.6, "sensor_height_mm": 4.2},
                                "position": {"x": 0.0, "y": 0.0, "z": 0.0},
                                "orientation": {"trend_deg": 0.0}}, "IMG_0001.json")
    hfov = 2 * math.degrees(math.atan2(800.0, prior_from_record(good, image_size=(1600, 1200))
                                       .intrinsics.fx))
    assert hfov == pytest.approx(2 * math.degrees(math.atan(2.8 / 4.25)), abs=1e-6)


def test_map_coordinates_given_as_the_model_frame_are_refused(tmp_path):
    """A record whose x, y are the georeference's easting and northing (not
    minus its origin) is refused in one line that gives the local values;
    a camera far off for another reason keeps the note."""
    import json

    from napari_imgreg.errors import InputError
    from napari_imgreg.prior import load_camera_and_pose

    bounds = np.array([[-100.0, -100.0, 0.0], [100.0, 100.0, 50.0]])
    scene = SimpleNamespace(georef=GEOREF, dem=None, terrain_height=None, bounds=bounds)
    photo = write_photo(tmp_path / "IMG_0012.jpg", lat=MAM_TOR[0], lon=MAM_TOR[1], alt=300.0,
                        direction=10.0, focal35=26)
    east, north = GEOREF.origin[0] + 20.0, GEOREF.origin[1] - 80.0
    record = tmp_path / "IMG_0012.json"
    record.write_text(json.dumps({"position": {"x": east, "y": north, "z": 2.0},
                                  "orientation": {"trend_deg": 10.0, "plunge_deg": 0.0}}))
    for load in (lambda: prior_for_photo(photo, scene=scene, record_path=record),
                 lambda: load_camera_and_pose(record, GEOREF, model_bounds=bounds)):
        with pytest.raises(InputError) as err:
            load()
        message = str(err.value)
        assert "\n" not in message and message.startswith(f"{record}: position x,y (")
        assert f"are map coordinates of {GEOREF.crs}" in message
        assert "(here (20.0, -80.0)); or give lat,lon" in message
    # Latitude and longitude swapped.
    lat, lon, _ = GEOREF.local_to_geodetic([20.0, -80.0, 0.0])
    record.write_text(json.dumps({"position": {"lat": lon, "lon": lat, "alt": 300.0},
                                  "orientation": {"trend_deg": 10.0, "plunge_deg": 0.0}}))
    for load in (lambda: prior_for_photo(photo, scene=scene, record_path=record),
                 lambda: load_camera_and_pose(record, GEOREF, model_bounds=bounds)):
        with pytest.raises(InputError, match=rf"position lat {lon:g}, lon {lat:g} look swapped: "
                                             r"read that way the camera is [\d,]+ km from the "
                                             rf"model, and at lat {lat:g}, lon {lon:g} it is at"):
            load()
    # 30 km off in the model frame: not map coordinates, a note as before.
    record.write_text(json.dumps({"position": {"x": 30000.0, "y": 0.0, "z": 2.0},
                                  "orientation": {"trend_deg": 10.0, "plunge_deg": 0.0}}))
    prior = prior_for_photo(photo, scene=scene, record_path=record)
    assert any(n.startswith("camera is 30 km from the model") for n in prior.assumptions)
