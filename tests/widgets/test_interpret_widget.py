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
    # napari's click-per-vertex tool (in napari 0.9 "add_path" draws freehand).
    assert shapes.metadata[INTERP_KEY] == "IMG_0001" and shapes.mode == "add_polyline"
    assert "double-click" in widget.status_label.text()
    assert to_hex(shapes.current_edge_color) == "#ffd400"  # sandstone yellow
    widget.add_label("coal")
    assert widget.current_label == "coal" and shapes.feature_defaults["label"][0] == "coal"
    widget.label_combo.setCurrentText("fault")
    assert to_hex(shapes.current_edge_color) == "#e31a1c"  # fault red


def test_draw_project_and_find_it_on_the_mesh(widget, sample, qtbot, tmp_path, monkeypatch):
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

    # The 3D layer is built for the 3D canvas (not while projecting on the 2D one)
    # and shows the line where the mesh is, in napari's (z, x, y) order.
    assert not any(PROJECTED_KEY in lay.metadata for lay in widget.viewer.layers)
    widget.viewer.dims.ndisplay = 3  # napari's own 3D button builds them too
    layer3d = next(lay for lay in widget.viewer.layers if PROJECTED_KEY in lay.metadata)
    widget.viewer.dims.ndisplay = 2
    widget.show_3d()  # the 3D canvas, from the photo's viewpoint, photo layers hidden
    assert layer3d in widget.viewer.layers  # built once, kept
    assert layer3d.metadata[PROJECTED_KEY] == "IMG_0001.jpg" and layer3d.ndim == 3
    first = world_from_napari(np.asarray(layer3d.data[0]))
    np.testing.assert_allclose(first, bed.parts[0], atol=1e-4)
    assert list(layer3d.features["label"])[0] == "sandstone"
    assert widget.viewer.dims.ndisplay == 3 and layer3d.visible
    assert not widget.photo_layer.visible and not shapes.visible
    layer3d.visible = False  # togglable per photo
    assert not layer3d.visible

    # Table and stereonet.
    assert widget.table.rowCount() == len(widget.measurements) >= 1
    assert widget.table.item(0, 1).text() == "sandstone"
    m = widget.measurements[0]
    if m.dip_deg is None:  # a trace in the viewing plane: no made-up dip (issue 14)
        assert widget.table.item(0, 3).text() == "" and m.note.startswith("no plane")
        assert widget.table.item(0, 10).toolTip() == m.note  # "why no plane", whole
        assert m.plunge_deg is not None
    else:
        dip, sigma = widget.table.item(0, 3).text().split(" ± ")  # each angle with its 1σ
        assert float(dip) == pytest.approx(12.0, abs=1.0)
        assert float(sigma) == pytest.approx(m.dip_sigma_deg, abs=0.05)
    plunge_cell = widget.table.item(0, 5).text()
    assert " ± " in plunge_cell and float(plunge_cell.split(" ± ")[0]) == pytest.approx(
        m.plunge_deg, abs=0.05)
    # The azimuth columns say which north they are from (the sample: UTM 30N).
    for col in (4, 6):
        tip = widget.table.horizontalHeaderItem(col).toolTip()
        assert "grid north of EPSG:32630" in tip and "true azimuth = grid azimuth + 0.9" in tip
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
    # georeferenced ticked on a model without a georeference: the dock's words
    # (not the command line's "--georeferenced needs ... --georef").
    monkeypatch.setattr(widget.scene, "georef", None)
    widget._guarded(widget.export, tmp_path / "plain.geojson", True)
    assert "the model has no georeference" in widget.status_label.text()
    assert "untick 'georeferenced'" in widget.status_label.text()
    assert "--" not in widget.status_label.text() and not (tmp_path / "plain.geojson").exists()


def test_project_without_registration_says_why(widget, qtbot):
    widget.photo_layer.metadata.pop("result")
    shapes = widget.new_interpretation_layer()
    shapes.add(napari_from_pixels(np.array([[100.0, 100.0], [200.0, 200.0]])), shape_type="path")
    with qtbot.waitSignal(widget.projection_failed, timeout=5000) as blocker:
        assert widget.project() is None
    assert "drawings are on photos without a registration" in blocker.args[0]


