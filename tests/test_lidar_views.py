"""Seed 003's lidar views and HOG features against known answers.

Small synthetic data only (the whole module runs in a few seconds): a
textured surface seen as an intensity render and as a photo under another
radiometry, shifted and turned; a cliff face and a ledge sampled as a point
cloud with 5 mm noise and clutter, rendered analytically from a camera.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial import cKDTree

from napari_imgreg.camera import Intrinsics, Pose
from napari_imgreg.registration import hog
from napari_imgreg.registration.lidar_views import (
    LidarViewParams,
    canny_edges,
    gradient_magnitude,
    lift_to_3d,
    line_view,
    lsd_mask,
    lsd_segments,
    match_view_pair,
    plane_mask,
    seed003_correspondences,
    segment_planes,
    wireframe_view,
)
from napari_imgreg.render import RenderResult
from napari_imgreg.validate import FieldValueError

SIDE = 320   # render / photo side, pixels


# ------------------------------------------------------------ textured surface
@pytest.fixture(scope="module")
def texture() -> np.ndarray:
    """A rock-like reflectance in [0, 1] on a canvas larger than the views:
    multi-scale noise, bedding bands and a few dark fractures."""
    rng = np.random.default_rng(3)
    n = SIDE + 80
    t = np.zeros((n, n), np.float32)
    for sigma, weight in ((1.5, 0.5), (4.0, 1.0), (10.0, 1.0)):
        layer = ndimage.gaussian_filter(rng.standard_normal((n, n)).astype(np.float32), sigma)
        t += weight * layer / layer.std()
    rows = np.arange(n, dtype=np.float32)[:, None]
    t += 1.5 * np.sin(rows / 9.0 + 0.8 * ndimage.gaussian_filter(
        rng.standard_normal((n, n)).astype(np.float32), 20) * 20)
    img = (t - t.min()) / (t.max() - t.min())
    for _ in range(12):                              # fractures
        x0, y0, x1, y1 = rng.uniform(0, n, 4)
        cv2.line(img, (int(x0), int(y0)), (int(x1), int(y1)), 0.05, 2, cv2.LINE_AA)
    return img


def _photo_of(texture: np.ndarray, M: np.ndarray, seed: int = 1) -> np.ndarray:
    """The texture warped by ``M`` (texture → photo pixels) under another
    radiometry: gamma 0.7, another gain and offset, 2-level sensor noise."""
    warped = cv2.warpAffine(texture, M, (SIDE, SIDE), flags=cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_REFLECT)
    rng = np.random.default_rng(seed)
    photo = 30.0 + 180.0 * warped ** 0.7 + rng.normal(0, 2.0, warped.shape)
    return np.clip(photo, 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def render_gradient(texture) -> np.ndarray:
    intensity = (texture[:SIDE, :SIDE] * 255).astype(np.uint8)   # the reflectivity view
    return gradient_magnitude(intensity, 1.0)


def _matches(render_gradient, photo):
    photo_gradient = gradient_magnitude(photo, 1.0)
    # 1 000 keypoints a side: plenty at 320 px, and half the matching time.
    return match_view_pair(render_gradient, photo_gradient,
                           params=LidarViewParams(max_keypoints=1000))


def test_hog_matching_finds_a_known_shift(texture, render_gradient):
    shift = np.array([6.4, -3.7])
    M = np.array([[1, 0, shift[0]], [0, 1, shift[1]]], np.float64)
    m = _matches(render_gradient, _photo_of(texture, M))
    assert len(m) >= 40
    d = m.points_b - m.points_a
    good = np.linalg.norm(d - shift, axis=1) < 1.5
    assert good.mean() >= 0.6                      # most HOG matches are right
    assert np.allclose(np.median(d[good], axis=0), shift, atol=0.25)


def test_hog_matching_finds_a_known_rotation(texture, render_gradient):
    angle_deg, centre = 6.0, (SIDE / 2, SIDE / 2)
    M = cv2.getRotationMatrix2D(centre, angle_deg, 1.0)
    M[:, 2] += (3.2, 2.1)
    m = _matches(render_gradient, _photo_of(texture, M, seed=2))
    assert len(m) >= 30
    A, inl = cv2.estimateAffinePartial2D(m.points_a, m.points_b, method=cv2.RANSAC,
                                         ransacReprojThreshold=1.5)
    assert inl.mean() >= 0.5
    corners = np.array([[0, 0, 1], [SIDE, 0, 1], [0, SIDE, 1], [SIDE, SIDE, 1]], float)
    assert np.abs(corners @ A.T - corners @ M.T).max() < 0.8   # pixels at the corners
    assert np.degrees(np.arctan2(A[0, 1], A[0, 0])) == pytest.approx(angle_deg, abs=0.2)


def test_vectorised_hog_equals_skimage():
    from skimage.feature import hog as sk_hog

    patches = np.random.default_rng(0).random((4, 32, 32)).astype(np.float32)
    ours = hog.hog_of_patches(patches, orientations=9, cell_px=8, block_cells=2)
    theirs = np.stack([sk_hog(q, orientations=9, pixels_per_cell=(8, 8), cells_per_block=(2, 2),
                              block_norm="L2-Hys") for q in patches])
    assert ours.shape == theirs.shape == (4, 324)
    assert np.abs(ours - theirs).max() < 0.01


def test_oriented_patch_follows_the_keypoint_turn():
    """A patch described at angle θ in an image turned by θ equals the upright
    patch of the original (the seed's orientation normalisation)."""
    rng = np.random.default_rng(5)
    img = ndimage.gaussian_filter(rng.random((200, 200)).astype(np.float32), 3)
    M = cv2.getRotationMatrix2D((99.5, 99.5), 30.0, 1.0)
    turned = cv2.warpAffine(img, M, (200, 200), flags=cv2.INTER_CUBIC)
    a = hog.oriented_patches(img, np.array([[99.5, 99.5]]), np.array([4.0]), np.array([0.0]),
                             scales=(8.0,))
    b = hog.oriented_patches(turned, np.array([[99.5, 99.5]]), np.array([4.0]),
                             np.array([30.0]), scales=(8.0,))
    assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.99


def test_match_hog_ratio_and_mutual_check():
    rng = np.random.default_rng(1)
    a = rng.standard_normal((300, 64)).astype(np.float32)
    perm = rng.permutation(300)
    b = a[perm] + rng.normal(0, 0.05, a.shape).astype(np.float32)
    b[0] = b[1] + 1e-3                           # two near-identical: ambiguous, rejected
    pairs = hog.match_hog(a, b, ratio=0.8)
    truth = {int(perm[j]): j for j in range(300)}
    assert all(truth[i] == j for i, j in pairs)
    assert len(pairs) >= 297 and perm[1] not in pairs[:, 0]
    assert hog.match_hog(a[:0], b).shape == (0, 2)


# --------------------------------------------------------------- photo side
def test_gradient_magnitude_is_contrast_invariant_and_ignores_the_mask_border(texture):
    img = texture[:SIDE, :SIDE]
    a = gradient_magnitude((40 + 200 * img).astype(np.float32) / 255.0, 1.0)
    b = gradient_magnitude((10 + 60 * img).astype(np.float32) / 255.0, 1.0)
    assert np.abs(a.astype(int) - b.astype(int)).max() <= 2
    mask = np.zeros((SIDE, SIDE), bool)
    mask[:, : SIDE // 2] = True
    flat_in_mask = np.where(mask, 0.5, 0.0).astype(np.float32)   # a hard edge at the mask
    assert gradient_magnitude(flat_in_mask, 1.0, mask=mask).max() == 0


def test_lsd_mask_covers_a_drawn_line():
    rng = np.random.default_rng(2)
    img = np.clip(rng.normal(120, 6, (240, 320)), 0, 255).astype(np.uint8)
    cv2.line(img, (30, 200), (290, 60), 230, 3)
    assert len(lsd_segments(img, 15)) >= 1
    mask = lsd_mask(img, radius_px=5.0, min_length_px=15.0)
    line = np.zeros_like(img)
    cv2.line(line, (40, 195), (280, 65), 1, 1)
    assert mask[line > 0].mean() >= 0.98
    assert mask.mean() < 0.1                     # and not the noise around it
    edges = canny_edges(img)
    assert edges[line > 0].sum() == 0 or edges.sum() > 0
    assert edges.sum() > 400                     # both sides of the 3 px line


def test_params_ranges():
    p = LidarViewParams()
    assert LidarViewParams.from_dict(p.to_dict()) == p
    with pytest.raises(FieldValueError):
        LidarViewParams(plane_distance_m=0.0)
    with pytest.raises(FieldValueError):
        LidarViewParams(hog_scales=(4.0, 100.0))
    with pytest.raises(ValueError):
        LidarViewParams(hog_patch_px=30, hog_cell_px=8)
    with pytest.raises(KeyError):
        LidarViewParams.from_dict({"plane_dist": 1.0})


# ----------------------------------------------------- cliff + ledge cloud
CLIFF_X, CLIFF_Z = (-6.0, 6.0), (2.0, 9.0)     # face y = 0, normal −y (toward the camera)
LEDGE_Y = (-4.0, 0.0)                          # ledge z = 2, normal +z


@pytest.fixture(scope="module")
def cliff_cloud():
    rng = np.random.default_rng(7)
    step = 0.06
    xs = np.arange(CLIFF_X[0], CLIFF_X[1] + 1e-9, step)
    zs = np.arange(CLIFF_Z[0], CLIFF_Z[1] + 1e-9, step)
    ys = np.arange(LEDGE_Y[0], LEDGE_Y[1], step)
    X, Z = np.meshgrid(xs, zs)
    cliff = np.c_[X.ravel(), np.zeros(X.size), Z.ravel()]
    X, Y = np.meshgrid(xs, ys)
    ledge = np.c_[X.ravel(), Y.ravel(), np.full(X.size, 2.0)]
    bush = rng.normal([3.0, -2.0, 2.8], 0.35, (1500, 3))          # vegetation on the ledge
    pts = np.vstack([cliff, ledge, bush])
    pts = pts + rng.normal(0, 0.005, pts.shape)                      # 5 mm range noise
    truth = np.r_[np.zeros(len(cliff), int), np.ones(len(ledge), int), np.full(len(bush), -1)]
    seg = segment_planes(pts, params=LidarViewParams(plane_distance_m=0.03))
    return pts, truth, seg


def test_plane_segmentation_recovers_cliff_and_ledge(cliff_cloud):
    pts, truth, seg = cliff_cloud
    assert len(seg) == 2
    expected = {0: np.array([0.0, -1.0, 0.0]), 1: np.array([0.0, 0.0, 1.0])}
    for k in range(2):
        # Which true plane this one is, by its points.
        true = np.bincount(truth[seg.labels == k] + 1).argmax() - 1
        n = seg.normals[k] * np.sign(seg.normals[k] @ expected[true])
        assert np.degrees(np.arccos(min(1.0, n @ expected[true]))) < 1.0
        away = (truth == true) & (np.abs(pts[:, 1]) + np.abs(pts[:, 2] - 2.0) > 0.3)
        assert (seg.labels[away] == k).mean() > 0.97
        assert seg.rms_m[k] < 0.01
    assert (seg.labels[truth == -1] >= 0).mean() < 0.2              # the bush is not a plane
    offsets = seg.offsets + np.einsum("ij,ij->i", seg.normals, seg.centroids)
    assert np.allclose(offsets, 0.0, atol=1e-9)


def _look_at(centre, target) -> Pose:
    z = np.asarray(target, float) - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return Pose.from_center(np.stack([x, y, z]), np.asarray(centre, float))


def _cast(intr: Intrinsics, pose: Pose, cloud: np.ndarray, texture: np.ndarray | None = None
          ) -> tuple[RenderResult, np.ndarray]:
    """The cliff and the ledge ray-cast analytically; each pixel sees the nearest
    cloud point (as a splat render's ``face_id``) and, with a texture, the
    surface's reflectance (cliff: texture at (x, z), ledge at (x, y), 25 px/m).

    Returns the render (reflectance × 255 as its intensity) and the
    reflectance image in [0, 1] (NaN where nothing is hit).
    """
    w, h = intr.width, intr.height
    cols, rows = np.meshgrid(np.arange(w), np.arange(h))
    origin, d = pose.rays(intr, np.c_[cols.ravel(), rows.ravel()])
    with np.errstate(divide="ignore", invalid="ignore"):
        t_cliff = -origin[1] / d[:, 1]
        t_ledge = (2.0 - origin[2]) / d[:, 2]
    hit_c = origin + t_cliff[:, None] * d
    hit_l = origin + t_ledge[:, None] * d
    ok_c = (t_cliff > 0) & (hit_c[:, 0] >= CLIFF_X[0]) & (hit_c[:, 0] <= CLIFF_X[1]) \
        & (hit_c[:, 2] >= CLIFF_Z[0]) & (hit_c[:, 2] <= CLIFF_Z[1])
    ok_l = (t_ledge > 0) & (hit_l[:, 0] >= CLIFF_X[0]) & (hit_l[:, 0] <= CLIFF_X[1]) \
        & (hit_l[:, 1] >= LEDGE_Y[0]) & (hit_l[:, 1] <= LEDGE_Y[1])
    t = np.where(ok_c, t_cliff, np.inf)
    on_ledge = ok_l & (t_ledge < t)
    t = np.where(on_ledge, t_ledge, t)
    mask = np.isfinite(t)
    xyz = np.full((h * w, 3), np.nan)
    xyz[mask] = origin + t[mask, None] * d[mask]
    face = np.full(h * w, -1, np.int32)
    face[mask] = cKDTree(cloud).query(xyz[mask])[1]
    depth = np.full(h * w, np.nan)
    depth[mask] = pose.transform(xyz[mask])[:, 2]
    refl = np.full(h * w, np.nan)
    if texture is not None:
        u = (xyz[mask, 0] - CLIFF_X[0]) * 25.0
        v = np.where(on_ledge[mask], 180.0 + (xyz[mask, 1] - LEDGE_Y[0]) * 25.0,
                     (CLIFF_Z[1] - xyz[mask, 2]) * 25.0)
        refl[mask] = ndimage.map_coordinates(texture, [v, u], order=1, mode="nearest")
    grey = np.where(mask, np.nan_to_num(refl) * 255.0, 0).astype(np.uint8).reshape(h, w)
    render = RenderResult(
        rgb=np.repeat(grey[..., None], 3, axis=2), xyz=xyz.reshape(h, w, 3).astype(np.float32),
        depth=depth.reshape(h, w).astype(np.float32), normal=np.zeros((h, w, 3), np.float32),
        face_id=face.reshape(h, w), mask=mask.reshape(h, w), intrinsics=intr,
        cam_from_world=pose)
    return render, refl.reshape(h, w)


@pytest.fixture(scope="module")
def cliff_render(cliff_cloud):
    intr = Intrinsics(320, 240, 260.0, 260.0, 159.5, 119.5)
    pose = _look_at(np.array([0.5, -14.0, 7.0]), np.array([0.0, 0.0, 3.5]))
    return _cast(intr, pose, cliff_cloud[0])[0]


def test_wireframe_puts_the_crease_where_it_projects(cliff_cloud, cliff_render):
    seg = cliff_cloud[2]
    view = wireframe_view(cliff_render, seg, LidarViewParams(plane_distance_m=0.03))
    assert len(view.intersections) == 1
    _, _, ends = view.intersections[0]
    assert np.abs(ends[:, 1]).max() < 0.03 and np.abs(ends[:, 2] - 2.0).max() < 0.03
    # The crease y = 0, z = 2 projected through the render's camera.
    xs = np.linspace(-6.0, 6.0, 480)
    crease = cliff_render.cam_from_world.project(cliff_render.intrinsics,
                                                 np.c_[xs, np.zeros_like(xs), np.full_like(xs, 2)])
    inner = np.abs(xs) <= 5.5        # away from the face's side edges, which meet it
    ys, xs_px = np.nonzero(view.lines)
    line_px = np.c_[xs_px, ys].astype(float)
    # Distance of each line pixel to the projected crease (dense samples).
    d_line, nearest = cKDTree(crease).query(line_px)
    near = (d_line < 4.0) & inner[nearest]
    assert np.median(d_line[near]) <= 0.6 and d_line[near].max() <= 1.0
    crease = crease[inner]
    d_cover, _ = cKDTree(line_px).query(crease)
    assert (d_cover <= 1.0).mean() >= 0.97                     # the whole crease is drawn
    length = np.linalg.norm(crease[-1] - crease[0])
    assert near.sum() <= 1.2 * length                          # once, not twice
    # The ledge's front edge and the cliff's top are drawn too.
    front = cliff_render.cam_from_world.project(cliff_render.intrinsics,
                                                np.c_[np.linspace(-5, 5, 50), np.full(50, -4.0),
                                                      np.full(50, 2.0)])
    assert (cKDTree(line_px).query(front)[0] <= 1.5).mean() >= 0.9
    # Render keypoints may sit on both planes.
    on = plane_mask(view.plane_labels, 2.0)
    assert on[cliff_render.mask].mean() > 0.95


def test_reflectivity_path_recovers_the_camera_by_dlt(texture, cliff_cloud):
    """Seed 003's own path: reflectivity render from a wrong prior (0.7 m, ~2° and
    15 % in focal length off), photo from the true camera under another
    radiometry; gradient images, LSD and plane masks, HOG matches lifted
    through the render's xyz, six-point DLT + RANSAC."""
    from napari_imgreg.registration.resection import dlt_ransac

    cloud, _, seg = cliff_cloud
    true_intr = Intrinsics(400, 300, 350.0, 350.0, 199.5, 149.5)
    true_pose = _look_at(np.array([1.0, -15.0, 6.5]), np.array([0.0, 0.0, 4.0]))
    prior = _look_at(np.array([1.5, -15.4, 6.8]), np.array([0.4, 0.0, 4.3]))
    render, _ = _cast(Intrinsics(400, 300, 300.0, 300.0, 199.5, 149.5), prior, cloud, texture)
    _, refl = _cast(true_intr, true_pose, cloud, texture)
    shade = np.where(np.isnan(refl), 0.0, 0.8)                    # the photo's sun and sky
    rng = np.random.default_rng(4)
    photo = np.where(np.isnan(refl), 210.0,
                     25 + 200 * np.clip(np.nan_to_num(refl) * shade, 0, 1) ** 0.7)
    photo = np.clip(photo + rng.normal(0, 2.0, photo.shape), 0, 255).astype(np.uint8)
    p = LidarViewParams(plane_distance_m=0.03)
    rock = ~np.isnan(refl)                                         # the sky mask a photo gets
    c = seed003_correspondences(photo, render, seg, p, photo_mask=rock)
    assert c.counts["reflectivity_lifted"] >= 40 and len(c) == c.points_3d.shape[0]
    assert set(c.source) <= {"reflectivity", "wireframe"}
    r = dlt_ransac(c.points_3d, c.points_2d, threshold_px=3.0)
    assert r.ok and r.n_inliers >= 30
    assert r.fx == pytest.approx(350.0, rel=0.01)
    check = np.c_[rng.uniform(-5, 5, 100), np.zeros(100), rng.uniform(2.5, 8.5, 100)]
    solved = Intrinsics(400, 300, r.fx, r.fy, r.cx, r.cy)
    err = np.linalg.norm(r.pose.project(solved, check) - true_pose.project(true_intr, check), axis=1)
    assert np.median(err) < 0.5                                    # pixels


def test_line_view_and_lift_to_3d(cliff_render):
    lines = np.zeros((40, 40), bool)
    lines[20, 5:35] = True
    img = line_view(lines, 1.0)
    assert img.max() == 255 and img[20, 20] == 255 and img[23, 20] < img[21, 20] < 255
    assert np.array_equal(line_view(lines, 0.0) > 0, lines)
    # A pixel on the cliff lifts to the point the render saw there; one off the
    # image or on the ledge's front edge (a depth jump to the sky) does not.
    r = cliff_render
    ys, xs = np.nonzero(r.mask)
    centre = np.array([[xs.mean(), ys.min() + 20.0]])
    X, ok = lift_to_3d(r, np.vstack([centre, [[-5.0, 10.0]]]))
    assert ok.tolist() == [True, False]
    assert np.allclose(X[0], r.xyz[int(centre[0, 1]), int(np.rint(centre[0, 0]))])
    assert abs(X[0, 1]) < 1e-4                                     # on the face y = 0
    bottom = np.array([[xs.mean(), ys[xs == int(xs.mean())].max()]])
    assert not lift_to_3d(r, bottom)[1][0]


def test_degenerate_inputs_give_empty_results_not_errors():
    flat = np.zeros((64, 64), np.uint8)
    assert len(match_view_pair(flat, flat)) == 0
    assert gradient_magnitude(flat, 1.0).max() == 0 and not lsd_mask(flat).any()
    assert len(segment_planes(np.random.default_rng(0).random((10, 3)))) == 0
    with pytest.raises(ValueError, match="non-finite"):
        segment_planes(np.array([[0.0, 0.0, np.nan]] * 5))


def test_line_segments_fall_back_to_hough_without_lsd(monkeypatch):
    """Where an OpenCV build lacks LSD, scikit-image's probabilistic Hough stands in."""
    import napari_imgreg.registration.lidar_views as lv

    img = np.full((120, 160), 90, np.uint8)
    cv2.line(img, (10, 100), (150, 30), 220, 3)
    monkeypatch.setattr(lv, "line_segment_backend", lambda: "skimage-hough")
    segs = lv.lsd_segments(img, 15.0)
    assert len(segs) >= 1
    line = np.zeros_like(img)
    cv2.line(line, (20, 95), (140, 35), 1, 1)
    assert lv.lsd_mask(img, 5.0, 15.0)[line > 0].mean() >= 0.95
