"""RANSAC EPnP pose estimation (pose.py) on synthetic correspondences with known pose."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from napari_imgreg.camera import Intrinsics, Pose
from napari_imgreg.registration.pose import (
    MIN_POINTS,
    PoseEstimate,
    PoseParams,
    estimate_pose,
    pose_agreement,
    reprojection_errors,
)

DISTORTION = (-0.12, 0.05, 0.001, -0.0008, 0.0)
UTM_OFFSET = np.array([512_345.0, 4_231_987.0, 312.0])  # georeferenced, UTM-sized numbers


def rotation_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle between two rotations, accurate for tiny angles (unlike acos of the trace)."""
    return float(np.degrees(2 * np.arcsin(min(1.0, np.linalg.norm(Ra - Rb) / (2 * np.sqrt(2))))))


def scene(seed: int, planar: bool, dist=(), offset=np.zeros(3), n=300, noise_px=0.0,
          outlier_fraction=0.0):
    """A random camera and pose, and points in front of it.

    Returns intrinsics, pose, 3D points, 2D points and the true inlier mask.
    Outliers are moved at least 40 px from their true image position, so the
    true inlier set is unambiguous at the default 6 px threshold.
    """
    rng = np.random.default_rng(seed)
    K = Intrinsics(1632, 1224, 1300 + rng.uniform(-100, 100), 1300 + rng.uniform(-100, 100),
                   815.5 + rng.uniform(-10, 10), 611.5 + rng.uniform(-10, 10), dist)
    pose = Pose.from_attitude(rng.uniform(0, 360), rng.uniform(-20, 20), rng.uniform(-10, 10),
                              rng.uniform(-50, 50, 3) + offset)
    uv = rng.uniform([20, 20], [1612, 1204], (n, 2))
    if planar:  # a rock face: the plane z = 12 + 0.4 x in the camera frame
        rays = K.normalized_rays(uv)
        Xc = rays * (12.0 / (rays[:, 2] - 0.4 * rays[:, 0]))[:, None]
    else:
        Xc = K.unproject(uv, rng.uniform(8, 25, n))
    X = pose.inverse_transform(Xc)
    x = pose.project(K, X)
    if noise_px:
        x = x + rng.normal(0, noise_px, x.shape)
    truth = np.ones(n, bool)
    bad = rng.choice(n, int(round(outlier_fraction * n)), replace=False)
    for i in bad:
        while True:
            q = rng.uniform([0, 0], [1632, 1224])
            if np.linalg.norm(q - x[i]) > 40:
                x[i] = q
                break
    truth[bad] = False
    return K, pose, X, x, truth


CASES = [(planar, dist) for planar in (False, True) for dist in ((), DISTORTION)]
CASE_IDS = [f"{'planar' if p else 'cloud'}-{'distorted' if d else 'pinhole'}" for p, d in CASES]


@pytest.mark.parametrize("planar, dist", CASES, ids=CASE_IDS)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_noise_free_pose_is_exact(planar, dist, seed):
    K, pose, X, x, truth = scene(seed, planar, dist)
    est = estimate_pose(K, X, x)
    assert est.ok and est.reason == ""
    # OpenCV's LM stops at FLT_EPSILON-sized steps: µ-level, not machine precision.
    assert rotation_deg(est.pose.R, pose.R) < 1e-5
    assert np.linalg.norm(est.pose.center - pose.center) < 1e-5
    assert est.inliers.all() and est.mean_error_px < 1e-4


@pytest.mark.parametrize("planar, dist", CASES, ids=CASE_IDS)
@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_pose_with_noise_and_30_percent_outliers(planar, dist, seed):
    K, pose, X, x, truth = scene(seed, planar, dist, noise_px=0.5, outlier_fraction=0.3)
    est = estimate_pose(K, X, x)
    assert est.ok, est.reason
    assert rotation_deg(est.pose.R, pose.R) < 0.05
    assert np.linalg.norm(est.pose.center - pose.center) < 0.01
    np.testing.assert_array_equal(est.inliers, truth)
    assert est.n_inliers == truth.sum()
    # The errors are those of the returned pose, for every correspondence.
    np.testing.assert_allclose(est.errors_px, reprojection_errors(K, est.pose, X, x))
    assert 0.2 < est.mean_error_px < 1.0  # ≈ 0.5 px · √(π/2)


@pytest.mark.parametrize("planar", [False, True], ids=["cloud", "planar"])
def test_pose_is_the_least_squares_optimum_on_the_inliers(planar):
    # Polishing the truth on the true inliers gives the maximum-likelihood pose
    # for this noise; a refined estimate must land on the same optimum.
    K, pose, X, x, truth = scene(11, planar, DISTORTION, noise_px=0.5, outlier_fraction=0.3)
    est = estimate_pose(K, X, x)
    c = X[truth].mean(axis=0)
    t0 = pose.t + pose.R @ c
    rvec, tvec = cv2.solvePnPRefineLM(X[truth] - c, x[truth], K.K, K.dist_coeffs,
                                      pose.rvec.reshape(3, 1).copy(), t0.reshape(3, 1).copy())
    opt = Pose.from_rvec_tvec(rvec, tvec)
    opt = Pose(opt.R, opt.t - opt.R @ c)
    assert rotation_deg(est.pose.R, opt.R) < 1e-4
    assert np.linalg.norm(est.pose.center - opt.center) < 1e-4