def test_project_with_nothing_drawn_says_to_draw(widget, qtbot):
    """A registered photo, nothing drawn: the next step, not a registration."""
    with qtbot.waitSignal(widget.projection_failed, timeout=5000) as blocker:
        assert widget.project() is None
    assert "nothing is drawn yet. Press New interpretation layer" in blocker.args[0]


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


def _click(layer, position, kind="mouse_press"):
    """A mouse event through the layer's callbacks, as napari's own tests do."""
    from napari.utils._test_utils import read_only_mouse_event
    from napari.utils.interactions import (
        mouse_double_click_callbacks,
        mouse_move_callbacks,
        mouse_press_callbacks,
        mouse_release_callbacks,
    )

    world = layer.data_to_world(position)
    event = read_only_mouse_event(type=kind, position=world, pos=np.asarray(position) * 3)
    {"mouse_press": mouse_press_callbacks, "mouse_move": mouse_move_callbacks,
     "mouse_release": mouse_release_callbacks,
     "mouse_double_click": mouse_double_click_callbacks}[kind](layer, event)


def _draw_by_clicks(layer, vertices_rc):
    """Click each vertex (moving the mouse between clicks), double-click the last."""
    for k, v in enumerate(vertices_rc):
        if k:
            _click(layer, (vertices_rc[k - 1] + v) / 2, "mouse_move")
            _click(layer, v, "mouse_move")
        _click(layer, v, "mouse_press")
        _click(layer, v, "mouse_release")
    _click(layer, vertices_rc[-1], "mouse_double_click")


def test_five_clicks_and_a_double_click_make_one_five_vertex_line(widget):
    shapes = widget.new_interpretation_layer()
    clicks = np.array([[300.0, 100.0], [310.0, 200.0], [290.0, 300.0], [320.0, 400.0],
                       [305.0, 500.0]])  # napari (row, col)
    _draw_by_clicks(shapes, clicks)
    assert len(shapes.data) == 1 and list(shapes.shape_type) == ["path"]
    np.testing.assert_allclose(shapes.data[0], clicks)
    items = interpretations_from_shapes(shapes)
    assert len(items) == 1 and len(items[0].pixels) == 5 and items[0].label == "sandstone"
    # A second line starts afresh.
    _draw_by_clicks(shapes, clicks[:3] + 50)
    assert [len(d) for d in shapes.data] == [5, 3]


def test_snapped_line_from_two_clicks_follows_the_contact(widget, sample, qtbot):
    folder, scene, truth = sample
    px, xyz = _true_bed_on_photo(sample)
    widget.snap_check.setChecked(True)
    shapes = widget.new_interpretation_layer()
    assert "snaps" in widget.status_label.text()
    ends = napari_from_pixels(px[[0, -1]])
    _draw_by_clicks(shapes, ends)
    qtbot.waitUntil(lambda: len(shapes.data) == 1 and len(shapes.data[0]) > 2, timeout=10000)
    snapped = interpretations_from_shapes(shapes)[0].pixels
    np.testing.assert_allclose(snapped[[0, -1]], px[[0, -1]], atol=4.0)
    # Along the true contact: the median offset under a pixel.
    dense = np.concatenate([np.linspace(a, b, 10, endpoint=False) for a, b in zip(px[:-1], px[1:])])
    d = cKDTree(dense).query(snapped)[0]
    assert np.median(d) < 1.0
    assert list(shapes.features["label"]) == ["sandstone"]  # still an ordinary path
    assert shapes.shape_type[0] == "path"
    # Lines added by code or loaded from a file are never snapped.
    shapes.add(napari_from_pixels(px[[0, -1]] + 20), shape_type="path")
    qtbot.wait(100)
    assert [len(d) for d in shapes.data][1] == 2


def _median_px(line: np.ndarray, contact: np.ndarray) -> float:
    dense = np.concatenate([np.linspace(a, b, 10, endpoint=False)
                            for a, b in zip(contact[:-1], contact[1:])])
    return float(np.median(cKDTree(dense).query(line)[0]))


