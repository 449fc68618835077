"""Priors from photo metadata: EXIF GPS/focal length and DJI XMP gimbal angles (io/records.py).

Photos are written with Pillow carrying real EXIF IFDs (Exif sub-IFD, GPS IFD)
and an XMP packet, then read back through ``load_photo``.
"""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
from PIL import ExifTags, Image
from PIL.TiffImagePlugin import IFDRational
from pyproj import Transformer

from napari_imgreg.camera import Intrinsics
from napari_imgreg.errors import InputError
from napari_imgreg.geo import Georef
from napari_imgreg.io.photos import load_photo
from napari_imgreg.io.exif import record_from_exif
from napari_imgreg.prior import prior_for_photo

W, H = 160, 120  # small photos: the metadata is what matters
MAM_TOR = (53.3490, -1.8100)  # inside UTM zone 30N
ORIGIN = np.array([580_000.0, 5_911_000.0, 300.0])
GEOREF = Georef(crs="EPSG:32630", origin=ORIGIN)


def dms(deg: float):
    """Unsigned degrees → EXIF (degrees, minutes, seconds) rationals."""
    deg = abs(deg)
    d = int(deg)
    m = int((deg - d) * 60)
    s = (deg - d - m / 60) * 3600
    return (IFDRational(d, 1), IFDRational(m, 1), IFDRational(int(round(s * 10000)), 10000))


def dji_xmp(yaw, pitch, roll) -> bytes:
    return (
        '<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF '
        'xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#"><rdf:Description '
        'xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/" '
        f'drone-dji:GimbalRollDegree="{roll}" drone-dji:GimbalYawDegree="{yaw}" '
        f'drone-dji:GimbalPitchDegree="{pitch}" drone-dji:FlightYawDegree="-1.0"/>'
        "</rdf:RDF></x:xmpmeta>"
    ).encode()


def write_photo(path, *, lat=None, lon=None, alt=None, below_sea=False, direction=None,
                direction_ref="T", focal=None, focal35=None, model=None, make=None,
                focal_plane_xres=None, focal_plane_unit=None, xmp=None):
    """A JPEG with the given EXIF (and XMP) tags; signed lat/lon set the N/S, E/W refs."""
    im = Image.fromarray(np.full((H, W, 3), 90, np.uint8))
    exif = Image.Exif()
    if make is not None:
        exif[ExifTags.Base.Make] = make
    if model is not None:
        exif[ExifTags.Base.Model] = model
    sub = exif.get_ifd(ExifTags.IFD.Exif)
    if focal is not None:
        sub[ExifTags.Base.FocalLength] = IFDRational(int(round(focal * 100)), 100)
    if focal35 is not None:
        sub[ExifTags.Base.FocalLengthIn35mmFilm] = int(focal35)
    if focal_plane_xres is not None:
        sub[ExifTags.Base.FocalPlaneXResolution] = IFDRational(int(focal_plane_xres), 1)
        sub[ExifTags.Base.FocalPlaneResolutionUnit] = int(focal_plane_unit)
    has_gps = lat is not None or alt is not None or direction is not None
    gps = exif.get_ifd(ExifTags.IFD.GPSInfo) if has_gps else {}
    if lat is not None:
        gps[ExifTags.GPS.GPSLatitudeRef] = "N" if lat >= 0 else "S"
        gps[ExifTags.GPS.GPSLatitude] = dms(lat)
        gps[ExifTags.GPS.GPSLongitudeRef] = "E" if lon >= 0 else "W"
        gps[ExifTags.GPS.GPSLongitude] = dms(lon)
    if alt is not None:
        gps[ExifTags.GPS.GPSAltitudeRef] = b"\x01" if below_sea else b"\x00"
        gps[ExifTags.GPS.GPSAltitude] = IFDRational(int(round(alt * 100)), 100)
    if direction is not None:
        gps[ExifTags.GPS.GPSImgDirectionRef] = direction_ref
        gps[ExifTags.GPS.GPSImgDirection] = IFDRational(int(round(direction * 100)), 100)
    kwargs = {"exif": exif}
    if xmp is not None:
        kwargs["xmp"] = xmp
    im.save(path, **kwargs)
    return load_photo(path)


