"""The illumination-robust stages of the registration (sun-lit renders, edges,
mutual information) against known poses."""

from __future__ import annotations

import numpy as np
import pytest

from napari_imgreg import Scene
from napari_imgreg.camera import Pose
from napari_imgreg.io.photos import load_photo
from napari_imgreg.io.records import Sigma
from napari_imgreg.prior import Prior, prior_for_photo
from napari_imgreg.registration.params import RegistrationParams
from napari_imgreg.registration.pipeline import register
from napari_imgreg.sample import load_truth, sample_scene
from napari_imgreg.registration.stages.relight import render_sunlit


@pytest.fixture(scope="module")
def sample():
    folder = sample_scene("small")
    scene = Scene.load(folder / "outcrop.obj", dem=folder / "dem.tif")
    scene.build_engine()
    return folder, scene


def _bare(scene: Scene) -> Scene:
    bare = Scene(scene.vertices, scene.faces, georef=scene.georef, dem=scene.dem, name="bare")
    bare._engine = scene.engine
    return bare


def _off(pose: Pose, d_trend: float, d_plunge: float, shift) -> Pose:
    t, p, r = pose.attitude
    return Pose.from_attitude(t + d_trend, p + d_plunge, r, pose.center + np.asarray(shift, float))


def test_untextured_model_registers_a_photo_of_its_shading_under_a_known_sun(sample):
    folder, scene = sample
    bare = _bare(scene)
    truth = load_truth(folder / "IMG_0001.jpg")
    sun = truth.conditions.sun
    # The photo of a uniform rock under the photo's sun: what a bare mesh can explain.
    shot = render_sunlit(bare, truth.intrinsics, truth.pose, sun, background=(150, 180, 230))
    rng = np.random.default_rng(3)
    img = 255.0 * (shot.rgb / 255.0) ** 0.8 + rng.normal(0, 3, shot.rgb.shape)
    photo = np.clip(img, 0, 255).astype(np.uint8)
    prior = Prior(truth.intrinsics, _off(truth.pose, 3.0, -1.5, (2.0, -1.5, 0.5)),
                  Sigma(position_m=3.0, altitude_m=2.0, angles_deg=3.0), sun=sun,
                  sun_source="test")
    reg = register(bare, photo, prior)
    assert reg.registered and reg.grade in ("excellent", "good")
    assert reg.pose.rotation_error_deg(truth.pose) < 0.2
    assert np.linalg.norm(reg.pose.center - truth.pose.center) < 0.3
    assert any(t.render_mode == "sunlit" for t in reg.trials)
    assert "sun from the test" in reg.assumptions


def _check_point_px(reg, truth) -> float:
    proj = reg.pose.project(truth.intrinsics, truth.check_xyz)
    return float(np.median(np.linalg.norm(proj - truth.check_pixels, axis=1)))


def test_untextured_model_registers_a_photo_of_coloured_rock_by_area_matching(sample):
    folder, scene = sample
    bare = _bare(scene)
    jpg = folder / "IMG_0003.jpg"
    truth = load_truth(jpg)
    photo = load_photo(jpg)  # bedding colours and texture the bare mesh knows nothing of
    prior = prior_for_photo(photo, bare)
    assert prior.sun is not None  # from the photo's EXIF capture time
    reg = register(bare, photo.image, prior)
    assert reg.registered, reg.hints
    best = reg.trials[reg.best_trial]
    assert best.matcher == "area" and best.render_mode == "sunlit" and best.verified
    assert best.to_dict()["matcher"] == "area"
    # From a prior 4.4° and 11.5 m off to about a pixel (1024 px photo).
    assert prior.pose.rotation_error_deg(truth.pose) > 4
    assert _check_point_px(reg, truth) < 2.0
    assert reg.pose.rotation_error_deg(truth.pose) < 0.4
    assert np.linalg.norm(reg.pose.center - truth.pose.center) < 0.5
    assert "area" in reg.timings_s


def test_area_matching_does_not_verify_a_mirrored_photo(sample):
    folder, scene = sample
    bare = _bare(scene)
    photo = load_photo(folder / "IMG_0003.jpg")
    prior = prior_for_photo(photo, bare)
    # The same rock, the same light, the same camera: but not this outcrop's shape.
    mirrored = np.ascontiguousarray(photo.image[:, ::-1])
    reg = register(bare, mirrored, prior, RegistrationParams(dense_refine=False))
    assert reg.status == "failed"
    assert reg.grade in ("poor", "failed")
    for t in reg.trials:
        if t.matcher == "area":
            assert not t.verified and t.grade in ("poor", "failed")
            assert t.hints


