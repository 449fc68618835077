"""The hints name the cause of a failed registration (registration/explain.py).

Fast: synthetic trials and correspondences, no rendering. The end-to-end
behaviour on the sample (a heading 90° off, a focal length 40 % off, an
overexposed photo ...) was measured by hand; these pin the text and the
evidence each line needs.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from napari_imgreg.camera import Intrinsics, Pose
from napari_imgreg.io.records import Sigma
from napari_imgreg.prior import Prior
from napari_imgreg.registration.explain import (
    diagnose,
    focal_refit,
    match_spread,
    photo_exposure,
    prior_offset_hint,
)
from napari_imgreg.registration.params import RegistrationParams
from napari_imgreg.registration.round import Correspondences

W, H = 1024, 768
CAM = Intrinsics(W, H, 777.0, 777.0, 511.5, 383.5)
TRUE = Pose.from_attitude(343.0, -4.0, 0.0, np.array([12.0, -80.0, 1.7]))


def _prior(pose=TRUE, cam=CAM):
    return Prior(cam, pose, sigma=Sigma())


def _cliff(n=400, seed=0):
    """Points on a rough cliff 75-100 m in front of TRUE, and their pixels."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(40, W - 40, n)
    v = rng.uniform(40, H - 40, n)
    depth = rng.uniform(75, 100, n)
    xc = (u - CAM.cx) / CAM.fx * depth
    yc = (v - CAM.cy) / CAM.fy * depth
    Xc = np.stack([xc, yc, depth], 1)
    X = (TRUE.R.T @ (Xc - TRUE.t).T).T
    return X, np.stack([u, v], 1)


def _corr(X, u, inlier=None):
    n = len(X)
    ones = np.ones(n, bool)
    return Correspondences(photo_points=u, render_points=u.copy(), feature_inlier=ones,
                           lifted=ones, pose_inlier=ones if inlier is None else inlier, xyz=X)


def _trial(metrics, *, pose=None, origin="prior", verified=False, corr=None, cam=CAM,
           matcher="keypoints", hints=()):
    return SimpleNamespace(metrics=metrics, pose=pose, origin=origin, verified=verified,
                           correspondences=corr, intrinsics=cam, matcher=matcher,
                           params=RegistrationParams(), hints=list(hints))


def _photo(value=120, noise=30, seed=0):
    rng = np.random.default_rng(seed)
    a = np.clip(rng.normal(value, noise, (H, W, 3)), 0, 255)
    return a.astype(np.uint8)


NOTHING = {"points_photo": 7400, "points_render": 1900, "feature_inliers": 0,
           "inliers_3d": 0, "inlier_ratio_2d": 0.0, "inlier_ratio_3d": 0.0}


def test_exposure_of_white_dark_and_normal_photos():
    white = np.full((H, W, 3), 255, np.uint8)
    assert photo_exposure(white)[0] == pytest.approx(1.0)
    assert photo_exposure(np.zeros((H, W, 3), np.uint8))[1] == pytest.approx(0.0)
    share, mean = photo_exposure(_photo())
    assert share < 0.01 and 100 < mean < 140


def test_overexposed_photo_is_named_first_and_the_pose_is_not_blamed():
    photo = _photo()
    photo[: int(0.6 * H)] = 255
    lines = diagnose([_trial(NOTHING)], _trial(NOTHING), "failed", _prior(), CAM, photo)
    assert lines and lines[0].startswith("The photo is overexposed: 60%")
    assert not any("heading" in line for line in lines)


def test_dark_photo():
    lines = diagnose([_trial(NOTHING)], _trial(NOTHING), "failed", _prior(), CAM,
                     _photo(15, 5))
    assert lines[0].startswith("The photo is very dark (mean brightness 15 of 255)")


