"""The interpretation dock widget in a real napari viewer (run under Xvfb)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from matplotlib.colors import to_hex
from scipy.spatial import cKDTree

from napari_imgreg import Scene
from napari_imgreg.widgets._layers import napari_from_pixels, surface_layer_data, world_from_napari
from napari_imgreg.io.photos import load_photo
from napari_imgreg.sample import load_truth, sample_scene
from napari_imgreg.widgets.interpret_widget import (
    INTERP_KEY,
    PROJECTED_KEY,
    InterpretWidget,
    camera_of_layer,
    interpretations_from_shapes,
)


@pytest.fixture(scope="module")
def sample():
    folder = sample_scene("small")
    scene = Scene.load(folder / "outcrop.obj", dem=folder / "dem.tif")
    return folder, scene, load_truth(folder)


@pytest.fixture
def widget(make_napari_viewer, sample):
    folder, scene, truth = sample
    viewer = make_napari_viewer()
    data, kwargs, _ = surface_layer_data(scene, name="sample outcrop")
    viewer.add_surface(data, **kwargs)
    photo = load_photo(folder / "IMG_0001.jpg")
    pt = truth.photos["IMG_0001.jpg"]
    # A registered photo: its RESULT.json carried in the layer's metadata.
    result = {"status": "registered", "photo": "IMG_0001.jpg",
              "camera": pt.intrinsics.to_dict(), "pose": pt.pose.to_dict()}
    viewer.add_image(photo.image, rgb=True, name="IMG_0001", metadata={"result": result})
    w = InterpretWidget(viewer)
    viewer.window.add_dock_widget(w, name="Interpret")
    w.photo_combo.setCurrentText("IMG_0001")
    w.surface_combo.setCurrentText("sample outcrop")
    return w


def _true_bed_on_photo(sample, min_px=150.0):
    """A true bed boundary visible in IMG_0001, as pixels, and its 3D trace."""
    folder, scene, truth = sample
    pt = truth.photos["IMG_0001.jpg"]
    best = None
    for feat in truth.lines["features"]:
        if feat["properties"]["label"] != "bed_boundary":
            continue
        xyz = np.asarray(feat["geometry"]["coordinates"])
        px = pt.pose.project(pt.intrinsics, xyz)
        ok = np.isfinite(px).all(1) & (px[:, 0] > 5) & (px[:, 1] > 5)
        ok &= (px[:, 0] < pt.intrinsics.width - 5) & (px[:, 1] < pt.intrinsics.height - 5)
        if ok.all():
            length = np.linalg.norm(np.diff(px, axis=0), axis=1).sum()
            if length > min_px and (best is None or length > best[2]):
                best = (px, xyz, length)
    assert best is not None
    return best[0], best[1]


def test_registered_photo_and_label_classes(widget):
    layer = widget.photo_layer
    intr, pose, name = camera_of_layer(layer)
    assert name == "IMG_0001.jpg" and intr.width == 1024
    assert [widget.label_combo.itemText(k) for k in range(3)] == ["sandstone", "mudstone", "fault"]
    shapes = widget.new_interpretation_layer()
    assert shapes.metadata[INTERP_KEY] == "IMG_0001" and shapes.mode == "add_path"
    assert to_hex(shapes.current_edge_color) == "#ffd400"  # sandstone yellow
    widget.add_label("coal")
    assert widget.current_label == "coal" and shapes.feature_defaults["label"][0] == "coal"
    widget.label_combo.setCurrentText("fault")
    assert to_hex(shapes.current_edge_color) == "#e31a1c"  # fault red


def test_draw_project_and_find_it_on_the_mesh(widget, sample, qtbot, tmp_path):
    folder, scene, truth = sample
    px, xyz = _true_bed_on_photo(sample)
    shapes = widget.new_interpretation_layer()
    # Draw the bed boundary as the geologist would: a path on the photo.
    shapes.add(napari_from_pixels(px), shape_type="path")
    widget.label_combo.setCurrentText("fault")
    shapes.add(napari_from_pixels(np.array([[300.0, 100.0], [320.0, 700.0]])), shape_type="path")
    items = interpretations_from_shapes(shapes)
    assert [i.label for i in items] == ["sandstone", "fault"]
    np.testing.assert_allclose(items[0].pixels, px)

    with qtbot.waitSignal(widget.projection_done, timeout=30000) as blocker:
        worker = widget.project()
    assert worker is not None  # projected in a thread worker, not on the GUI thread
    qtbot.waitUntil(lambda: widget.project_button.isEnabled(), timeout=5000)
    features = blocker.args[0]
    bed = features[0]
    assert bed.source == "IMG_0001.jpg" and bed.label == "sandstone"
    # On the mesh: every point within 5 cm of the true 3D bed boundary.
    t = np.linspace(0, 1, 30)[:, None, None]
    dense = (xyz[:-1][None] * (1 - t) + xyz[1:][None] * t).reshape(-1, 3)
    d = cKDTree(dense).query(bed.points)[0]
    assert np.median(d) < 0.03 and np.percentile(d, 95) < 0.1

    # The 3D layer shows it where the mesh is, in napari's (z, x, y) order.
    layer3d = next(lay for lay in widget.viewer.layers if PROJECTED_KEY in lay.metadata)
    assert layer3d.metadata[PROJECTED_KEY] == "IMG_0001.jpg" and layer3d.ndim == 3
    first = world_from_napari(np.asarray(layer3d.data[0]))
    np.testing.assert_allclose(first, bed.parts[0], atol=1e-4)
    assert list(layer3d.features["label"])[0] == "sandstone"
    widget.show_3d()  # the 3D canvas, from the photo's viewpoint, photo layers hidden
    assert widget.viewer.dims.ndisplay == 3 and layer3d.visible
    assert not widget.photo_layer.visible and not shapes.visible
    layer3d.visible = False  # togglable per photo
    assert not layer3d.visible

    # Table and stereonet.
    assert widget.table.rowCount() == len(widget.measurements) >= 1
    assert widget.table.item(0, 1).text() == "sandstone"
    assert float(widget.table.item(0, 3).text()) == pytest.approx(12.0, abs=1.0)
    assert widget.figure.axes and widget.figure.axes[0].lines

    # Save / load pixel GeoJSON and exports.
    path = tmp_path / "IMG_0001.lines.geojson"
    assert widget.save_geojson(path) == 2
    doc = json.loads(path.read_text())
    assert [f["properties"]["label"] for f in doc["features"]] == ["sandstone", "fault"]
    widget.viewer.layers.remove(shapes)
    loaded = widget.load_geojson(path)  # from the 3D canvas: back to drawing in 2D
    assert widget.viewer.dims.ndisplay == 2 and widget.photo_layer.visible
    assert len(loaded.data) == 2 and list(loaded.features["label"]) == ["sandstone", "fault"]
    widget.export(tmp_path / "lines3d.geojson", georeferenced=True)
    geo = json.loads((tmp_path / "lines3d.geojson").read_text())
    assert geo["napari_imgreg"]["frame"] == "crs"
    widget.save_measurements(tmp_path / "m.csv")
    widget.save_stereonet(tmp_path / "net.png")
    assert (tmp_path / "m.csv").read_text().startswith("id,label,kind,x,y,z")
    assert (tmp_path / "net.png").stat().st_size > 5000


def test_project_without_registration_says_why(widget, qtbot):
    widget.photo_layer.metadata.pop("result")
    shapes = widget.new_interpretation_layer()
    shapes.add(napari_from_pixels(np.array([[100.0, 100.0], [200.0, 200.0]])), shape_type="path")
    with qtbot.waitSignal(widget.projection_failed, timeout=5000) as blocker:
        assert widget.project() is None
    assert "registration" in blocker.args[0]


def test_attach_result(widget, tmp_path, sample):
    _, _, truth = sample
    pt = truth.photos["IMG_0001.jpg"]
    widget.photo_layer.metadata.pop("result")
    assert camera_of_layer(widget.photo_layer) is None
    path = tmp_path / "IMG_0001.result.json"
    path.write_text(json.dumps({"photo": "IMG_0001.jpg", "camera": pt.intrinsics.to_dict(),
                                "pose": pt.pose.to_dict()}))
    widget.attach_result(path)
    _, pose, _ = camera_of_layer(widget.photo_layer)
    np.testing.assert_allclose(pose.R, pt.pose.R)
