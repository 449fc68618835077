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