def drone_photo(tmp_path, name="DJI_0001.jpg", **changes):
    """A DJI Phantom 4 Pro photo over Mam Tor: GPS, focal lengths, gimbal angles."""
    tags = dict(lat=MAM_TOR[0], lon=MAM_TOR[1], alt=452.3, focal=8.8, focal35=24,
                make="DJI", model="FC6310", xmp=dji_xmp(123.4, -30.5, 1.2))
    tags.update(changes)
    return write_photo(tmp_path / name, **tags)


def scene_with_georef():
    """What prior_for_photo reads from a scene: georeference, no DEM, no terrain."""
    return SimpleNamespace(georef=GEOREF, dem=None, terrain_height=None)


def utm_local(lat, lon, alt):
    e, n = Transformer.from_crs("EPSG:4326", "EPSG:32630", always_xy=True).transform(lon, lat)
    return np.array([e, n, alt]) - ORIGIN


def grid_azimuth(lat, lon, true_azimuth, crs="EPSG:32630"):
    """The grid azimuth in ``crs`` of a true azimuth at (lat, lon): a point 100 m
    along it on the ellipsoid, projected (independent of the code under test)."""
    from pyproj import Geod

    lon2, lat2, _ = Geod(ellps="WGS84").fwd(lon, lat, true_azimuth, 100.0)
    to_grid = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    (e1, e2), (n1, n2) = to_grid.transform([lon, lon2], [lat, lat2])
    return math.degrees(math.atan2(e2 - e1, n2 - n1)) % 360.0


# --------------------------------------------------------- writing works
def test_pillow_writes_what_we_read_back(tmp_path):
    photo = drone_photo(tmp_path)
    assert photo.size == (W, H)
    assert photo.exif["Model"] == "FC6310" and photo.exif["Make"] == "DJI"
    assert float(photo.exif["FocalLength"]) == pytest.approx(8.8)
    assert "drone-dji:GimbalYawDegree" in photo.exif["XMP"]
    assert photo.exif["GPSInfo"]["GPSLatitudeRef"] == "N"


# ------------------------------------------------------ record_from_exif
@pytest.mark.parametrize("lat, lon", [(-33.8568, -70.5125), (53.349, -1.81), (-12.5, 130.75),
                                      (47.25, 11.4)])
def test_gps_signs_follow_the_references(tmp_path, lat, lon):
    photo = write_photo(tmp_path / "a.jpg", lat=lat, lon=lon, alt=120.5)
    record, notes = record_from_exif(photo)
    assert record.position["lat"] == pytest.approx(lat, abs=1e-7)
    assert record.position["lon"] == pytest.approx(lon, abs=1e-7)
    assert record.position["alt"] == pytest.approx(120.5)
    assert "position from EXIF GPS" in notes


def test_altitude_below_sea_level_is_negative(tmp_path):
    photo = write_photo(tmp_path / "a.jpg", lat=31.5, lon=35.5, alt=415.0, below_sea=True)
    record, _ = record_from_exif(photo)
    assert record.position["alt"] == pytest.approx(-415.0)


def test_gps_without_altitude_has_no_alt(tmp_path):
    photo = write_photo(tmp_path / "a.jpg", lat=10.0, lon=20.0)
    record, _ = record_from_exif(photo)
    assert set(record.position) == {"lat", "lon"}


def test_dji_gimbal_angles_give_trend_plunge_roll(tmp_path):
    record, notes = record_from_exif(drone_photo(tmp_path))
    # DJI pitch is positive nose-up: plunge (positive down) = −pitch.
    assert record.orientation == {"trend_deg": pytest.approx(123.4),
                                  "plunge_deg": pytest.approx(30.5),
                                  "roll_deg": pytest.approx(1.2), "heading_reference": "true"}
    assert "attitude from DJI gimbal angles (XMP)" in notes


@pytest.mark.parametrize("yaw, pitch, roll, trend, plunge", [
    (-56.7, -90.0, 0.0, 303.3, 90.0),  # nadir, yaw west of north
    (180.0, 0.0, -2.5, 180.0, 0.0),
    (359.9, 12.0, 0.0, 359.9, -12.0),  # looking up
])
def test_dji_angle_conventions(tmp_path, yaw, pitch, roll, trend, plunge):
    record, _ = record_from_exif(drone_photo(tmp_path, xmp=dji_xmp(yaw, pitch, roll)))
    o = record.orientation
    assert o["trend_deg"] == pytest.approx(trend)
    assert o["plunge_deg"] == pytest.approx(plunge)
    assert o["roll_deg"] == pytest.approx(roll)