def test_snapping_follows_the_models_contact_from_the_registered_pose(widget, sample, qtbot):
    """A registered pose 0.06° off (about a pixel, pitched): the model seen
    from it shows the contact a pixel from where the photo does. Followed,
    the snapped line lies on the model's contact; unticked, on the photo's."""
    from napari_imgreg.camera import Pose

    folder, scene, truth = sample
    px, xyz = _true_bed_on_photo(sample)
    pt = truth.photos["IMG_0001.jpg"]
    a = np.radians(0.06)
    pitch = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    registered = Pose(pitch @ pt.pose.R, pitch @ pt.pose.t)  # turned about its centre
    photo_layer = widget.viewer.layers["IMG_0001"]
    photo_layer.metadata["result"]["pose"] = registered.to_dict()
    model_contact = registered.project(pt.intrinsics, xyz)
    assert _median_px(px, model_contact) > 0.7
    widget.snap_check.setChecked(True)
    # Rendered ahead, in the background, once snapping is on.
    qtbot.waitUntil(lambda: widget._reference_cache is not None, timeout=10000)
    assert widget._reference_cache[1].shape == (pt.intrinsics.height, pt.intrinsics.width, 3)
    shapes = widget.new_interpretation_layer()
    _draw_by_clicks(shapes, napari_from_pixels(px[[0, -1]]))
    qtbot.waitUntil(lambda: len(shapes.data) == 1 and len(shapes.data[0]) > 2, timeout=10000)
    assert "following the model where it shows" in widget.status_label.text()
    followed = interpretations_from_shapes(shapes)[0].pixels
    assert _median_px(followed, model_contact) < 0.35 < _median_px(followed, px)
    widget.follow_model_check.setChecked(False)
    _draw_by_clicks(shapes, napari_from_pixels(px[[0, -1]]))
    qtbot.waitUntil(lambda: len(shapes.data) == 2 and len(shapes.data[1]) > 2, timeout=10000)
    assert "following the model" not in widget.status_label.text()
    alone = interpretations_from_shapes(shapes)[1].pixels
    assert _median_px(alone, px) < 0.35 < _median_px(alone, model_contact)
    # A photo that is not registered (its sensor prior, metres off) is not followed.
    photo_layer.metadata["result"]["status"] = "not registered"
    widget.follow_model_check.setChecked(True)
    assert widget._snap_reference(photo_layer, photo_layer.data) == (None, False)


def test_a_snap_never_waits_for_the_models_view(widget, sample, qtbot, monkeypatch):
    """A line snapped while the model's view is still rendering (seconds for a
    large point cloud) is placed at once on the photo alone, without waiting on
    the GUI thread, and follows the model's contact when the render is ready."""
    import time

    from napari_imgreg.camera import Pose
    from napari_imgreg.widgets import interpret_widget as module

    folder, scene, truth = sample
    px, xyz = _true_bed_on_photo(sample)
    pt = truth.photos["IMG_0001.jpg"]
    a = np.radians(0.06)
    pitch = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    registered = Pose(pitch @ pt.pose.R, pitch @ pt.pose.t)
    widget.viewer.layers["IMG_0001"].metadata["result"]["pose"] = registered.to_dict()
    model_contact = registered.project(pt.intrinsics, xyz)
    real = module.model_reference
    monkeypatch.setattr(module, "model_reference",
                        lambda *args: (time.sleep(3.0), real(*args))[1])  # a slow render
    widget.snap_check.setChecked(True)
    qtbot.waitUntil(lambda: widget._reference_thread is not None, timeout=5000)
    shapes = widget.new_interpretation_layer()
    _draw_by_clicks(shapes, napari_from_pixels(px[[0, -1]]))
    qtbot.waitUntil(lambda: len(shapes.data) == 1 and len(shapes.data[0]) > 2, timeout=10000)
    assert widget._reference_thread.is_alive()  # placed while the render still runs
    assert "still rendering" in widget.status_label.text()
    first = interpretations_from_shapes(shapes)[0].pixels
    assert _median_px(first, px) < 0.35 < _median_px(first, model_contact)  # the photo's
    # Then, once rendered, the line follows the model's contact.
    qtbot.waitUntil(lambda: "now follows the model" in widget.status_label.text(), timeout=15000)
    followed = interpretations_from_shapes(shapes)[0].pixels
    assert _median_px(followed, model_contact) < 0.35 < _median_px(followed, px)
    assert widget._pending_follow == []
    # A line whose layer is closed before the render arrives is left alone.
    widget.viewer.layers["IMG_0001"].metadata["result"]["pose"] = pt.pose.to_dict()  # a new pose
    _draw_by_clicks(shapes, napari_from_pixels(px[[0, -1]]))
    qtbot.waitUntil(lambda: len(shapes.data) == 2 and len(shapes.data[1]) > 2, timeout=10000)
    assert len(widget._pending_follow) == 1
    placed = np.array(shapes.data[1])
    widget.viewer.layers.remove(shapes)
    qtbot.waitUntil(lambda: not widget._pending_follow, timeout=15000)
    np.testing.assert_array_equal(shapes.data[1], placed)  # left as it was


