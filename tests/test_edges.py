"""Known-answer tests for :mod:`napari_imgreg.registration.stages.edges`.

Structure edges are checked against the analytic projection of a box; the
skyline detector against a drawn skyline; chamfer alignment against scenes
whose "photo" is rendered (or was generated) from a known pose under another
light, started from a pose a few degrees and metres off.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from napari_imgreg.camera import Intrinsics, Pose
from napari_imgreg.registration.stages.edges import (
    ALBEDO,
    CREASE,
    OCCLUDING,
    SKYLINE,
    EdgeParams,
    align_edges,
    canny_edges,
    chamfer_distances,
    detect_skyline,
    edge_agreement,
    photo_edges,
    render_edges,
)
from napari_imgreg.io.photos import load_photo
from napari_imgreg.render import render
from napari_imgreg.sample import load_truth, sample_scene
from napari_imgreg.scene import Scene

# ---------------------------------------------------------------------------
# scenes
# ---------------------------------------------------------------------------


def _box(lo, hi):
    """Corners (8, 3) and outward-wound triangles (12, 3) of an axis-aligned box."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    corners = np.array([[(hi if (i >> k) & 1 else lo)[k] for k in range(3)] for i in range(8)])
    quads = [(0, 4, 6, 2), (1, 3, 7, 5), (0, 1, 5, 4), (2, 6, 7, 3), (0, 2, 3, 1), (4, 5, 7, 6)]
    faces = [tri for a, b, c, d in quads for tri in ((a, b, c), (a, c, d))]
    return corners, np.array(faces)


def _steps_scene(coloured: bool = True) -> Scene:
    """Blocks and steps 8–45 m in front of the camera on a 120 m ground plane.

    Near and far blocks give parallax, so a step of the camera and a turn do
    not look alike: the pose is fully determined by the edges.
    """
    verts, faces, colours = [], [], []

    def add(v, f, colour):
        faces.append(f + sum(len(x) for x in verts))
        verts.append(v)
        colours.append(np.tile(colour, (len(v), 1)))

    n = 24  # a subdivided ground, like terrain
    gx, gy = np.meshgrid(np.linspace(-60, 60, n + 1), np.linspace(-20, 100, n + 1))
    ground = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    idx = np.arange(len(ground)).reshape(n + 1, n + 1)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    add(ground, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]), (110, 120, 80))
    blocks = [
        ((-9, 10, 0), (-5, 14, 3.0)), ((-2, 16, 0), (3, 19, 1.5)), ((5, 12, 0), (8, 15, 4.5)),
        ((-14, 25, 0), (-6, 30, 6.0)), ((2, 28, 0), (12, 33, 3.0)), ((4, 28, 0), (9, 33, 6.5)),
        ((-4, 40, 0), (4, 46, 9.0)), ((14, 20, 0), (18, 24, 2.0)), ((-20, 15, 0), (-16, 19, 2.5)),
    ]
    palette = [(180, 150, 120), (150, 160, 170), (200, 180, 140), (170, 130, 110), (160, 170, 150),
               (190, 160, 150), (140, 140, 160), (200, 170, 120), (150, 130, 100)]
    for (lo, hi), colour in zip(blocks, palette):
        add(*_box(lo, hi), colour)
    vertex_colors = np.concatenate(colours).astype(np.uint8) if coloured else None
    return Scene(np.concatenate(verts), np.concatenate(faces), vertex_colors=vertex_colors)


def _synthetic_photo(scene: Scene, intr: Intrinsics, pose: Pose) -> np.ndarray:
    """The scene under another light, with a bright graded sky, blur and noise."""
    mode = "color_shaded" if scene.vertex_colors is not None else "shaded"
    r = render(scene, intr, pose, mode=mode, light_direction=np.array([0.6, -0.3, 0.75]),
               ambient=0.45)
    h, w = r.shape
    rows = np.linspace(0.0, 1.0, h)[:, None, None]
    sky = (1 - 0.3 * rows) * np.array([120, 170, 235.0]) + 0.3 * rows * np.array([200, 215, 235.0])
    img = np.where(r.mask[..., None], r.rgb.astype(np.float64), sky)
    img = cv2.GaussianBlur(img, (0, 0), 0.7)
    img += np.random.default_rng(0).normal(0.0, 3.0, img.shape)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


