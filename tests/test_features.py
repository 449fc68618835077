"""Keypoints, matching and geometric verification (features.py) with known warps."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
from skimage import data

from napari_imgreg.registration import features as F
from napari_imgreg.camera import Intrinsics, Pose
from napari_imgreg.registration.features import (
    PRESETS,
    FeatureParams,
    available,
    detect_and_describe,
    match_features,
    preset,
    verify_geometry,
)
from napari_imgreg.registration.filters import to_gray


def _similarity(w: int, h: int, angle_deg=10.0, scale=0.9, shift=(12.0, -7.0)) -> np.ndarray:
    """Homography: rotate by ``angle_deg`` and scale about the centre, then shift."""
    c = np.array([w / 2.0, h / 2.0])
    a = np.deg2rad(angle_deg)
    A = scale * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    H = np.eye(3)
    H[:2, :2] = A
    H[:2, 2] = c - A @ c + np.asarray(shift)
    return H


def _warp(img: np.ndarray, H: np.ndarray):
    """Warped image and its valid region, eroded so no keypoint sits on the black rim."""
    h, w = img.shape[:2]
    out = cv2.warpPerspective(img, H, (w, h), flags=cv2.INTER_LINEAR)
    valid = cv2.warpPerspective(np.full((h, w), 255, np.uint8), H, (w, h), flags=cv2.INTER_NEAREST)
    valid = cv2.erode(valid, np.ones((15, 15), np.uint8)) > 0
    return out, valid


def _map(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return cv2.perspectiveTransform(pts.reshape(-1, 1, 2).astype(np.float64), H).reshape(-1, 2)


def _rock_texture(h=480, w=640, seed=0) -> np.ndarray:
    """Procedural multi-scale colour texture (rock-like), RGB uint8."""
    rng = np.random.default_rng(seed)
    acc = np.zeros((h, w, 3), np.float32)
    for scale in (2, 4, 8, 16, 32):
        noise = rng.standard_normal((h // scale + 2, w // scale + 2, 3)).astype(np.float32)
        acc += cv2.resize(noise, (w, h), interpolation=cv2.INTER_CUBIC)[:h, :w] * scale**0.5
    acc = (acc - acc.mean()) / acc.std()
    return np.clip(127 + 45 * acc, 0, 255).astype(np.uint8)


def _pair(img: np.ndarray):
    H = _similarity(img.shape[1], img.shape[0])
    warped, valid = _warp(img, H)
    return img, warped, valid, H


@pytest.fixture(scope="module")
def pairs():
    """Textures and their known warps, built once: a procedural rock texture
    and scikit-image's astronaut photo (512 × 512 RGB)."""
    return {"rock": _pair(_rock_texture()), "astronaut": _pair(data.astronaut())}


# ----------------------------------------------------------- known warps
@pytest.mark.parametrize("texture, name", [("rock", n) for n in PRESETS]
                         + [("astronaut", n) for n in ("SIFT", "ORB", "AKAZE")])
def test_preset_inliers_follow_the_known_homography(texture, name, pairs):
    p = preset(name)
    if not (available(p.detector) and available(p.descriptor)):
        pytest.skip(f"{p.name} not in this OpenCV build")
    img, warped, valid, H = pairs[texture]
    # The scene is a plane, so the homography is the right model to verify with.
    p = replace(p, geometric_model="homography")
    fa = detect_and_describe(to_gray(img), p, color=img)
    fb = detect_and_describe(to_gray(warped), p, mask=valid, color=warped)
    m = match_features(fa, fb, p)
    inl = m.inlier
    pa, pb = fa.points[m.idx_a[inl]], fb.points[m.idx_b[inl]]
    err = np.linalg.norm(_map(H, pa) - pb, axis=1)
    if p.detector in ("SIFT", "ORB", "AKAZE"):
        assert inl.sum() >= 30, f"{name}: only {inl.sum()} inliers"
    else:
        assert inl.sum() >= 10, f"{name}: only {inl.sum()} inliers"
    # MSER/MSCR keypoints are ellipse centres fitted to pixel regions: they are
    # localised to a few pixels, so they are held to the verification threshold.
    tol = p.geometric_threshold_px if p.detector in ("MSER", "MSCR") else 2.0
    frac = float(np.mean(err < tol))
    assert frac >= 0.9, f"{name}: {frac:.0%} of {inl.sum()} inliers within {tol} px"
    # Inliers are a subset of the putative matches, and every index is valid.
    assert len(m.idx_a) == len(m.idx_b) == len(m.inlier)
    assert m.idx_a.max() < len(fa) and m.idx_b.max() < len(fb)
    assert m.model is not None and m.model.shape == (3, 3)