def test_choosing_the_next_label_does_not_relabel_the_line_just_drawn(widget):
    """napari leaves a drawn line selected: choosing the label of the next line
    while drawing must not relabel it; with the select tool it relabels."""
    shapes = widget.new_interpretation_layer()
    assert shapes.mode == "add_polyline"
    widget.label_combo.setCurrentText("sandstone")
    shapes.add(napari_from_pixels(np.array([[100.0, 100.0], [200.0, 120.0]])), shape_type="path")
    shapes.selected_data = {0}  # as napari leaves it after the double-click
    widget.label_combo.setCurrentText("mudstone")
    shapes.add(napari_from_pixels(np.array([[100.0, 300.0], [200.0, 320.0]])), shape_type="path")
    assert [i.label for i in interpretations_from_shapes(shapes)] == ["sandstone", "mudstone"]
    shapes.mode = "select"
    shapes.selected_data = {0}
    widget.label_combo.setCurrentText("fault")
    assert [i.label for i in interpretations_from_shapes(shapes)] == ["fault", "mudstone"]


def test_note_and_units_per_feature_reach_the_geojson(widget, tmp_path):
    shapes = widget.new_interpretation_layer()
    shapes.add(napari_from_pixels(np.array([[100.0, 100.0], [200.0, 120.0]])), shape_type="path")
    shapes.add(napari_from_pixels(np.array([[100.0, 300.0], [200.0, 320.0]])), shape_type="path")
    shapes.mode = "select"  # relabelling is done with the select tool
    shapes.selected_data = {1}
    widget.label_combo.setCurrentText("fault")
    assert widget.set_selected_text(comment="offset 2 m", above="Unit B", below="Unit A") == 1
    items = interpretations_from_shapes(shapes)
    assert items[0].properties.get("comment") is None
    assert items[1].label == "fault"
    assert (items[1].properties["comment"], items[1].properties["above"],
            items[1].properties["below"]) == ("offset 2 m", "Unit B", "Unit A")
    # Selecting one shape shows its note and units; an emptied box clears one.
    shapes.selected_data = {0}
    assert widget.comment_edit.text() == ""
    shapes.selected_data = {1}
    assert (widget.comment_edit.text(), widget.above_edit.text()) == ("offset 2 m", "Unit B")
    widget.comment_edit.setText("")
    assert widget.set_selected_text() == 1
    assert interpretations_from_shapes(shapes)[1].properties.get("comment") in (None, "")
    assert interpretations_from_shapes(shapes)[1].properties["above"] == "Unit B"
    widget.comment_edit.setText("offset 2 m")
    widget.set_selected_text()
    path = tmp_path / "lines.geojson"
    widget.save_geojson(path)
    widget.viewer.layers.remove(shapes)
    loaded = widget.load_geojson(path)
    assert list(loaded.features["unit_above"]) == ["", "Unit B"]
    assert list(loaded.features["comment"]) == ["", "offset 2 m"]
    # A contact name (the same on every photo it is drawn on) and the id a
    # loaded drawing came with travel to the GeoJSON and back.
    loaded.mode = "select"
    loaded.selected_data = {1}
    assert widget.set_selected_text(loaded, contact="K7") == 1
    assert interpretations_from_shapes(loaded)[1].properties["contact"] == "K7"
    from napari_imgreg.interpret.files import read_interpretations, write_interpretations

    with_id = tmp_path / "with_id.geojson"
    items = interpretations_from_shapes(loaded)
    items[0].properties["id"] = "c2"
    write_interpretations(with_id, items)
    again = widget.load_geojson(with_id)
    widget.save_geojson(tmp_path / "again.geojson", widget.photo_layer)
    back = read_interpretations(tmp_path / "again.geojson")
    # (loaded onto the layer, after the shapes already there)
    assert back[-2].properties["id"] == "c2" and back[-1].properties["contact"] == "K7"
    assert again is not None


