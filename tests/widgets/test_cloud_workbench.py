"""The workbench on a lidar point cloud (issue 16): the cloud opens as the
model, shows as a Points layer in 3D, and the photo gets its intensity render."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("napari")

from napari_imgreg.io.pointclouds import PointCloud, write_point_cloud  # noqa: E402
from napari_imgreg.widgets.workbench import Workbench  # noqa: E402


@pytest.fixture
def workbench(make_napari_viewer, qtbot):
    viewer = make_napari_viewer()
    wb = Workbench.add_to_viewer(viewer)
    yield wb
    qtbot.waitUntil(lambda: not wb.controller.busy, timeout=30_000)


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
    render = ctrl.last_render
    assert render.mask.mean() > 0.75  # the wall fills the view but for ground and sky
    # Intensity, not shading: the beds' two levels are in the render.
    grey = render.rgb[render.mask, 0]
    assert np.percentile(grey, 90) - np.percentile(grey, 10) > 40
    # The depth is the wall's: 30 m straight ahead.
    assert abs(np.nanmedian(render.depth) - 30.0) < 0.1
