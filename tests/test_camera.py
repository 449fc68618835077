"""Known-answer tests for :mod:`napari_imgreg.camera` (contract §1–§2)."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from napari_imgreg.camera import (
    SENSOR_WIDTHS_MM,
    Intrinsics,
    Pose,
    attitude_from_rotation,
    match_scale,
    pixels_to_full,
    pixels_to_scaled,
    rotation_from_attitude,
    scaled_size,
)

# ---------------------------------------------------------------------------
# the contract's reference formula (interfaces.md §2), re-implemented verbatim
# ---------------------------------------------------------------------------


def contract_R(trend, plunge, roll):
    T, P, Ro = math.radians(trend), math.radians(plunge), math.radians(roll)
    z = np.array([math.sin(T) * math.cos(P), math.cos(T) * math.cos(P), -math.sin(P)])
    x0 = np.array([math.cos(T), -math.sin(T), 0.0])
    y0 = np.cross(z, x0)
    x = math.cos(Ro) * x0 + math.sin(Ro) * y0
    y = np.cross(z, x)
    return np.stack([x, y, z])


def angle_diff(a, b):
    """Signed smallest difference a - b of two angles in degrees."""
    return (a - b + 180.0) % 360.0 - 180.0


def rot_axis_angle(axis, angle_deg):
    """Rodrigues formula written out: rotation by ``angle`` about unit ``axis``."""
    k = np.asarray(axis, float)
    k = k / np.linalg.norm(k)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    th = math.radians(angle_deg)
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * (K @ K)


EAST, NORTH, UP = np.eye(3)

# ---------------------------------------------------------------------------
# attitude → rotation
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("trend", [0.0, 17.0, 90.0, 135.5, 180.0, 263.0, 359.0])
@pytest.mark.parametrize("plunge", [-90.0, -60.0, -4.5, 0.0, 12.0, 45.0, 89.0, 90.0])
@pytest.mark.parametrize("roll", [-170.0, -30.0, 0.0, 1.0, 30.0, 95.0, 180.0])
def test_rotation_matches_contract_formula(trend, plunge, roll):
    R = rotation_from_attitude(trend, plunge, roll)
    assert R.shape == (3, 3)
    np.testing.assert_allclose(R, contract_R(trend, plunge, roll), rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    "trend, view, right",
    [
        (0.0, NORTH, EAST),
        (90.0, EAST, -NORTH),
        (180.0, -NORTH, -EAST),
        (270.0, -EAST, NORTH),
    ],
)
def test_cardinal_trends(trend, view, right):
    R = rotation_from_attitude(trend, 0.0, 0.0)
    np.testing.assert_allclose(R[2], view, atol=1e-12)  # camera z = view direction
    np.testing.assert_allclose(R[0], right, atol=1e-12)  # camera x = photographer's right
    np.testing.assert_allclose(R[1], -UP, atol=1e-12)  # image down = world down
    assert abs(R[0] @ UP) < 1e-12  # x horizontal at roll 0


def test_trend_zero_x_axis_is_east():
    R = rotation_from_attitude(0.0, 0.0, 0.0)
    np.testing.assert_allclose(R, [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-12)


@pytest.mark.parametrize("trend", [0.0, 33.0, 200.0])
def test_x_axis_horizontal_at_roll_zero_for_any_plunge(trend):
    for plunge in (-80.0, -20.0, 0.0, 35.0, 80.0):
        R = rotation_from_attitude(trend, plunge, 0.0)
        assert abs(R[0] @ UP) < 1e-12
        # image "down" has a downward (or zero) world component
        assert R[1] @ UP <= 1e-12


def test_plunge_positive_is_downward():
    R = rotation_from_attitude(40.0, 30.0, 0.0)
    assert R[2] @ UP == pytest.approx(-0.5, abs=1e-12)  # sin 30° below horizontal
    R = rotation_from_attitude(40.0, -30.0, 0.0)
    assert R[2] @ UP == pytest.approx(0.5, abs=1e-12)


@pytest.mark.parametrize("trend", [0.0, 90.0, 212.0])
def test_vertical_views(trend):
    down = rotation_from_attitude(trend, 90.0, 0.0)
    np.testing.assert_allclose(down[2], [0, 0, -1], atol=1e-12)
    up = rotation_from_attitude(trend, -90.0, 0.0)
    np.testing.assert_allclose(up[2], [0, 0, 1], atol=1e-12)
    # the x axis is still the trend's horizontal right-hand direction
    T = math.radians(trend)
    np.testing.assert_allclose(down[0], [math.cos(T), -math.sin(T), 0], atol=1e-12)


@pytest.mark.parametrize("trend, plunge", [(0.0, 0.0), (123.0, 20.0), (300.0, -35.0)])
def test_positive_roll_turns_x_axis_down(trend, plunge):
    R = rotation_from_attitude(trend, plunge, 30.0)
    assert R[0] @ UP < 0
    assert R[0] @ UP == pytest.approx(-math.sin(math.radians(30.0)) * math.cos(math.radians(plunge)), abs=1e-12)
    R = rotation_from_attitude(trend, plunge, -30.0)
    assert R[0] @ UP > 0
    # roll is a rotation about the view direction: z is unchanged
    np.testing.assert_allclose(R[2], rotation_from_attitude(trend, plunge, 0.0)[2], atol=1e-12)


def test_positive_roll_is_clockwise_for_the_photographer():
    # Looking north, level: a clockwise turn (seen from behind the camera)
    # tips the right end of the long axis down.
    R = rotation_from_attitude(0.0, 0.0, 90.0)
    np.testing.assert_allclose(R[0], -UP, atol=1e-12)  # x points down
    np.testing.assert_allclose(R[1], -EAST, atol=1e-12)  # image down points west


def test_rotation_is_proper_orthonormal():
    rng = np.random.default_rng(1)
    for trend, plunge, roll in zip(
        rng.uniform(0, 360, 200), rng.uniform(-90, 90, 200), rng.uniform(-180, 180, 200)
    ):
        R = rotation_from_attitude(trend, plunge, roll)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)


# ---------------------------------------------------------------------------
# rotation → attitude
# ---------------------------------------------------------------------------


def test_attitude_round_trip_random():
    rng = np.random.default_rng(7)
    n = 2000
    trends = rng.uniform(-720, 720, n)  # outside [0, 360): must wrap
    plunges = rng.uniform(-89.9, 89.9, n)
    rolls = rng.uniform(-179.9, 179.9, n)
    for t, p, r in zip(trends, plunges, rolls):
        R = rotation_from_attitude(t, p, r)
        t2, p2, r2 = attitude_from_rotation(R)
        assert 0.0 <= t2 < 360.0
        assert -90.0 <= p2 <= 90.0
        assert -180.0 < r2 <= 180.0
        assert abs(angle_diff(t2, t % 360.0)) < 1e-7
        assert p2 == pytest.approx(p, abs=1e-7)
        assert abs(angle_diff(r2, r)) < 1e-7
        np.testing.assert_allclose(rotation_from_attitude(t2, p2, r2), R, atol=1e-12)


def test_attitude_round_trip_known_values():
    for att in [(0.0, 0.0, 0.0), (352.0, 4.5, -1.0), (90.0, -45.0, 30.0), (180.0, 10.0, 170.0)]:
        got = attitude_from_rotation(rotation_from_attitude(*att))
        np.testing.assert_allclose(got, att, atol=1e-9)


def test_trend_360_wraps_to_zero():
    t, p, r = attitude_from_rotation(rotation_from_attitude(360.0, 10.0, 5.0))
    assert t == pytest.approx(0.0, abs=1e-9) and 0.0 <= t < 360.0


@pytest.mark.parametrize("plunge, sign", [(90.0, 1.0), (-90.0, -1.0)])
def test_vertical_view_folds_roll_into_trend(plunge, sign):
    rng = np.random.default_rng(3)
    for trend, roll in zip(rng.uniform(0, 360, 100), rng.uniform(-180, 180, 100)):
        R = rotation_from_attitude(trend, plunge, roll)
        t2, p2, r2 = attitude_from_rotation(R)
        assert p2 == plunge
        assert r2 == 0.0
        assert 0.0 <= t2 < 360.0
        # looking down, roll adds to the trend; looking up it subtracts
        assert abs(angle_diff(t2, trend + sign * roll)) < 1e-9
        np.testing.assert_allclose(rotation_from_attitude(t2, p2, r2), R, atol=1e-12)


@pytest.mark.parametrize("plunge", [89.999, 89.9999999, -89.9999999, -89.999])
def test_near_vertical_view_reproduces_rotation(plunge):
    rng = np.random.default_rng(4)
    for trend, roll in zip(rng.uniform(0, 360, 50), rng.uniform(-180, 180, 50)):
        R = rotation_from_attitude(trend, plunge, roll)
        np.testing.assert_allclose(
            rotation_from_attitude(*attitude_from_rotation(R)), R, atol=1e-8
        )


# ---------------------------------------------------------------------------
# Pose
# ---------------------------------------------------------------------------


def test_pose_center_and_from_center():
    R = rotation_from_attitude(120.0, 15.0, -7.0)
    C = np.array([12.0, -140.5, 31.2])
    pose = Pose.from_center(R, C)
    np.testing.assert_allclose(pose.t, -R @ C, atol=1e-12)
    np.testing.assert_allclose(pose.center, C, atol=1e-12)
    np.testing.assert_allclose(Pose(R, pose.t).center, -R.T @ pose.t, atol=1e-12)
    # the camera centre maps to the camera-frame origin
    np.testing.assert_allclose(pose.transform(C[None]), [[0, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(pose.view_direction, R[2])
    other = Pose.from_attitude(120.0, 15.0, -7.0, C)
    np.testing.assert_allclose(other.R, R, atol=1e-15)
    np.testing.assert_allclose(other.t, pose.t, atol=1e-12)
    moved = pose.with_center([1.0, 2.0, 3.0])
    np.testing.assert_allclose(moved.center, [1, 2, 3], atol=1e-12)
    np.testing.assert_allclose(moved.R, R)


def test_pose_transform_and_inverse():
    rng = np.random.default_rng(5)
    R = rotation_from_attitude(33.0, -12.0, 44.0)
    t = np.array([3.0, -1.0, 20.0])
    pose = Pose(R, t)
    X = rng.uniform(-50, 50, (100, 3))
    Xc = pose.transform(X)
    np.testing.assert_allclose(Xc, (R @ X.T).T + t, atol=1e-12)
    np.testing.assert_allclose(pose.inverse_transform(Xc), X, atol=1e-12)
    M = pose.matrix
    np.testing.assert_allclose((M @ np.c_[X, np.ones(100)].T).T[:, :3], Xc, atol=1e-12)


def test_pose_projects_a_known_point():
    intr = Intrinsics(160, 120, 100.0, 110.0, 79.5, 59.5)
    pose = Pose.from_attitude(0.0, 0.0, 0.0, [0.0, 0.0, 0.0])  # looking north, level
    # 1 m east, 10 m north, 0.5 m below: camera (x, y, z) = (1, 0.5, 10)
    uv = pose.project(intr, [[1.0, 10.0, -0.5]])
    np.testing.assert_allclose(uv, [[100.0 * 0.1 + 79.5, 110.0 * 0.05 + 59.5]], atol=1e-12)
    # moved camera, looking east: the same relation in its own frame
    pose = Pose.from_attitude(90.0, 0.0, 0.0, [5.0, 5.0, 2.0])
    uv = pose.project(intr, [[25.0, 3.0, 1.0]])  # 20 m ahead, 2 m right, 1 m down
    np.testing.assert_allclose(uv, [[100.0 * 0.1 + 79.5, 110.0 * 0.05 + 59.5]], atol=1e-12)
    # behind the camera: NaN
    assert np.isnan(pose.project(intr, [[-25.0, 3.0, 1.0]])).all()


def test_pose_rays_pass_through_pixels():
    intr = Intrinsics(160, 120, 100.0, 100.0, 80.2, 58.7)
    pose = Pose.from_attitude(250.0, 20.0, 10.0, [1.0, 2.0, 3.0])
    px = np.array([[0.0, 0.0], [159.0, 119.0], [80.2, 58.7], [33.3, 99.9]])
    origin, d = pose.rays(intr, px)
    np.testing.assert_allclose(origin, pose.center)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(pose.project(intr, origin + 7.0 * d), px, atol=1e-9)
    np.testing.assert_allclose(d[2], pose.view_direction, atol=1e-12)


def test_from_rvec_tvec_matches_rodrigues():
    axis = np.array([0.3, -0.5, 0.8])
    axis /= np.linalg.norm(axis)
    angle = 37.0
    rvec = axis * math.radians(angle)
    tvec = np.array([1.0, 2.0, 3.0])
    pose = Pose.from_rvec_tvec(rvec, tvec)
    np.testing.assert_allclose(pose.R, rot_axis_angle(axis, angle), atol=1e-12)
    np.testing.assert_allclose(pose.t, tvec)
    np.testing.assert_allclose(pose.rvec, rvec, atol=1e-12)
    # shapes OpenCV returns are accepted
    pose2 = Pose.from_rvec_tvec(rvec.reshape(3, 1), tvec.reshape(3, 1))
    np.testing.assert_allclose(pose2.R, pose.R)


@pytest.mark.parametrize("angle", [0.0, 0.5, 17.0, 90.0, 179.0, 180.0])
def test_rotation_error_deg_known(angle):
    R = rotation_from_attitude(47.0, 12.0, -5.0)
    dR = rot_axis_angle([0.2, 0.9, -0.4], angle)
    a = Pose(R, np.zeros(3))
    b = Pose(dR @ R, np.ones(3))  # translation does not matter
    assert a.rotation_error_deg(b) == pytest.approx(angle, abs=1e-5)
    assert b.rotation_error_deg(a) == pytest.approx(angle, abs=1e-5)
    # a change of trend alone on a level camera is that many degrees
    c = Pose.from_attitude(47.0 + angle, 0.0, 0.0, [0, 0, 0])
    d = Pose.from_attitude(47.0, 0.0, 0.0, [0, 0, 0])
    assert c.rotation_error_deg(d) == pytest.approx(angle, abs=1e-5)


def test_pose_dict_round_trip():
    pose = Pose.from_attitude(352.0, 4.5, -1.0, [12.0, -140.5, 31.2])
    d = pose.to_dict()
    json.dumps(d)  # plain JSON types
    assert set(d) >= {"R", "t", "position", "trend_deg", "plunge_deg", "roll_deg"}
    np.testing.assert_allclose(d["position"], [12.0, -140.5, 31.2], atol=1e-12)
    assert d["trend_deg"] == pytest.approx(352.0, abs=1e-9)
    assert d["plunge_deg"] == pytest.approx(4.5, abs=1e-9)
    assert d["roll_deg"] == pytest.approx(-1.0, abs=1e-9)
    back = Pose.from_dict(json.loads(json.dumps(d)))
    np.testing.assert_array_equal(back.R, pose.R)
    np.testing.assert_array_equal(back.t, pose.t)


# ---------------------------------------------------------------------------
# Intrinsics: construction
# ---------------------------------------------------------------------------


def test_from_focal_length_mm():
    intr = Intrinsics.from_focal_length_mm(1632, 1224, 3.92, 4.6)
    assert intr.fx == pytest.approx(3.92 * 1632 / 4.6)
    assert intr.fy == intr.fx
    assert (intr.cx, intr.cy) == (815.5, 611.5)
    intr = Intrinsics.from_focal_length_mm(1632, 1224, 3.92, 4.6, 3.52)
    assert intr.fy == pytest.approx(3.92 * 1224 / 3.52)
    with pytest.raises(ValueError):
        Intrinsics.from_focal_length_mm(100, 100, 0.0, 4.6)


def test_from_35mm_equivalent_phone():
    intr = Intrinsics.from_35mm_equivalent(4000, 3000, 26.0)
    f = 26.0 * 5000.0 / 43.2666
    assert intr.fx == pytest.approx(f, rel=1e-5)
    assert intr.fy == intr.fx
    assert (intr.cx, intr.cy) == (1999.5, 1499.5)
    # the diagonal field of view equals that of a 26 mm lens on 36 x 24 mm
    diag_fov = 2 * math.atan(5000.0 / 2 / intr.fx)
    assert diag_fov == pytest.approx(2 * math.atan(math.hypot(36, 24) / 2 / 26.0), rel=1e-12)


def test_from_fov():
    intr = Intrinsics.from_fov(160, 120, 90.0)
    assert intr.fx == pytest.approx(80.0)
    assert intr.hfov_deg == pytest.approx(2 * math.degrees(math.atan(80.0 / 80.0)))


# A full-frame camera: 5616 px across 36 mm.
FF_FOCAL = 24.0
FF_PX_PER_MM = 5616 / 36.0


@pytest.mark.parametrize(
    "xres, unit",
    [
        (FF_PX_PER_MM * 25.4, 2),  # pixels per inch
        (FF_PX_PER_MM * 10.0, 3),  # pixels per centimetre
        (FF_PX_PER_MM, 4),  # pixels per millimetre
        (FF_PX_PER_MM * 25.4, None),  # unit absent: inches (EXIF default)
    ],
)
def test_from_exif_focal_plane_resolution(xres, unit):
    exif = {"FocalLength": FF_FOCAL, "FocalPlaneXResolution": xres, "Model": "unknown"}
    if unit is not None:
        exif["FocalPlaneResolutionUnit"] = unit
    intr = Intrinsics.from_exif(exif, 5616, 3744)
    assert intr.fx == pytest.approx(FF_FOCAL * FF_PX_PER_MM, rel=1e-9)
    assert intr.fy == intr.fx
    assert (intr.cx, intr.cy) == (5615 / 2, 3743 / 2)


def test_from_exif_focal_plane_resolution_rationals_and_downsized_photo():
    from PIL.TiffImagePlugin import IFDRational

    exif = {
        "FocalLength": IFDRational(240, 10),
        "FocalPlaneXResolution": (int(FF_PX_PER_MM * 25.4 * 1000), 1000),
        "FocalPlaneResolutionUnit": 2,
        "ExifImageWidth": 5616,
    }
    # the photo was resized to half: pixels per mm halve too
    intr = Intrinsics.from_exif(exif, 2808, 1872)
    assert intr.fx == pytest.approx(FF_FOCAL * FF_PX_PER_MM / 2, rel=1e-5)


def test_from_exif_35mm_only():
    intr = Intrinsics.from_exif({"FocalLengthIn35mmFilm": 26}, 4000, 3000)
    assert intr.fx == pytest.approx(26.0 * 5000.0 / 43.2666, rel=1e-5)
    # a FocalLength without pixel pitch or known model does not block it
    intr = Intrinsics.from_exif(
        {"FocalLength": 4.25, "FocalLengthIn35mmFilm": 26, "Model": "SM-G991B"}, 4000, 3000
    )
    assert intr.fx == pytest.approx(26.0 * 5000.0 / 43.2666, rel=1e-5)


def test_from_exif_known_model_only():
    exif = {"FocalLength": 8.8, "Model": "FC6310\x00 "}
    intr = Intrinsics.from_exif(exif, 5472, 3648)
    assert SENSOR_WIDTHS_MM["FC6310"] == 13.2
    assert intr.fx == pytest.approx(8.8 * 5472 / 13.2)
    assert intr.fy == intr.fx


@pytest.mark.parametrize(
    "exif",
    [
        {},
        {"FocalLength": 4.25},
        {"FocalLength": 4.25, "Model": "Some Unknown Phone"},
        {"FocalPlaneXResolution": 4000.0, "Model": "FC6310"},
        {"FocalLength": 0, "FocalLengthIn35mmFilm": 0, "Model": "FC6310"},
        {"FocalLength": (0, 0), "Model": "FC6310"},
    ],
)
def test_from_exif_nothing_usable_raises(exif):
    with pytest.raises(ValueError, match="focal length"):
        Intrinsics.from_exif(exif, 4000, 3000)


def test_from_exif_undefined_rational_focal_length_is_ignored():
    from PIL.TiffImagePlugin import IFDRational

    # Pillow reads an undefined rational (0/0) as IFDRational(0, 0) == nan.
    exif = {
        "FocalLength": IFDRational(0, 0),
        "FocalPlaneXResolution": FF_PX_PER_MM * 25.4,
        "FocalLengthIn35mmFilm": 26,
    }
    intr = Intrinsics.from_exif(exif, 4000, 3000)
    assert intr.fx == pytest.approx(26.0 * 5000.0 / 43.2666, rel=1e-5)


def test_from_dict_pixels_and_mm():
    d = {"width": 1632, "height": 1224, "fx": 1400.0, "fy": 1410.0, "cx": 810.0, "cy": 600.0,
         "dist": [0.1, -0.05, 0.001, 0.002, 0.01]}
    intr = Intrinsics.from_dict(d)
    assert (intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy) == (
        1632, 1224, 1400.0, 1410.0, 810.0, 600.0)
    assert intr.dist == (0.1, -0.05, 0.001, 0.002, 0.01)
    np.testing.assert_allclose(intr.K, [[1400, 0, 810], [0, 1410, 600], [0, 0, 1]])
    assert Intrinsics.from_dict(json.loads(json.dumps(intr.to_dict()))) == intr
    # defaults: fy = fx, principal point at the centre, no distortion
    intr = Intrinsics.from_dict({"width": 160, "height": 120, "fx": 100})
    assert (intr.fy, intr.cx, intr.cy, intr.dist) == (100.0, 79.5, 59.5, ())
    assert not intr.has_distortion
    np.testing.assert_array_equal(intr.dist_coeffs, np.zeros(5))
    # the contract's millimetre block
    mm = {"width": 1632, "height": 1224, "focal_length_mm": 3.92,
          "sensor_width_mm": 4.6, "sensor_height_mm": 3.52}
    intr = Intrinsics.from_dict(mm)
    assert intr.fx == pytest.approx(3.92 * 1632 / 4.6)
    assert intr.fy == pytest.approx(3.92 * 1224 / 3.52)
    assert (intr.cx, intr.cy) == (815.5, 611.5)
    with pytest.raises((KeyError, ValueError)):
        Intrinsics.from_dict({"width": 10, "height": 10, "focal_length_mm": 4.0})


def test_scaled_keeps_pixel_centre_convention():
    intr = Intrinsics(4000, 3000, 3000.0, 3010.0, 2001.3, 1497.8, (0.05, -0.01, 0, 0, 0))
    rng = np.random.default_rng(11)
    P = np.c_[rng.uniform(-2, 2, (50, 2)), rng.uniform(5, 20, 50)]
    for s in (0.5, 0.25, 2.0):
        small = intr.scaled(s)
        assert (small.width, small.height) == (int(4000 * s), int(3000 * s))
        assert small.dist == intr.dist
        np.testing.assert_allclose(small.project(P), (intr.project(P) + 0.5) * s - 0.5, atol=1e-9)
    assert intr.scaled(1.0) == intr
    # the first pixel's centre: (0 + 0.5) * 0.5 - 0.5 = -0.25
    half = Intrinsics(160, 120, 100.0, 100.0, 0.0, 0.0).scaled(0.5)
    assert (half.cx, half.cy, half.fx) == (-0.25, -0.25, 50.0)


def test_match_scale_reduces_to_the_working_width_and_never_enlarges():
    assert match_scale(2000, 500) == 0.25
    assert match_scale(1632, 1024) == 1024 / 1632
    assert match_scale(800, 1024) == 1.0 and match_scale(1024, 1024) == 1.0
    assert scaled_size(1632, 1224, match_scale(1632, 1024)) == (1024, 768)
    assert scaled_size(1500, 1000, 640 / 1500) == (640, 427)  # 426.67 rounds up
    assert scaled_size(10, 10, 0.01) == (1, 1)  # never empty


def test_pixel_centre_shift_known_answers():
    # Halving: reduced pixel 0 covers full pixels 0 and 1, so its centre is 0.5;
    # the left edge (-0.5) stays the left edge; reduced 1 covers full 2 and 3.
    np.testing.assert_array_equal(
        pixels_to_full(np.array([[0.0, 0.0], [-0.5, -0.5], [1.0, 3.0]]), 0.5),
        [[0.5, 0.5], [-0.5, -0.5], [2.5, 6.5]])
    # A quarter: reduced pixel 0 covers full pixels 0..3, centre 1.5.
    assert pixels_to_full(0.0, 0.25) == 1.5
    assert pixels_to_scaled(1.5, 0.25) == 0.0
    assert pixels_to_scaled(-0.5, 0.25) == -0.5
    # Inverse of each other; an array keeps its dtype (float32 keypoints).
    pts = np.array([[12.25, 700.5], [0.0, 3.0]], np.float32)
    back = pixels_to_scaled(pixels_to_full(pts, 0.6), 0.6)
    assert back.dtype == np.float32
    np.testing.assert_allclose(back, pts, atol=1e-4)


def test_pixel_shift_is_what_a_scaled_camera_sees():
    """A 3D point projects in the scaled camera where the shift puts its full-size pixel."""
    intr = Intrinsics(1632, 1224, 1300.0, 1300.0, 815.5, 611.5)
    rng = np.random.default_rng(4)
    P = np.c_[rng.uniform(-3, 3, (40, 2)), rng.uniform(5, 30, 40)]
    s = match_scale(intr.width, 1024)
    small = intr.scaled(s)
    np.testing.assert_allclose(small.project(P), pixels_to_scaled(intr.project(P), s), atol=1e-9)
    np.testing.assert_allclose(pixels_to_full(small.project(P), s), intr.project(P), atol=1e-9)


# ---------------------------------------------------------------------------
# Intrinsics: project / unproject
# ---------------------------------------------------------------------------


def _points(n=200, seed=0):
    rng = np.random.default_rng(seed)
    z = rng.uniform(2, 80, n)
    return np.c_[rng.uniform(-0.5, 0.5, n) * z, rng.uniform(-0.4, 0.4, n) * z, z]


def test_project_pinhole_known():
    intr = Intrinsics(160, 120, 100.0, 120.0, 79.5, 59.5)
    P = _points()
    uv = intr.project(P)
    np.testing.assert_allclose(uv[:, 0], 100.0 * P[:, 0] / P[:, 2] + 79.5, atol=1e-12)
    np.testing.assert_allclose(uv[:, 1], 120.0 * P[:, 1] / P[:, 2] + 59.5, atol=1e-12)
    # the optical axis projects to the principal point
    np.testing.assert_allclose(intr.project([[0, 0, 5.0]]), [[79.5, 59.5]])
    assert np.isnan(intr.project([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])).all()


@pytest.mark.parametrize(
    "dist",
    [(), (-0.12, 0.03, 0.0005, -0.0003, 0.0), (0.08, -0.02, -0.001, 0.0008, 0.005)],
)
def test_project_unproject_round_trip(dist):
    intr = Intrinsics(160, 120, 130.0, 128.0, 80.3, 58.9, dist)
    P = _points()
    uv = intr.project(P)
    back = intr.unproject(uv, P[:, 2])
    np.testing.assert_allclose(back, P, rtol=0, atol=1e-6 * P[:, 2:].max())
    rays = intr.normalized_rays(uv)
    np.testing.assert_allclose(rays[:, 2], 1.0)


@pytest.mark.parametrize(
    "dist",
    [(-0.12, 0.03, 0.0005, -0.0003, 0.0), (0.08, -0.02, -0.001, 0.0008, 0.005), (-0.2,)],
)
def test_distortion_matches_opencv(dist):
    intr = Intrinsics(160, 120, 130.0, 128.0, 80.3, 58.9, dist)
    assert intr.has_distortion
    P = _points(seed=2)
    ours = intr.project(P)
    cv, _ = cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), intr.K, intr.dist_coeffs)
    np.testing.assert_allclose(ours, cv.reshape(-1, 2), atol=1e-9)
