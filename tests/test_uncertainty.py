"""The independent error estimate of a pose (registration/uncertainty.py) against known answers.

A synthetic camera 100 m in front of a cliff (with ground in front of it) sees
known 3D points; the photo keypoints are their exact projections plus 0.5 px
noise, and in the biased cases plus a smooth, spatially varying shift (what
shading under another sun does to keypoints on relief the model does not
resolve). The true error of a pose is measured at points over the whole frame.
"""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from napari_imgreg.camera import Intrinsics, Pose
from napari_imgreg.registration.params import RegistrationParams
from napari_imgreg.registration.pose import estimate_pose
from napari_imgreg.registration.round import Correspondences, Round, trial_from_round
from napari_imgreg.registration.uncertainty import (
    UNCERTAIN_PX,
    Uncertainty,
    UncertaintyParams,
    estimate_uncertainty,
    frame_points,
)

W, H = 1632, 1224


def _scene(seed: int):
    rng = np.random.default_rng(seed)
    intr = Intrinsics.from_fov(W, H, 65.0)
    true = Pose.from_attitude(0.0, -5.0, 0.0, np.array([0.0, -100.0, 1.6]))
    face = np.c_[rng.uniform(-60, 60, 1500), rng.normal(0, 1.0, 1500), rng.uniform(0, 40, 1500)]
    ground = np.c_[rng.uniform(-30, 30, 400), rng.uniform(-75, -5, 400), rng.normal(0, 0.2, 400)]
    X = np.r_[face, ground]
    u = true.project(intr, X)
    inside = (u[:, 0] > 0) & (u[:, 0] < W) & (u[:, 1] > 0) & (u[:, 1] < H)
    return intr, true, X[inside], u[inside], rng