@pytest.mark.parametrize("planar", [False, True], ids=["cloud", "planar"])
def test_georeferenced_coordinates_far_from_the_origin(planar):
    K, pose, X, x, truth = scene(5, planar, DISTORTION, offset=UTM_OFFSET, noise_px=0.5,
                                 outlier_fraction=0.3)
    assert np.abs(X).max() > 4e6
    est = estimate_pose(K, X, x)
    assert est.ok, est.reason
    assert rotation_deg(est.pose.R, pose.R) < 0.05
    assert np.linalg.norm(est.pose.center - pose.center) < 0.01
    np.testing.assert_array_equal(est.inliers, truth)
    # Same answer as the same scene near the origin (the code centres the points).
    K0, pose0, X0, x0, _ = scene(5, planar, DISTORTION, noise_px=0.5, outlier_fraction=0.3)
    est0 = estimate_pose(K0, X0, x0)
    assert rotation_deg(est.pose.R, est0.pose.R) < 1e-4
    np.testing.assert_allclose(est.pose.center - UTM_OFFSET, est0.pose.center, atol=1e-4)


def test_seeded_runs_are_reproducible():
    K, pose, X, x, _ = scene(3, False, (), noise_px=0.5, outlier_fraction=0.3)
    a = estimate_pose(K, X, x, rng_seed=7)
    b = estimate_pose(K, X, x, rng_seed=7)
    np.testing.assert_array_equal(a.pose.R, b.pose.R)
    np.testing.assert_array_equal(a.pose.t, b.pose.t)
    np.testing.assert_array_equal(a.inliers, b.inliers)


def test_threshold_sets_the_inliers():
    # Outliers 40+ px away, noise 0.5 px: with a 1.5 px threshold, points with
    # a larger error are not inliers, whatever RANSAC saw.
    K, pose, X, x, truth = scene(4, False, (), noise_px=0.5, outlier_fraction=0.3)
    est = estimate_pose(K, X, x, PoseParams(reprojection_error_px=1.5))
    assert est.ok
    np.testing.assert_array_equal(est.inliers, est.errors_px < 1.5)
    assert not est.inliers[~truth].any()


# ----------------------------------------------------------------- failures
@pytest.mark.parametrize("n", range(MIN_POINTS))
def test_too_few_points_fail_with_a_reason(n):
    K, pose, X, x, _ = scene(0, False, (), n=max(n, 1))
    est = estimate_pose(K, X[:n], x[:n])
    assert isinstance(est, PoseEstimate)
    assert est.ok is False and est.pose is None
    assert str(n) in est.reason and str(MIN_POINTS) in est.reason
    assert est.inliers.shape == (n,) and not est.inliers.any()
    assert est.errors_px.shape == (n,) and np.all(np.isnan(est.errors_px))
    assert est.n_inliers == 0 and np.isnan(est.mean_error_px)


def test_minimum_number_of_points_works():
    K, pose, X, x, _ = scene(0, False, (), n=MIN_POINTS)
    est = estimate_pose(K, X, x)
    assert est.ok and rotation_deg(est.pose.R, pose.R) < 1e-3


def _collinear(seed=0, n=50, noise_px=0.0):
    rng = np.random.default_rng(seed)
    K = Intrinsics(1632, 1224, 1300.0, 1300.0, 815.5, 611.5)
    pose = Pose.from_attitude(30.0, 5.0, 2.0, [10.0, -20.0, 5.0])
    lam = rng.uniform(-5, 5, n)
    Xc = np.array([0.0, 0.0, 20.0]) + lam[:, None] * np.array([1.0, 0.3, 0.2])
    X = pose.inverse_transform(Xc)
    x = pose.project(K, X) + rng.normal(0, noise_px, (n, 2))
    return K, pose, X, x


def test_collinear_points_do_not_raise():
    K, pose, X, x = _collinear()
    est = estimate_pose(K, X, x)  # must not raise
    assert isinstance(est, PoseEstimate)
    assert est.inliers.shape == (50,) and est.errors_px.shape == (50,)


@pytest.mark.parametrize("noise_px", [0.0, 0.5])
def test_collinear_points_fail_with_a_reason(noise_px):
    K, pose, X, x = _collinear(noise_px=noise_px)
    est = estimate_pose(K, X, x)
    assert est.ok is False and est.pose is None
    assert "collinear" in est.reason


def test_identical_points_fail_with_a_reason():
    K, pose, X, x = _collinear()
    est = estimate_pose(K, np.repeat(X[:1], 20, axis=0), np.repeat(x[:1], 20, axis=0))
    assert est.ok is False and est.pose is None and est.reason


