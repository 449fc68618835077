"""Issue 15, the validation layer: shared checks (napari_imgreg.validate),
cameras and poses checked where they are made, declared parameter ranges,
photos of every bit depth, EXIF orientation applied to pixels and camera."""

from __future__ import annotations

import json
import math
import os
from dataclasses import fields

import numpy as np
import pytest
from PIL import Image

from napari_imgreg.camera import Intrinsics, Pose
from napari_imgreg.errors import InputError
from napari_imgreg.io.photos import load_photo
from napari_imgreg.io.records import parse_sensor_record
from napari_imgreg.prior import prior_from_record
from napari_imgreg.registration.features import FeatureParams
from napari_imgreg.registration.filters import FilterParams
from napari_imgreg.registration.params import RegistrationParams
from napari_imgreg.registration.pose import PoseParams
from napari_imgreg.registration.stages.area import AreaParams
from napari_imgreg.registration.stages.dense import DenseParams
from napari_imgreg.registration.stages.edges import EdgeParams
from napari_imgreg.validate import (
    FieldValueError,
    check_number,
    check_option,
    check_ranges,
    check_render_size,
    check_writable,
    param_range,
)

PARAM_CLASSES = (RegistrationParams, FilterParams, FeatureParams, PoseParams, AreaParams,
                 EdgeParams, DenseParams)


# ---------------------------------------------------------------- validate
@pytest.mark.parametrize("value, kwargs, expected", [
    (3, {}, 3.0),
    (np.float32(2.5), {}, 2.5),
    (640.0, {"integer": True}, 640),
    (np.int64(7), {"low": 0, "high": 10}, 7.0),
])
def test_check_number_accepts(value, kwargs, expected):
    out = check_number(value, "f", **kwargs)
    assert out == expected and type(out) is type(expected)


@pytest.mark.parametrize("value, kwargs, message", [
    (True, {}, "field 'f' must be a number, got True"),
    ("3", {}, "field 'f' must be a number, got '3'"),
    (None, {}, "field 'f' must be a number, got None"),
    (math.nan, {}, "field 'f' must be a finite number, got nan"),
    (-math.inf, {}, "field 'f' must be a finite number, got -inf"),
    (2.5, {"integer": True}, "field 'f' must be a whole number, got 2.5"),
    (0, {"low": 0, "high": 1, "low_open": True}, "field 'f' must be within (0, 1], got 0"),
    (11, {"low": 0, "high": 10}, "field 'f' must be within [0, 10], got 11"),
    (10**400, {"low": 0, "high": 10}, "got an integer of 401 digits"),
    (2**63, {"low": 0, "high": 1e6}, "must be within [0, 1000000], got 9223372036854775808"),
])
def test_check_number_refuses(value, kwargs, message):
    with pytest.raises(FieldValueError) as err:
        check_number(value, "f", **kwargs)
    assert message in str(err.value)
    assert err.value.field == "f"
    assert err.value.within("camera").startswith("field 'camera.f' ")


def test_check_option_is_one_input_error():
    assert check_option(2.0, "--scale", 0, 8, low_open=True) == 2.0
    with pytest.raises(InputError, match=r"^--scale must be a finite number, got nan$"):
        check_option(float("nan"), "--scale", 0, 8)


def test_check_render_size_known_answer():
    check_render_size(8000, 8000)  # 64 MP: the limit itself
    with pytest.raises(InputError, match=r"8001×8000 px .* reduce the scale by 1× or more"):
        check_render_size(8001, 8000)
    # 4× the limit in pixels: half the scale in each direction.
    with pytest.raises(InputError, match=r"reduce the scale by 0.5× or more"):
        check_render_size(16000, 16000)


def test_check_writable(tmp_path):
    assert check_writable(tmp_path / "new" / "deeper" / "out.json") == \
        tmp_path / "new" / "deeper" / "out.json"
    assert not (tmp_path / "new").exists()  # nothing created by the check
    assert list(tmp_path.iterdir()) == []  # and its probe file removed
    check_writable(tmp_path / "folder", folder=True)
    (tmp_path / "f.txt").write_text("x")
    with pytest.raises(InputError, match="f.txt is a file, not a folder"):
        check_writable(tmp_path / "f.txt" / "out.json")
    with pytest.raises(InputError, match="it is a file, not a folder"):
        check_writable(tmp_path / "f.txt", folder=True)
    with pytest.raises(InputError, match="it is a folder, not a file"):
        check_writable(tmp_path)
    with pytest.raises(InputError, match="does not take new files"):
        check_writable("/proc/some/out.json")