def test_gimbal_wins_over_compass_direction(tmp_path):
    photo = drone_photo(tmp_path, direction=10.0)
    record, _ = record_from_exif(photo)
    assert record.orientation["trend_deg"] == pytest.approx(123.4)


def test_intrinsics_from_the_35mm_equivalent(tmp_path):
    record, notes = record_from_exif(drone_photo(tmp_path))
    # FocalLengthIn35mmFilm applies to the diagonal: f = 24 · hypot(W, H) / hypot(36, 24).
    f = 24 * math.hypot(W, H) / math.hypot(36, 24)
    cam = record.camera
    assert (cam["width"], cam["height"]) == (W, H)
    assert cam["fx"] == pytest.approx(f) and cam["fy"] == pytest.approx(f)
    assert (cam["cx"], cam["cy"]) == ((W - 1) / 2, (H - 1) / 2)
    # A nominal value: the registration starts from it and refines it.
    assert cam["estimated"] == ["fx", "fy"]
    assert "camera from EXIF focal length (nominal: refined by the registration)" in notes


def test_intrinsics_from_focal_length_and_known_model(tmp_path):
    photo = drone_photo(tmp_path, focal35=None)  # FC6310: 13.2 mm sensor width
    record, _ = record_from_exif(photo)
    assert record.camera["fx"] == pytest.approx(8.8 * W / 13.2)


def test_intrinsics_from_focal_plane_resolution(tmp_path):
    # 4 mm lens, 1000 pixels per cm on the focal plane → 400 px.
    photo = write_photo(tmp_path / "a.jpg", focal=4.0, focal_plane_xres=1000,
                        focal_plane_unit=3, focal35=28, model="Unknown")
    record, _ = record_from_exif(photo)
    assert record.camera["fx"] == pytest.approx(400.0)


def test_no_focal_length_leaves_no_camera(tmp_path):
    photo = write_photo(tmp_path / "a.jpg", lat=1.0, lon=2.0, focal=5.0, model="Mystery")
    record, notes = record_from_exif(photo)
    assert record.camera is None
    # Said: without it the prior's "no focal length" reads as a missing tag.
    assert notes == ["camera not from EXIF FocalLength 5 mm: no sensor size for it (no "
                     "FocalLengthIn35mmFilm, no FocalPlaneXResolution, camera model "
                     "'Mystery' not known)",
                     "position from EXIF GPS"]


def test_compass_direction_alone_gives_the_trend(tmp_path):
    photo = write_photo(tmp_path / "a.jpg", lat=10.0, lon=20.0, direction=372.5)
    record, notes = record_from_exif(photo)
    assert record.orientation == {"trend_deg": pytest.approx(12.5), "heading_reference": "true"}
    assert "trend from EXIF GPSImgDirection" in notes


# -------------------------------------------------------- prior_for_photo
def test_prior_from_exif_and_xmp_with_a_georef(tmp_path):
    photo = drone_photo(tmp_path)
    prior = prior_for_photo(photo, scene=scene_with_georef())
    np.testing.assert_allclose(prior.pose.center, utm_local(*MAM_TOR, 452.3), atol=1e-3)
    trend, plunge, roll = prior.pose.attitude
    # The gimbal yaw is from true north; the trend from the model's +Y, grid north
    # (0.96° apart at Mam Tor, 1.2° east of UTM 30's central meridian).
    grid = grid_azimuth(*MAM_TOR, 123.4)
    assert grid == pytest.approx(123.4 - 0.955, abs=0.01)
    assert (trend, plunge, roll) == pytest.approx((grid, 30.5, 1.2), abs=2e-3)
    f = 24 * math.hypot(W, H) / math.hypot(36, 24)
    assert prior.intrinsics == Intrinsics(W, H, f, f, (W - 1) / 2, (H - 1) / 2,
                                          estimated=("fx", "fy"))  # nominal: refined
    assert prior.assumptions == [
        "camera from EXIF focal length (nominal: refined by the registration)",
        "position from EXIF GPS",
        "attitude from DJI gimbal angles (XMP)",
        "trend 123.40° from true north is 122.45° from the grid north of EPSG:32630 "
        "(meridian convergence +0.95° at the camera)",
    ]


