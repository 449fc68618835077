"""The illumination-robust stages of the registration (sun-lit renders, edges,
mutual information) against known poses."""

from __future__ import annotations

import numpy as np
import pytest

from napari_imgreg import Scene
from napari_imgreg.camera import Pose
from napari_imgreg.io.photos import load_photo
from napari_imgreg.io.records import Prior, Sigma, prior_for_photo
from napari_imgreg.params import RegistrationParams
from napari_imgreg.pipeline import register
from napari_imgreg.sample import load_truth, sample_scene
from napari_imgreg.sun import render_sunlit


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


def test_stage_poses_are_never_graded_above_poor(sample):
    folder, scene = sample
    bare = _bare(scene)
    photo = load_photo(folder / "IMG_0002.jpg")  # rock colours a bare mesh cannot explain
    prior = prior_for_photo(photo, bare)
    reg = register(bare, photo.image, prior, RegistrationParams(n_search=2))
    for t in reg.trials:
        if t.origin in ("edges", "mutual information") and t.rounds == 0:
            assert t.grade in ("poor", "failed") and not t.verified
    if not reg.registered:
        assert reg.grade not in ("excellent", "good")