def test_preset_verified_with_fundamental_matrix_also_follows_the_warp(pairs):
    img, warped, valid, H = pairs["astronaut"]
    p = preset("SIFT")
    assert p.geometric_model == "fundamental"
    fa = detect_and_describe(to_gray(img), p)
    fb = detect_and_describe(to_gray(warped), p, mask=valid)
    m = match_features(fa, fb, p)
    err = np.linalg.norm(_map(H, fa.points[m.idx_a[m.inlier]]) - fb.points[m.idx_b[m.inlier]], axis=1)
    assert m.n_inliers >= 30 and np.mean(err < 2.0) >= 0.9


def _isoluminant_discs(seed=1, n=12):
    """Red discs on a green ground of the same BT.601 luma: invisible in grey."""
    rng = np.random.default_rng(seed)
    h, w = 240, 320
    img = np.zeros((h, w, 3), np.uint8)
    img[:] = (0, 100, 0)  # luma 58.7
    centres: list[tuple[int, int]] = []
    while len(centres) < n:
        x, y = int(rng.integers(25, w - 25)), int(rng.integers(25, h - 25))
        if all(np.hypot(x - a, y - b) > 34 for a, b in centres):
            centres.append((x, y))
            cv2.circle(img, (x, y), 10, (196, 0, 0), -1)  # luma 58.6
    # Soft edges: MSCR follows a region's growth through rising colour distance.
    return cv2.GaussianBlur(img, (0, 0), 1.0), np.array(centres, float)


def test_mscr_finds_colour_regions_that_grey_mser_cannot():
    if not available("MSER"):
        pytest.skip("MSER not in this OpenCV build")
    img, centres = _isoluminant_discs()
    gray = to_gray(img)
    assert np.ptp(gray) <= 1  # the discs vanish in grey
    mscr = detect_and_describe(gray, FeatureParams("MSCR", "SIFT"), color=img)
    mser = detect_and_describe(gray, FeatureParams("MSER", "SIFT"), color=img)
    no_colour = detect_and_describe(gray, FeatureParams("MSCR", "SIFT"))
    assert mser.n_detected == 0 and no_colour.n_detected == 0
    assert mscr.n_detected >= len(centres) // 2
    # Each colour region is found at a disc's centre, and most discs are found.
    d = np.linalg.norm(mscr.points[:, None, :] - centres[None], axis=2)
    assert np.all(d.min(axis=1) < 2.0)
    assert np.sum(d.min(axis=0) < 2.0) >= 10


