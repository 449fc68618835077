"""The top-level functions a script calls first: known answers end to end."""

from __future__ import annotations

import subprocess
import sys
import warnings

import numpy as np
import pytest

import napari_imgreg as ir
from napari_imgreg.sample import load_truth, sample_scene


@pytest.fixture(scope="module")
def folder():
    return sample_scene("small")


def test_import_is_light_and_lazy():
    # napari imports the package to read its manifest: not the stage packages.
    code = ("import sys, napari_imgreg; print(any(m.startswith(tuple("
            "'napari_imgreg.' + p for p in ('registration', 'interpret', 'orient', 'sample')))"
            " for m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
    assert set(ir.__all__) <= set(dir(ir))


def test_register_project_measure_from_paths(folder):
    truth = load_truth(folder / "IMG_0001.jpg")
    scene = ir.Scene.load(folder / "outcrop.obj", dem=folder / "dem.tif")
    reg = ir.register(scene, folder / "IMG_0001.jpg")  # the sensor record beside it
    assert isinstance(reg, ir.Registration) and reg.status == "registered"
    assert reg.pose.rotation_error_deg(truth.pose) < 0.2
    # A horizontal line across the middle of the photo lands on the model,
    # at the points the true camera sees there.
    w, h = reg.intrinsics.width, reg.intrinsics.height
    line = ir.Interpretation("LineString", [[0.3 * w, 0.5 * h], [0.7 * w, 0.5 * h]],
                             {"label": "bed"})
    features = ir.project(scene, reg, [line])
    assert features and all(isinstance(f, ir.Feature3D) for f in features)
    pts = np.concatenate([p for f in features for p in f.parts])
    px = truth.pose.project(truth.intrinsics, pts)
    assert np.median(np.abs(px[:, 1] - 0.5 * h)) < 2.0
    measurements = ir.measure(features)
    assert len(measurements) == len(features)
    assert all(isinstance(m, ir.Measurement) for m in measurements)


def test_orient_is_callable_as_the_package_and_the_function():
    from napari_imgreg.orient import OrientationResult
    from napari_imgreg.sample.survey import simulate_survey

    survey = simulate_survey(np.random.default_rng(3))
    result = ir.orient(survey.estimated, survey.measured)  # the package, called
    assert isinstance(result, OrientationResult)
    import napari_imgreg.orient as orient_package

    assert ir.orient is orient_package and callable(orient_package)
    again = orient_package.orient(survey.estimated, survey.measured)
    assert np.allclose(again.delta_xi_deg, result.delta_xi_deg) and again.method == result.method


def test_old_module_paths_warn_and_resolve():
    from napari_imgreg.registration import pipeline

    for old in ("napari_imgreg.pipeline",):
        sys.modules.pop(old, None)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        import napari_imgreg.pipeline as old_pipeline  # noqa: F401
    assert old_pipeline is pipeline
    assert any(issubclass(w.category, DeprecationWarning) and "registration.pipeline"
               in str(w.message) for w in caught)


# ------------------------------------------------- what a script hands over
@pytest.fixture(scope="module")
def registered(folder):
    scene = ir.Scene.load(folder / "outcrop.obj", dem=folder / "dem.tif")
    reg = ir.register(scene, folder / "IMG_0001.jpg")
    assert reg.status == "registered"
    return scene, reg


def test_project_takes_the_registrations_own_pose_error(folder, registered, tmp_path):
    """The sigmas of ``project(scene, reg)`` come from the registration's
    uncertainty, as the command line's do from its RESULT.json; a failed
    registration gets the sensor prior's error."""
    import dataclasses

    from napari_imgreg.interpret.uncertainty import PoseUncertainty

    scene, reg = registered
    w, h = reg.intrinsics.width, reg.intrinsics.height
    line = [ir.Interpretation("LineString", [[0.3 * w, 0.5 * h], [0.5 * w, 0.52 * h],
                                             [0.7 * w, 0.5 * h]])]
    own = PoseUncertainty.from_estimate(reg.uncertainty, reg.status, reg.metrics,
                                        reg.intrinsics.fx)
    assert own.source == "result"
    by_reg = ir.measure(ir.project(scene, reg, line))[0]
    given = ir.measure(ir.project(scene, (reg.intrinsics, reg.pose), line,
                                  pose_uncertainty=own))[0]
    assert by_reg.plunge_sigma_deg == pytest.approx(given.plunge_sigma_deg)
    # The same through the RESULT.json path, as `napari-imgreg project` reads it.
    result = tmp_path / "IMG_0001.result.json"
    import json

    result.write_text(json.dumps(reg.to_dict()))
    by_file = ir.measure(ir.project(scene, result, line))[0]
    assert by_file.plunge_sigma_deg == pytest.approx(by_reg.plunge_sigma_deg, rel=1e-3)
    failed = dataclasses.replace(reg, status="failed", uncertainty=None)
    by_failed = ir.measure(ir.project(scene, failed, line))[0]
    assert by_failed.plunge_sigma_deg > 5 * by_reg.plunge_sigma_deg
    # Read back, the registration is the one written.
    again = ir.load_registration(result)
    assert again.status == reg.status and again.grade == reg.grade
    assert np.allclose(again.pose.R, reg.pose.R) and np.allclose(again.pose.t, reg.pose.t)
    assert again.uncertainty.reprojection_px == pytest.approx(reg.uncertainty.reprojection_px,
                                                             abs=1e-3)  # written rounded
    assert len(again.trials) == len(reg.trials)
    assert len(repr(again)) < 200 and "registered" in repr(again)


def test_a_pose_that_is_not_a_camera_is_refused_before_any_ray(registered):
    scene, reg = registered
    nan_pose = ir.Pose(reg.pose.R, [np.nan, 0.0, 0.0])
    with pytest.raises(ir.InputError, match="non-finite"):
        ir.render(scene, reg.intrinsics, nan_pose, scale=0.25)
    with pytest.raises(ir.InputError, match="not a rotation"):
        ir.render(scene, reg.intrinsics, ir.Pose(3 * reg.pose.R, reg.pose.t), scale=0.25)
    with pytest.raises(ir.InputError, match="ambient"):
        ir.render(scene, reg.intrinsics, reg.pose, scale=0.25, ambient=2.0)
    with pytest.raises(ir.InputError, match="light_direction"):
        ir.render(scene, reg.intrinsics, reg.pose, scale=0.25, mode="shaded",
                  light_direction=[0.0, 0.0, 0.0])
    with pytest.raises(ir.InputError, match="non-finite"):
        ir.project(scene, (reg.intrinsics, nan_pose), [])


def test_points_of_the_wrong_shape_are_refused_not_reshaped(registered):
    _, reg = registered
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        ir.Interpretation("LineString", np.zeros((4, 3)))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        reg.pose.project(reg.intrinsics, np.zeros((3, 4)))  # transposed
    assert reg.pose.project(reg.intrinsics, np.zeros(3) + [0, 0, 1]).shape == (1, 2)
    assert reg.pose.transform(np.zeros((5, 7, 3))).shape == (35, 3)  # a grid of points


def test_inputs_a_script_has_at_hand(folder, registered, tmp_path):
    from napari_imgreg.io.photos import load_photo

    scene, reg = registered
    # A misspelt record is an error, not a quiet fall-back to the EXIF.
    with pytest.raises(ir.InputError, match="no such file"):
        ir.register(scene, folder / "IMG_0001.jpg", prior=folder / "IMG_0001_typo.json")
    # An image in memory needs a prior; a grey one is taken as RGB; floats are refused.
    image = load_photo(folder / "IMG_0001.jpg").image
    with pytest.raises(ir.InputError, match="needs a prior"):
        ir.register(scene, image)
    with pytest.raises(ir.InputError, match="uint8"):
        ir.Photo(image.astype(float) / 255)
    assert ir.Photo(image[..., 0]).image.shape == image.shape
    # An earlier registration as the start, and parameters as a dict.
    again = ir.register(scene, image, prior=reg, params={"max_trials": 1})
    assert again.status == "registered"
    assert again.pose.rotation_error_deg(reg.pose) < 0.1
    # A bad field value is an InputError too.
    with pytest.raises(ir.InputError):
        ir.RegistrationParams(max_trials=0)
    # One path to add, not one per character.
    ws = ir.Workspace()
    ws.open_scene(folder / "outcrop.obj", dem=folder / "dem.tif")
    assert ws.add_photos(str(folder / "IMG_0002.jpg")) == [] and len(ws.photos) == 1


def test_a_dem_scene_uses_the_georef_beside_it(folder):
    scene = ir.Scene.from_dem(folder / "dem.tif")
    frame = ir.Scene.load(folder / "outcrop.obj")
    assert np.allclose(scene.georef.origin, frame.georef.origin)
    assert np.allclose(ir.Scene.from_dem(folder / "dem.tif",
                                         georef=folder / "georef.json").georef.origin,
                       frame.georef.origin)