def test_a_loaded_drawings_other_properties_survive_the_layer(widget, tmp_path):
    """Properties the layer has no column for (a formation, an observer, a
    nested record) go back out as they came in; a line drawn after gets none."""
    from napari_imgreg.interpret.files import read_interpretations

    path = tmp_path / "field.geojson"
    path.write_text(json.dumps({"type": "FeatureCollection", "features": [{
        "type": "Feature",
        "properties": {"label": "sandstone", "formation": "Kinder Scout Grit", "observer": "AB",
                       "station": {"id": 7, "gps": [53.35, -1.81]}},
        "geometry": {"type": "LineString", "coordinates": [[100, 100], [300, 140]]}}]}))
    layer = widget.load_geojson(path)
    layer.add(napari_from_pixels(np.array([[100.0, 300.0], [200.0, 320.0]])), shape_type="path")
    items = interpretations_from_shapes(layer)
    assert items[0].properties["formation"] == "Kinder Scout Grit"
    assert items[0].properties["station"] == {"id": 7, "gps": [53.35, -1.81]}
    assert "formation" not in items[1].properties and "observer" not in items[1].properties
    widget.save_geojson(tmp_path / "back.geojson", widget.photo_layer)
    back = read_interpretations(tmp_path / "back.geojson")
    assert back[0].properties["observer"] == "AB" and back[0].label == "sandstone"


def test_plane_from_three_points_is_still_importable_from_the_widget():
    """Moved to interpret/structural.py (its known answers are tested there)."""
    from napari_imgreg.interpret import structural
    from napari_imgreg.widgets import interpret_widget

    assert interpret_widget.plane_from_three_points is structural.plane_from_three_points


def test_three_point_plane_drawn_by_clicks(widget, sample, qtbot):
    from napari_imgreg.widgets.interpret_widget import plane_from_three_points

    folder, scene, truth = sample
    pt = truth.photos["IMG_0001.jpg"]
    px, xyz = _true_bed_on_photo(sample)
    chord = np.interp(px[:, 0], px[[0, -1], 0], px[[0, -1], 1])
    k = int(np.argmax(np.abs(px[:, 1] - chord)))
    triple = np.array([0, k, len(px) - 1])
    widget.three_point_check.setChecked(True)
    shapes = widget.new_interpretation_layer()
    _draw_by_clicks(shapes, napari_from_pixels(px[triple]))
    qtbot.waitUntil(lambda: "measure" in shapes.features
                    and list(shapes.features["measure"]) == ["three_point"], timeout=5000)
    items = interpretations_from_shapes(shapes)
    assert items[0].properties["measure"] == "three_point"
    with qtbot.waitSignal(widget.projection_done, timeout=30000):
        widget.project()
    (m,) = widget.measurements
    # The true points give the true bedding (12°/200°); the clicked ones, cast
    # onto the mesh, the same within the mesh's and the clicks' error.
    expected = plane_from_three_points(xyz[triple], pt.pose.center)
    assert expected == pytest.approx((12.0, 200.0), abs=0.01)
    assert m.dip_deg == pytest.approx(12.0, abs=0.5)
    assert m.dip_direction_deg == pytest.approx(200.0, abs=2.0)
    assert m.n_points == 3 and "3-point" in m.note and m.plunge_deg is None