def test_check_writable_follows_symlinks(tmp_path):
    real = tmp_path / "real"
    real.mkdir()
    link = tmp_path / "out.json"
    link.symlink_to(real / "out.json")  # dangling: the target is what gets written
    check_writable(link)
    folder_link = tmp_path / "as_folder.json"
    folder_link.symlink_to(real)
    with pytest.raises(InputError, match="it is a folder, not a file"):
        check_writable(folder_link)


# ------------------------------------------------------- declared ranges
@pytest.mark.parametrize("cls", PARAM_CLASSES)
def test_every_numeric_parameter_declares_its_range(cls):
    """One declared range per number, the default inside it."""
    defaults = cls()
    for f in fields(cls):
        value = getattr(defaults, f.name)
        elements = value if isinstance(value, tuple) else (value,)
        numeric = bool(elements) and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in elements)
        if numeric:
            assert f.name in cls.RANGES, f"{cls.__name__}.{f.name} has no declared range"
    for name, (low, high) in cls.RANGES.items():
        value = getattr(defaults, name)
        assert low <= high
        assert all(low <= v <= high for v in (value if isinstance(value, tuple) else (value,)))
        assert param_range(defaults, name) == (low, high)
    check_ranges(defaults)


@pytest.mark.parametrize("cls, field, bad", [
    (RegistrationParams, "max_trials", 0),
    (RegistrationParams, "match_width", 0),
    (RegistrationParams, "max_iterations", 0),
    (FeatureParams, "ratio", float("nan")),
    (FilterParams, "gamma", 0.0),
    (PoseParams, "confidence", 1.0),
    (AreaParams, "width", 10),
])
def test_out_of_range_parameters_are_refused_when_built(cls, field, bad):
    with pytest.raises(FieldValueError, match=f"field '{field}' must be within"):
        cls(**{field: bad})


def test_params_file_names_file_and_nested_field(tmp_path):
    path = tmp_path / "p.json"
    path.write_text(json.dumps({"features": {"max_features": 0}}))
    from napari_imgreg.registration.params import load_params

    with pytest.raises(InputError, match=r"p.json: field 'features.max_features' must be "
                                         r"within \[10, 1000000\], got 0"):
        load_params(path)


# ---------------------------------------------------------------- cameras
@pytest.mark.parametrize("change, field", [
    ({"fx": 0.0}, "fx"), ({"fy": -1.0}, "fy"), ({"fx": math.nan}, "fx"),
    ({"width": 0}, "width"), ({"height": 10**12}, "height"), ({"width": 2.5}, "width"),
    ({"cx": math.inf}, "cx"), ({"cy": 1e9}, "cy"),
    ({"dist": (math.nan, 0, 0, 0, 0)}, "dist"), ({"dist": (0.0,) * 8}, "dist"),
    ({"fx": 1e-6}, "fx"),  # a view of 180°: not a pinhole
])
def test_intrinsics_refuse_nonsense(change, field):
    kw = dict(width=640, height=480, fx=500.0, fy=500.0, cx=319.5, cy=239.5)
    kw.update(change)
    with pytest.raises(FieldValueError) as err:
        Intrinsics(**kw)
    assert err.value.field == field


def test_intrinsics_scaled_refuses_nan_scale():
    with pytest.raises(FieldValueError, match="scale"):
        Intrinsics(64, 48, 50.0, 50.0, 31.5, 23.5).scaled(float("nan"))


def test_pose_from_dict_refuses_nan_and_non_rotations():
    good = Pose.from_attitude(10.0, 5.0, 0.0, [1.0, 2.0, 3.0])
    d = good.to_dict()
    assert np.allclose(Pose.from_dict(d).R, good.R)
    with pytest.raises(FieldValueError, match="field 't' must be 3 finite"):
        Pose.from_dict({**d, "t": [math.nan, 0, 0]})
    with pytest.raises(FieldValueError, match="field 'R' is not a rotation"):
        Pose.from_dict({**d, "R": (2 * np.eye(3)).tolist()})
    with pytest.raises(FieldValueError, match="field 'R' is not a rotation"):
        Pose.from_dict({**d, "R": np.diag([1.0, 1.0, -1.0]).tolist()})  # a mirror


