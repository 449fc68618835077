"""Known-answer tests for :mod:`napari_imgreg.registration.stages.dense` (mutual-information refinement).

The refinement tests use the small generated outcrop. Two photo kinds:

* a synthetic "photo" rendered from a known pose under another light, with a
  gamma curve and noise (so it is not the render the refinement makes), seen
  from 20 m up and 60 m out, where every surface is 33–70 m away;
* the sample's own photos (generated under another sun, with shadows, wet
  rock, haze, vignetting, JPEG) whose ground truth comes with the sample.
"""

from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from napari_imgreg.camera import Intrinsics, Pose
from napari_imgreg.registration.stages.dense import (
    DenseParams,
    DenseResult,
    entropy,
    mi_score,
    mi_scores,
    mutual_information,
    refine_pose_mi,
)
from napari_imgreg.render import render
from napari_imgreg.sample import load_truth, sample_scene
from napari_imgreg.scene import Scene

# Direction toward the light of the synthetic photos (from the south-east, high).
PHOTO_LIGHT = np.array([0.6, -0.5, 0.6])


# ----------------------------------------------------------------- MI itself
def test_mi_of_an_image_with_itself_is_its_entropy():
    rng = np.random.default_rng(0)
    a = rng.integers(0, 32, (120, 160))  # 32 levels in 32 bins: binning is exact
    h = entropy(a, bins=32)
    assert h == pytest.approx(5.0, abs=0.01)  # near-uniform over 32 values
    assert mutual_information(a, a, bins=32) == pytest.approx(h, abs=1e-9)
    assert mutual_information(a, a, bins=32, normalized=True) == pytest.approx(2.0)
    # Any bijective relabelling keeps all the information.
    perm = rng.permutation(32)
    assert mutual_information(a, perm[a], bins=32) == pytest.approx(h, abs=1e-9)


def test_mi_of_independent_noise_is_near_zero():
    rng = np.random.default_rng(1)
    a = rng.random((256, 256))
    b = rng.random((256, 256))
    # Finite-sample bias of the plug-in estimate: (bins - 1)² / (2 N ln 2) ≈ 0.011 bit.
    assert mutual_information(a, b, bins=32) < 0.03
    assert mutual_information(a, b, bins=32, normalized=True) < 1.01