# ------------------------------------------------------- even selection
def test_even_selection_caps_every_cell_when_the_strong_points_cluster():
    rng = np.random.default_rng(0)
    h, w, grid = 480, 640, (8, 6)
    cells = grid[0] * grid[1]
    per_cell = 10
    n_max = per_cell * cells
    # 40 weak points in every cell, plus 2000 strong ones crowded in one cell.
    weak = np.concatenate([
        rng.uniform([i * 80, j * 80], [(i + 1) * 80 - 1, (j + 1) * 80 - 1], (40, 2))
        for i in range(8) for j in range(6)
    ])
    strong = rng.uniform([85, 85], [155, 155], (2000, 2))
    pts = np.concatenate([weak, strong]).astype(np.float32)
    resp = np.concatenate([rng.uniform(0, 1, len(weak)), rng.uniform(5, 6, len(strong))])
    keep = F._even_selection(pts, resp.astype(np.float32), n_max, grid, (h, w))
    assert len(keep) == n_max
    cell_of = (pts[keep, 1] // 80).astype(int) * 8 + (pts[keep, 0] // 80).astype(int)
    counts = np.bincount(cell_of, minlength=cells)
    assert counts.max() <= per_cell and counts.min() == per_cell
    # Control: keeping the strongest points would have piled them in one cell.
    top = np.argsort(-resp)[:n_max]
    assert np.all(top >= len(weak))


def test_even_selection_keeps_all_points_of_sparse_cells():
    rng = np.random.default_rng(1)
    h, w, grid = 480, 640, (8, 6)
    sparse = np.concatenate([
        rng.uniform([i * 80 + 1, j * 80 + 1], [(i + 1) * 80 - 2, (j + 1) * 80 - 2], (3, 2))
        for i in range(8) for j in range(6) if (i, j) != (1, 1)
    ])
    cluster = rng.uniform([85, 85], [155, 155], (3000, 2))
    pts = np.concatenate([sparse, cluster]).astype(np.float32)
    resp = np.concatenate([np.full(len(sparse), 0.1), rng.uniform(5, 6, len(cluster))])
    keep = F._even_selection(pts, resp.astype(np.float32), 480, grid, (h, w))
    assert len(keep) == 480
    assert set(range(len(sparse))) <= set(keep.tolist())  # weak but alone: all kept
    # The rest is filled from the cluster, strongest first.
    filled = keep[keep >= len(sparse)]
    assert resp[filled].min() >= np.sort(resp[len(sparse):])[-len(filled)]


def test_even_selection_through_detection_spreads_points():
    rng = np.random.default_rng(2)
    h, w = 480, 640
    # Fine texture everywhere, one very high-contrast patch in cell (1, 1).
    img = np.clip(128 + 40 * cv2.GaussianBlur(rng.standard_normal((h, w)), (0, 0), 1.2),
                  0, 255).astype(np.uint8)
    patch = rng.integers(0, 2, (20, 20)).astype(np.uint8) * 255
    img[90:170, 90:170] = cv2.resize(patch, (80, 80), interpolation=cv2.INTER_NEAREST)
    p = FeatureParams("SIFT", "SIFT", max_features=480, grid=(8, 6))

    def cells(points):
        return (points[:, 1] * 6 // h).astype(int) * 8 + (points[:, 0] * 8 // w).astype(int)

    everything = detect_and_describe(img, replace(p, max_features=10**6))
    available_per_cell = np.bincount(cells(everything.points), minlength=48)
    assert available_per_cell.min() >= 10  # every cell could fill its share
    strongest = np.argsort(-everything.responses)[:480]
    assert np.bincount(cells(everything.points[strongest]), minlength=48).max() > 30

    f = detect_and_describe(img, p)
    assert f.n_detected == len(everything) and len(f) == 480
    np.testing.assert_array_equal(np.bincount(cells(f.points), minlength=48), 10)


@pytest.mark.parametrize("name", list(PRESETS))
def test_max_features_is_respected(name):
    p = preset(name)
    if not (available(p.detector) and available(p.descriptor)):
        pytest.skip(f"{p.name} not in this OpenCV build")
    img = _rock_texture(240, 320, seed=7)
    p = replace(p, max_features=150, threshold_scale=0.5)
    f = detect_and_describe(to_gray(img), p, color=img)
    assert 0 < len(f) <= 150
    assert f.n_detected >= len(f)
    assert len(f.descriptors) == len(f.points) == len(f.sizes) == len(f.responses)


def test_max_features_is_respected_with_a_fine_grid():
    rng = np.random.default_rng(0)
    pts = rng.uniform([0, 0], [640, 480], (5000, 2)).astype(np.float32)
    resp = rng.random(5000).astype(np.float32)
    keep = F._even_selection(pts, resp, 500, (32, 24), (480, 640))
    assert len(keep) <= 500


def test_detection_honours_the_mask():
    img = to_gray(_rock_texture())
    mask = np.zeros(img.shape, bool)
    mask[:, 256:] = True
    f = detect_and_describe(img, FeatureParams("SIFT", "SIFT"), mask=mask)
    assert len(f) > 50 and f.points[:, 0].min() >= 250


def test_featureless_image_gives_empty_features_and_matches():
    flat = np.full((100, 120), 128, np.uint8)
    p = FeatureParams("SIFT", "SIFT")
    f = detect_and_describe(flat, p)
    assert len(f) == 0 and f.n_detected == 0
    m = match_features(f, f, p)
    assert len(m) == 0 and m.n_inliers == 0 and m.model is None


# --------------------------------------------- ratio test and symmetry
@pytest.fixture(scope="module")
def repeated_pair():
    rng = np.random.default_rng(5)
    h, w = 480, 640
    tile = cv2.GaussianBlur(rng.integers(0, 256, (60, 60)).astype(np.uint8), (0, 0), 1.5)
    tile = cv2.normalize(tile, None, 0, 255, cv2.NORM_MINMAX)
    img = np.tile(tile, (h // 60 + 1, w // 60 + 1))[:h, :w].copy()  # repeated texture
    uniq = cv2.GaussianBlur(rng.integers(0, 256, (160, 200)).astype(np.uint8), (0, 0), 1.5)
    img[160:320, 220:420] = cv2.normalize(uniq, None, 0, 255, cv2.NORM_MINMAX)
    H = _similarity(w, h)
    warped, valid = _warp(img, H)
    return img, warped, valid, H


@pytest.mark.parametrize("name, n", [("SIFT", 1500), ("ORB", 2500)])
def test_ratio_and_symmetry_reduce_outliers_on_repeated_texture(name, n, repeated_pair):
    img, warped, valid, H = repeated_pair
    base = replace(preset(name), geometric_model="none", max_features=n)
    fa = detect_and_describe(img, base)
    fb = detect_and_describe(warped, base, mask=valid)

    def outlier_fraction(ratio, symmetric):
        m = match_features(fa, fb, replace(base, ratio=ratio, symmetric=symmetric))
        err = np.linalg.norm(_map(H, fa.points[m.idx_a]) - fb.points[m.idx_b], axis=1)
        assert m.inlier.all()  # "none": no verification
        return float(np.mean(err > 3.0)), len(m)

    plain, n_plain = outlier_fraction(1.0, False)  # nearest neighbour only
    ratio, n_ratio = outlier_fraction(0.8, False)
    sym, n_sym = outlier_fraction(1.0, True)
    both, n_both = outlier_fraction(0.8, True)
    assert plain > 0.5  # the repeated texture really confuses plain matching
    assert ratio < plain and sym < plain
    assert both <= min(ratio, sym) and both < 0.1
    assert n_both <= min(n_ratio, n_sym) <= n_plain


# ------------------------------------------------------ verify_geometry
def _far_outliers(rng, good: np.ndarray, n_out: int, lo, hi, dist_fn, min_dist: float):
    """Random points at least ``min_dist`` (by ``dist_fn``) from the true positions."""
    out = good.copy()
    idx = rng.choice(len(good), n_out, replace=False)
    for i in idx:
        while True:
            q = rng.uniform(lo, hi)
            if dist_fn(i, q) > min_dist:
                out[i] = q
                break
    mask = np.ones(len(good), bool)
    mask[idx] = False
    return out, mask


def test_verify_homography_recovers_the_inlier_set():
    rng = np.random.default_rng(3)
    n = 200
    pa = rng.uniform([0, 0], [1000, 750], (n, 2))
    H = np.array([[0.9, -0.15, 40.0], [0.12, 0.95, -20.0], [1e-4, -5e-5, 1.0]])
    pb_true = _map(H, pa)
    pb = pb_true + rng.normal(0, 0.3, pb_true.shape)
    pb, truth = _far_outliers(rng, pb, 60, [0, 0], [1000, 750],
                              lambda i, q: np.linalg.norm(q - pb_true[i]), 30.0)
    inl, model = verify_geometry(pa, pb, FeatureParams(geometric_model="homography",
                                                       geometric_threshold_px=3.0))
    np.testing.assert_array_equal(inl, truth)
    # The model maps the inliers' sources onto their true positions.
    assert np.abs(_map(model, pa[truth]) - pb_true[truth]).max() < 1.0


def _epipolar_distance(Fm, a, b):
    line = Fm @ np.append(a, 1.0)
    return abs(line @ np.append(b, 1.0)) / np.hypot(line[0], line[1])


def test_verify_fundamental_recovers_the_inlier_set():
    rng = np.random.default_rng(4)
    n = 200
    K = Intrinsics(1000, 750, 900.0, 900.0, 499.5, 374.5)
    X = rng.uniform([-8, -5, 25], [8, 5, 45], (n, 3))  # a non-planar cloud ahead
    P1 = Pose(np.eye(3), np.zeros(3))  # camera 1 at the origin, looking along +z
    R2 = cv2.Rodrigues(np.deg2rad([2.0, -6.0, 1.5]))[0]
    P2 = Pose.from_center(R2, [3.0, 0.5, 0.2])
    xa = P1.project(K, X) + rng.normal(0, 0.3, (n, 2))
    xb_true = P2.project(K, X)
    xb = xb_true + rng.normal(0, 0.3, (n, 2))
    # True fundamental matrix: F = K^-T [t]x R K^-1 for camera 2 relative to camera 1.
    t = P2.t
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    Kinv = np.linalg.inv(K.K)
    F_true = Kinv.T @ tx @ P2.R @ Kinv
    xb, truth = _far_outliers(rng, xb, 60, [0, 0], [1000, 750],
                              lambda i, q: _epipolar_distance(F_true, xa[i], q), 20.0)
    inl, model = verify_geometry(xa, xb, FeatureParams(geometric_model="fundamental",
                                                       geometric_threshold_px=3.0))
    np.testing.assert_array_equal(inl, truth)
    d = [_epipolar_distance(model, a, b) for a, b in zip(xa[truth], xb[truth])]
    assert max(d) < 3.0


def test_verify_geometry_none_and_too_few_points():
    rng = np.random.default_rng(0)
    pa, pb = rng.uniform(0, 100, (7, 2)), rng.uniform(0, 100, (7, 2))
    inl, model = verify_geometry(pa, pb, FeatureParams(geometric_model="none"))
    assert inl.all() and model is None
    inl, model = verify_geometry(pa, pb, FeatureParams(geometric_model="fundamental"))
    assert not inl.any() and model is None  # 8 needed
    inl, model = verify_geometry(pa[:3], pb[:3], FeatureParams(geometric_model="homography"))
    assert not inl.any() and model is None  # 4 needed


# ------------------------------------------------------ FeatureParams
@pytest.mark.parametrize("kwargs, words", [
    ({"detector": "SURF"}, "detector"),
    ({"descriptor": "FREAK"}, "descriptor"),
    ({"detector": "SIFT", "descriptor": "AKAZE"}, "AKAZE"),
    ({"detector": "ORB", "descriptor": "AKAZE"}, "AKAZE"),
    ({"geometric_model": "affine"}, "geometric_model"),
])
def test_feature_params_validation(kwargs, words):
    with pytest.raises(ValueError, match=words):
        FeatureParams(**kwargs)


def test_feature_params_normalise_and_round_trip():
    p = FeatureParams("fast", "sift", grid=[4, 3])
    assert (p.detector, p.descriptor, p.grid) == ("FAST", "SIFT", (4, 3))
    assert p.name == "FAST–SIFT"
    assert FeatureParams.from_dict(p.to_dict()) == p
    with pytest.raises(KeyError, match="nfeatures"):
        FeatureParams.from_dict({"nfeatures": 10})


def test_preset_is_a_copy_and_accepts_either_dash():
    a = preset("fast–sift")
    b = preset("FAST-SIFT")
    assert a == b == PRESETS["FAST-SIFT"]
    a.max_features = 123
    a.ratio = 0.55
    assert PRESETS["FAST-SIFT"].max_features != 123 and preset("FAST-SIFT") == b
    with pytest.raises(KeyError, match="SURF"):
        preset("SURF")


def test_presets_are_the_papers_combinations():
    names = {p.name for p in PRESETS.values()}
    assert {"SIFT–SIFT", "FAST–SIFT", "MSCR–SIFT", "ORB–ORB", "AKAZE–AKAZE",
            "BRISK–BRISK"} <= names


# ------------------------------------------- registration-tuned options
def _shift_pair(img: np.ndarray, shift=(9.0, -6.0)):
    """A pure translation (no rotation): the case upright descriptors are for."""
    H = np.array([[1.0, 0.0, shift[0]], [0.0, 1.0, shift[1]], [0.0, 0.0, 1.0]])
    warped, valid = _warp(img, H)
    return warped, valid, H


def test_root_sift_descriptors_are_unit_length_square_roots():
    img = _rock_texture()
    plain = detect_and_describe(to_gray(img), FeatureParams())
    root = detect_and_describe(to_gray(img), FeatureParams(root_sift=True))
    np.testing.assert_array_equal(plain.points, root.points)
    # RootSIFT (Arandjelović & Zisserman 2012): L1-normalise, then square root,
    # so the result has unit L2 norm and equals sqrt(d / |d|_1).
    np.testing.assert_allclose(np.linalg.norm(root.descriptors, axis=1), 1.0, atol=1e-4)
    expected = np.sqrt(plain.descriptors / plain.descriptors.sum(axis=1, keepdims=True))
    np.testing.assert_allclose(root.descriptors, expected, atol=1e-4)


def test_upright_keypoints_have_zero_angle_one_per_place_and_follow_a_shift():
    img = _rock_texture()
    warped, valid, H = _shift_pair(img)
    p = FeatureParams(upright=True, root_sift=True)
    fa = detect_and_describe(to_gray(img), p)
    fb = detect_and_describe(to_gray(warped), p, mask=valid)
    places = {(round(float(x), 2), round(float(y), 2), round(float(s), 2))
              for (x, y), s in zip(fa.points, fa.sizes)}
    assert len(places) == len(fa)  # SIFT's extra orientations are not described twice
    m = match_features(fa, fb, replace(p, geometric_model="homography"))
    inl = m.inlier
    assert inl.sum() >= 50
    err = np.linalg.norm(_map(H, fa.points[m.idx_a[inl]]) - fb.points[m.idx_b[inl]], axis=1)
    assert np.mean(err < 2.0) >= 0.95


def test_guided_matching_finds_the_shifted_counterparts_within_the_radius():
    img = _rock_texture()
    warped, valid, H = _shift_pair(img, shift=(4.0, 3.0))
    p = FeatureParams(upright=True, root_sift=True, guided_radius_px=8.0,
                      geometric_model="homography")
    fa = detect_and_describe(to_gray(img), p)
    fb = detect_and_describe(to_gray(warped), p, mask=valid)
    m = F.match_guided(fa, fb, p)
    inl = m.inlier
    assert inl.sum() >= 50
    pa, pb = fa.points[m.idx_a[inl]], fb.points[m.idx_b[inl]]
    np.testing.assert_allclose(np.median(pb - pa, axis=0), [4.0, 3.0], atol=0.3)
    # A radius smaller than the shift cannot reach the true counterparts:
    # whatever it pairs up does not follow the shift.
    near = F.match_guided(fa, fb, p, radius_px=2.0)
    qa, qb = fa.points[near.idx_a], fb.points[near.idx_b]
    assert np.mean(np.linalg.norm(_map(H, qa) - qb, axis=1) < 1.0) < 0.05