def _frame(intr: Intrinsics, pose: Pose) -> np.ndarray:
    """Model points seen at a 40 × 30 grid of pixels: the cliff plane y = 0, else the ground z = 0."""
    gx, gy = np.meshgrid(np.linspace(20, W - 20, 40), np.linspace(20, H - 20, 30))
    o, d = pose.rays(intr, np.c_[gx.ravel(), gy.ravel()])
    o = np.broadcast_to(o, d.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_face = np.where(d[:, 1] > 0, -o[:, 1] / d[:, 1], np.inf)
        t_ground = np.where(d[:, 2] < 0, -o[:, 2] / d[:, 2], np.inf)
    t = np.minimum(t_face, t_ground)
    return o + t[:, None] * d


def _shading_bias(u: np.ndarray, amplitude_px: float) -> np.ndarray:
    """A smooth shift that varies over the image and that no pose change absorbs."""
    x, y = u[:, 0] / W - 0.5, u[:, 1] / H - 0.5
    return amplitude_px * np.c_[4 * x * x - 1 / 3, 4 * x * y]


def _solve(seed: int, bias_px: float):
    intr, true, X, u, rng = _scene(seed)
    photo = u + rng.normal(0, 0.5, u.shape) + _shading_bias(u, bias_px)
    est = estimate_pose(intr, X, photo)
    assert est.ok
    E = _frame(intr, true)
    err = float(np.median(np.linalg.norm(est.pose.project(intr, E) - true.project(intr, E), axis=1)))
    return intr, true, X, photo, est, E, err


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_unbiased_pose_is_certain_and_its_error_within_the_estimate(seed):
    intr, _true, X, photo, est, E, err = _solve(seed, 0.0)
    unc = estimate_uncertainty(intr, est.pose, X, photo, E)
    assert unc.splits == 4
    assert unc.is_small(W)
    assert unc.reprojection_px < 1.0
    assert err <= 2 * unc.reprojection_px
    assert unc.position_m < 0.2 and unc.rotation_deg < 0.1


@pytest.mark.parametrize("seed", [0, 1])
def test_pose_on_keypoints_shifted_by_a_shading_bias_is_uncertain(seed):
    intr, true, X, photo, est, E, err = _solve(seed, 12.0)
    # The fit residual does not see the bias: the inliers agree with the wrong pose...
    assert est.mean_error_px < 3.0
    assert err >= UNCERTAIN_PX  # ... which is ≥ 4 px off over the frame
    unc = estimate_uncertainty(intr, est.pose, X, photo, E)
    assert not unc.is_small(W)
    assert unc.reprojection_px >= 0.5 * err
    assert err <= 2 * unc.reprojection_px
    assert unc.position_m > 0.5  # the camera really is metres off
    assert np.linalg.norm(est.pose.center - true.center) > 1.0


def test_estimate_grows_with_the_bias():
    values = []
    for bias in (0.0, 4.0, 8.0, 12.0):
        intr, _true, X, photo, est, E, _err = _solve(0, bias)
        values.append(estimate_uncertainty(intr, est.pose, X, photo, E).reprojection_px)
    assert values == sorted(values)
    assert values[0] < 0.5
    assert values[-1] > 2.0


def test_too_few_correspondences_is_an_infinite_estimate_written_as_null():
    intr, true, X, u, _ = _scene(0)
    unc = estimate_uncertainty(intr, true, X[:20], u[:20])
    assert math.isinf(unc.reprojection_px) and unc.splits == 0
    assert not unc.is_small(W)
    d = unc.to_dict()
    assert d == {"reprojection_px": None, "position_m": None, "rotation_deg": None}
    json.dumps(d, allow_nan=False)
    assert math.isinf(Uncertainty.from_dict(d).reprojection_px)


def test_threshold_scales_with_the_photo_width():
    unc = Uncertainty(3.0, 0.1, 0.01)
    assert unc.is_small(1632)
    assert not unc.is_small(1024)  # 4 px at 1632 px is 2.5 px at 1024 px


def test_params_are_validated():
    with pytest.raises(ValueError):
        UncertaintyParams(min_half=3)
    with pytest.raises(ValueError):
        UncertaintyParams(gain=-1.0)
    with pytest.raises(ValueError):
        UncertaintyParams(directions_deg=())


def test_frame_points_subsample_the_render_evenly_and_skip_the_sky():
    xyz = np.full((100, 200, 3), np.nan, np.float32)
    xyz[50:] = 1.0  # bottom half hit
    pts = frame_points(xyz, 800)
    assert 300 <= len(pts) <= 500
    assert np.isfinite(pts).all()


def _round_of(intr, X, photo, est, E_image):
    n = len(X)
    ok = np.ones(n, bool)
    pose_inlier = est.inliers.copy()
    corr = Correspondences(photo, photo, ok, ok, pose_inlier, X)
    metrics = {"points_photo": 4000, "points_render": 4000, "putative_matches": n,
               "feature_inliers": n, "correspondences_3d": n, "inlier_ratio_2d": 1.0,
               "inliers_3d": int(est.inliers.sum()), "inlier_ratio_3d": 0.99,
               "reprojection_error_px": float(est.mean_error_px), "render_coverage": 0.9}
    rendered = SimpleNamespace(xyz=E_image, coverage=0.9)
    return Round(est, metrics, corr, rendered)


@pytest.mark.parametrize("bias, registered", [(0.0, True), (12.0, False)])
def test_trial_grade_and_hints_follow_the_estimate(bias, registered):
    intr, true, X, photo, est, E, _err = _solve(0, bias)
    last = _round_of(intr, X, photo, est, E.reshape(30, 40, 3))
    params = RegistrationParams()
    trial = trial_from_round(last, index=0, params=params, pose=est.pose, start_pose=true,
                             rounds=3, converged=True, origin="prior", seconds=1.0,
                             image_width=W, intrinsics=intr)
    assert trial.uncertainty is not None
    assert trial.to_dict()["uncertainty"] == trial.uncertainty.to_dict()
    assert trial.verified is registered
    if registered:
        assert trial.grade in ("good", "excellent")
        assert not any("Independent check" in h for h in trial.hints)
    else:
        # Q alone would say excellent (many inliers, small residuals): never good or excellent.
        assert trial.grade not in ("good", "excellent")
        assert any("Independent check" in h for h in trial.hints)
        assert not any("residual flow" in h for h in trial.hints)  # the flow itself was fine
    # Without the camera nothing is estimated and the grade is as before.
    plain = trial_from_round(last, index=0, params=params, pose=est.pose, start_pose=true,
                             rounds=3, converged=True, origin="prior", seconds=1.0, image_width=W)
    assert plain.uncertainty is None and plain.verified


def test_quality_panel_line_says_the_estimate():
    pytest.importorskip("qtpy")
    from napari_imgreg.widgets._quality import uncertainty_text

    assert "not estimated" in uncertainty_text(None, W)
    small = uncertainty_text(Uncertainty(0.8, 0.05, 0.02), W)
    assert "0.8 px" in small and "0.05 m" in small and "#b9f6ca" in small
    large = uncertainty_text(Uncertainty(6.5, 1.2, 0.4), W)
    assert "6.5 px" in large and "#ff8a80" in large
    assert "unknown" in uncertainty_text(Uncertainty(math.inf, math.inf, math.inf), W)