@pytest.mark.parametrize("turns", [1, 2, -1])
def test_rotated_camera_sees_the_rotated_image(turns):
    """Known answer: a point at pixel (u, v) of the stored image is at
    (H-1-v, u) after a clockwise quarter turn, (W-1-u, H-1-v) after a half
    turn, (v, W-1-u) after an anticlockwise one — distortion included."""
    K = Intrinsics(400, 300, 350.0, 340.0, 210.3, 140.7, (0.1, -0.02, 0.003, -0.002, 0.01))
    P = Pose.from_attitude(30.0, 10.0, 5.0, [1.0, 2.0, 3.0])
    rng = np.random.default_rng(0)
    X = P.center + 20 * P.view_direction + rng.normal(size=(30, 3)) * 3
    u, v = P.project(K, X).T
    W, H = K.width, K.height
    expected = {1: np.c_[H - 1 - v, u], 2: np.c_[W - 1 - u, H - 1 - v],
                -1: np.c_[v, W - 1 - u]}[turns]
    got = P.rotated(turns).project(K.rotated(turns), X)
    assert np.abs(got - expected).max() < 1e-9
    # The roll changes by -90° per clockwise quarter turn; trend and plunge stay.
    t0, p0, r0 = P.attitude
    t1, p1, r1 = P.rotated(turns).attitude
    assert (t1, p1) == pytest.approx((t0, p0))
    assert (r1 - r0 + 90 * turns + 180) % 360 - 180 == pytest.approx(0.0, abs=1e-9)


# ----------------------------------------------------------------- photos
def test_16_bit_grey_png_reads_right(tmp_path):
    grey = (np.arange(48 * 64).reshape(48, 64) * 21).astype(np.uint16)  # 0 … 64491
    Image.fromarray(grey).save(tmp_path / "g16.png")
    image = load_photo(tmp_path / "g16.png").image
    assert image.dtype == np.uint8 and image.shape == (48, 64, 3)
    expected = np.round(grey / 257.0).astype(np.uint8)
    assert np.array_equal(image[..., 0], expected)
    assert np.array_equal(image[..., 0], image[..., 2])
    assert image.max() == 251 and image.min() == 0  # not all white (before: 255 everywhere)


def test_16_bit_rgb_and_8_bit_grey(tmp_path):
    import cv2

    bgr = np.zeros((20, 30, 3), np.uint16)
    bgr[..., 2] = 40000  # red
    bgr[..., 1] = 20000
    cv2.imwrite(str(tmp_path / "c16.png"), bgr)
    rgb = load_photo(tmp_path / "c16.png").image
    assert tuple(rgb[0, 0]) == pytest.approx((40000 / 257, 20000 / 257, 0), abs=1)
    Image.fromarray(np.full((10, 12), 77, np.uint8)).save(tmp_path / "g8.png")
    assert (load_photo(tmp_path / "g8.png").image == 77).all()


def test_float_tiff_in_unit_range(tmp_path):
    data = np.linspace(0, 1, 40 * 30, dtype=np.float32).reshape(30, 40)
    Image.fromarray(data, mode="F").save(tmp_path / "f.tif")
    image = load_photo(tmp_path / "f.tif").image
    assert np.array_equal(image[..., 1], np.round(data * 255).astype(np.uint8))


def _exif_photo(path, stored: np.ndarray, orientation: int, base_exif=None):
    im = Image.fromarray(stored)
    exif = base_exif if base_exif is not None else Image.Exif()
    exif[0x0112] = orientation
    im.save(path, exif=exif, quality=95)


def test_exif_orientation_turns_the_pixels(tmp_path):
    stored = np.zeros((30, 40, 3), np.uint8)
    stored[0, 0] = 255  # top-left of the stored (sensor) image
    _exif_photo(tmp_path / "p.png", stored, 6)
    photo = load_photo(tmp_path / "p.png")
    assert photo.size == (30, 40)  # shown portrait
    assert photo.exif["Orientation"] == 6
    # Turned clockwise: the stored top-left is now the top-right.
    assert photo.image[0, 29].min() == 255 and photo.image[0, 0].max() == 0