def test_non_finite_input_fails_with_a_reason():
    K, pose, X, x, _ = scene(0, False, ())
    X = X.copy()
    X[3] = np.nan
    est = estimate_pose(K, X, x, PoseParams(iterations=300))
    assert est.ok is False and est.reason


def test_points_behind_the_camera_are_never_inliers():
    # 100 correct correspondences plus 30 whose 3D point lies behind the camera
    # although its pixel is where the pinhole formula x/z would put it (the
    # mirror image): physically impossible, so never an inlier.
    rng = np.random.default_rng(8)
    K = Intrinsics(1632, 1224, 1300.0, 1300.0, 815.5, 611.5)
    pose = Pose.from_attitude(200.0, -5.0, 3.0, [10.0, -20.0, 5.0])
    uv_f = rng.uniform([0, 0], [1632, 1224], (100, 2))
    X_f = pose.inverse_transform(K.unproject(uv_f, rng.uniform(10, 30, 100)))
    uv_b = rng.uniform([0, 0], [1632, 1224], (30, 2))
    X_b = pose.inverse_transform(-K.unproject(uv_b, rng.uniform(10, 30, 30)))
    X, x = np.r_[X_f, X_b], np.r_[uv_f, uv_b]
    est = estimate_pose(K, X, x)
    assert est.ok
    assert rotation_deg(est.pose.R, pose.R) < 1e-4
    assert est.inliers[:100].all() and not est.inliers[100:].any()
    assert np.all(np.isinf(est.errors_px[100:]))  # no projection behind the camera
    assert np.all(est.pose.transform(X[est.inliers])[:, 2] > 0)


def test_all_points_behind_the_camera_give_no_pose_through_them():
    rng = np.random.default_rng(9)
    K = Intrinsics(1632, 1224, 1300.0, 1300.0, 815.5, 611.5)
    pose = Pose.from_attitude(20.0, 5.0, 0.0, [0.0, 0.0, 0.0])
    uv = rng.uniform([0, 0], [1632, 1224], (100, 2))
    X = pose.inverse_transform(-K.unproject(uv, rng.uniform(10, 30, 100)))
    est = estimate_pose(K, X, uv)  # no exception
    assert isinstance(est, PoseEstimate)
    if est.ok:
        # Whatever pose RANSAC settles on explains only a chance handful, and
        # puts its inliers in front of itself.
        assert est.n_inliers < 0.1 * len(X)
        assert np.all(est.pose.transform(X[est.inliers])[:, 2] > 0)
    else:
        assert est.reason


def test_unrefined_pose_on_a_planar_scene():
    # Noise-free, no outliers: every seed must give the exact pose (today 3 of
    # these 10 come back 43.6° off with ok=True and 14–21 of 300 inliers).
    wrong = []
    for seed in range(10):
        K, pose, X, x, truth = scene(seed, True, ())
        est = estimate_pose(K, X, x, PoseParams(refine=False))
        if not (est.ok and rotation_deg(est.pose.R, pose.R) < 0.01 and est.inliers.all()):
            wrong.append((seed, est.ok, round(rotation_deg(est.pose.R, pose.R), 1)
                          if est.pose is not None else None, est.n_inliers))
    assert not wrong, wrong


def test_pose_params_dict_round_trip_and_unknown_keys():
    p = PoseParams(reprojection_error_px=3.0, iterations=200, confidence=0.99, refine=False)
    assert PoseParams.from_dict(p.to_dict()) == p
    with pytest.raises(KeyError, match="threshold"):
        PoseParams.from_dict({"threshold": 3.0})


def test_a_given_pose_is_scored_like_an_estimate():
    """pose_agreement: the inliers an estimate would have at the same pose, nothing solved."""
    K, pose, X, x, truth = scene(3, False, (), noise_px=0.5, outlier_fraction=0.3)
    est = estimate_pose(K, X, x)
    agreed = pose_agreement(K, est.pose, X, x)
    assert agreed.ok and agreed.pose is est.pose
    np.testing.assert_array_equal(agreed.inliers, est.inliers)
    assert agreed.mean_error_px == est.mean_error_px
    np.testing.assert_array_equal(agreed.inliers, truth)
    # A pose 5 degrees off agrees with nothing: not ok, with the reason.
    t, p, r = pose.attitude
    off = pose_agreement(K, Pose.from_attitude(t + 5.0, p, r, pose.center), X, x,
                         PoseParams(reprojection_error_px=3.0))
    assert not off.ok and off.pose is None and off.n_inliers == 0 and "3 px" in off.reason
    empty = pose_agreement(K, pose, np.zeros((0, 3)), np.zeros((0, 2)))
    assert not empty.ok and empty.inliers.shape == (0,)


def test_estimate_pose_takes_no_initial_pose():
    K, pose, X, x, _ = scene(0, False, ())
    with pytest.raises(TypeError):
        estimate_pose(K, X, x, None, pose)  # the unused ``initial`` is gone
    assert estimate_pose(K, X, x, rng_seed=3).ok
