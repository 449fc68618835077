"""Camera resection without known intrinsics: the six-point DLT and P4Pf, known answers.

A known camera (1632 × 1224, fx = 1400 px: a 60° view) looks at points 50–100 m
away; their pixels get 0.5 px of Gaussian noise and 30 % of them are replaced
by random pixels (outliers). Both solvers must give the camera back.
"""

from __future__ import annotations

import numpy as np
import pytest

from napari_imgreg.camera import Intrinsics, Pose
from napari_imgreg.registration.resection import (
    dlt_camera,
    dlt_ransac,
    nonplanarity,
    pose_unknown_focal,
)

W, H, F = 1632, 1224, 1400.0


def _scene(n=1000, outliers=0.3, noise=0.5, k1=0.0, seed=1, principal=None):
    rng = np.random.default_rng(seed)
    cx, cy = principal or ((W - 1) / 2.0, (H - 1) / 2.0)
    intr = Intrinsics(W, H, F, F, cx, cy, (k1, 0.0, 0.0, 0.0, 0.0) if k1 else ())
    pose = Pose.from_attitude(35.0, 8.0, -3.0, np.array([120.0, -40.0, 15.0]))
    px = np.c_[rng.uniform(0, W - 1, n), rng.uniform(0, H - 1, n)]
    X = pose.inverse_transform(intr.unproject(px, rng.uniform(50.0, 100.0, n)))
    x = pose.project(intr, X) + rng.normal(0.0, noise, (n, 2))
    bad = rng.random(n) < outliers
    x[bad] = np.c_[rng.uniform(0, W - 1, bad.sum()), rng.uniform(0, H - 1, bad.sum())]
    return intr, pose, X, x, ~bad


@pytest.fixture(scope="module")
def scene():
    return _scene()


def test_dlt_exact_on_noise_free_pairs():
    intr, pose, X, x, _ = _scene(n=20, outliers=0.0, noise=0.0, principal=(790.0, 640.0))
    P, K, R, t = dlt_camera(X, x)
    np.testing.assert_allclose(K, intr.K, rtol=1e-6, atol=1e-5)
    np.testing.assert_allclose(R, pose.R, atol=1e-8)
    np.testing.assert_allclose(t, pose.t, atol=1e-5)
    assert np.linalg.det(R) == pytest.approx(1.0) and (np.diag(K) > 0).all()
    # P reproduces the pixels.
    uvw = np.c_[X, np.ones(len(X))] @ P.T
    np.testing.assert_allclose(uvw[:, :2] / uvw[:, 2:], x, atol=1e-6)


def test_dlt_ransac_recovers_the_camera(scene):
    intr, pose, X, x, good = scene
    r = dlt_ransac(X, x, threshold_px=4.0, seed=0)
    assert r.ok, r.reason
    assert r.method == "dlt" and set(r.estimated) == {"fx", "fy", "cx", "cy"}
    assert abs(r.fx / F - 1) < 0.005 and abs(r.fy / F - 1) < 0.005
    assert r.pose.rotation_error_deg(pose) < 0.05
    # Unknown focal length and principal point: the centre along the view
    # trades with them; with known intrinsics the same pairs give 6 mm.
    assert np.linalg.norm(r.pose.center - pose.center) < 0.02
    assert (r.inliers == good).mean() > 0.99
    cam = r.intrinsics(W, H)
    assert cam.estimated == ("fx", "fy", "cx", "cy") and not cam.focal_known


def test_unknown_focal_recovers_the_camera(scene):
    intr, pose, X, x, good = scene
    r = pose_unknown_focal(X, x, W, H, threshold_px=4.0, seed=0)
    assert r.ok, r.reason
    assert r.fx == r.fy and abs(r.fx / F - 1) < 0.005
    assert (r.cx, r.cy) == ((W - 1) / 2.0, (H - 1) / 2.0)  # held at the centre
    assert r.pose.rotation_error_deg(pose) < 0.05
    assert np.linalg.norm(r.pose.center - pose.center) < 0.02
    assert (r.inliers == good).mean() > 0.99
    errors = r.errors_px[r.inliers]
    assert np.median(errors) < 1.0  # 0.5 px noise per axis: median ≈ 0.59 px
    assert r.intrinsics(W, H).estimated == ("fx", "fy")


def test_unknown_focal_on_a_planar_scene():
    rng = np.random.default_rng(3)
    intr = Intrinsics(W, H, F, F, (W - 1) / 2.0, (H - 1) / 2.0)
    pose = Pose.from_attitude(10.0, 20.0, 2.0, np.array([0.0, -60.0, 25.0]))
    # A cliff face: the plane y = 0, seen obliquely.
    X = np.c_[rng.uniform(-30, 30, 300), np.zeros(300), rng.uniform(0, 30, 300)]
    x = pose.project(intr, X) + rng.normal(0.0, 0.5, (300, 2))
    keep = np.isfinite(x).all(axis=1) & (x[:, 0] > 0) & (x[:, 0] < W) & (x[:, 1] > 0) \
        & (x[:, 1] < H)
    X, x = X[keep], x[keep]
    assert nonplanarity(X) == 0.0
    r = pose_unknown_focal(X, x, W, H, threshold_px=4.0)
    assert r.ok, r.reason
    assert abs(r.fx / F - 1) < 0.01
    # ... which the DLT refuses, saying why.
    d = dlt_ransac(X, x)
    assert not d.ok and "one plane" in d.reason


def test_dlt_refuses_coplanar_points_clearly():
    rng = np.random.default_rng(0)
    X = np.c_[rng.uniform(0, 30, 40), np.full(40, 5.0), rng.uniform(0, 10, 40)]
    with pytest.raises(ValueError, match="lie on one plane.*P4Pf"):
        dlt_camera(X, rng.uniform(0, 1000, (40, 2)))
    with pytest.raises(ValueError, match="at least 6"):
        dlt_camera(X[:5], rng.uniform(0, 1000, (5, 2)))


def test_refinement_recovers_k1():
    intr, pose, X, x, good = _scene(n=600, k1=-0.08)
    r = pose_unknown_focal(X, x, W, H, threshold_px=4.0, estimate_k1=True)
    assert r.ok, r.reason
    assert r.k1 == pytest.approx(-0.08, abs=0.005)
    assert abs(r.fx / F - 1) < 0.005 and r.pose.rotation_error_deg(pose) < 0.05
    assert "dist" in r.estimated
    assert r.intrinsics(W, H).dist[0] == pytest.approx(r.k1)
    # Without k1 the same pairs leave a bias: the estimate is worse.
    plain = pose_unknown_focal(X, x, W, H, threshold_px=4.0)
    assert np.median(plain.errors_px[good]) > 2 * np.median(r.errors_px[good])


def test_too_few_pairs_fail_with_a_reason():
    intr, pose, X, x, _ = _scene(n=4, outliers=0.0)
    assert "only 4" in pose_unknown_focal(X, x, W, H).reason
    assert "only 4" in dlt_ransac(X, x).reason