def _related_pair(seed: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """A smooth image and a noisy, partly independent copy of it (0..255)."""
    rng = np.random.default_rng(seed)
    a = cv2.GaussianBlur(rng.random((200, 240)).astype(np.float32), (0, 0), 3.0)
    a = (a - a.min()) / (a.max() - a.min()) * 255.0
    b = np.clip(0.8 * a + 0.2 * rng.random(a.shape) * 255.0, 0, 255)
    return a, b


def test_mi_is_invariant_to_a_monotone_intensity_remap():
    a, b = _related_pair()
    b_gamma = 255.0 * (b / 255.0) ** 0.45  # another exposure curve
    mi = mutual_information(a, b, binning="quantile")
    assert mi > 0.5
    # Equal-population bins do not see an increasing remap at all ...
    assert mutual_information(a, b_gamma, binning="quantile") == pytest.approx(mi, abs=1e-12)
    # ... and equal-width bins see it only through where the bin edges fall.
    mi_uniform = mutual_information(a, b)
    assert mutual_information(a, b_gamma) == pytest.approx(mi_uniform, rel=0.1)
    # A harsh S-curve: MI (equal-population bins) still unmoved, while a
    # linear measure such as the correlation coefficient drops.
    b_s = 255.0 / (1.0 + np.exp(-(b - 128.0) / 12.0))
    assert mutual_information(a, b_s, binning="quantile") == pytest.approx(mi, abs=1e-12)
    r = np.corrcoef(a.ravel(), b.ravel())[0, 1]
    assert np.corrcoef(a.ravel(), b_s.ravel())[0, 1] < r - 0.05


def test_mi_masks_and_ignores_non_finite_values():
    a, b = _related_pair(3)
    mask = np.zeros(a.shape, bool)
    mask[20:150, 30:200] = True
    b_nan = b.copy()
    b_nan[~mask] = np.nan
    expected = mutual_information(a[20:150, 30:200], b[20:150, 30:200],
                                  range_a=(0, 255), range_b=(0, 255))
    assert mutual_information(a, b, mask=mask, range_a=(0, 255), range_b=(0, 255)) == \
        pytest.approx(expected, abs=1e-12)
    assert mutual_information(a, b_nan, range_a=(0, 255), range_b=(0, 255)) == \
        pytest.approx(expected, abs=1e-12)
    # Parzen smoothing of the joint histogram lowers the estimate a little, never raises it much.
    assert mutual_information(a, b, smoothing=1.0) < mutual_information(a, b) + 0.01


def test_mi_rejects_mismatched_shapes():
    with pytest.raises(ValueError):
        mutual_information(np.zeros((4, 4)), np.zeros((4, 5)))


# --------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def small():
    folder = sample_scene("small")
    return folder, Scene.load(folder / "outcrop.obj")


def _synthetic_photo(scene: Scene, intr: Intrinsics, pose: Pose, untextured: bool = False):
    """A render under PHOTO_LIGHT with gamma 0.6, a pale sky and noise, uint8."""
    src = Scene(scene.vertices, scene.faces) if untextured else scene
    rr = render(src, intr, pose, mode="shaded" if untextured else "color_shaded",
                light_direction=PHOTO_LIGHT)
    img = 255.0 * (rr.rgb / 255.0) ** 0.6
    img[~rr.mask] = (200, 220, 250)
    img += np.random.default_rng(5).normal(0.0, 3.0, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8), rr


@pytest.fixture(scope="module")
def aerial(small):
    """The cliff seen from 20 m up and 60 m out, with a little sky."""
    _, scene = small
    intr = Intrinsics.from_fov(800, 600, 60.0)
    truth = Pose.from_attitude(0.0, 3.0, 0.0, np.array([0.0, -60.0, 20.0]))
    photo, rr = _synthetic_photo(scene, intr, truth)
    return scene, photo, intr, truth, rr


def _perturbed(truth: Pose, rot_deg: float, pos_m: float, seed: int) -> Pose:
    """``truth`` turned by ``rot_deg`` about a random axis and moved ``pos_m``."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    shift = rng.normal(size=3)
    R = cv2.Rodrigues(axis / np.linalg.norm(axis) * math.radians(rot_deg))[0] @ truth.R
    return Pose.from_center(R, truth.center + shift / np.linalg.norm(shift) * pos_m)


def _errors(truth: Pose, pose: Pose) -> tuple[float, float]:
    return truth.rotation_error_deg(pose), float(np.linalg.norm(pose.center - truth.center))


def _rms_reprojection_px(truth: Pose, pose: Pose, intr: Intrinsics, points: np.ndarray,
                         intr_found: Intrinsics | None = None) -> float:
    d = truth.project(intr, points) - pose.project(intr_found or intr, points)
    return float(np.sqrt((d * d).sum(axis=1).mean()))


# ---------------------------------------------------------- known answers
@pytest.mark.parametrize("seed", [0, 1])
def test_refine_recovers_a_pose_1deg_1m_off(aerial, seed):
    scene, photo, intr, truth, rr = aerial
    start = _perturbed(truth, 1.0, 1.0, seed)
    res = refine_pose_mi(scene, photo, intr, start, DenseParams(levels=(128, 256, 512, 800)))
    assert isinstance(res, DenseResult)
    assert res.converged, res.reason
    rot, pos = _errors(truth, res.pose)
    assert rot < 0.1 and pos < 0.1, (rot, pos)
    points = rr.xyz[rr.mask][::40].astype(np.float64)
    assert _rms_reprojection_px(truth, res.pose, intr, points) < 0.4
    assert res.score > res.score_start
    assert res.sharpness > 0.15  # on the peak
    assert [lv.width for lv in res.history] == [128, 256, 512, 800]
    assert res.n_renders >= len(res.history) and res.n_evaluations > res.n_renders


@pytest.mark.parametrize("image", ["IMG_0002.jpg", "IMG_0003.jpg"])
def test_refine_sample_photo_under_another_sun(small, image):
    """The sample's own photo: other sun, shadows, wet rock, JPEG; near ground at ~4 m.

    A metre of position error moves that ground by ~100 px, beyond a dense
    method's reach; from 1° and 0.25 m it converges.
    """
    folder, scene = small
    truth = load_truth(folder / image)
    photo = cv2.cvtColor(cv2.imread(str(folder / image)), cv2.COLOR_BGR2RGB)
    start = _perturbed(truth.pose, 1.0, 0.25, seed=3)
    res = refine_pose_mi(scene, photo, truth.intrinsics, start)
    assert res.converged, res.reason
    rot, pos = _errors(truth.pose, res.pose)
    assert rot < 0.1 and pos < 0.1, (rot, pos)
    assert _rms_reprojection_px(truth.pose, res.pose, truth.intrinsics, truth.check_xyz) < 1.0


def test_refine_from_the_true_pose_stays_there(aerial):
    scene, photo, intr, truth, _ = aerial
    res = refine_pose_mi(scene, photo, intr, truth, DenseParams(levels=(512, 800)))
    rot, pos = _errors(truth, res.pose)
    assert rot < 0.05 and pos < 0.05, (rot, pos)
    assert res.score >= res.score_start


def test_refine_untextured_mesh_against_a_shading_photo(aerial):
    """No texture: the model's shading (light known) against a photo of the shape."""
    scene, _, intr, truth, _ = aerial
    bare = Scene(scene.vertices, scene.faces)
    photo, rr = _synthetic_photo(scene, intr, truth, untextured=True)
    start = _perturbed(truth, 1.0, 1.0, seed=0)
    res = refine_pose_mi(bare, photo, intr, start, DenseParams(modes=("shaded",)),
                         light_direction=PHOTO_LIGHT)
    assert res.converged, res.reason
    rot, pos = _errors(truth, res.pose)
    assert rot < 0.15 and pos < 0.15, (rot, pos)
    points = rr.xyz[rr.mask][::40].astype(np.float64)
    assert _rms_reprojection_px(truth, res.pose, intr, points) < 0.5


def test_refine_focal_length(aerial):
    scene, photo, intr, truth, rr = aerial
    wrong = replace(intr, fx=intr.fx * 1.02, fy=intr.fy * 1.02)
    start = _perturbed(truth, 0.5, 0.5, seed=4)
    res = refine_pose_mi(scene, photo, wrong, start, DenseParams(optimize_focal=True))
    assert res.converged, res.reason
    assert res.intrinsics.fx / intr.fx == pytest.approx(1.0, abs=0.004)
    assert res.intrinsics.fx == pytest.approx(res.intrinsics.fy * intr.fx / intr.fy)
    points = rr.xyz[rr.mask][::40].astype(np.float64)
    assert _rms_reprojection_px(truth, res.pose, intr, points, res.intrinsics) < 0.5


def test_refine_with_lens_distortion(small):
    _, scene = small
    intr = replace(Intrinsics.from_fov(640, 480, 60.0), dist=(-0.08, 0.02, 0.0, 0.0, 0.0))
    truth = Pose.from_attitude(10.0, 3.0, 1.0, np.array([5.0, -60.0, 20.0]))
    photo, rr = _synthetic_photo(scene, intr, truth)
    res = refine_pose_mi(scene, photo, intr, _perturbed(truth, 0.5, 0.5, seed=5))
    points = rr.xyz[rr.mask][::40].astype(np.float64)
    assert _rms_reprojection_px(truth, res.pose, intr, points) < 0.4


def test_refine_uses_a_custom_renderer(aerial):
    scene, photo, intr, truth, _ = aerial
    calls = []

    def render_fn(intrinsics, pose, scale):
        calls.append(scale)
        return render(scene, intrinsics, pose, scale=scale, mode="color")

    start = _perturbed(truth, 0.3, 0.3, seed=6)
    res = refine_pose_mi(None, photo, intr, start, DenseParams(levels=(128, 256)),
                         render_fn=render_fn)
    assert len(calls) == res.n_renders >= 2
    assert res.modes == ("detail", "normal")  # coloured: the renderer brings colour
    assert _errors(truth, res.pose)[0] < _errors(truth, start)[0]


def test_refine_keeps_the_keywords_and_the_renderer_of_version_0_1(aerial):
    """Settings as keywords and a ``render_fn(pose, scale)`` still work, with a warning,
    and give the same result as the parameter object."""
    scene, photo, intr, truth, _ = aerial
    start = _perturbed(truth, 0.3, 0.3, seed=6)
    params = DenseParams(levels=(128,), max_iterations=5)

    def old_render_fn(pose, scale):
        return render(scene, intr, pose, scale=scale, mode="color")

    with pytest.warns(DeprecationWarning, match="levels, max_iterations"):
        old = refine_pose_mi(scene, photo, intr, start, levels=(128,), max_iterations=5)
    new = refine_pose_mi(scene, photo, intr, start, params)
    assert np.array_equal(old.pose.R, new.pose.R) and np.array_equal(old.pose.t, new.pose.t)
    assert old.score == new.score
    with pytest.warns(DeprecationWarning, match=r"render_fn\(pose, scale\)"):
        old = refine_pose_mi(None, photo, intr, start, params, render_fn=old_render_fn)
    assert old.n_renders >= 1
    with pytest.raises(TypeError, match="levelz"):
        refine_pose_mi(scene, photo, intr, start, levelz=(128,))


def test_refine_stops_when_cancelled_and_keeps_the_start(aerial):
    scene, photo, intr, truth, _ = aerial
    start = _perturbed(truth, 1.0, 1.0, seed=0)
    res = refine_pose_mi(scene, photo, intr, start, cancelled=lambda: True)
    assert res.reason == "cancelled" and not res.converged
    assert res.pose is start
    res = refine_pose_mi(scene, photo, intr, start, DenseParams(max_seconds=0.0))
    assert res.reason == "time limit"


@pytest.mark.parametrize("kwargs, words", [
    ({"levels": ()}, "levels"),
    ({"levels": (16, 256)}, "levels"),
    ({"levels": (128.5,)}, "integers"),
    ({"bins": 4}, "bins"),
    ({"max_step_px": 0.0}, "max_step_px"),
    ({"supersample": True}, "supersample"),
    ({"modes": ("normal", "colour")}, "colour"),
    ({"modes": "normal"}, "list"),
    ({"modes": ()}, "empty"),
])
def test_dense_params_reject_values_out_of_range(kwargs, words):
    with pytest.raises(ValueError, match=words):
        DenseParams(**kwargs)


def test_dense_params_defaults_lie_in_their_ranges_and_lists_become_tuples():
    p = DenseParams()
    assert set(p.RANGES) <= {f for f in p.to_dict()}
    q = DenseParams(levels=[128, 256], modes=["shaded", "normal"])
    assert q.levels == (128, 256) and q.modes == ("shaded", "normal")
    assert DenseParams.from_dict(q.to_dict()) == q
    with pytest.raises(KeyError, match="max_second"):
        DenseParams.from_dict({"max_second": 3})


def test_refine_rejects_a_photo_of_the_wrong_size(aerial):
    scene, photo, intr, truth, _ = aerial
    with pytest.raises(ValueError):
        refine_pose_mi(scene, photo[:100], intr, truth)


# ------------------------------------------------------------ verification
def test_mi_score_prefers_the_true_pose(small):
    """Right vs wrong poses on a sample photo (other sun): the true pose scores highest."""
    folder, scene = small
    truth = load_truth(folder / "IMG_0001.jpg")
    photo = cv2.cvtColor(cv2.imread(str(folder / "IMG_0001.jpg")), cv2.COLOR_BGR2RGB)
    intr = truth.intrinsics
    right = mi_scores(scene, photo, intr, truth.pose)
    assert set(right["per_mode"]) == {"detail", "normal"}
    assert 1.0 < right["nmi"] < 2.0 and right["mi"] > 0
    turned = mi_scores(scene, photo, intr, _perturbed(truth.pose, 2.0, 0.0, seed=7))
    moved = mi_scores(scene, photo, intr, _perturbed(truth.pose, 0.0, 5.0, seed=8))
    for wrong in (turned, moved):
        assert right["nmi"] > wrong["nmi"] + 0.04
        assert right["mi"] > 2 * wrong["mi"]
        # The right pose sits on a peak, a wrong one does not.
        assert right["sharpness"] > 0.3 > 0.1 > wrong["sharpness"]
    assert mi_score(scene, photo, intr, truth.pose) == pytest.approx(right["nmi"])
    assert mi_score(scene, photo, intr, truth.pose, normalized=False) == \
        pytest.approx(right["mi"])