def test_stage_poses_are_never_graded_above_poor(sample):
    folder, scene = sample
    bare = _bare(scene)
    photo = load_photo(folder / "IMG_0002.jpg")
    prior = prior_for_photo(photo, bare)
    # Area matching off: the edge and MI stages' own poses are what is tested.
    reg = register(bare, photo.image, prior, RegistrationParams(n_search=2, area_match=False))
    for t in reg.trials:
        if t.origin in ("edges", "mutual information") and t.rounds == 0:
            assert t.grade in ("poor", "failed") and not t.verified
    if not reg.registered:
        assert reg.grade not in ("excellent", "good")


def test_regional_residual_flow_sees_a_systematic_misfit_not_block_noise():
    from napari_imgreg.registration.round import Correspondences, residual_flow

    rng = np.random.default_rng(5)
    render_pts = rng.uniform(0, 1024, (600, 2))
    noise = rng.normal(0, 1.0, (600, 2))  # a block's peak: about a pixel of noise
    ones = np.ones(600, bool)

    def flow(photo_pts, regional):
        corr = Correspondences(photo_pts, render_pts, ones, ones, ones)
        return residual_flow(corr, 256.0 if regional else None)

    right = render_pts + noise
    assert flow(right, False) > 1.0  # the median length of pure noise
    assert flow(right, True) < 0.4  # ... averages out within each region
    # Two thirds of the image 3 px off: a real misfit survives the regional median.
    misfit = right.copy()
    misfit[render_pts[:, 0] > 340] += (3.0, 0.0)
    assert flow(misfit, True) > 2.5


def test_biased_keypoints_go_straight_to_area_matching(sample, monkeypatch):
    """A keypoint trial whose split halves disagree (the gate fires) is biased:
    no adapted keypoint trials and no prior search follow it (they share the
    bias, issue 13: 39–69 s per photo spent on them), area matching does."""
    import napari_imgreg.registration.round as round_mod
    from napari_imgreg.registration.uncertainty import Uncertainty

    folder, scene = sample
    photo = load_photo(folder / "IMG_0001.jpg")
    prior = prior_for_photo(photo, scene)
    real = round_mod.estimate_uncertainty
    calls = []

    def first_biased(*args, **kwargs):
        calls.append(1)
        if len(calls) == 1:  # the first keypoint trial: halves 10 px apart
            return Uncertainty(10.0, 2.0, 0.5, 4)
        return real(*args, **kwargs)

    monkeypatch.setattr(round_mod, "estimate_uncertainty", first_biased)
    reg = register(scene, photo.image, prior, RegistrationParams())
    first = reg.trials[0]
    assert first.biased and not first.verified
    assert first.adaptation == "biased matches: to area matching"
    assert reg.trials[1].matcher == "area" and reg.trials[1].origin == "area matching"
    assert not any(t.origin == "search" for t in reg.trials)
    truth = load_truth(folder / "IMG_0001.jpg")
    assert reg.registered and reg.best_trial == 1
    assert _check_point_px(reg, truth) < 2.0


def test_a_trial_without_enough_inliers_is_not_called_biased():
    from napari_imgreg.registration.round import MIN_VERIFIED_INLIERS, Trial
    from napari_imgreg.registration.uncertainty import Uncertainty
    from napari_imgreg.camera import Intrinsics

    intr = Intrinsics.from_fov(1632, 1224, 60.0)
    pose = Pose.from_attitude(0.0, 0.0, 0.0, np.zeros(3))

    def trial(inliers, px, matcher="keypoints"):
        return Trial(index=0, params=RegistrationParams(), metrics={"inliers_3d": inliers}, q=1.0,
                     grade="fair", hints=[], pose=pose, start_pose=pose, rounds=2, converged=True,
                     verified=False, residual_flow_px=1.0, matcher=matcher,
                     uncertainty=Uncertainty(px, 1.0, 0.1, 4), intrinsics=intr)

    assert trial(MIN_VERIFIED_INLIERS, 4.0).biased
    assert not trial(MIN_VERIFIED_INLIERS, 3.9).biased          # the estimate is small
    assert not trial(MIN_VERIFIED_INLIERS - 1, 10.0).biased     # too few matches to tell
    assert not trial(500, 10.0, matcher="area").biased          # blocks, not keypoints


