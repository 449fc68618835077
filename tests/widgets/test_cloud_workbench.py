"""The workbench on a lidar point cloud (issue 16): the cloud opens as the
model, shows as a Points layer in 3D, and the photo gets its intensity render."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("napari")

from napari_imgreg.io.pointclouds import PointCloud, write_point_cloud  # noqa: E402


def _wall_cloud(path, n=60_000, seed=0):
    """A 40 × 20 m wall at y = 0 facing -y, beds of two intensities."""
    rng = np.random.default_rng(seed)
    x, z = rng.uniform(-20, 20, n), rng.uniform(0, 20, n)
    xyz = np.column_stack([x, rng.normal(0, 0.005, n), z])
    intensity = np.where((z // 2) % 2 == 0, 0.6, 0.3).astype(np.float32)
    write_point_cloud(path, PointCloud(xyz=xyz, intensity=intensity))


def test_a_point_cloud_opens_as_points_and_renders_intensity(workbench, qtbot, tmp_path):
    import json

    cloud = tmp_path / "scan.ply"
    _wall_cloud(cloud)
    photo = tmp_path / "IMG_0001.png"
    import cv2

    cv2.imwrite(str(photo), np.full((240, 320, 3), 128, np.uint8))
    photo.with_suffix(".json").write_text(json.dumps({
        "camera": {"width": 320, "height": 240, "fx": 300.0, "fy": 300.0, "cx": 160, "cy": 120},
        "position": {"x": 0.0, "y": -30.0, "z": 10.0},
        "orientation": {"trend_deg": 0.0, "plunge_deg": 0.0, "roll_deg": 0.0}}))
    ctrl = workbench.controller
    ctrl.open_scene(cloud, photos=[photo])
    qtbot.waitUntil(lambda: ctrl.current is not None, timeout=60_000)
    qtbot.waitUntil(lambda: ctrl.last_render is not None, timeout=60_000)
    layer = ctrl.layers.get("surface")
    assert layer is not None and type(layer).__name__ == "Points"
    assert len(layer.data) == 60_000  # under the display cap: every point
    # The Scene tab says what the scan shows (not "no texture") and keeps the
    # reader's notes in view (the status line moved on to the photos).
    summary = workbench.scene_panel.scene_label.text()
    assert "60,000 points, intensity," in summary and "texture" not in summary, summary
    assert "<li>PLY files carry no CRS: coordinates taken as the model frame</li>" in summary
    render = ctrl.last_render
    assert render.mask.mean() > 0.75  # the wall fills the view but for ground and sky
    # Intensity, not shading: the beds' two levels are in the render.
    grey = render.rgb[render.mask, 0]
    assert np.percentile(grey, 90) - np.percentile(grey, 10) > 40
    # The depth is the wall's: 30 m straight ahead.
    assert abs(np.nanmedian(render.depth) - 30.0) < 0.1


def _wall_and_ground_cloud(path, n=120_000, seed=1):
    """The wall of :func:`_wall_cloud` standing on a ground plane in front of it
    (z = 0, y in [-15, 0]): control points off one plane for the solver."""
    rng = np.random.default_rng(seed)
    m = n // 2
    wall = np.column_stack([rng.uniform(-20, 20, m), rng.normal(0, 0.003, m),
                            rng.uniform(0, 20, m)])
    ground = np.column_stack([rng.uniform(-20, 20, m), rng.uniform(-15, 0, m),
                              rng.normal(0, 0.003, m)])
    xyz = np.vstack([wall, ground])
    # A checker of intensities: corners a user can click on both images.
    cells = (np.floor(xyz[:, 0] / 2) + np.floor((xyz[:, 2] + xyz[:, 1]) / 2)) % 2
    write_point_cloud(path, PointCloud(xyz=xyz, intensity=(0.3 + 0.4 * cells).astype(np.float32)))


def test_manual_pairs_on_the_intensity_render_of_a_cloud_recover_the_pose(workbench, qtbot,
                                                                        tmp_path):
    """Issue 16 item 5: control points against a cloud's intensity render."""
    import json

    import cv2

    from napari_imgreg.camera import Intrinsics, Pose

    cloud = tmp_path / "scan.ply"
    _wall_and_ground_cloud(cloud)
    photo = tmp_path / "IMG_0001.png"
    cv2.imwrite(str(photo), np.full((480, 640, 3), 128, np.uint8))
    photo.with_suffix(".json").write_text(json.dumps({  # the sensors: 3° and ~1.4 m off
        "camera": {"width": 640, "height": 480, "fx": 600.0, "fy": 600.0, "cx": 320, "cy": 240},
        "position": {"x": 1.0, "y": -31.0, "z": 9.0},
        "orientation": {"trend_deg": 3.0, "plunge_deg": 12.0, "roll_deg": 0.0}}))
    intr = Intrinsics(640, 480, 600.0, 600.0, 320.0, 240.0)
    truth = Pose.from_attitude(0.0, 15.0, 0.0, np.array([0.0, -30.0, 10.0]))
    ctrl = workbench.controller
    ctrl.open_scene(cloud, photos=[photo])
    qtbot.waitUntil(lambda: ctrl.current is not None, timeout=60_000)
    qtbot.waitUntil(lambda: not ctrl.busy, timeout=60_000)
    with qtbot.waitSignal(ctrl.reference_ready, timeout=60_000):
        ctrl.make_reference("pose")
    ref = ctrl.current.reference
    # Points on the wall and on the ground, seen by both cameras.
    xyz = np.array([[x, 0.0, z] for x in (-7.0, 0.0, 7.0) for z in (7.0, 12.0)]
                   + [[x, -2.0, 0.0] for x in (-6.0, 0.0, 6.0)])
    photo_px = truth.project(intr, xyz)
    ref_px = ref.cam_from_world.project(ref.intrinsics, xyz)
    lifted, valid = ref.lift(ref_px)
    # The render's 3D is the cloud's: within a point spacing on the wall; on the
    # ground, seen at 20°, a splat's centre depth can be a spacing / tan(20°) off.
    assert valid.all() and np.abs(lifted - xyz)[:6].max() < 0.05
    assert np.abs(lifted - xyz)[6:].max() < 0.25
    ctrl.workspace.set_pair_points(photo_px, ref_px)
    with qtbot.waitSignal(ctrl.manual_finished, timeout=60_000) as solved:
        ctrl.solve_manual()
    sol = solved.args[0]
    assert sol.ok
    assert ctrl.current.pose.rotation_error_deg(truth) < 0.5  # from 3° off
    assert np.linalg.norm(ctrl.current.pose.center - truth.center) < 0.5  # from 1.7 m off