def test_prior_in_the_southern_hemisphere(tmp_path):
    # Signs reach the projection: 33.86° S, 70.51° W in UTM 19S.
    lat, lon = -33.8568, -70.5125
    photo = drone_photo(tmp_path, lat=lat, lon=lon, alt=2500.0)
    origin = np.array([350_000.0, 6_250_000.0, 2000.0])
    scene = SimpleNamespace(georef=Georef(crs="EPSG:32719", origin=origin), dem=None,
                            terrain_height=None)
    prior = prior_for_photo(photo, scene=scene)
    e, n = Transformer.from_crs("EPSG:4326", "EPSG:32719", always_xy=True).transform(lon, lat)
    np.testing.assert_allclose(prior.pose.center, np.array([e, n, 2500.0]) - origin, atol=1e-3)


def test_gps_without_a_georef_is_an_input_error(tmp_path):
    photo = drone_photo(tmp_path)
    with pytest.raises(InputError, match="georef"):
        prior_for_photo(photo)


def test_sidecar_blocks_win_over_exif(tmp_path):
    photo = drone_photo(tmp_path)
    sidecar = {
        "camera": {"width": W, "height": H, "fx": 150.0, "fy": 151.0, "cx": 80.0, "cy": 60.0},
        "position": {"x": 12.0, "y": -40.0, "z": 31.0},
        "orientation": {"trend_deg": 10.0, "plunge_deg": 5.0, "roll_deg": -2.0},
    }
    (tmp_path / "DJI_0001.json").write_text(json.dumps(sidecar))
    assert photo.sidecar == tmp_path / "DJI_0001.json"
    prior = prior_for_photo(photo, scene=scene_with_georef())
    np.testing.assert_allclose(prior.pose.center, [12.0, -40.0, 31.0], atol=1e-9)
    assert prior.pose.attitude == pytest.approx((10.0, 5.0, -2.0))
    assert (prior.intrinsics.fx, prior.intrinsics.fy) == (150.0, 151.0)
    assert prior.assumptions == []  # nothing taken from EXIF, nothing assumed


def test_missing_sidecar_blocks_come_from_exif_and_say_so(tmp_path):
    photo = drone_photo(tmp_path)
    (tmp_path / "DJI_0001.json").write_text(json.dumps(
        {"orientation": {"trend_deg": 200.0, "plunge_deg": 10.0, "roll_deg": 0.5},
         "sigma": {"position_m": 3.0}}))
    prior = prior_for_photo(photo, scene=scene_with_georef())
    # Orientation from the sidecar, position and camera from EXIF.
    assert prior.pose.attitude == pytest.approx((200.0, 10.0, 0.5))
    np.testing.assert_allclose(prior.pose.center, utm_local(*MAM_TOR, 452.3), atol=1e-3)
    f = 24 * math.hypot(W, H) / math.hypot(36, 24)
    assert prior.intrinsics.fx == pytest.approx(f)
    assert prior.sigma.position_m == 3.0
    assert "camera from EXIF focal length (nominal: refined by the registration)" in \
        prior.assumptions
    assert "position from EXIF GPS" in prior.assumptions
    assert not any("attitude" in a or "trend" in a for a in prior.assumptions)


def test_sidecar_camera_without_focal_length_takes_it_from_exif(tmp_path):
    photo = drone_photo(tmp_path)
    (tmp_path / "DJI_0001.json").write_text(json.dumps(
        {"camera": {"width": W, "height": H},
         "position": {"x": 0.0, "y": 0.0, "z": 10.0},
         "orientation": {"trend_deg": 0.0, "plunge_deg": 0.0, "roll_deg": 0.0}}))
    prior = prior_for_photo(photo, scene=scene_with_georef())
    f = 24 * math.hypot(W, H) / math.hypot(36, 24)
    assert prior.intrinsics.fx == pytest.approx(f)
    assert "focal length from EXIF" in prior.assumptions