def test_few_keypoints_under_a_known_sun_go_to_relit_area_matching_first(sample, monkeypatch):
    """A textured model, a photo with its sun known, and keypoints that find
    next to nothing (as when their descriptors see the survey light):
    blocks on the relit render come next, before any adapted keypoint trial
    or the prior search (issue 13: those cost 16–28 s on the photos whose
    area matching then won anyway)."""
    folder, scene = sample
    assert scene.survey_sun is not None
    photo = load_photo(folder / "IMG_0001.jpg")
    prior = prior_for_photo(photo, scene)
    assert prior.sun is not None
    _starve_keypoints(monkeypatch)
    reg = register(scene, photo.image, prior)
    first, second = reg.trials[0], reg.trials[1]
    assert first.matcher == "keypoints" and not first.verified
    assert first.adaptation.startswith("not verified, sun known")
    assert second.matcher == "area" and second.render_mode == "sunlit"
    assert second.origin == "area matching"
    assert len(reg.trials) == 2 and not any(t.origin == "search" for t in reg.trials)
    truth = load_truth(folder / "IMG_0001.jpg")
    assert reg.registered and reg.best_trial == 1
    assert _check_point_px(reg, truth) < 2.0


def _starve_keypoints(monkeypatch) -> None:
    """Every keypoint matching keeps 5 putative matches, whatever the images."""
    import napari_imgreg.registration.round as round_mod
    from napari_imgreg.registration.features import Matches

    def starved(real):
        def match(a, b, params):
            m = real(a, b, params)
            keep = slice(0, 5)
            return Matches(m.idx_a[keep], m.idx_b[keep], m.inlier[keep], m.model)
        return match

    monkeypatch.setattr(round_mod, "match_features", starved(round_mod.match_features))
    monkeypatch.setattr(round_mod, "match_guided", starved(round_mod.match_guided))


def test_without_a_sun_few_keypoints_adapt_as_before(sample, monkeypatch):
    """No sun: nothing to relight, so no early area trial; the keypoint
    adaptation runs as it always did."""
    folder, scene = sample
    photo = load_photo(folder / "IMG_0001.jpg")
    prior = prior_for_photo(photo, scene)
    prior.sun = None
    _starve_keypoints(monkeypatch)
    reg = register(scene, photo.image, prior, RegistrationParams(
        search_prior=False, edge_align=False, dense_refine=False))
    assert not any(t.adaptation.startswith("not verified, sun known") for t in reg.trials)
    assert reg.trials[1].matcher == "keypoints" and reg.trials[0].adaptation.startswith("rule")


def test_when_the_early_blocks_fail_too_the_keypoints_adapt_and_say_both(sample, monkeypatch):
    """Keypoints and blocks both find nothing: the adapted keypoint trials
    follow the early area trial, and the first trial's note keeps both steps."""
    import napari_imgreg.registration.round as round_mod
    from napari_imgreg.registration.stages.area import BlockMatches

    folder, scene = sample
    photo = load_photo(folder / "IMG_0001.jpg")
    prior = prior_for_photo(photo, scene)
    _starve_keypoints(monkeypatch)
    empty = np.zeros((0, 2))
    monkeypatch.setattr(round_mod, "match_blocks", lambda *a, **k: BlockMatches(
        empty, empty.copy(), np.zeros(0), np.zeros(0), np.zeros(0, bool)))
    reg = register(scene, photo.image, prior, RegistrationParams(
        search_prior=False, edge_align=False, dense_refine=False))
    assert not reg.registered
    first = reg.trials[0].adaptation
    assert first.startswith("not verified, sun known: area matching; rule")
    assert reg.trials[1].matcher == "area" and reg.trials[2].matcher == "keypoints"


def _first_estimate(monkeypatch, px: float, later_px: float | None = None):
    """The first keypoint trial's error estimate set to ``px`` (verified below
    4 px); every later estimate is the real one, or ``later_px``."""
    import napari_imgreg.registration.round as round_mod
    from napari_imgreg.registration.uncertainty import Uncertainty

    real = round_mod.estimate_uncertainty
    calls = []

    def patched(*args, **kwargs):
        calls.append(1)
        if len(calls) == 1:
            return Uncertainty(px, 0.05, 0.02, 4, halves_px=px)
        if later_px is not None:
            return Uncertainty(later_px, 0.05, 0.02, 4, halves_px=later_px)
        return real(*args, **kwargs)

    monkeypatch.setattr(round_mod, "estimate_uncertainty", patched)