# ------------------------------------------------- portrait photos, priors
def _landscape_record(tmp_path):
    data = {"camera": {"width": 160, "height": 120, "fx": 110.0, "fy": 112.0, "cx": 80.3,
                       "cy": 58.9},
            "position": {"x": 1.0, "y": 2.0, "z": 3.0},
            "orientation": {"trend_deg": 40.0, "plunge_deg": 5.0, "roll_deg": 2.0}}
    return parse_sensor_record(data, tmp_path / "IMG_0001.json")


@pytest.mark.parametrize("orientation, turns", [(6, 1), (8, -1)])
def test_portrait_photo_with_landscape_record_turns_the_camera(tmp_path, orientation, turns):
    record = _landscape_record(tmp_path)
    sensor = prior_from_record(record, image_size=(160, 120))
    prior = prior_from_record(record, image_size=(120, 160), exif_orientation=orientation)
    assert prior.intrinsics == sensor.intrinsics.rotated(turns)
    assert (prior.intrinsics.width, prior.intrinsics.height) == (120, 160)
    assert np.allclose(prior.pose.R, sensor.pose.rotated(turns).R)
    assert np.allclose(prior.pose.center, sensor.pose.center)
    assert any("turned" in note for note in prior.assumptions)


def test_portrait_photo_resized_with_landscape_record(tmp_path):
    record = _landscape_record(tmp_path)
    prior = prior_from_record(record, image_size=(60, 80), exif_orientation=6)
    sensor = prior_from_record(record, image_size=(160, 120))
    assert (prior.intrinsics.width, prior.intrinsics.height) == (60, 80)
    assert prior.intrinsics.fx == pytest.approx(sensor.intrinsics.fy / 2)


@pytest.mark.parametrize("orientation, words", [
    (None, "EXIF orientation does not turn it (tag absent); give the camera of the photo "
           "as shown: width 120, height 160"),
    (1, "(tag 1)"),
    (5, "EXIF orientation 5 mirrors it"),
])
def test_portrait_photo_without_turn_is_refused_with_the_fix(tmp_path, orientation, words):
    record = _landscape_record(tmp_path)
    with pytest.raises(InputError) as err:
        prior_from_record(record, image_size=(120, 160), exif_orientation=orientation)
    assert str(tmp_path / "IMG_0001.json") in str(err.value) and words in str(err.value)
    assert "\n" not in str(err.value)


def test_geodetic_errors_name_the_record(tmp_path, monkeypatch):
    from napari_imgreg.geo import Georef
    from napari_imgreg.io.rasters import GeoError

    georef = Georef("EPSG:32632", (500000.0, 5100000.0, 0.0))

    def refuse(*args, **kwargs):
        raise GeoError("cannot project lat 46.0, lon 7.0 into EPSG:32632")

    monkeypatch.setattr(Georef, "geodetic_to_local", refuse)
    record = parse_sensor_record(
        {"camera": {"width": 64, "height": 48, "fx": 50.0},
         "position": {"lat": 46.0, "lon": 7.0, "alt": 500.0},
         "orientation": {"trend_deg": 0.0}}, tmp_path / "R.json")
    with pytest.raises(InputError, match=r"R.json: field 'position' \(lat 46.0, lon 7.0\): "
                                         r"cannot project"):
        prior_from_record(record, georef=georef)


@pytest.mark.slow
def test_portrait_phone_photo_registers(tmp_path):
    """End to end: a sample photo stored landscape with EXIF orientation 6 (as
    a phone held upright stores it) and its landscape sensor record registers;
    the pose is the true one turned with the pixels."""
    from napari_imgreg import Scene
    from napari_imgreg.prior import prior_for_photo
    from napari_imgreg.registration.pipeline import register
    from napari_imgreg.sample import load_truth, sample_scene

    folder = sample_scene("small")
    scene = Scene.load(folder / "outcrop.obj", dem=folder / "dem.tif")
    with Image.open(folder / "IMG_0001.jpg") as im:
        stored, exif = np.asarray(im.convert("RGB")), im.getexif()
    photo_path = tmp_path / "IMG_0001.jpg"
    _exif_photo(photo_path, stored, 6, exif)
    (tmp_path / "IMG_0001.json").write_text((folder / "IMG_0001.json").read_text())
    photo = load_photo(photo_path)
    assert photo.size == (stored.shape[0], stored.shape[1])  # portrait
    prior = prior_for_photo(photo, scene)
    truth = load_truth(folder / "IMG_0001.jpg")
    turned_truth = truth.pose.rotated(1)
    assert (prior.intrinsics.width, prior.intrinsics.height) == photo.size
    reg = register(scene, photo.image, prior, photo_name=photo_path.name)
    assert reg.status == "registered"
    assert reg.pose.rotation_error_deg(turned_truth) < 0.2
    assert np.linalg.norm(reg.pose.center - turned_truth.center) < 0.3
    assert os.fspath(photo_path)  # the photo's own file, not the sample's


