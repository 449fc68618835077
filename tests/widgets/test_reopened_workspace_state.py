"""A workspace saved and opened again in the workbench shows what it showed
before: the Interpret tab's projection is not called out of date when nothing
changed (lines drawn in napari carry a colour the saved file leaves out), and
the Manual tab gets its reference render, its pairs on it, and its solution's
residuals and text back."""

from __future__ import annotations

import numpy as np

from napari_imgreg.widgets._layers import napari_from_pixels

from ._workbench import (
    idle as _idle,
    load_sample as _load_sample,
    reference_and_truth_pairs,
    registered_on_truth,
    save_and_reopen,
)




def _project(iw, qtbot) -> None:
    with qtbot.waitSignal(iw.projection_done, timeout=60_000):
        assert iw.project() is not None
    qtbot.waitUntil(lambda: iw.project_button.isEnabled(), timeout=10_000)


# ------------------------------------------------------------------ Interpret
def test_what_a_projection_is_made_from_leaves_the_colour_out():
    """The fingerprint of a photo's projection: the drawings' kind, pixels (to
    the saved 1/1000 px) and properties but the colour, the camera, the pose."""
    from types import SimpleNamespace

    from napari_imgreg.camera import Intrinsics, Pose
    from napari_imgreg.interpret.project import Interpretation
    from napari_imgreg.workspace import _projection_input

    intr = Intrinsics(1000, 750, 800.0, 800.0, 499.5, 374.5)
    pose = Pose.from_attitude(10.0, 5.0, 1.0, np.array([0.0, -50.0, 2.0]))
    px = np.array([[100.1234567, 200.0], [300.0, 400.9876543]])

    def digest(items, pose=pose, intr=intr):
        return _projection_input(SimpleNamespace(interpretations=items, pose=pose,
                                                 intrinsics=intr))

    base = digest([Interpretation("LineString", px, {"label": "fault", "contact": "K7"})])
    same = [  # as napari's layer gives it, and as the saved file reads back
        [Interpretation("LineString", px, {"contact": "K7", "color": "#ff0000",
                                           "label": "fault"})],
        [Interpretation("LineString", np.round(px, 3), {"label": "fault", "contact": "K7"})],
    ]
    assert all(digest(items) == base for items in same)
    changed = [
        [Interpretation("LineString", px + (0.01, 0), {"label": "fault", "contact": "K7"})],
        [Interpretation("Polygon", np.vstack([px, [[150.0, 500.0]]]),
                        {"label": "fault", "contact": "K7"})],
        [Interpretation("LineString", px, {"label": "sandstone", "contact": "K7"})],
        [Interpretation("LineString", px, {"label": "fault", "contact": "K8"})],
    ]
    assert all(digest(items) != base for items in changed)
    items = [Interpretation("LineString", px, {"label": "fault", "contact": "K7"})]
    assert digest(items, pose=Pose.from_attitude(10.1, 5.0, 1.0, pose.center)) != base
    assert digest(items, intr=Intrinsics(1000, 750, 810.0, 810.0, 499.5, 374.5)) != base