def test_blurred_photo_has_far_fewer_points_than_the_render():
    m = {**NOTHING, "points_photo": 430, "points_render": 2600, "feature_inliers": 67,
         "inliers_3d": 57}
    lines = diagnose([_trial(m)], _trial(m), "failed", _prior(), CAM, _photo())
    assert any("probably blurred" in line and "(430 against 2600)" in line for line in lines)


def test_no_common_ground_from_the_prior_points_at_the_record():
    lines = diagnose([_trial(NOTHING)], _trial(NOTHING), "failed", _prior(), CAM, _photo())
    text = " ".join(lines)
    assert "camera position or the heading in the sensor record is far off" in text
    assert "move the camera on the DEM map" in text
    assert "±15°" in text and "±5 m" in text  # what the search covered (3 σ, σ)


def test_a_bare_mesh_blames_neither_the_record_nor_the_photo():
    """Keypoints of a bare mesh's shading rarely match from any pose."""
    m = {**NOTHING, "points_photo": 430, "points_render": 2600}
    assert diagnose([_trial(m)], _trial(m), "failed", _prior(), CAM, _photo(),
                    appearance=False) == []


def test_a_verified_trial_or_a_matching_prior_blames_no_record():
    ok = {**NOTHING, "feature_inliers": 800, "inliers_3d": 770}
    assert not any("heading" in line for line in
                   diagnose([_trial(ok)], _trial(ok), "failed", _prior(), CAM, _photo()))
    assert diagnose([_trial(NOTHING, verified=True)], _trial(NOTHING, verified=True),
                    "registered", _prior(), CAM, _photo()) == []


def test_focal_refit_finds_the_true_focal_length():
    X, u = _cliff()
    wrong = Intrinsics(W, H, 1088.0, 1088.0, 511.5, 383.5)
    fx, e0, e1 = focal_refit(_corr(X, u), TRUE, wrong)
    assert fx == pytest.approx(777.0, rel=0.02)
    assert e1 < 0.1 < e0
    # The right focal length stays.
    fx, e0, e1 = focal_refit(_corr(X, u), TRUE, CAM)
    assert fx == pytest.approx(777.0, rel=1e-3) and e0 < 0.01
    assert focal_refit(_corr(X[:10], u[:10]), TRUE, CAM) is None  # too few pairs


def test_wrong_focal_length_in_the_record_is_named():
    X, u = _cliff()
    wrong = Intrinsics(W, H, 1088.0, 1088.0, 511.5, 383.5)
    m = {**NOTHING, "feature_inliers": 320, "inliers_3d": 280}
    t = _trial(m, pose=TRUE, corr=_corr(X, u), cam=wrong)
    lines = diagnose([t], t, "failed", _prior(cam=wrong), wrong, _photo())
    focal = [line for line in lines if line.startswith("The focal length looks wrong")]
    assert focal and "fx ≈ 777 px" in focal[0] and "given 1088 px" in focal[0]
    assert "delete it there so that it is estimated" in focal[0]
    # An estimated focal length is not second-guessed.
    est = Intrinsics(W, H, 1088.0, 1088.0, 511.5, 383.5, estimated=("fx", "fy"))
    t = _trial(m, pose=TRUE, corr=_corr(X, u), cam=est)
    assert not any("focal length looks wrong" in line
                   for line in diagnose([t], t, "failed", _prior(cam=est), est, _photo()))


def test_matches_in_one_corner_of_the_photo():
    X, u = _cliff()
    inside = (u[:, 0] < W / 4) & (u[:, 1] < H / 4)
    assert match_spread(_corr(X, u, inside), W, H)[0] == 1
    assert match_spread(_corr(X, u), W, H) == (16, 16)
    m = {**NOTHING, "feature_inliers": 70, "inliers_3d": 66}
    t = _trial(m, pose=TRUE, corr=_corr(X, u, inside))
    lines = diagnose([t], t, "failed", _prior(), CAM, _photo())
    assert any(line.startswith("The matches hold only 1 of 16 parts of the photo")
               for line in lines)


