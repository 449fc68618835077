"""Unknown intrinsics end to end: a record with the camera's size only is
registered with its focal length estimated, and RESULT.json says so."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from PIL import Image

from napari_imgreg import Scene
from napari_imgreg.camera import Intrinsics, Pose
from napari_imgreg.errors import InputError
from napari_imgreg.io.photos import load_photo
from napari_imgreg.io.records import parse_sensor_record
from napari_imgreg.prior import load_camera_and_pose, prior_for_photo, prior_from_record
from napari_imgreg.registration.params import RegistrationParams
from napari_imgreg.registration.pipeline import register
from napari_imgreg.registration.pose import PoseParams, estimate_pose
from napari_imgreg.registration.uncertainty import Uncertainty
from napari_imgreg.sample import load_truth, sample_scene
from napari_imgreg.validate import FieldValueError

W, H = 1024, 768


# --------------------------------------------------------------- the camera
def test_a_record_without_focal_gives_an_unknown_focal():
    record = parse_sensor_record({"camera": {"width": W, "height": H},
                                  "position": {"x": 0, "y": 0, "z": 1},
                                  "orientation": {"trend_deg": 0}})
    prior = prior_from_record(record)
    intr = prior.intrinsics
    assert not intr.focal_known and intr.estimated == ("fx", "fy")
    assert intr.hfov_deg == pytest.approx(65.0)  # the start of the estimation
    assert any("estimated during registration" in a for a in prior.assumptions)
    known = prior_from_record(parse_sensor_record(
        {"camera": {"width": W, "height": H, "fx": 800.0}, "position": {"x": 0, "y": 0, "z": 1},
         "orientation": {"trend_deg": 0}}))
    assert known.intrinsics.focal_known and "estimated" not in known.intrinsics.to_dict()


def test_estimated_survives_the_camera_operations():
    intr = Intrinsics(W, H, 800.0, 800.0, 511.5, 383.5, estimated=["fy", "fx"])
    assert intr.estimated == ("fx", "fy")  # one order
    assert Intrinsics.from_dict(intr.to_dict()) == intr
    assert intr.to_dict()["estimated"] == ["fx", "fy"]
    assert intr.scaled(0.5).estimated == intr.estimated
    assert intr.rotated(1).estimated == intr.estimated
    with pytest.raises(FieldValueError, match="estimated"):
        Intrinsics(W, H, 800.0, 800.0, 511.5, 383.5, estimated=("k7",))
    with pytest.raises(InputError, match="camera.estimated"):
        parse_sensor_record({"camera": {"width": W, "height": H, "estimated": "fx"}}, "r.json")


def test_pose_params_solver_is_checked_and_read_from_params_files():
    assert PoseParams().solver == "auto"
    with pytest.raises(ValueError, match="solver"):
        PoseParams(solver="p3p")
    with pytest.raises(ValueError, match="min_hfov_deg"):
        PoseParams(min_hfov_deg=90.0, max_hfov_deg=60.0)
    params = RegistrationParams.from_dict({"pose": {"solver": "dlt", "estimate_k1": True}})
    assert params.pose.solver == "dlt" and params.pose.estimate_k1
    with pytest.raises(InputError, match="solver"):
        RegistrationParams.from_dict({"pose": {"solver": "nope"}}, "params.json")
    with pytest.raises(InputError, match="pose.solver"):
        RegistrationParams.from_dict({"pose": {"solver": 3}}, "params.json")


# ----------------------------------------------------------------- the pose
def _pairs(planar=False, n=300, seed=2):
    rng = np.random.default_rng(seed)
    truth = Intrinsics(W, H, 777.0, 777.0, 511.5, 383.5)
    pose = Pose.from_attitude(20.0, 5.0, 1.0, np.array([0.0, -70.0, 10.0]))
    px = np.c_[rng.uniform(0, W - 1, n), rng.uniform(0, H - 1, n)]
    if planar:  # the cliff y = 0
        rays = pose.rays(truth, px)[1]
        c = pose.center
        X = c + rays * (-c[1] / rays[:, 1])[:, None]
    else:
        X = pose.inverse_transform(truth.unproject(px, rng.uniform(50, 100, n)))
    x = pose.project(truth, X) + rng.normal(0, 0.5, (n, 2))
    x[: n // 4] = rng.uniform(0, W - 1, (n // 4, 2))  # 25 % outliers
    return truth, pose, X, x


@pytest.mark.parametrize("solver,planar,method", [
    ("auto", False, "p4pf"), ("auto", True, "p4pf"), ("dlt", False, "dlt"), ("dlt", True, "p4pf")])
def test_estimate_pose_estimates_an_unknown_focal(solver, planar, method):
    truth, pose, X, x = _pairs(planar)
    start = Intrinsics.from_fov(W, H, 65.0)
    start = replace(start, estimated=("fx", "fy"))
    params = PoseParams(reprojection_error_px=4.0, solver=solver)
    est = estimate_pose(start, X, x, params, auto_focal=True)
    assert est.ok, est.reason
    assert est.solver == method and est.intrinsics is not None
    assert est.intrinsics.fx == pytest.approx(777.0, rel=0.005)
    assert est.pose.rotation_error_deg(pose) < 0.1
    assert {"fx", "fy"} <= set(est.intrinsics.estimated)
    if method == "dlt":
        assert {"cx", "cy"} <= set(est.intrinsics.estimated)


def test_a_direct_call_keeps_the_camera_unless_told():
    truth, pose, X, x = _pairs()
    start = replace(truth, estimated=("fx", "fy"))
    est = estimate_pose(start, X, x, PoseParams(reprojection_error_px=4.0))
    assert est.ok and est.solver == "epnp" and est.intrinsics is None
    # A known focal length is estimated only when the solver says so.
    forced = estimate_pose(truth, X, x, PoseParams(reprojection_error_px=4.0, solver="p4pf"))
    assert forced.ok and forced.intrinsics.estimated == ("fx", "fy")


# -------------------------------------------------------------- end to end
@pytest.fixture(scope="module")
def sample():
    folder = sample_scene("small")
    scene = Scene.load(folder / "outcrop.obj", dem=folder / "dem.tif")
    scene.build_engine()
    return folder, scene


def test_width_height_only_record_registers_with_the_focal_estimated(sample, tmp_path):
    folder, scene = sample
    name = "IMG_0001"
    # The photo without its EXIF (which gives a focal length) and a record
    # with the camera's size only.
    Image.fromarray(load_photo(folder / f"{name}.jpg").image).save(tmp_path / f"{name}.png")
    record = json.loads((folder / f"{name}.json").read_text())
    record["camera"] = {"width": record["camera"]["width"], "height": record["camera"]["height"]}
    (tmp_path / f"{name}.json").write_text(json.dumps(record))
    photo = load_photo(tmp_path / f"{name}.png")
    prior = prior_for_photo(photo, scene)
    assert not prior.intrinsics.focal_known
    truth = load_truth(folder / f"{name}.jpg")
    true_fx = 4.25 * W / 5.6  # the sample's camera: 4.25 mm on a 5.6 mm-wide sensor
    assert abs(prior.intrinsics.fx / true_fx - 1) > 0.03  # the start really is off

    # Small and fast: one trial at 512 px, no robust stages.
    params = RegistrationParams(match_width=512, max_trials=1, search_prior=False,
                                sun_relight=False, edge_align=False, dense_refine=False,
                                area_match=False)
    reg = register(scene, photo.image, prior, params, photo_name=f"{name}.png")
    assert reg.status == "registered", reg.hints
    assert reg.intrinsics.fx == pytest.approx(true_fx, rel=0.01)
    assert reg.intrinsics.fy == reg.intrinsics.fx
    assert reg.pose.rotation_error_deg(truth.pose) < 0.2
    proj = reg.pose.project(reg.intrinsics, truth.check_xyz)
    assert np.median(np.linalg.norm(proj - truth.check_pixels, axis=1)) < 1.5

    result = tmp_path / f"{name}.result.json"
    result.write_text(json.dumps(reg.to_dict()))
    data = json.loads(result.read_text())
    assert data["camera"]["estimated"] == ["fx", "fy"]
    assert data["camera"]["fx"] == pytest.approx(reg.intrinsics.fx)
    assert data["uncertainty"]["reprojection_px"] < 4.0  # still estimated
    # The focal length's expected error, from draws that re-solve it: a
    # fraction of a percent here, and the true error within 3 × of it.
    focal_px = data["uncertainty"]["focal_px"]
    assert 0 < focal_px < 0.01 * true_fx
    assert abs(reg.intrinsics.fx - true_fx) < 3 * focal_px + 0.5
    assert Uncertainty.from_dict(data["uncertainty"]).focal_px == pytest.approx(focal_px)
    assert any(f"± {focal_px:.1f} px" in h for h in data["quality"]["hints"])
    assert {"inliers_3d", "reprojection_error_px"} <= set(data["metrics"])
    assert any("estimated" in h for h in data["quality"]["hints"])
    assert any("estimated during registration: fx" in a for a in reg.assumptions)
    camera, pose, kind, _ = load_camera_and_pose(result)  # what render/project read
    assert kind == "result" and camera == reg.intrinsics


@pytest.mark.parametrize("factor", [1.4, 0.6])
def test_a_wrong_focal_length_in_the_record_is_estimated_when_nothing_verifies(sample, factor):
    """The record's focal length 40 % off: no trial verifies with it, the
    matches of one fit the true focal length far better, so one more trial
    estimates it (before, five trials failed and the result said 'fair')."""
    folder, scene = sample
    name = "IMG_0002"
    photo = load_photo(folder / f"{name}.jpg")
    prior = prior_for_photo(photo, scene)
    truth = load_truth(folder / f"{name}.jpg")
    true_fx = prior.intrinsics.fx
    wrong = replace(prior.intrinsics, fx=factor * true_fx, fy=factor * prior.intrinsics.fy)
    prior = replace(prior, intrinsics=wrong)
    params = RegistrationParams(match_width=512, max_trials=2, search_prior=False,
                                sun_relight=False, edge_align=False, dense_refine=False,
                                area_match=False)
    reg = register(scene, photo.image, prior, params, photo_name=name)
    assert reg.status == "registered", reg.hints
    assert reg.intrinsics.estimated == ("fx", "fy")
    assert reg.intrinsics.fx == pytest.approx(true_fx, rel=0.01)
    assert reg.pose.rotation_error_deg(truth.pose) < 0.2
    assert any("did not fit the photo" in a for a in reg.assumptions)
    assert reg.trials[reg.best_trial].origin == "focal length"
    # Without adaptation the record's focal length stands, and fails.
    fixed = register(scene, photo.image, prior, replace(params, auto_adapt=False),
                     photo_name=name)
    assert fixed.status == "failed" and fixed.intrinsics.fx == wrong.fx