def test_a_projection_drawn_in_napari_is_not_out_of_date_once_reopened(
        workbench, qtbot, tmp_path):
    wb = workbench
    ctrl = _load_sample(wb, qtbot)
    ws = ctrl.workspace
    ws.record_registration(registered_on_truth(ws.current))
    _idle(wb, qtbot)
    wb.show_tab("Interpret")
    iw = wb.interpret_widget
    # Drawn in napari (the layer gives each line its edge colour), one a
    # fault, with vertices that are no round numbers.
    shapes = iw.new_interpretation_layer()
    shapes.add(napari_from_pixels(np.array([[150.123456, 450.98765], [500.5, 430.25],
                                            [850.0, 460.0]])), shape_type="path")
    iw.label_combo.setCurrentText("fault")
    shapes.add(napari_from_pixels(np.array([[300.0, 100.0], [320.333333, 700.0]])),
               shape_type="path")
    shapes.mode = "pan_zoom"
    ps = ws.current
    assert len(ps.interpretations) == 2
    assert all("color" in item.properties for item in ps.interpretations)
    _project(iw, qtbot)
    assert ws.projection_out_of_date() == []
    name = ps.name

    ws = save_and_reopen(wb, qtbot, tmp_path / "drawn")
    ps = ws.current
    assert ps.name == name and len(ps.interpretations) == 2
    # The saved lines leave the label's own colour out: the check still matches.
    assert ws.projection_inputs_known and ws.projection_out_of_date() == []
    text = iw.status_label.text()
    assert "The workspace's last projection" in text and "Out of date" not in text, text

    # "New interpretation layer" on the photo's saved lines is no edit either.
    layer = iw.new_interpretation_layer()
    assert len(layer.data) == 2
    qtbot.wait(200)
    assert ws.projection_out_of_date() == []
    assert "Out of date" not in iw.status_label.text()
    layer.mode = "pan_zoom"
    qtbot.wait(200)
    assert ws.projection_out_of_date() == []

    # Really moving a vertex is: the photo is named.
    data = [np.array(d, float) for d in layer.data]
    data[0][1] += (3.0, -2.0)
    layer.data = data
    qtbot.waitUntil(lambda: ws.projection_out_of_date() == [ps], timeout=5_000)
    assert f"Out of date for {name}" in iw.status_label.text()
    _project(iw, qtbot)
    assert ws.projection_out_of_date() == []

    # So is moving the pose; moving it back is not.
    ctrl.nudge("turn right 1", d_trend=1.0)
    qtbot.waitUntil(lambda: f"Out of date for {name}" in iw.status_label.text(), timeout=5_000)
    assert ws.projection_out_of_date() == [ps]
    ctrl.undo()
    _idle(wb, qtbot)
    assert ws.projection_out_of_date() == []


# --------------------------------------------------------------------- Manual
def _table(panel) -> list[list[str]]:
    t = panel.table
    return [[t.item(r, c).text() if t.item(r, c) else "" for c in range(t.columnCount())]
            for r in range(t.rowCount())]


def _points_on(points_layer, image_layer) -> bool:
    """Every point of a Points layer lies on an Image layer (world coordinates)."""
    world = np.asarray(points_layer.data) * points_layer.scale + points_layer.translate
    lo, hi = np.asarray(image_layer.extent.world)
    return bool(len(world)) and bool(((world >= lo) & (world <= hi)).all())


def _open_in(wb, qtbot, folder):
    """Open a saved workspace folder in a workbench (nothing saved first)."""
    ctrl = wb.controller
    _idle(wb, qtbot)
    ctrl.workspace.detach()
    ctrl.open_workspace(folder)
    qtbot.waitUntil(lambda: ctrl.workspace_folder is not None and ctrl.current is not None,
                    timeout=90_000)
    _idle(wb, qtbot)
    return ctrl.workspace


def _manual_tab_as_saved(wb, qtbot, rgb, ref_text, table, result_text) -> None:
    """The Manual tab of photo 2 shows what it showed when it was saved."""
    ctrl, panel = wb.controller, wb.manual_panel
    ctrl.select_photo(1)
    _idle(wb, qtbot)
    ps = ctrl.current
    layers = wb.viewer.layers
    assert "reference render" in layers
    reference = layers["reference render"]
    assert reference.visible
    np.testing.assert_allclose(np.asarray(reference.data, float), rgb.astype(float), atol=1)
    # The numbered points sit on the reference, where they were picked.
    ref_points = layers["reference pairs"]
    assert ref_points.visible and _points_on(ref_points, reference)
    assert _points_on(layers["photo pairs"], layers[ps.photo.path.stem])
    # The tab says what it said: the reference, the pairs with their
    # residuals, and the solve's result.
    assert panel.reference_label.text() == ref_text
    assert _table(panel) == table
    assert panel.result_label.text() == result_text