def test_registered_far_from_the_record_says_what_was_off():
    prior_pose = Pose.from_attitude(343.0 + 40.0, -4.0, 0.0, TRUE.center)
    text = prior_offset_hint(TRUE, _prior(prior_pose), registered=True)
    assert text.startswith("The sensor record was off: the heading by 40°")
    assert "found the pose anyway" in text and "check the compass" in text
    assert "GPS" not in text
    moved = Pose.from_attitude(343.0, -4.0, 0.0, TRUE.center + [150.0, 0, 0])
    text = prior_offset_hint(TRUE, _prior(moved), True)
    assert "the camera position by 150 m" in text and "check the GPS fix" in text
    # Within 3 σ: nothing to say.
    near = Pose.from_attitude(346.0, -4.0, 0.0, TRUE.center + [4.0, 0, 0])
    assert prior_offset_hint(TRUE, _prior(near), True) is None


def test_failed_pose_far_from_the_record_is_called_wrong():
    far = Pose.from_attitude(343.0 + 126.0, -4.0, 0.0, TRUE.center + [100.0, 30.0, 0.0])
    text = prior_offset_hint(far, _prior(), registered=False)
    assert "far beyond the record's stated accuracy (5 m, 5°)" in text
    assert "do not map on it" in text


def test_rule_5_says_when_its_ratio_rests_on_a_handful_of_matches():
    from napari_imgreg.registration.quality import evaluate_rules

    few = {"points_photo": 7000, "points_render": 4900, "feature_inliers": 9,
           "inlier_ratio_2d": 0.47, "inliers_3d": 0, "inlier_ratio_3d": 0.0}
    hit = next(h for h in evaluate_rules(few, RegistrationParams(), W) if h.rule == 5)
    assert "(ratio 0.47, but of only 9 matches: perhaps chance ones" in hit.hint
    many = {**few, "feature_inliers": 300, "inliers_3d": 20, "inlier_ratio_3d": 0.07}
    hit = next(h for h in evaluate_rules(many, RegistrationParams(), W) if h.rule == 5)
    assert "chance" not in hit.hint and hit.hint.startswith("2D correspondences are good (ratio")


def test_diagnosis_never_breaks_a_registration():
    assert diagnose(None, None, "failed", None, CAM, _photo()) == []


def test_an_unmeasurable_expected_error_reads_without_inf(monkeypatch):
    """A pose on too few matches for the split halves: no "≈ inf px" in the hint."""
    from napari_imgreg.registration import round as round_mod
    from napari_imgreg.registration.pose import estimate_pose
    from napari_imgreg.registration.round import Round, trial_from_round
    from napari_imgreg.registration.uncertainty import Uncertainty

    X, u = _cliff(60)
    est = estimate_pose(CAM, X, u)
    n = len(X)
    ok = np.ones(n, bool)
    metrics = {"points_photo": 4000, "points_render": 4000, "putative_matches": n,
               "feature_inliers": n, "correspondences_3d": n, "inlier_ratio_2d": 1.0,
               "inliers_3d": n, "inlier_ratio_3d": 1.0, "reprojection_error_px": 0.1,
               "render_coverage": 0.9}
    last = Round(est, metrics, Correspondences(u, u, ok, ok, est.inliers.copy(), X),
                 SimpleNamespace(xyz=np.zeros((30, 40, 3)), coverage=0.9))
    inf = float("inf")
    monkeypatch.setattr(round_mod, "estimate_uncertainty",
                        lambda *a, **k: Uncertainty(inf, inf, inf, halves_px=inf))
    trial = trial_from_round(last, index=0, params=RegistrationParams(), pose=est.pose,
                             start_pose=TRUE, rounds=3, converged=True, origin="prior",
                             seconds=1.0, image_width=W, intrinsics=CAM)
    assert not trial.verified
    check = [h for h in trial.hints if h.startswith("Independent check")]
    assert check and "inf" not in check[0]
    assert "could not be solved separately" in check[0]
