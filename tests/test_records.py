"""Sensor records (contract §3) → camera and prior pose."""

from __future__ import annotations

import json

import numpy as np
import pytest

from napari_imgreg import InputError, Intrinsics, Pose
from napari_imgreg.geo import DEM, Georef
from napari_imgreg.io.records import Sigma, load_sensor_record, parse_sensor_record
from napari_imgreg.prior import load_camera_and_pose, prior_from_record

CONTRACT_EXAMPLE = {
    "camera": {"width": 1632, "height": 1224, "focal_length_mm": 3.92,
               "sensor_width_mm": 4.6, "sensor_height_mm": 3.52},
    "position": {"x": 12.0, "y": -140.5, "z": 31.2},
    "orientation": {"trend_deg": 352.0, "plunge_deg": 4.5, "roll_deg": -1.0},
    "sigma": {"position_m": 5.0, "altitude_m": 10.0, "angles_deg": 5.0},
}


def write(tmp_path, data, name="IMG_0001.json"):
    path = tmp_path / name
    path.write_text(json.dumps(data))
    return path


def test_contract_example_gives_its_pose(tmp_path):
    record = load_sensor_record(write(tmp_path, CONTRACT_EXAMPLE))
    prior = prior_from_record(record)
    assert prior.intrinsics.fx == pytest.approx(3.92 * 1632 / 4.6)
    assert prior.intrinsics.fy == pytest.approx(3.92 * 1224 / 3.52)
    np.testing.assert_allclose(prior.pose.center, [12.0, -140.5, 31.2], atol=1e-9)
    trend, plunge, roll = prior.pose.attitude
    assert (trend, plunge, roll) == pytest.approx((352.0, 4.5, -1.0))
    assert prior.sigma == Sigma(5.0, 10.0, 5.0)
    assert prior.assumptions == []


def test_altitude_from_dem_plus_height_above_ground(tmp_path):
    # DEM in CRS coordinates: h = 300 + 0.1 E' (E' relative to the grid corner).
    e0, n0 = 500_000.0, 5_900_000.0
    heights = 300 + 0.1 * np.arange(50)[None, :].repeat(40, axis=0) * 5.0
    dem = DEM.from_array(heights, x0=e0, y0=n0 + 39 * 5.0, dx=5.0, dy=5.0, crs="EPSG:32630")
    georef = Georef(crs="EPSG:32630", origin=np.array([e0, n0, 250.0]))
    data = {**CONTRACT_EXAMPLE, "position": {"x": 100.0, "y": 60.0}}
    record = parse_sensor_record(data, "IMG.json")
    prior = prior_from_record(record, georef=georef, dem=dem)
    expected_z = (300 + 0.1 * 100.0) - 250.0 + 1.6
    assert prior.pose.center[2] == pytest.approx(expected_z)
    assert any("DEM" in a for a in prior.assumptions)


def test_geodetic_position_through_georef(tmp_path):
    georef = Georef(crs="EPSG:32630", origin=np.array([500_000.0, 0.0, 0.0]))
    data = {**CONTRACT_EXAMPLE, "position": {"lat": 0.0, "lon": -3.0, "alt": 12.0}}
    prior = prior_from_record(parse_sensor_record(data, "x.json"), georef=georef)
    np.testing.assert_allclose(prior.pose.center, [0.0, 0.0, 12.0], atol=1e-6)


def test_geodetic_without_georef_is_a_clear_error():
    data = {**CONTRACT_EXAMPLE, "position": {"lat": 53.3, "lon": -1.8}}
    with pytest.raises(InputError, match="x.json.*georef"):
        prior_from_record(parse_sensor_record(data, "x.json"))


def test_missing_blocks_are_named(tmp_path):
    data = {k: v for k, v in CONTRACT_EXAMPLE.items() if k != "orientation"}
    with pytest.raises(InputError, match="IMG_0001.json.*trend"):
        prior_from_record(load_sensor_record(write(tmp_path, data)))
    data = {**CONTRACT_EXAMPLE, "position": {"x": 1.0, "y": 2.0}}
    with pytest.raises(InputError, match="altitude"):
        prior_from_record(load_sensor_record(write(tmp_path, data)))