def test_explicit_record_path_is_used(tmp_path):
    photo = drone_photo(tmp_path)
    other = tmp_path / "elsewhere.json"
    other.write_text(json.dumps({"position": {"x": 1.0, "y": 2.0, "z": 3.0}}))
    prior = prior_for_photo(photo, scene=scene_with_georef(), record_path=other)
    np.testing.assert_allclose(prior.pose.center, [1.0, 2.0, 3.0])
    lat, lon, _ = GEOREF.local_to_geodetic([1.0, 2.0, 3.0])
    assert prior.pose.attitude == pytest.approx((grid_azimuth(lat, lon, 123.4), 30.5, 1.2),
                                                abs=2e-3)  # from XMP, turned to grid north
    assert "attitude from DJI gimbal angles (XMP)" in prior.assumptions


@pytest.mark.parametrize("tags", [
    {},  # nothing at all
    {"focal": 5.0, "focal35": 28},  # a camera but no position or heading
    {"lat": 53.0, "lon": -1.8, "alt": 300.0},  # a position but no heading
    {"direction": 90.0},  # a heading but no position
])
def test_no_record_and_no_gps_or_heading_names_the_photo(tmp_path, tags):
    photo = write_photo(tmp_path / "IMG_0042.jpg", **tags)
    with pytest.raises(InputError) as err:
        prior_for_photo(photo, scene=scene_with_georef())
    assert "IMG_0042.jpg" in str(err.value)


def test_compass_direction_alone_assumes_a_level_camera_and_says_so(tmp_path):
    photo = write_photo(tmp_path / "IMG_0007.jpg", lat=MAM_TOR[0], lon=MAM_TOR[1], alt=410.0,
                        direction=287.25, focal35=26)
    prior = prior_for_photo(photo, scene=scene_with_georef())
    trend, plunge, roll = prior.pose.attitude
    assert trend == pytest.approx(grid_azimuth(*MAM_TOR, 287.25), abs=2e-3)
    assert plunge == pytest.approx(0.0, abs=1e-9) and roll == pytest.approx(0.0, abs=1e-9)
    assert "trend from EXIF GPSImgDirection" in prior.assumptions
    assert any("plunge assumed 0" in a for a in prior.assumptions)
    assert any("roll assumed 0" in a for a in prior.assumptions)
    np.testing.assert_allclose(prior.pose.center, utm_local(*MAM_TOR, 410.0), atol=1e-3)


def test_no_focal_length_assumes_a_phone_field_of_view(tmp_path):
    photo = write_photo(tmp_path / "a.jpg", lat=MAM_TOR[0], lon=MAM_TOR[1], alt=410.0,
                        direction=10.0)
    prior = prior_for_photo(photo, scene=scene_with_georef())
    assert prior.intrinsics.hfov_deg == pytest.approx(65.0)
    assert any("65°" in a for a in prior.assumptions)


def test_missing_altitude_comes_from_the_terrain(tmp_path):
    photo = drone_photo(tmp_path, alt=None)
    scene = SimpleNamespace(georef=GEOREF, dem=None, terrain_height=lambda x, y: 17.0)
    prior = prior_for_photo(photo, scene=scene)
    expected = utm_local(*MAM_TOR, 0.0)
    expected[2] = 17.0 + 1.6
    np.testing.assert_allclose(prior.pose.center, expected, atol=1e-3)
    assert any("model surface" in a for a in prior.assumptions)


def test_magnetic_compass_direction_is_stated(tmp_path):
    photo = write_photo(tmp_path / "a.jpg", lat=MAM_TOR[0], lon=MAM_TOR[1], alt=410.0,
                        direction=45.0, direction_ref="M", focal35=26)
    prior = prior_for_photo(photo, scene=scene_with_georef())
    assert any("magnetic" in a for a in prior.assumptions)


def test_empty_gps_ifd_is_no_gps(tmp_path):
    im = Image.fromarray(np.full((H, W, 3), 90, np.uint8))
    exif = Image.Exif()
    exif.get_ifd(ExifTags.IFD.Exif)[ExifTags.Base.FocalLengthIn35mmFilm] = 26
    exif.get_ifd(ExifTags.IFD.GPSInfo)  # the pointer is written, the IFD is empty
    im.save(tmp_path / "IMG_0099.jpg", exif=exif)
    photo = load_photo(tmp_path / "IMG_0099.jpg")
    record, notes = record_from_exif(photo)
    assert record.position is None and record.orientation is None
    assert record.camera is not None
    with pytest.raises(InputError, match="IMG_0099.jpg"):
        prior_for_photo(photo, scene=scene_with_georef())