def test_a_photo_layer_gives_the_error_of_its_pose():
    """What is projected from a photo layer carries its RESULT.json's
    ``uncertainty``; without one, the documented default, never silently 1 px
    for a sensor record."""
    from types import SimpleNamespace

    from napari_imgreg.camera import Intrinsics
    from napari_imgreg.widgets.interpret_widget import pose_uncertainty_of_layer

    intr = Intrinsics(fx=1000.0, fy=1000.0, cx=511.5, cy=383.5, width=1024, height=768)
    result = {"status": "registered", "pose": {}, "metrics": {"reprojection_error_px": 0.5},
              "uncertainty": {"reprojection_px": 0.7, "position_m": 0.03, "rotation_deg": 0.02}}
    unc = pose_uncertainty_of_layer(SimpleNamespace(metadata={"result": result}), intr)
    assert (unc.source, unc.reprojection_px, unc.position_m) == ("result", 0.7, 0.03)
    del result["uncertainty"]
    unc = pose_uncertainty_of_layer(SimpleNamespace(metadata={"result": result}), intr)
    assert unc.source == "default" and unc.reprojection_px == 1.0
    unc = pose_uncertainty_of_layer(SimpleNamespace(metadata={}), intr)
    assert unc.source == "default (sensor prior)" and unc.position_m == 5.0


# ------------------------------------------------------------ audit fixes
def _notifications(monkeypatch):
    """napari notifications raised (severity, message), as the user sees them."""
    from napari.utils import notifications

    seen = []
    monkeypatch.setattr(notifications, "show_error", lambda m: seen.append(("error", m)))
    monkeypatch.setattr(notifications, "show_warning", lambda m: seen.append(("warning", m)))
    return seen


def test_attach_a_sensor_record_projects_with_the_prior_pose_and_warns(
        widget, sample, qtbot, monkeypatch):
    folder, _, _ = sample
    seen = _notifications(monkeypatch)
    widget.photo_layer.metadata.pop("result")
    # As `napari-imgreg project` does: a sensor record gives the prior pose.
    assert widget.attach_result(folder / "IMG_0001.json") == "prior"
    assert "PRIOR pose" in widget.status_label.text()
    assert any(sev == "warning" and "PRIOR pose" in msg for sev, msg in seen)
    intr, pose, name = camera_of_layer(widget.photo_layer)
    assert intr.width == 1024 and name == "IMG_0001"  # a record names no photo: the layer's
    # Its lines carry the sensor prior's error, not a registration's.
    from napari_imgreg.widgets.interpret_widget import pose_uncertainty_of_layer

    assert pose_uncertainty_of_layer(widget.photo_layer, intr).reprojection_px == 50.0
    shapes = widget.new_interpretation_layer()
    shapes.add(napari_from_pixels(np.array([[300.0, 100.0], [320.0, 700.0]])), shape_type="path")
    with qtbot.waitSignal(widget.projection_done, timeout=30000) as done:
        widget.project()
    assert done.args[0][0].source == "IMG_0001" and done.args[0][0].parts


def test_errors_are_notified_and_saving_the_stereonet_says_so(
        widget, tmp_path, monkeypatch):
    seen = _notifications(monkeypatch)
    (tmp_path / "bad.json").write_text('{"camera": 1}')
    widget._guarded(widget.attach_result, tmp_path / "bad.json")
    assert seen and seen[-1][0] == "error" and "bad.json" in seen[-1][1]
    assert seen[-1][1] in widget.status_label.text()
    assert widget.project() is None  # nothing drawn
    assert seen[-1] == ("error", widget.status_label.text())
    widget.save_stereonet(tmp_path / "net.png")
    assert widget.status_label.text() == "Saved stereonet to net.png."
    assert (tmp_path / "net.png").stat().st_size > 1000
    # A name without a picture suffix is one clear error, not matplotlib's
    # ValueError (a traceback dialog) from the temporary file's random suffix.
    for name in ("stereonet", "net.bmpx"):
        widget._guarded(widget.save_stereonet, tmp_path / name)
        assert seen[-1][0] == "error" and name in seen[-1][1] and ".png" in seen[-1][1]
        assert not (tmp_path / name).exists()
    widget.save_stereonet(tmp_path / "net.SVG")
    assert (tmp_path / "net.SVG").read_text().lstrip().startswith("<?xml")


