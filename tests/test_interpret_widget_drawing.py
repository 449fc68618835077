"""The Interpret tab among the workbench's layers (a real napari viewer, under
Xvfb): only photos are offered to draw on, and while drawing nothing of the
registration covers the photo.

The viewer holds the layers the workbench makes, named as it names them
(widgets/_controller.py): the photo (``metadata["photo_path"]`` and its
camera), "render" beside it, "overlay render" over it, "photo · filtered" and
"render · filtered", the "correspondences" lines across both.
"""

from __future__ import annotations

import numpy as np
import pytest

from napari_imgreg.camera import Intrinsics, Pose
from napari_imgreg.widgets._layers import napari_from_pixels
from napari_imgreg.widgets.interpret_widget import (
    INTERP_KEY,
    InterpretWidget,
    is_photo_layer,
)

pytestmark = pytest.mark.gui

H, W = 60, 80
COVERING = ("overlay render", "correspondences", "photo · filtered")


@pytest.fixture
def viewer(make_napari_viewer):
    viewer = make_napari_viewer()
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 255, (H, W, 3), dtype=np.uint8)
    intr = Intrinsics(W, H, 70.0, 70.0, (W - 1) / 2, (H - 1) / 2)
    viewer.add_image(rgb, rgb=True, name="IMG_0001",
                     metadata={"photo_path": "/data/IMG_0001.jpg", "intrinsics": intr,
                               "pose": Pose(np.eye(3), np.zeros(3))})
    viewer.add_image(rgb[..., 0], name="photo · filtered", colormap="gray")
    viewer.add_image(rgb, rgb=True, name="render", translate=(0, W * 1.05))
    viewer.add_image(rgb[..., 1], name="render · filtered", colormap="gray",
                     translate=(0, W * 1.05))
    viewer.add_image(rgb, rgb=True, name="overlay render", opacity=0.5)
    viewer.add_image(rgb, rgb=True, name="render (sun-lit)")
    viewer.add_image(rgb, rgb=True, name="reference render")
    viewer.add_vectors(np.array([[[10, 10], [0, 90]], [[30, 20], [5, 90]]], float),
                       name="correspondences", vector_style="line")
    viewer.add_image(rgb, rgb=True, name="my own image")  # offered: a RESULT.json may be attached
    return viewer


def test_only_photos_are_offered_to_draw_on(viewer):
    w = InterpretWidget(viewer)
    offered = [w.photo_combo.itemText(i) for i in range(w.photo_combo.count())]
    assert offered == ["IMG_0001", "my own image"]
    assert not is_photo_layer(viewer.layers["photo · filtered"])
    assert not is_photo_layer(viewer.layers["render · filtered"])
    # A photo file called like a render is still a photo (the workbench marks it).
    assert is_photo_layer(type("L", (), {"name": "render", "metadata": {"photo_path": "x"}})())


def _top(viewer):
    return viewer.layers[-1]


def test_drawing_puts_the_drawing_on_top_and_hides_what_covers_the_photo(viewer):
    w = InterpretWidget(viewer)
    viewer.window.add_dock_widget(w, name="Interpret")
    w.photo_combo.setCurrentText("IMG_0001")
    viewer.layers.move(viewer.layers.index("correspondences"), len(viewer.layers))
    layer = w.new_interpretation_layer()
    assert layer.metadata[INTERP_KEY] == "IMG_0001" and layer.mode == "add_polyline"
    assert w.drawing_layer() is layer
    assert _top(viewer) is layer
    for name in COVERING:
        assert not viewer.layers[name].visible, name
    assert viewer.layers["render"].visible  # beside the photo, not over it

    # The workbench adds new correspondence lines while drawing: hidden too.
    viewer.layers.remove("correspondences")
    viewer.add_vectors(np.array([[[1, 1], [0, 50]]], float), name="correspondences",
                       vector_style="line")
    viewer.layers.selection.active = layer
    assert not viewer.layers["correspondences"].visible and _top(viewer) is layer

    # Drawing stops (pan/zoom): everything comes back as it was.
    layer.mode = "pan_zoom"
    assert w.drawing_layer() is None
    for name in COVERING:
        assert viewer.layers[name].visible, name
    # Editing shapes again (the vertex tools) is drawing too.
    layer.mode = "direct"
    assert not viewer.layers["overlay render"].visible
    # Another layer chosen in the layer list: drawing stops.
    viewer.layers.selection.active = viewer.layers["render"]
    assert viewer.layers["overlay render"].visible


def test_a_layer_the_user_hid_stays_hidden(viewer):
    viewer.layers["overlay render"].visible = False
    w = InterpretWidget(viewer)
    w.photo_combo.setCurrentText("IMG_0001")
    layer = w.new_interpretation_layer()
    layer.mode = "pan_zoom"
    assert not viewer.layers["overlay render"].visible
    assert viewer.layers["correspondences"].visible


def test_going_to_3d_while_drawing_leaves_the_workbench_to_restore_its_layers(viewer):
    w = InterpretWidget(viewer)
    w.photo_combo.setCurrentText("IMG_0001")
    layer = w.new_interpretation_layer()
    lines = viewer.layers["correspondences"]
    assert not lines.visible
    # The workbench's own 3D switch: it remembers its 2D layers' visibility...
    lines.metadata["imgreg_visible_2d"] = lines.visible
    viewer.dims.ndisplay = 3
    # ...and is told the lines were only hidden for drawing.
    assert lines.metadata["imgreg_visible_2d"] is True
    assert w.drawing_layer() is None and layer is not None