def test_a_loosely_held_keypoint_pose_is_refined_by_area_matching(sample, monkeypatch):
    """A verified keypoint pose whose expected error is 0.5 px or more gets one
    area-matching trial from it (on the relit render: the sample's sun is
    known); kept, as here, when verified with a smaller estimate."""
    folder, scene = sample
    photo = load_photo(folder / "IMG_0001.jpg")
    prior = prior_for_photo(photo, scene)
    _first_estimate(monkeypatch, 2.0)
    reg = register(scene, photo.image, prior, RegistrationParams())
    first, refined = reg.trials[0], reg.trials[1]
    assert first.verified and first.matcher == "keypoints"
    assert first.adaptation == "verified: refined by area matching"
    assert refined.matcher == "area" and refined.origin == "trial 1"
    assert refined.render_mode == "sunlit"
    assert refined.uncertainty.reprojection_px < 2.0
    assert reg.registered and reg.best_trial == 1
    assert _check_point_px(reg, load_truth(folder / "IMG_0001.jpg")) < 1.0


def test_a_tightly_held_keypoint_pose_is_not_refined(sample, monkeypatch):
    """Below 0.5 px (at 1632 px width; 0.31 px at the sample's 1024 px)
    blocks rarely do better: no area trial, no time spent."""
    folder, scene = sample
    photo = load_photo(folder / "IMG_0001.jpg")
    prior = prior_for_photo(photo, scene)
    _first_estimate(monkeypatch, 0.3)
    reg = register(scene, photo.image, prior, RegistrationParams())
    assert len(reg.trials) == 1 and not reg.trials[0].adaptation
    assert reg.registered


def test_area_refinement_is_kept_only_when_its_estimate_is_smaller(sample, monkeypatch):
    """An area trial whose estimate is not smaller leaves the keypoint pose as the answer."""
    folder, scene = sample
    photo = load_photo(folder / "IMG_0001.jpg")
    prior = prior_for_photo(photo, scene)
    _first_estimate(monkeypatch, 0.5, later_px=1.0)  # the area trial's is larger
    reg = register(scene, photo.image, prior, RegistrationParams())
    assert len(reg.trials) == 2 and reg.trials[1].matcher == "area"
    assert reg.trials[1].verified and reg.trials[1].uncertainty.reprojection_px == 1.0
    assert reg.best_trial == 0
    assert reg.trials[0].adaptation == "verified: area matching from it was no better"


def test_area_matching_keeps_the_render_that_resembles_the_photo(sample):
    """Under a known sun, area matching on a textured model matches and solves
    both the relit render and the texture as it is, and keeps the round whose
    pose inliers fit better: a photo under the survey light (the model's own
    render) gets the texture as it is, a photo under its sun (the sample's,
    rendered from a surface whose shading the model has) the relit render."""
    from napari_imgreg.registration import pipeline as P
    from napari_imgreg.registration.round import lit_as, score_round
    from napari_imgreg.render import render

    folder, scene = sample
    photo = load_photo(folder / "IMG_0001.jpg")
    truth = load_truth(folder / "IMG_0001.jpg")
    prior = prior_for_photo(photo, scene)
    assert prior.sun is not None
    params = RegistrationParams()
    survey_light = render(scene, truth.intrinsics, truth.pose).rgb
    for image, expected in ((survey_light, "plain"), (photo.image, "sunlit")):
        ctx = P._Context(scene, image, truth.intrinsics, params, lambda: None)
        ctx.sun = prior.sun
        assert P._area_light(ctx, "sunlit") == "auto"
        rnd = score_round(ctx, truth.pose, params, 1024, matcher="area", search_px=8, mode="auto")
        m = rnd.metrics
        assert lit_as("auto", m) == expected, m
        assert (m["area_residual_unlit_px"] < m["area_residual_sunlit_px"]) == (expected == "plain")
        # The round solved from the kept render: its synthetic light only when relit.
        assert (rnd.rendered.shading_share or 0.0) > 0 if expected == "sunlit" else \
            not rnd.rendered.shading_share
        err = rnd.estimate.pose.project(truth.intrinsics, truth.check_xyz) - truth.check_pixels
        assert np.median(np.linalg.norm(err, axis=1)) < 1.0