STEPS_INTR = Intrinsics.from_fov(800, 600, 60.0)
STEPS_TRUTH = Pose.from_attitude(4.0, 6.0, 0.5, [0.5, -3.0, 1.7])


@pytest.fixture(scope="module")
def sample():
    folder = sample_scene("small")
    scene = Scene.load(folder / "outcrop.obj")
    scene.build_engine()
    return folder, scene


def _sample_photo(folder, name):
    return load_photo(folder / f"{name}.jpg").image, load_truth(folder / f"{name}.jpg")


def _offset(pose: Pose, d_trend: float, d_plunge: float, d_roll: float, step) -> Pose:
    trend, plunge, roll = pose.attitude
    return Pose.from_attitude(trend + d_trend, plunge + d_plunge, roll + d_roll,
                              pose.center + np.asarray(step, float))


def _check_point_error(pose: Pose, truth) -> float:
    """Median distance (px) of the check points from where the photo shows them."""
    proj = pose.project(truth.intrinsics, truth.check_xyz)
    return float(np.median(np.linalg.norm(proj - truth.check_pixels, axis=1)))


# ---------------------------------------------------------------------------
# render edges
# ---------------------------------------------------------------------------


def _distance_to_polygon(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Distance (N,) from points (N, 2) to the boundary of a closed polygon (M, 2)."""
    a = polygon
    b = np.roll(polygon, -1, axis=0)
    ab = b - a
    t = np.clip(np.einsum("nmk,mk->nm", points[:, None] - a[None], ab) / (ab * ab).sum(1), 0, 1)
    closest = a[None] + t[..., None] * ab[None]
    return np.linalg.norm(points[:, None] - closest, axis=2).min(axis=1)


def test_render_edges_box_silhouette_matches_projection():
    corners, faces = _box([-1.0, 9.0, -0.5], [1.5, 11.0, 1.2])
    scene = Scene(corners, faces)
    intr = Intrinsics(320, 240, 260.0, 262.0, 161.3, 118.6)
    pose = Pose.from_attitude(-25.0, 18.0, 3.0, [4.0, 2.0, 4.5])  # three faces in view
    r = render(scene, intr, pose)
    es = render_edges(r, border_px=0)
    hull = cv2.convexHull(pose.project(intr, corners).astype(np.float32)).reshape(-1, 2)

    sky = es.kind == SKYLINE  # everything around the box is empty
    assert sky.sum() > 0.8 * cv2.arcLength(hull, True)  # the whole outline
    assert not np.isin(es.kind, (OCCLUDING, ALBEDO)).any()  # grey, nothing behind
    d = _distance_to_polygon(es.points_px[sky], hull.astype(np.float64))
    assert d.max() <= 1.0  # the near-side pixel of the outline
    # Every outline point is lifted onto the box (near side of the jump).
    assert np.all(es.xyz[sky] >= corners.min(0) - 1e-3)
    assert np.all(es.xyz[sky] <= corners.max(0) + 1e-3)
    # The box's inner edges (between two visible faces) are creases, inside.
    crease = es.kind == CREASE
    assert crease.sum() > 20
    inside = cv2.pointPolygonTest
    assert all(inside(hull, (float(x), float(y)), True) > 1.0 for x, y in es.points_px[crease])
    # Their 3D points lie on box edges: on two of the three bounding planes.
    planes = np.stack([corners.min(0), corners.max(0)], axis=1)  # (3, 2)
    on_plane = np.isclose(es.xyz[crease][:, :, None], planes, atol=0.05).any(axis=2).sum(axis=1)
    assert np.mean(on_plane >= 2) > 0.9


def test_render_edges_grazing_ground_has_no_false_contours():
    # A flat ground seen from eye height: depth grows fast from row to row
    # near the horizon, but nothing occludes anything.
    v = np.array([[-200.0, 1, 0], [200.0, 1, 0], [200.0, 300, 0], [-200.0, 300, 0]])
    scene = Scene(v, np.array([[0, 1, 2], [0, 2, 3]]))
    intr = Intrinsics.from_fov(320, 240, 60.0)
    r = render(scene, intr, Pose.from_attitude(0.0, 10.0, 0.0, [0.0, 0.0, 1.6]))
    es = render_edges(r)
    assert (es.kind == OCCLUDING).sum() == 0
    assert (es.kind == CREASE).sum() == 0
    # The far edge of the ground is its skyline, one point per column.
    sky = es.kind == SKYLINE
    assert abs(sky.sum() - (320 - 4)) <= 4


def test_render_edges_thinning_keeps_the_skyline():
    scene = _steps_scene()
    r = render(scene, STEPS_INTR, STEPS_TRUTH, scale=0.5)
    full = render_edges(r)
    few = render_edges(r, max_points=600)
    assert len(few) <= 600
    # Skyline and occluding contours keep up to half of the budget, both
    # thinned alike; creases and colour edges share the rest.
    contours = ("skyline", "occluding")
    n_full = sum(full.counts()[k] for k in contours)
    n_few = sum(few.counts()[k] for k in contours)
    assert n_few == min(n_full, 300)
    share = full.counts()["skyline"] / n_full
    assert few.counts()["skyline"] / n_few == pytest.approx(share, abs=0.02)


# ---------------------------------------------------------------------------
# photo edges
# ---------------------------------------------------------------------------


def _landscape(h=240, w=320, brightness=1.0):
    """Graded blue sky over textured ground; returns the image and the true skyline."""
    rng = np.random.default_rng(7)
    cols = np.arange(w)
    skyline = np.round(80 + 25 * np.sin(cols / 37.0) + 10 * np.cos(cols / 11.0)).astype(int)
    rows = np.arange(h)[:, None]
    ground = cv2.GaussianBlur(rng.normal(120, 40, (h, w)).astype(np.float32), (0, 0), 1.5)
    img = np.empty((h, w, 3), np.float32)
    img[..., 0] = ground * 1.0
    img[..., 1] = ground * 0.85
    img[..., 2] = ground * 0.6
    sky = rows < skyline[None, :]
    sky_colour = np.array([130, 175, 235], np.float32) + rows[..., None] * 0.1
    img = np.where(sky[..., None], sky_colour, img) * brightness
    return np.clip(img, 0, 255).astype(np.uint8), skyline


def test_detect_skyline_finds_the_drawn_one():
    img, truth = _landscape()
    skyline, sky = detect_skyline(img)
    err = np.abs(skyline - truth)
    assert np.isfinite(skyline).all()
    assert np.mean(err <= 1) > 0.95
    cols = np.arange(len(truth))
    assert sky[truth - 2, cols].all() and not sky[truth, cols].any()


def test_detect_skyline_reports_none_without_sky():
    img, _ = _landscape()
    rock = img.copy()
    rock[:] = img[-1:, :, :]  # ground colours from top to bottom
    rock = cv2.add(rock, np.random.default_rng(1).integers(0, 40, rock.shape, dtype=np.uint8))
    skyline, sky = detect_skyline(rock)
    assert np.isnan(skyline).all() and not sky.any()


def test_canny_thresholds_follow_the_exposure():
    bright, _ = _landscape()
    dark, _ = _landscape(brightness=0.35)
    n_bright = canny_edges(cv2.cvtColor(bright, cv2.COLOR_RGB2GRAY))[0].sum()
    n_dark = canny_edges(cv2.cvtColor(dark, cv2.COLOR_RGB2GRAY))[0].sum()
    assert n_dark == pytest.approx(n_bright, rel=0.25)


def test_oriented_chamfer_ignores_crossing_edges():
    img = np.zeros((100, 100, 3), np.uint8)
    img[:, 50:] = 200  # one vertical edge near column 50
    pe = photo_edges(img, skyline=False)
    at_edge = np.array([[50.0, 50.0], [49.5, 50.0]])
    kinds = np.array([CREASE, CREASE], np.uint8)
    along = chamfer_distances(pe, at_edge, kinds, np.zeros(2))  # normal along x: vertical edge
    across = chamfer_distances(pe, at_edge, kinds, np.full(2, np.pi / 2), truncate_px=30.0)
    assert along.max() <= 1.0
    assert across.min() == 30.0  # no horizontal edge anywhere


def test_photo_edges_lines_option_adds_long_segments():
    img = np.full((120, 160, 3), 90, np.uint8)
    cv2.line(img, (10, 100), (150, 20), (200, 200, 200), 3)
    pe = photo_edges(img, skyline=False, lines=True)
    assert pe.edges.sum() > 100


# ---------------------------------------------------------------------------
# alignment
# ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def steps():
    scene = _steps_scene()
    scene.build_engine()
    return scene, _synthetic_photo(scene, STEPS_INTR, STEPS_TRUTH)


def test_align_edges_recovers_a_rendered_pose(steps):
    scene, photo = steps
    start = _offset(STEPS_TRUTH, 3.0, -1.5, 0.0, [1.4, 1.4, 0.0])
    res = align_edges(scene, photo, STEPS_INTR, start)
    assert res.ok, res.reason
    assert res.pose.rotation_error_deg(STEPS_TRUTH) < 0.3  # measured: 0.022°
    assert np.linalg.norm(res.pose.center - STEPS_TRUTH.center) < 0.5  # measured: 0.013 m
    assert res.score < 0.5 * res.start_score
    assert res.inlier_fraction > 0.5 and res.agreement > 0.4  # measured: 0.68, 0.59
    # The 2D–3D pairs agree with the true pose.
    corr = res.correspondences
    assert len(corr) > 200
    err = np.linalg.norm(STEPS_TRUTH.project(STEPS_INTR, corr.xyz) - corr.photo_points, axis=1)
    assert np.median(err) < 1.5
    assert [h["stage"] for h in res.history][:2] == ["rotation search", "rotation"]


def test_align_edges_stops_when_cancelled(steps):
    scene, photo = steps
    res = align_edges(scene, photo, STEPS_INTR, STEPS_TRUTH, cancelled=lambda: True)
    assert not res.ok and res.reason == "cancelled"
    assert res.pose is STEPS_TRUTH


def test_align_edges_takes_a_renderer_and_its_settings(steps):
    """A custom RenderFn sees the photo's camera (widened for the first search)
    at the levels' scales; the settings come from EdgeParams."""
    scene, photo = steps
    calls = []

    def render_fn(intrinsics, pose, scale):
        calls.append((intrinsics.width, scale))
        return render(scene, intrinsics, pose, scale=scale)

    params = EdgeParams(levels=(200,), search_rotation_deg=(2.0, 2.0, 0.0), keep=1, max_rounds=1)
    res = align_edges(scene, photo, STEPS_INTR, STEPS_TRUTH, params, search_position_m=None,
                      render_fn=render_fn)
    assert res.reason != "cancelled" and res.history[0]["width"] == 200
    assert {scale for _, scale in calls} == {0.25}
    assert calls[0][0] > STEPS_INTR.width and calls[-1][0] == STEPS_INTR.width


def test_align_edges_keeps_the_keywords_and_the_renderer_of_version_0_1(steps):
    scene, photo = steps
    params = EdgeParams(levels=(200,), search_rotation_deg=(2.0, 2.0, 0.0), keep=1, max_rounds=1,
                        kind_weights={"albedo": 0.0})
    new = align_edges(scene, photo, STEPS_INTR, STEPS_TRUTH, params, search_position_m=None)
    with pytest.warns(DeprecationWarning) as warned:
        old = align_edges(scene, photo, STEPS_INTR, STEPS_TRUTH, levels=(200,),
                          search_rotation_deg=(2.0, 2.0, 0.0), keep=1, max_rounds=1,
                          weights={ALBEDO: 0.0}, search_position_m=None,
                          render_fn=lambda s, intr, pose, scale: render(s, intr, pose, scale=scale))
    messages = " ".join(str(w.message) for w in warned)
    assert "EdgeParams" in messages and "render_fn(scene, intrinsics, pose, scale)" in messages
    assert np.array_equal(old.pose.R, new.pose.R) and np.array_equal(old.pose.t, new.pose.t)
    assert old.score == new.score
    with pytest.raises(TypeError, match="levelz"):
        align_edges(scene, photo, STEPS_INTR, STEPS_TRUTH, levelz=(200,))


@pytest.mark.parametrize("kwargs, words", [
    ({"levels": ()}, "levels"),
    ({"levels": (32, 768)}, "levels"),
    ({"levels": (320.0,)}, "integers"),
    ({"search_rotation_deg": (12.0, 6.0)}, "3 numbers"),
    ({"search_rotation_deg": (12.0, 60.0, 4.0)}, "search_rotation_deg"),
    ({"search_step_deg": 0.0}, "search_step_deg"),
    ({"keep": 0}, "keep"),
    ({"min_inlier_fraction": 1.5}, "min_inlier_fraction"),
    ({"oriented": True, "max_points": 10}, "max_points"),
    ({"kind_weights": {"sky": 1.0}}, "sky"),
    ({"kind_weights": {"albedo": -1.0}}, "albedo"),
])
def test_edge_params_reject_values_out_of_range(kwargs, words):
    with pytest.raises(ValueError, match=words):
        EdgeParams(**kwargs)


def test_edge_params_lists_become_tuples_and_weights_map_to_kinds():
    p = EdgeParams(levels=[256, 512], search_rotation_deg=[10, 5, 3],
                   kind_weights={"skyline": 3, "albedo": 0})
    assert p.levels == (256, 512) and p.search_rotation_deg == (10.0, 5.0, 3.0)
    assert p.weights_by_kind() == {SKYLINE: 3.0, ALBEDO: 0.0}
    assert EdgeParams.from_dict(p.to_dict()) == p
    assert EdgeParams().weights_by_kind() == {}  # the defaults of DEFAULT_KIND_WEIGHTS
    q = EdgeParams()
    q.kind_weights["crease"] = 1.0
    assert EdgeParams().kind_weights == {}  # no shared default dict
    with pytest.raises(KeyError, match="levelz"):
        EdgeParams.from_dict({"levelz": [256]})


def test_align_edges_fails_gracefully_on_a_blank_photo(steps):
    scene, _ = steps
    blank = np.full((600, 800, 3), 128, np.uint8)
    res = align_edges(scene, blank, STEPS_INTR, STEPS_TRUTH)
    assert not res.ok and res.reason


def test_align_edges_on_a_sample_photo(sample):
    # A generated photo: another sun, wet patches, clouds, camera noise.
    folder, scene = sample
    photo, truth = _sample_photo(folder, "IMG_0002")
    start = _offset(truth.pose, -3.0, 1.5, 1.0, [0.0, 0.0, 0.0])
    assert _check_point_error(start, truth) > 40
    res = align_edges(scene, photo, truth.intrinsics, start)
    assert res.ok, res.reason
    assert _check_point_error(res.pose, truth) < 3.0  # measured: 0.45 px (1024 px wide)
    assert res.pose.rotation_error_deg(truth.pose) < 0.3  # measured: 0.02°


def test_align_edges_untextured_model(sample):
    # No texture: the render is shaded grey, so only geometry is left to
    # match: the skyline, occluding contours and creases.
    folder, textured = sample
    scene = Scene(textured.vertices, textured.faces)
    photo, truth = _sample_photo(folder, "IMG_0001")
    start = _offset(truth.pose, 3.0, -1.5, 1.0, [0.0, 0.0, 0.0])
    res = align_edges(scene, photo, truth.intrinsics, start)
    assert res.ok, res.reason
    assert _check_point_error(res.pose, truth) < 4.0  # measured: 2.1 px (from 50 px)
    assert res.correspondences.kind.tolist().count(ALBEDO) == 0


def test_edge_score_separates_right_from_wrong_poses(sample):
    folder, scene = sample
    photo, truth = _sample_photo(folder, "IMG_0003")
    right = edge_agreement(scene, photo, truth.pose, truth.intrinsics)
    wrong = edge_agreement(scene, photo, _offset(truth.pose, 3.0, 1.0, 0.0, [0, 0, 0]),
                           truth.intrinsics)
    assert right.score > 0.35  # measured: 0.60 (fraction 0.68, chance 0.19)
    assert abs(wrong.score) < 0.1  # measured: -0.04 (fraction 0.12, chance 0.15)
    assert right.fraction > 2 * right.chance
    # A render made elsewhere can be scored as it is.
    r = render(scene, truth.intrinsics, truth.pose, scale=0.5)
    assert edge_agreement(r, photo).score == pytest.approx(
        edge_agreement(scene, photo, truth.pose, truth.intrinsics, width=512).score, abs=1e-9)
    assert math.isfinite(right.chance)