# ---------------------------------------------------------- in the workbench
def test_in_the_workbench_while_drawing(make_napari_viewer, qtbot):
    """The same with the workbench's own layers: the sample's photo with a
    trial's correspondence lines, the render overlay and both filtered views."""
    from napari_imgreg.registration.round import Correspondences, Trial
    from napari_imgreg.sample import sample_scene
    from napari_imgreg.widgets.workbench import Workbench
    from napari_imgreg.workspace import read_photos, read_scene

    viewer = make_napari_viewer()
    wb = Workbench.add_to_viewer(viewer)
    ctrl, ws = wb.controller, wb.controller.workspace
    folder = sample_scene("small")
    scene, terrain = read_scene(folder / "outcrop.obj", dem=folder / "dem.tif")
    loaded, _ = read_photos(sorted(folder.glob("IMG_*.jpg"))[:1], scene)
    ws.load_scene(scene, terrain, {"mesh": folder / "outcrop.obj", "dem": folder / "dem.tif"})
    ws.add_loaded_photos(loaded)
    qtbot.waitUntil(lambda: ctrl.layers.get("render") is not None and not ctrl.busy,
                    timeout=60_000)
    n = 30
    pts = np.random.default_rng(1).uniform(50, 700, (n, 2))
    trial = Trial(index=0, params=ws.params, metrics={}, q=0.1, grade="fair", hints=[],
                  pose=ws.current.pose, start_pose=ws.current.pose, rounds=1, converged=True,
                  verified=False, residual_flow_px=3.0)
    trial.correspondences = Correspondences(pts, pts + 3.0, np.ones(n, bool), np.ones(n, bool),
                                            np.ones(n, bool))
    ws.add_trial(trial)
    ws.select_trial(len(ws.current.trials) - 1)
    ctrl.set_blend(opacity=0.5, visible=True)
    gray = np.asarray(ws.current.photo.image)[..., 0]
    ctrl.layers.show_filtered("photo", gray, (1.0, 1.0), (0.0, 0.0))
    ctrl.layers.show_filtered("render", gray, (1.0, 1.0), (0.0, ctrl.layers.offset))
    keys = ("correspondences", "blend", "photo_filtered")
    assert all(ctrl.layers.get(k).visible for k in keys)

    iw = wb.interpret_widget
    offered = {iw.photo_combo.itemText(i) for i in range(iw.photo_combo.count())}
    assert offered == {ctrl.photo_layer().name}  # not the render, overlay or filtered views
    shapes = iw.new_interpretation_layer()
    assert viewer.layers[-1] is shapes
    assert not any(ctrl.layers.get(k).visible for k in keys)
    assert ctrl.layers.get("render").visible and ctrl.photo_layer().visible
    shapes.add(napari_from_pixels(np.array([[250.0, 420.0], [520.0, 400.0]])), shape_type="path")
    assert [i.label for i in ws.current.interpretations] == ["sandstone"]
    shapes.mode = "pan_zoom"
    assert all(ctrl.layers.get(k).visible for k in keys)


def test_drawings_left_out_of_a_projection_are_named(viewer):
    """Lines on a photo without a registration are not projected, and the
    projection says which photo's were left out (never silently)."""
    w = InterpretWidget(viewer)
    w.photo_combo.setCurrentText("my own image")
    layer = w.new_interpretation_layer()
    layer.add(napari_from_pixels(np.array([[10.0, 10.0], [40.0, 30.0]])), shape_type="path")
    w.photo_combo.setCurrentText("IMG_0001")
    drawn = w.new_interpretation_layer()
    drawn.add(napari_from_pixels(np.array([[10.0, 10.0], [40.0, 30.0]])), shape_type="path")
    jobs = w._jobs()
    assert len(jobs) == 1  # IMG_0001's
    assert len(w.projection_warnings) == 1
    assert w.projection_warnings[0].startswith("my own image: 1 drawing(s) not projected")


def test_a_trace_keeps_its_id_when_another_is_deleted(viewer):
    w = InterpretWidget(viewer)
    w.photo_combo.setCurrentText("IMG_0001")
    layer = w.new_interpretation_layer()
    for y in (10.0, 20.0, 30.0):
        layer.add(napari_from_pixels(np.array([[10.0, y], [40.0, y + 5]])), shape_type="path")
    w._jobs()
    assert list(layer.features["drawing_id"]) == ["IMG_0001:1", "IMG_0001:2", "IMG_0001:3"]
    layer.selected_data = {1}
    layer.remove_selected()
    layer.add(napari_from_pixels(np.array([[10.0, 50.0], [40.0, 55.0]])), shape_type="path")
    w._jobs()
    assert list(layer.features["drawing_id"]) == ["IMG_0001:1", "IMG_0001:3", "IMG_0001:4"]
    from napari_imgreg.widgets.interpret_widget import interpretations_from_shapes

    assert [i.properties["id"] for i in interpretations_from_shapes(layer)] == [
        "IMG_0001:1", "IMG_0001:3", "IMG_0001:4"]