def test_check_writable_read_only_folder(tmp_path, monkeypatch):
    """A folder that does not take a new file (read-only, as a user who is not
    root meets it) is refused with the reason; simulated, since root writes
    anywhere."""
    import napari_imgreg.validate as validate

    def refuse(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(validate.tempfile, "mkstemp", refuse)
    with pytest.raises(InputError, match=r"out.json: cannot write here: folder .* does not "
                                         r"take new files \(Permission denied\)"):
        check_writable(tmp_path / "out.json")


def test_workbench_ranges_lie_within_the_declared_ones():
    """The GUI offers only values the dataclasses accept."""
    pytest.importorskip("qtpy")
    from napari_imgreg.widgets._panels import FilterEditor

    for name, _label, _kind, lo, hi, _dec in FilterEditor.FIELDS:
        low, high = FilterParams.RANGES[name]
        assert low <= lo <= hi <= high, name


# ------------------------------------------------- HEIC/HEIF (phone photos)
def _heic_photo(path, stored: np.ndarray, orientation: int) -> None:
    """A HEIC as an iPhone writes one: the tag says how to turn the sensor's
    pixels; pillow-heif stores that turn in the container (libheif applies it)."""
    from pillow_heif import register_heif_opener

    register_heif_opener()
    exif = Image.Exif()
    exif[0x0112] = orientation
    exif[0x010F], exif[0x0110] = "Apple", "iPhone 15"
    exif[0x8825] = {1: "N", 2: (46.0, 30.0, 0.0), 3: "E", 4: (7.0, 15.0, 0.0)}
    Image.fromarray(stored).save(path, exif=exif.tobytes(), quality=100)


@pytest.mark.parametrize("suffix", [".heic", ".HEIF"])
def test_heic_photo_is_read_turned_with_its_tags(tmp_path, suffix):
    stored = np.zeros((30, 40, 3), np.uint8)
    stored[:4, :4] = 255  # top-left of the stored (sensor) image
    _heic_photo(tmp_path / f"p{suffix}", stored, 6)
    photo = load_photo(tmp_path / f"p{suffix}")
    assert photo.size == (30, 40)  # shown portrait, as the JPEG would be
    # The tag as written, for the prior to turn the camera with the pixels.
    assert photo.exif["Orientation"] == 6
    assert photo.exif["Make"] == "Apple" and photo.exif["GPSInfo"]["GPSLatitudeRef"] == "N"
    # Turned clockwise once (not twice): the stored top-left is now the top-right.
    assert photo.image[:3, -3:].min() > 200 and photo.image[:3, :3].max() < 60


def test_portrait_heic_with_landscape_record_turns_the_camera(tmp_path):
    record = _landscape_record(tmp_path)
    _heic_photo(tmp_path / "IMG_0001.heic", np.full((120, 160, 3), 90, np.uint8), 6)
    photo = load_photo(tmp_path / "IMG_0001.heic")
    prior = prior_from_record(record, image_size=photo.size,
                              exif_orientation=photo.exif["Orientation"])
    sensor = prior_from_record(record, image_size=(160, 120))
    assert prior.intrinsics == sensor.intrinsics.rotated(1)
    assert np.allclose(prior.pose.R, sensor.pose.rotated(1).R)


def test_unreadable_heic_is_one_error_line(tmp_path):
    bad = tmp_path / "broken.heic"
    bad.write_bytes(b"\x00\x00\x00\x18ftypheic" + b"\x00" * 64)
    good = tmp_path / "good.heic"
    _heic_photo(good, np.random.default_rng(0).integers(0, 255, (120, 160, 3), np.uint8), 1)
    truncated = tmp_path / "truncated.heic"  # libheif's message ends in a newline
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    for path in (bad, truncated):
        with pytest.raises(InputError) as err:
            load_photo(path)
        assert str(path) in str(err.value) and "\n" not in str(err.value)