def test_the_manual_tab_comes_back_with_its_reference_pairs_and_solution(
        workbench, qtbot, tmp_path, monkeypatch, make_napari_viewer):
    import json
    import threading

    from napari_imgreg import workspace as workspace_module

    wb = workbench
    ctrl, ps, photo_px, ref_px = reference_and_truth_pairs(wb, qtbot)
    panel = wb.manual_panel
    rng = np.random.default_rng(1)
    ctrl.workspace.set_pair_points(photo_px + rng.normal(0, 1.0, photo_px.shape),
                                   ref_px + rng.normal(0, 1.0, ref_px.shape))
    with qtbot.waitSignal(ctrl.manual_finished, timeout=60_000) as solved:
        panel.solve_button.click()
    _idle(wb, qtbot)
    assert solved.args[0].ok
    rgb = np.array(ps.reference.rgb)
    ref_text = panel.reference_label.text()
    result_text = panel.result_label.text()
    table = _table(panel)
    assert all(row[4].endswith(" px") for row in table)  # the residual column
    assert "Pose from 8 of 8 pairs" in result_text and "scored" in result_text

    # The reference is rendered again from its saved camera as the folder is
    # read: in the opening worker, never on the GUI thread.
    threads = []
    render = workspace_module.render

    def recording_render(*args, **kwargs):
        threads.append(threading.current_thread())
        return render(*args, **kwargs)

    monkeypatch.setattr(workspace_module, "render", recording_render)
    # Opened again in this window...
    ws = save_and_reopen(wb, qtbot, tmp_path / "manual")
    assert threads and threading.main_thread() not in threads
    _manual_tab_as_saved(wb, qtbot, rgb, ref_text, table, result_text)
    # ... and in a new one, which has no reference layer yet.
    folder = ctrl.workspace_folder
    _idle(wb, qtbot)
    ctrl.workspace.detach()  # the folder let go of, for the new window
    threads.clear()
    from napari_imgreg.widgets.workbench import Workbench

    fresh = Workbench.add_to_viewer(make_napari_viewer())
    try:
        _open_in(fresh, qtbot, folder)
        assert threads and threading.main_thread() not in threads
        fresh.show_tab("Manual")
        _manual_tab_as_saved(fresh, qtbot, rgb, ref_text, table, result_text)
    finally:
        _idle(fresh, qtbot)
        fresh.controller.workspace.detach()
    ws = _open_in(wb, qtbot, folder)
    layers = wb.viewer.layers
    ctrl.select_photo(1)
    _idle(wb, qtbot)
    ps = ctrl.current

    # Another photo (no solve there) shows no result; back, the solve again.
    ctrl.select_photo(0)
    _idle(wb, qtbot)
    assert panel.result_label.text() == "" and panel.table.rowCount() == 0
    ctrl.select_photo(1)
    _idle(wb, qtbot)
    assert panel.result_label.text() == result_text
    # A pair moved since the solve: its residuals are no longer shown as the pairs'.
    picked = ctrl.current.reference_points_px.copy()
    moved = picked.copy()
    moved[2] += (6.0, -4.0)
    ws.set_pair_points(ctrl.current.photo_points_px, moved)
    assert ws.manual_solution_of_pairs() is None

    # A workspace that kept its pairs but not their reference's camera: the
    # tab says so, and the reference picks are not drawn over the render.
    ws.set_pair_points(ctrl.current.photo_points_px, picked)
    assert ws.manual_solution_of_pairs() is not None
    folder = ctrl.workspace_folder
    _idle(wb, qtbot)
    ws.detach()
    state_file = next(p for p in (folder / "photos").glob("*/photo.json")
                      if json.loads(p.read_text()).get("pairs", {}).get("photo_px"))
    state = json.loads(state_file.read_text())
    del state["pairs"]["reference_pose"], state["pairs"]["reference_camera"]
    state_file.write_text(json.dumps(state))
    ws = _open_in(wb, qtbot, folder)
    ctrl.select_photo(1)
    _idle(wb, qtbot)
    ps = ctrl.current
    assert ps.reference is None and len(ps.photo_points_px) == 8
    assert not layers["reference render"].visible
    assert not layers["reference pairs"].visible
    assert "8 pairs are kept" in panel.reference_label.text()
    assert "make a reference again" in panel.reference_label.text()
    assert panel.result_label.text() == ""
    assert [row[3] for row in _table(panel)] == ["no reference"] * 8  # not "off the model"
    assert not panel.solve_button.isEnabled()