def test_new_interpretation_layer_on_a_photo_that_has_one_keeps_its_lines(widget):
    shapes = widget.new_interpretation_layer()
    shapes.add(napari_from_pixels(np.array([[100.0, 100.0], [200.0, 120.0]])), shape_type="path")
    again = widget.new_interpretation_layer()
    assert again is shapes and len(again.data) == 1 and again.mode == "add_polyline"
    assert [lay for lay in widget.viewer.layers if INTERP_KEY in lay.metadata] == [shapes]


def test_only_a_line_drawn_by_mouse_counts_as_drawn(widget, qtbot):
    """Drawing is told apart through napari's public API (mouse callbacks, the
    data event), not its private ``_is_creating``; a line added by code (or
    loaded, or pasted) is never taken for a fresh drawing."""
    import warnings

    widget.three_point_check.setChecked(True)
    shapes = widget.new_interpretation_layer()
    with warnings.catch_warnings():
        warnings.simplefilter("error", FutureWarning)  # napari's private-access warning
        shapes.add(napari_from_pixels(np.array([[300.0, 100.0], [310.0, 300.0], [305.0, 500.0]])),
                   shape_type="path")
        qtbot.wait(50)
        assert "measure" not in shapes.features  # added by code: not a 3-point plane
        _draw_by_clicks(shapes, np.array([[400.0, 100.0], [410.0, 300.0], [405.0, 500.0]]))
        qtbot.waitUntil(lambda: "measure" in shapes.features, timeout=5000)
    assert list(shapes.features["measure"]) == ["", "three_point"]


def test_the_interpret_tab_fits_a_narrow_dock(widget):
    """Rows of at most two widgets: nothing is cut off in a 380 px dock."""
    from pathlib import Path

    assert widget.minimumSizeHint().width() <= 360
    widget.resize(360, 900)
    out = Path("/tmp/gui_fix")
    out.mkdir(exist_ok=True)
    widget.grab().save(str(out / "test_interpret_360.png"))


def test_a_name_typed_without_a_suffix_takes_the_chosen_filters():
    """Qt's own save dialog adds no suffix: "outcrop" saved under *GeoPackage*
    was refused as an unknown format, "net" under *SVG* raised."""
    from napari_imgreg.widgets.interpret_widget import _EXPORT_FILTER, with_filter_suffix

    gpkg = _EXPORT_FILTER.split(";;")[1]
    assert with_filter_suffix("/d/outcrop", gpkg) == "/d/outcrop.gpkg"
    assert with_filter_suffix("/d/net", "SVG (*.svg)") == "/d/net.svg"
    assert with_filter_suffix("/d/a.b/lines", "GeoJSON (*.geojson *.json)") == "/d/a.b/lines.geojson"
    assert with_filter_suffix("/d/outcrop.shp", gpkg) == "/d/outcrop.shp"  # the name's wins
    assert with_filter_suffix("", gpkg) == ""  # cancelled
    assert with_filter_suffix("/d/x", "All files (*)") == "/d/x"


def test_on_its_own_the_dock_frames_the_photo_to_draw_on(widget, qtbot):
    """With the model and a photo in one viewer (Plugins → Interpret), the
    canvas was fitted to both: the photo small in a corner of a black canvas,
    a slice of the model over it. Drawing hides the model in 2D and frames
    the photo; Show in 3D brings the model back."""
    viewer = widget.viewer
    model, photo = viewer.layers["sample outcrop"], viewer.layers["IMG_0001"]
    viewer.dims.ndisplay = 3
    viewer.reset_view()
    widget.new_interpretation_layer()
    assert viewer.dims.ndisplay == 2 and not model.visible and photo.visible
    h, w = photo.data.shape[:2]
    camera = viewer.scene.camera
    center = np.asarray(camera.center[-2:])
    assert np.allclose(center, [(h - 1) / 2, (w - 1) / 2], atol=0.05 * w)
    canvas_h, canvas_w = viewer.canvas.size
    # The photo fills the canvas's width or height (napari's 5 % margin).
    assert max(w * camera.zoom / canvas_w, h * camera.zoom / canvas_h) > 0.85
    # The model hidden, its height slider moves nothing: no slider bar.
    assert viewer.window._qt_viewer.dims.isHidden()
    widget.show_3d()  # nothing projected yet: stays; the model comes back with a projection