@pytest.mark.parametrize(
    "patch, field",
    [
        ({"camera": "wide"}, "camera"),
        ({"position": {"x": "12", "y": 1.0}}, "position.x"),
        ({"orientation": {"trend_deg": None, "plunge_deg": 120.0}}, "plunge_deg"),
        ({"sigma": {"position_m": "five"}}, "sigma.position_m"),
        ({"camera": {"width": 10, "height": 10, "dist": "none"}}, "camera.dist"),
    ],
)
def test_wrong_fields_name_file_and_field(tmp_path, patch, field):
    path = write(tmp_path, {**CONTRACT_EXAMPLE, **patch})
    with pytest.raises(InputError) as err:
        load_sensor_record(path)
    message = str(err.value)
    assert "IMG_0001.json" in message and field in message and "\n" not in message


def test_invalid_json_and_missing_file(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{ not json")
    with pytest.raises(InputError, match="bad.json: invalid JSON at line 1"):
        load_sensor_record(bad)
    with pytest.raises(InputError, match="nope.json: no such file"):
        load_sensor_record(tmp_path / "nope.json")
    # A message json ends in "at": the place follows in full, not cut off.
    bad.write_text('{"camera": "a\nb"}')
    with pytest.raises(InputError) as err:
        load_sensor_record(bad)
    assert str(err.value).endswith("bad.json: invalid JSON at line 1 column 14: "
                                   "Invalid control character"), str(err.value)


def test_defaults_are_stated():
    data = {"camera": {"width": 800, "height": 600},
            "position": {"x": 0.0, "y": 0.0, "z": 0.0},
            "orientation": {"trend_deg": 10.0}}
    prior = prior_from_record(parse_sensor_record(data, "r.json"))
    assert prior.intrinsics.hfov_deg == pytest.approx(65.0)
    text = " ".join(prior.assumptions)
    assert "field of view" in text and "plunge" in text and "roll" in text


def test_resized_photo_scales_the_camera():
    record = parse_sensor_record(CONTRACT_EXAMPLE, "r.json")
    prior = prior_from_record(record, image_size=(816, 612))
    assert prior.intrinsics.width == 816
    assert prior.intrinsics.fx == pytest.approx(3.92 * 1632 / 4.6 / 2)


def test_result_json_pose_is_read_back(tmp_path):
    intr = Intrinsics(640, 480, 500.0, 500.0, 319.5, 239.5)
    pose = Pose.from_attitude(123.0, -7.0, 2.0, [1.0, 2.0, 3.0])
    path = write(tmp_path, {"status": "registered", "camera": intr.to_dict(),
                            "pose": pose.to_dict()}, "RESULT.json")
    intr2, pose2, kind, _ = load_camera_and_pose(path)
    assert kind == "result" and intr2 == Intrinsics(640, 480, 500.0, 500.0, 319.5, 239.5)
    np.testing.assert_allclose(pose2.R, pose.R, atol=1e-12)
    np.testing.assert_allclose(pose2.t, pose.t, atol=1e-12)
    bad = {"camera": intr.to_dict(), "pose": {**pose.to_dict(), "R": [[2, 0, 0], [0, 1, 0], [0, 0, 1]]}}
    with pytest.raises(InputError, match="not a rotation"):
        load_camera_and_pose(write(tmp_path, bad, "BAD.json"))


# ------------------------------------------------------- sun at capture
def test_prior_carries_the_sun_of_the_exif_capture_time():
    from napari_imgreg import Scene
    from napari_imgreg.io.photos import load_photo
    from napari_imgreg.prior import prior_for_photo
    from napari_imgreg.sample import load_truth, sample_scene

    folder = sample_scene("small")
    scene = Scene.load(folder / "outcrop.obj", dem=folder / "dem.tif")
    photo = load_photo(folder / "IMG_0002.jpg")
    prior = prior_for_photo(photo, scene)
    truth = load_truth(photo.path)
    # The photo was lit by the sun of its EXIF instant, seen from its true
    # centre; the prior's centre is metres off, which moves the sun by far
    # less than 0.01°.
    assert prior.sun_source.startswith("EXIF time")
    assert np.degrees(np.arccos(np.clip(prior.sun @ truth.conditions.sun, -1, 1))) < 0.01


def test_record_time_and_sun_override_exif(tmp_path):
    from napari_imgreg import Scene
    from napari_imgreg.io.photos import load_photo
    from napari_imgreg.prior import prior_for_photo
    from napari_imgreg.sample import sample_scene
    from napari_imgreg.solar import meridian_convergence_deg

    folder = sample_scene("small")
    scene = Scene.load(folder / "outcrop.obj", dem=folder / "dem.tif")
    photo = load_photo(folder / "IMG_0002.jpg")
    record = json.loads((folder / "IMG_0002.json").read_text())
    path = tmp_path / "r.json"
    path.write_text(json.dumps({**record, "sun": {"azimuth_deg": 180.0, "elevation_deg": 30.0}}))
    prior = prior_for_photo(photo, scene, record_path=path)
    assert prior.sun_source == "sensor record sun"
    # True south turned to grid: azimuth 180 − convergence.
    conv = meridian_convergence_deg(scene.georef, prior.pose.center)
    az = np.degrees(np.arctan2(prior.sun[0], prior.sun[1])) % 360
    assert az == pytest.approx(180.0 - conv, abs=1e-6)
    assert np.degrees(np.arcsin(prior.sun[2])) == pytest.approx(30.0)
    path.write_text(json.dumps({**record, "time": "2024-06-21T12:00:00+00:00"}))
    prior = prior_for_photo(photo, scene, record_path=path)
    assert prior.sun_source.startswith("sensor record time")
    assert 55 < np.degrees(np.arcsin(prior.sun[2])) < 62  # midsummer noon at 53° N


@pytest.mark.parametrize("extra, words", [
    ({"time": "2024-06-21T12:00:00"}, "UTC offset"),
    ({"time": 12}, "ISO 8601"),
    ({"sun": {"azimuth_deg": "south", "elevation_deg": 3}}, "sun.azimuth_deg"),
    ({"sun": {"azimuth_deg": 10, "elevation_deg": 95}}, "sun.elevation_deg"),
])
def test_bad_time_or_sun_fields_name_the_field(tmp_path, extra, words):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps({"position": {"x": 0, "y": 0}, **extra}))
    with pytest.raises(InputError) as err:
        load_sensor_record(path)
    assert words in str(err.value) and "bad.json" in str(err.value)


# ------------------------------------------------------- old paths (0.1)
def test_moved_names_stay_importable_with_a_deprecation_warning():
    import importlib
    import sys

    from napari_imgreg import geo, prior, solar
    from napari_imgreg.io import exif, orientation_tables, rasters, records
    from napari_imgreg.registration.stages import relight

    moved = [
        (records, "Prior", prior.Prior),
        (records, "prior_for_photo", prior.prior_for_photo),
        (records, "prior_from_record", prior.prior_from_record),
        (records, "load_camera_and_pose", prior.load_camera_and_pose),
        (records, "record_from_exif", exif.record_from_exif),
        (records, "_dms", exif.gps_degrees),
        (records, "DEFAULT_HEIGHT_ABOVE_GROUND_M", geo.DEFAULT_HEIGHT_ABOVE_GROUND_M),
        (geo, "read_geotiff", rasters.read_geotiff),
        (geo, "GeoRaster", rasters.GeoRaster),
        (geo, "NODATA_WRITE", rasters.NODATA_WRITE),
        (orientation_tables, "dji_gimbal_angles", exif.dji_gimbal_angles),
        (orientation_tables, "attitude_from_dji_gimbal", exif.attitude_from_dji_gimbal),
        (orientation_tables, "raw_xmp", exif.raw_xmp),
    ]
    for module, name, new in moved:
        with pytest.warns(DeprecationWarning, match="moved to"):
            assert getattr(module, name) is new
    with pytest.raises(AttributeError):
        records.no_such_name  # noqa: B018
    # The old sun module: one view of its three new homes.
    sys.modules.pop("napari_imgreg.sun", None)
    with pytest.warns(DeprecationWarning, match="napari_imgreg.solar"):
        sun = importlib.import_module("napari_imgreg.sun")
    assert sun.sun_position is solar.sun_position
    assert sun.read_capture_time is exif.read_capture_time
    assert sun.render_sunlit is relight.render_sunlit and sun.GREY_ALBEDO == relight.GREY_ALBEDO