def test_area_light_is_auto_only_for_photographed_colours_under_a_known_sun(sample):
    from napari_imgreg.registration import pipeline as P

    folder, scene = sample
    photo = load_photo(folder / "IMG_0001.jpg")
    params = RegistrationParams()
    ctx = P._Context(scene, photo.image, load_truth(folder / "IMG_0001.jpg").intrinsics, params,
                     lambda: None)
    assert P._area_light(ctx, "sunlit") == "sunlit"  # no sun set: nothing to compare
    ctx.sun = np.array([0.0, -0.5, 0.866])
    assert P._area_light(ctx, "plain") == "plain"
    bare = P._Context(_bare(scene), photo.image, ctx.intrinsics, params, lambda: None)
    bare.sun = ctx.sun
    assert P._area_light(bare, "sunlit") == "sunlit"  # grey shading is no photo's colours


def test_the_unlit_twin_of_a_sunlit_render_is_the_plain_render(sample):
    """One ray cast serves both renders of an "auto" round: the plain render of the
    view just rendered sun-lit is its unlit twin, identical to a fresh plain render;
    another view is rendered afresh."""
    from napari_imgreg.registration import pipeline as P
    from napari_imgreg.registration.round import score_round
    from napari_imgreg.render import render

    folder, scene = sample
    truth = load_truth(folder / "IMG_0001.jpg")
    photo = load_photo(folder / "IMG_0001.jpg")
    ctx = P._Context(scene, photo.image, truth.intrinsics, RegistrationParams(), lambda: None)
    ctx.sun = prior_for_photo(photo, scene).sun
    scale = 0.5
    lit = ctx.render(truth.pose, scale, "sunlit")
    twin = ctx.render(truth.pose, scale, "plain")
    fresh = render(scene, truth.intrinsics, truth.pose, scale=scale)
    assert np.array_equal(twin.rgb, fresh.rgb) and not np.array_equal(twin.rgb, lit.rgb)
    assert twin.xyz is lit.xyz  # the same geometry, not a second cast
    other = _off(truth.pose, 1.0, 0.0, (0.0, 0.0, 0.0))
    assert np.array_equal(ctx.render(other, scale, "plain").rgb,
                          render(scene, truth.intrinsics, other, scale=scale).rgb)
    with pytest.raises(ValueError, match="area matching only"):
        score_round(ctx, truth.pose, RegistrationParams(), 512, mode="auto")


def test_photographed_colours_and_appearance(sample):
    """A texture is photographed colours (and an appearance); a bare mesh is
    neither; a scan's intensity is an appearance but not colours."""
    from types import SimpleNamespace

    from napari_imgreg.scene import has_appearance, has_colours

    _, scene = sample
    assert has_colours(scene) and has_appearance(scene)
    assert not has_colours(_bare(scene)) and not has_appearance(_bare(scene))
    scan = SimpleNamespace(has_texture=False, vertex_colors=None, intensity=np.ones(3))
    assert not has_colours(scan) and has_appearance(scan)


@pytest.mark.parametrize("d_trend", [90.0, 180.0])
def test_a_compass_far_off_is_found_by_headings_all_round(sample, d_trend):
    """Nothing in common from the sensor heading and the prior's ±3σ search:
    headings all round are tried at reduced resolution, the best refined and
    verified (a compass 90° off failed after nine trials)."""
    folder, scene = sample
    photo = load_photo(folder / "IMG_0002.jpg")
    prior = prior_for_photo(photo, scene)
    truth = load_truth(folder / "IMG_0002.jpg")
    prior.pose = _off(prior.pose, d_trend, 0.0, (0.0, 0.0, 0.0))
    fast = dict(match_width=512, max_trials=1, n_search=2, sun_relight=False,
                edge_align=False, dense_refine=False, area_match=False)
    reg = register(scene, photo.image, prior, RegistrationParams(**fast))
    assert reg.status == "registered" and reg.pose.rotation_error_deg(truth.pose) < 0.2
    best = reg.trials[reg.best_trial]
    assert best.origin == "heading search" and "headings all round" in best.adaptation
    assert any("the heading by" in h for h in reg.hints)  # what was off, for the next photos
    # Without adaptation nothing is searched beyond the prior's uncertainty.
    fixed = register(scene, photo.image, prior, RegistrationParams(**fast, auto_adapt=False))
    assert fixed.status == "failed"
    assert not any(t.origin == "heading search" for t in fixed.trials)
