"""The registration workbench driven as a user would, in a real napari viewer
(run under Xvfb): load the sample, nudge and move the pose, filter, register,
restore a trial, and register manually from control points.

These prove the wiring — buttons, layers, docks following the workspace. The
state's own rules (pose history, trials, suggestions, pairs, suns,
interpretations) are tested without a viewer in ``tests/test_workspace.py``."""

from __future__ import annotations

from dataclasses import replace

import shutil

import numpy as np
import pytest
from qtpy.QtCore import QPoint, Qt

from napari_imgreg.widgets._layers import napari_from_pixels
from napari_imgreg.io.photos import load_photo
from napari_imgreg.registration.filters import filtered_for_matching
from napari_imgreg.io.records import load_sensor_record
from napari_imgreg.prior import prior_for_photo, prior_from_record
from napari_imgreg.registration.quality import GRADES, METRICS
from napari_imgreg.sample import load_truth, truth_pairs
from napari_imgreg.widgets._controller import GAP, controller_for
from napari_imgreg.widgets._quality import CLASS_COLORS
from napari_imgreg.widgets.workbench import INTERPRET_TAB, QUALITY_NAME, WORKBENCH_NAME, Workbench

from ._workbench import LOAD_S, idle as _idle, load_sample as _load_sample


def _map_point(canvas, x, y) -> QPoint:
    """Widget coordinates of the map point (x, y) (matplotlib: physical pixels, y up)."""
    canvas.draw()
    px, py = canvas.ax.transData.transform((x, y))
    dpr = canvas.device_pixel_ratio
    return QPoint(int(round(px / dpr)), int(round((canvas.figure.bbox.height - py) / dpr)))


# ------------------------------------------------------------------ scene
def test_sample_shows_photo_beside_render_and_model_with_cameras_in_3d(workbench, qtbot):
    wb = workbench
    ctrl = _load_sample(wb, qtbot)
    viewer = wb.viewer
    assert controller_for(viewer) is ctrl
    assert wb.scene_panel.photo_list.count() == 3
    assert "IMG_0001.jpg" in wb.scene_panel.prior_label.text()
    assert "DEM" in wb.scene_panel.scene_label.text()
    # The georef.json the reader found beside the mesh is the one shown.
    assert "georeferenced" in wb.scene_panel.scene_label.text()
    assert wb.scene_panel.georef_edit.text().endswith("georef.json")
    photo, render = ctrl.layers.get("photo"), ctrl.layers.get("render")
    assert photo.data.shape == (768, 1024, 3) and render.data.shape == (768, 1024, 3)
    assert render.translate[1] == pytest.approx(1024 * (1 + GAP))  # side by side
    assert ctrl.last_render is not None and ctrl.last_render.shape == (768, 1024)
    assert wb.quality is viewer.window.dock_widgets[QUALITY_NAME].panel
    assert wb.tabs.tabText(wb.tabs.count() - 1) == INTERPRET_TAB
    from napari_imgreg.widgets.interpret_widget import InterpretWidget

    assert isinstance(wb.tabs.widget(wb.tabs.count() - 1).widget(), InterpretWidget)

    wb.scene_panel.view_3d_button.click()
    assert viewer.dims.ndisplay == 3
    surface, cameras = ctrl.layers.get("surface"), ctrl.layers.get("cameras")
    assert surface.visible and cameras.visible and not photo.visible
    assert len(cameras.data) == 3 and len(ctrl.layers.get("frusta").data) == 3 * 8
    # Cameras in colours no interpretation label has (not taken for mapped lines).
    from matplotlib.colors import to_rgba

    from napari_imgreg.interpret.project import LABEL_COLORS, label_color
    from napari_imgreg.widgets._layers import world_from_napari

    labels = [to_rgba(c) for c in LABEL_COLORS.values()]
    labels += [to_rgba(label_color(f"label {k}")) for k in range(40)]
    shown = [tuple(c) for c in cameras.face_color] + [tuple(ctrl.layers.get("frusta").edge_color[0])]
    for c in shown:
        assert min(np.abs(np.subtract(c[:3], lab[:3])).max() for lab in labels) > 0.15, c
    # Oblique, facing the outcrop as the cameras do (not straight down).
    view = world_from_napari(np.asarray(ctrl.camera.view_direction, float))
    heading = np.mean([ps.pose.view_direction for ps in ctrl.photos], axis=0)
    heading[2] = 0
    assert view[2] == pytest.approx(-np.sin(np.radians(30)), abs=0.05)
    assert np.dot(view[:2], heading[:2] / np.linalg.norm(heading[:2])) > 0.8
    # Seen from the pose, the cameras about the viewpoint are left out.
    wb.scene_panel.view_pose_button.click()
    eye = ctrl.current.pose.center
    drawn = world_from_napari(np.asarray(ctrl.layers.get("cameras").data, float))
    assert len(drawn) < 3 and all(np.linalg.norm(d - eye) > 1.0 for d in drawn)
    wb.scene_panel.view_3d_button.click()
    assert len(ctrl.layers.get("cameras").data) == 3
    wb.scene_panel.view_2d_button.click()
    assert viewer.dims.ndisplay == 2 and photo.visible and not surface.visible

    with qtbot.waitSignal(ctrl.render_shown, timeout=20_000,
                          check_params_cb=lambda kind: kind == "full"):
        wb.scene_panel.photo_list.setCurrentRow(2)
    assert ctrl.current.name == "IMG_0003.jpg"
    assert wb.interpret_widget.photo_combo.currentText() == "IMG_0003"  # follows the photo
    assert not ctrl.layers.get(f"photo:{ctrl.photos[0].photo.path}").visible
    assert ctrl.last_render.cam_from_world is ctrl.current.pose


def test_the_docks_are_views_of_the_workspace(workbench, qtbot):
    """Edits made on the workspace itself, as a script would make them, reach
    the docks and the layers; what is drawn in the Interpret tab is kept in it.
    (The state's own rules: tests/test_workspace.py.)"""
    wb = workbench
    ctrl = _load_sample(wb, qtbot)
    ws = ctrl.workspace
    assert ctrl.current is ws.current and wb.quality.ws is ws and wb.pose_panel.ws is ws

    def full_render():
        return qtbot.waitSignal(ctrl.render_shown, timeout=20_000,
                                check_params_cb=lambda kind: kind == "full")

    with full_render():
        ws.select_photo(1)
    assert wb.scene_panel.photo_list.currentRow() == 1
    assert ctrl.photo_layer().name == "IMG_0002" and ctrl.photo_layer().visible
    t0 = ws.current.pose.attitude[0]
    with full_render():
        ws.nudge("turn right 2", d_trend=2.0)
    assert wb.pose_panel.trend_spin.value() == pytest.approx((t0 + 2.0) % 360, abs=0.01)
    assert "turn right 2" in wb.pose_panel.title.text() and wb.pose_panel.undo_button.isEnabled()
    assert ctrl.photo_layer().metadata["pose"] is ws.current.pose  # for the interpretation tools
    assert ctrl.last_render.cam_from_world is ws.current.pose

    box = wb.register_panel.sun_box
    ws.set_sun_angles(200.0, 25.0)
    assert box.azimuth_spin.value() == pytest.approx(200.0, abs=0.05)
    assert "set by hand" in box.source_label.text() and box.reset_button.isEnabled()

    # Pairs added to the workspace show as numbered points, in napari's (row, col).
    with qtbot.waitSignal(ctrl.reference_ready, timeout=20_000):
        ctrl.make_reference()
    ws.add_pair([100.0, 200.0], [110.0, 190.0])
    ws.add_pair([300.0, 250.0], [310.0, 240.0])
    photo_layer, ref_layer = ctrl.layers.get("photo_pairs"), ctrl.layers.get("reference_pairs")
    np.testing.assert_allclose(photo_layer.data, [[200.0, 100.0], [250.0, 300.0]])
    np.testing.assert_allclose(ref_layer.data, [[190.0, 110.0], [240.0, 310.0]])
    assert list(ref_layer.features["pair"]) == [1, 2] and wb.manual_panel.table.rowCount() == 2
    ws.remove_pair(0)
    assert len(photo_layer.data) == len(ref_layer.data) == 1
    assert wb.manual_panel.table.rowCount() == 1

    # Drawn on the photo in the Interpret tab: the photo's interpretations.
    iw = wb.interpret_widget
    assert iw.workspace is ws and iw.photo_combo.currentText() == "IMG_0002"
    shapes = iw.new_interpretation_layer()
    shapes.add(napari_from_pixels(np.array([[250.0, 420.0], [520.0, 400.0], [800.0, 430.0]])),
               shape_type="path")
    assert [i.label for i in ws.current.interpretations] == ["sandstone"]
    np.testing.assert_allclose(ws.current.interpretations[0].pixels[0], [250.0, 420.0])
    with qtbot.waitSignal(iw.projection_done, timeout=30_000):
        iw.project()
    assert ws.features_3d == iw.features and ws.features_3d[0].source == "IMG_0002.jpg"
    assert ws.measurements == iw.measurements
    # Snapping follows the model only from a registered (or accepted) pose.
    photo_layer = iw.photo_layer
    registered = ws.photo_status(ws.current) in ("registered", "accepted")
    assert (iw._registered_camera(photo_layer) is not None) == registered
    ws.accept()
    intr, pose = iw._registered_camera(photo_layer)
    assert pose is ws.current.pose and intr is ws.current.intrinsics
    iw.snap_check.setChecked(True)
    qtbot.waitUntil(lambda: iw._reference_cache is not None, timeout=20_000)
    image = np.asarray(photo_layer.data)
    reference, pending = iw._snap_reference(photo_layer, image)
    assert not pending and reference is not None and reference.shape[:2] == image.shape[:2]
    # A new pose (here nudged, then accepted): its view is rendered ahead once the edits pause.
    ws.nudge(d_trend=0.05)
    ws.accept()
    key = iw._reference_source(photo_layer)[0]
    qtbot.waitUntil(lambda: iw._reference_cache[0] == key, timeout=20_000)
    iw.snap_check.setChecked(False)

    # An unverified pose with a high Q: the banner says why it is only fair.
    from napari_imgreg.registration.round import Trial

    unverified = Trial(index=0, params=ws.params, metrics={}, q=1.6, grade="fair", hints=[],
                       pose=ws.current.pose, start_pose=ws.current.pose, rounds=1,
                       converged=True, verified=False, residual_flow_px=3.0)
    ws.add_trial(unverified, kind="Manual")
    ws.select_trial(len(ws.current.trials) - 1)
    text = wb.quality.banner.text()
    assert text.startswith("FAIR · Q = 1.60 (Q alone: excellent; capped, not verified)")


# ------------------------------------------------------------------- pose
def test_pose_nudges_map_moves_undo_and_save_to_the_sensor_record(workbench, qtbot, tmp_path):
    wb = workbench
    ctrl = _load_sample(wb, qtbot)
    # A copy of a photo and its sensor record: saving must not touch the cached sample.
    folder = ctrl.current.photo.path.parent
    for name in ("IMG_0002.jpg", "IMG_0002.json"):
        shutil.copy(folder / name, tmp_path / name)
    ctrl.add_photos([tmp_path / "IMG_0002.jpg"])
    qtbot.waitUntil(lambda: len(ctrl.photos) == 4, timeout=20_000)
    wb.scene_panel.photo_list.setCurrentRow(3)
    _idle(wb, qtbot)
    ps = ctrl.current
    assert ps.photo.path == tmp_path / "IMG_0002.jpg"
    panel = wb.pose_panel
    wb.show_tab("Pose")
    t0, p0, r0 = ps.pose.attitude
    before = ctrl.layers.get("render").data.copy()

    # Nudge: the reduced render comes first, the full one when the edits stop.
    with qtbot.waitSignal(ctrl.render_shown, timeout=10_000,
                          check_params_cb=lambda kind: kind == "preview"):
        panel.nudge_buttons["turn right"].click()
    assert ps.pose.attitude[0] == pytest.approx((t0 + 1.0) % 360)
    assert not np.array_equal(ctrl.layers.get("render").data, before)
    with qtbot.waitSignal(ctrl.render_shown, timeout=10_000,
                          check_params_cb=lambda kind: kind == "full"):
        pass
    assert ctrl.last_render.cam_from_world is ps.pose
    assert panel.trend_spin.value() == pytest.approx((t0 + 1.0) % 360, abs=0.01)
    fine = next(b for b in panel.step_group.buttons() if b.property("step") == "fine")
    fine.click()
    panel.nudge_buttons["look down"].click()
    assert ps.pose.attitude[1] == pytest.approx(p0 + 0.1)
    trend_before = ps.pose.attitude[0]
    panel.roll_spin.setValue(r0 + 2.0)  # typed (arrows/Enter) like any value
    assert ps.pose.attitude[2] == pytest.approx(round(r0 + 2.0, 2))
    assert ps.pose.attitude[0] == pytest.approx(trend_before, abs=1e-9)  # the others untouched

    # Click on the DEM map: the camera moves there, keeping its height above the DEM.
    agl = ctrl.height_above_ground()
    x, y = ps.pose.center[0] + 12.0, ps.pose.center[1] - 6.0
    canvas = panel.map
    qtbot.mouseClick(canvas, Qt.LeftButton, pos=_map_point(canvas, x, y))
    cell = max(np.diff(canvas.ax.get_xlim())[0], np.diff(canvas.ax.get_ylim())[0]) / 200
    assert np.allclose(ps.pose.center[:2], (x, y), atol=3 * cell)
    ground = ctrl.scene.terrain_height(*ps.pose.center[:2])
    assert ps.pose.center[2] == pytest.approx(ground + agl, abs=1e-6)
    assert panel.agl_spin.value() == pytest.approx(agl, abs=0.01)
    moved = ps.pose
    # Drag: one undo step for the whole drag.
    a, b = _map_point(canvas, x, y), _map_point(canvas, x - 10.0, y + 5.0)
    qtbot.mousePress(canvas, Qt.LeftButton, pos=a)
    qtbot.mouseMove(canvas, pos=QPoint((a.x() + b.x()) // 2, (a.y() + b.y()) // 2))
    qtbot.mouseMove(canvas, pos=b)
    qtbot.mouseRelease(canvas, Qt.LeftButton, pos=b)
    assert np.allclose(ps.pose.center[:2], (x - 10.0, y + 5.0), atol=3 * cell)
    panel.undo_button.click()
    assert ps.pose is moved
    panel.redo_button.click()
    assert ps.pose is not moved
    # Shift-click turns the camera toward the point.
    target = ps.pose.center[:2] + np.array([30.0, 30.0])
    qtbot.mouseClick(canvas, Qt.LeftButton, Qt.ShiftModifier, pos=_map_point(canvas, *target))
    assert ps.pose.attitude[0] == pytest.approx(45.0, abs=1.0)

    # Save into the sensor record (what it keeps: tests/test_workspace.py).
    panel.save_button.click()
    prior = prior_from_record(load_sensor_record(tmp_path / "IMG_0002.json"))
    np.testing.assert_allclose(prior.pose.center, ps.pose.center, atol=1e-6)
    assert "pose saved to IMG_0002.json" in wb.status_label.text()
    panel.prior_button.click()
    assert ps.pose is ps.prior.pose


# ---------------------------------------------------------------- filters
def test_filter_sliders_preview_photo_and_render(workbench, qtbot):
    wb = workbench
    ctrl = _load_sample(wb, qtbot)
    panel = wb.filters_panel
    wb.show_tab("Filters")
    with qtbot.waitSignals([ctrl.filters_shown, ctrl.filters_shown], timeout=10_000):
        panel.preview_check.setChecked(True)
    photo_f, render_f = ctrl.layers.get("photo_filtered"), ctrl.layers.get("render_filtered")
    assert photo_f.visible and render_f.visible
    photo = ctrl.current.photo.image
    with qtbot.waitSignal(ctrl.filters_shown, timeout=10_000,
                          check_params_cb=lambda which: which == "photo"):
        panel.photo_editor.widgets["gamma"].setValue(1.8)
    assert ctrl.params.photo_filters.gamma == pytest.approx(1.8)
    # The preview is what the detector reads: the photo reduced to the match
    # width, then filtered (a Wallis window means pixels at that width).
    assert ctrl.params.match_width < photo.shape[1]  # the reduction is exercised
    np.testing.assert_array_equal(
        photo_f.data, filtered_for_matching(photo, ctrl.params.photo_filters, ctrl.params.match_width))
    assert photo_f.data.shape[1] == ctrl.params.match_width
    panel.tabs.setCurrentIndex(1)
    # Wallis is on for both images by default; turning it off for the render
    # leaves the photo's untouched (the two are filtered independently).
    assert ctrl.params.render_filters.wallis and ctrl.params.photo_filters.wallis
    with qtbot.waitSignal(ctrl.filters_shown, timeout=10_000,
                          check_params_cb=lambda which: which == "render"):
        panel.render_editor.wallis_check.setChecked(False)
    assert not ctrl.params.render_filters.wallis and ctrl.params.photo_filters.wallis
    assert not panel.render_editor.widgets["wallis_window"].isEnabled()
    rendered = ctrl.last_render
    np.testing.assert_array_equal(render_f.data, filtered_for_matching(
        rendered.rgb, ctrl.params.render_filters, ctrl.params.match_width, mask=rendered.mask))
    with qtbot.waitSignal(ctrl.filters_shown, timeout=10_000,
                          check_params_cb=lambda which: which == "render"):
        panel.render_editor.wallis_check.setChecked(True)
    assert panel.render_editor.widgets["wallis_window"].isEnabled()
    np.testing.assert_array_equal(render_f.data, filtered_for_matching(
        rendered.rgb, ctrl.params.render_filters, ctrl.params.match_width, mask=rendered.mask))
    # Gradient magnitude (for a lidar intensity render): its σ follows the switch.
    editor = panel.render_editor
    assert not editor.widgets["gradient_sigma_px"].isEnabled()
    with qtbot.waitSignal(ctrl.filters_shown, timeout=10_000,
                          check_params_cb=lambda which: which == "render"):
        editor.gradient_check.setChecked(True)
    assert ctrl.params.render_filters.gradient and editor.widgets["gradient_sigma_px"].isEnabled()
    np.testing.assert_array_equal(render_f.data, filtered_for_matching(
        rendered.rgb, ctrl.params.render_filters, ctrl.params.match_width, mask=rendered.mask))
    with qtbot.waitSignal(ctrl.filters_shown, timeout=10_000,
                          check_params_cb=lambda which: which == "render"):
        editor.gradient_check.setChecked(False)
    # Linked: an edit of one applies to both.
    panel.link_check.setChecked(True)
    with qtbot.waitSignal(ctrl.filters_shown, timeout=10_000):
        panel.photo_editor.clahe_check.setChecked(True)
    assert ctrl.params.render_filters.clahe
    assert ctrl.params.render_filters.gamma == pytest.approx(1.8)
    _idle(wb, qtbot)
    panel.preview_check.setChecked(False)
    assert not photo_f.visible and not render_f.visible


# ----------------------------------------------------------- registration
def test_run_apply_suggestion_auto_to_good_and_restore_an_earlier_trial(workbench, qtbot):
    wb = workbench
    ctrl = _load_sample(wb, qtbot)
    ps = ctrl.current
    truth = load_truth(ps.photo.path)
    reg_panel, quality = wb.register_panel, wb.quality
    wb.show_tab("Register")
    wb.pose_panel.nudge_buttons["turn left"].click()  # the geologist's own correction
    wb.pose_panel.nudge_buttons["turn left"].click()
    _idle(wb, qtbot)

    # A first Run with a too strict detector: few points, the rules say why
    # (keypoints only: the stages for another light are the subject of other tests).
    for check in (reg_panel.sun_relight_check, reg_panel.area_match_check,
                  reg_panel.edge_align_check, reg_panel.dense_refine_check):
        check.setChecked(False)
    reg_panel.threshold_spin.setValue(4.0)
    reg_panel.max_features_spin.setValue(500)
    assert reg_panel.preset_combo.currentText() == "(custom)"
    with qtbot.waitSignal(ctrl.registration_finished, timeout=60_000) as run:
        reg_panel.run_button.click()
        assert not reg_panel.run_button.isEnabled() and reg_panel.cancel_button.isEnabled()
    first = run.args[0]
    assert first is not None and len(first.trials) == 1
    t1 = ps.trials[0].trial
    assert t1.grade not in ("excellent", "good")
    assert quality.history.rowCount() == 1
    assert t1.grade.upper() in quality.banner.text()
    points = quality.metric_cell("points_photo")
    assert points.background().color().name() == CLASS_COLORS[-1]  # inferior: too few
    assert "Too few salient points" in quality.hint_label.text()
    assert "threshold" in quality.adapt_label.text() and quality.apply_button.isEnabled()
    assert reg_panel.progress.value() == 100

    # Apply the suggestion: the rule's adaptation lands in the parameters and the GUI.
    quality.apply_button.click()
    assert ctrl.params.features.threshold_scale == pytest.approx(2.0)
    assert reg_panel.threshold_spin.value() == pytest.approx(2.0)
    assert reg_panel.max_features_spin.value() == 750

    # Auto: good or better, the pose applied, correspondences drawn, the render blended.
    with qtbot.waitSignal(ctrl.registration_finished, timeout=90_000) as auto:
        reg_panel.auto_button.click()
    reg = auto.args[0]
    assert reg.registered and reg.grade in ("excellent", "good")
    best = ps.trials[ps.selected_trial].trial
    assert best.grade in ("excellent", "good") and best.verified
    assert ps.pose.rotation_error_deg(truth.pose) < 0.2
    assert np.linalg.norm(ps.pose.center - truth.pose.center) < 0.3
    grade = next(g for g in GRADES if g.name == best.grade)
    assert grade.name.upper() in quality.banner.text()
    assert grade.color in quality.banner.styleSheet()
    arrows = [quality.metric_cell(m.key, 2).data(Qt.UserRole) for m in METRICS]
    assert arrows[0] == 1  # more photo points than the strict first trial: ▲ better
    assert quality.metric_cell("points_photo", 2).text() == "▲"
    assert quality.history.rowCount() == len(ps.trials) >= 2
    lines = ctrl.layers.get("correspondences")
    assert lines.visible and len(lines.data) > 20
    assert ctrl.layers.get("blend").visible and reg_panel.blend_check.isChecked()
    _idle(wb, qtbot)
    reg_panel.outlier_check.setChecked(True)
    assert len(ctrl.layers.get("correspondences").data) >= len(lines.data)

    # The photo layer carries the registered camera for the interpretation tools.
    from napari_imgreg.widgets.interpret_widget import camera_of_layer

    intr, pose, _ = camera_of_layer(ctrl.layers.get("photo"))
    assert pose is ps.pose and intr == ps.intrinsics

    # Restore the first trial: its parameters and its pose come back (undoable).
    registered_pose = ps.pose
    quality.history.selectRow(0)
    assert t1.grade.upper() in quality.banner.text()
    quality.restore_button.click()
    assert ctrl.params.features.threshold_scale == pytest.approx(4.0)
    assert reg_panel.threshold_spin.value() == pytest.approx(4.0)
    assert ctrl.params.features.max_features == 500
    expected = t1.pose if t1.pose is not None else t1.start_pose
    assert ps.pose is expected and "trial 1 restored" in ps.history.label
    wb.pose_panel.undo_button.click()
    assert ps.pose is registered_pose


def test_cancel_stops_a_registration(workbench, qtbot):
    wb = workbench
    ctrl = _load_sample(wb, qtbot)
    ctrl.params.features.max_features = 30_000  # slow enough to be cancelled
    with qtbot.waitSignal(ctrl.registration_finished, timeout=60_000) as finished:
        wb.register_panel.auto_button.click()
        qtbot.waitUntil(lambda: ctrl.is_running("registration"), timeout=5000)
        wb.register_panel.cancel_button.click()
    assert finished.args[0] is None
    assert wb.register_panel.status_label.text() == "Cancelled."
    assert ctrl.current.trials == []
    _idle(wb, qtbot)
    assert wb.register_panel.run_button.isEnabled()


def test_errors_become_one_line_messages(workbench, qtbot, tmp_path, monkeypatch):
    from napari.utils import notifications

    notified = []
    monkeypatch.setattr(notifications, "show_error", notified.append)
    wb = workbench
    ctrl = wb.controller
    with qtbot.waitSignal(ctrl.status, timeout=2000) as status:
        ctrl.add_photos([tmp_path / "x.jpg"])  # no model yet
    assert "Open a model first" in status.args[0]
    with qtbot.waitSignal(ctrl.failed, timeout=20_000) as failed:
        ctrl.open_scene(tmp_path / "missing.obj")
    job, message = failed.args
    assert job == "open scene" and "missing.obj" in message and "\n" not in message
    assert message in wb.status_label.text()
    # Seen as a napari notification too, as the validation errors are.
    assert notified[-1] == f"open scene failed: {message}"


# --------------------------------------------------------- another light
def _angle_deg(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    c = a @ b / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def test_light_stage_checkboxes_edit_the_parameters_both_ways(workbench, qtbot):
    wb = workbench
    panel, ctrl = wb.register_panel, wb.controller
    checks = {"sun_relight": panel.sun_relight_check, "area_match": panel.area_match_check,
              "edge_align": panel.edge_align_check, "dense_refine": panel.dense_refine_check}
    for name, check in checks.items():
        assert check.isChecked() == getattr(ctrl.params, name) is True  # the defaults
        assert check.toolTip()
        check.setChecked(False)
        assert getattr(ctrl.params, name) is False
    panel.preset_combo.setCurrentIndex(panel.preset_combo.findData("ORB"))
    assert not any(c.isChecked() for c in checks.values())  # a preset is features only
    restored = ctrl.params.copy()  # e.g. a restored trial's parameters
    restored.edge_align = True
    ctrl.workspace.set_params(restored)
    assert panel.edge_align_check.isChecked() and not panel.dense_refine_check.isChecked()


def test_sun_box_shows_the_exif_sun_and_a_hand_set_sun_is_the_one_registered(
        workbench, qtbot, monkeypatch):
    from napari_imgreg.registration import pipeline
    from napari_imgreg.solar import sun_vector_enu

    wb = workbench
    ctrl = _load_sample(wb, qtbot)
    ps, box = ctrl.current, wb.register_panel.sun_box
    wb.show_tab("Register")
    exif_sun = prior_for_photo(load_photo(ps.photo.path), ctrl.scene).sun
    assert exif_sun is not None
    assert "from EXIF time 2024-" in box.source_label.text()
    assert ctrl.scene.georef.crs in box.north_label.text()
    conv = ctrl.convergence_deg()
    assert 0.5 < abs(conv) < 2.0  # the sample lies off its UTM zone's central meridian
    shown = sun_vector_enu(box.azimuth_spin.value() - conv, box.elevation_spin.value())
    assert _angle_deg(shown, exif_sun) < 0.1
    az_true, el = ctrl.workspace.sun_angles()  # from true north (tests/test_workspace.py)
    assert box.azimuth_spin.value() == pytest.approx(az_true, abs=0.05)
    assert not box.reset_button.isEnabled()
    assert box.note_label.isHidden()  # survey.json gives the texture's sun: it will relight
    wb.register_panel.sun_relight_check.setChecked(False)
    assert "Sun-lit matching is off" in box.note_label.text() and not box.note_label.isHidden()
    wb.register_panel.sun_relight_check.setChecked(True)

    # Swing the sun round by hand: it is this photo's sun from now on.
    box.azimuth_spin.setValue(az_true + 40.0)
    assert ps.sun_override is not None and ps.sun_source == "hand setting"
    assert ctrl.sun_angles()[0] == pytest.approx(round(az_true, 1) + 40.0, abs=1e-6)
    assert _angle_deg(ps.sun, exif_sun) > 20.0
    assert "set by hand" in box.source_label.text() and box.reset_button.isEnabled()

    # The registration starts from a prior carrying that sun.
    seen = []

    def fake_register(scene, image, prior, params, **kwargs):
        seen.append((prior, params))
        raise pipeline.Cancelled()
        yield  # a generator, as the real one

    monkeypatch.setattr(pipeline, "register_photo", fake_register)
    with qtbot.waitSignal(ctrl.registration_finished, timeout=10_000):
        wb.register_panel.run_button.click()
    prior, params = seen[0]
    np.testing.assert_allclose(prior.sun, ps.sun)
    assert prior.sun_source == "hand setting" and prior.pose is ps.pose
    assert prior.sigma == ps.prior.sigma and params.sun_relight

    box.reset_button.click()
    assert ps.sun_override is None and _angle_deg(ps.sun, exif_sun) < 1e-9
    assert box.azimuth_spin.value() == pytest.approx(az_true, abs=0.05)
    assert "from EXIF time 2024-" in box.source_label.text() and not box.reset_button.isEnabled()


def test_sun_lit_preview_and_the_sun_read_from_the_photo(workbench, qtbot):
    wb = workbench
    ctrl = _load_sample(wb, qtbot)
    ps, box = ctrl.current, wb.register_panel.sun_box
    layer = ctrl.layers.get("render")
    plain = layer.data.copy()
    mask = ctrl.last_render.mask
    assert ctrl.shown_look == ("plain",) and layer.name == "render"

    with qtbot.waitSignal(ctrl.render_shown, timeout=20_000,
                          check_params_cb=lambda kind: kind == "full"):
        box.preview_check.setChecked(True)
    assert ctrl.shown_look[0] == "sunlit" and layer.name == "render (sun-lit)"
    np.testing.assert_allclose(ctrl.shown_look[1], ps.sun)
    lit = layer.data.copy()
    diff = np.abs(lit.astype(float) - plain.astype(float)).mean(axis=-1)
    assert diff[mask].mean() > 5.0  # morning sun from the east, texture lit from the SSE
    assert np.array_equal(lit[~mask], plain[~mask])  # the sky stays

    # Move the sun: the relit render follows (reduced first, then full).
    az, el = ctrl.sun_angles()
    with qtbot.waitSignal(ctrl.render_shown, timeout=20_000,
                          check_params_cb=lambda kind: kind == "full"):
        box.azimuth_spin.setValue((az + 90.0) % 360)
    assert not np.array_equal(layer.data, lit)

    # Read the sun from the photo, from the true pose: close to the EXIF sun.
    truth = load_truth(ps.photo.path)
    ctrl.set_pose(truth.pose, "true pose")
    with qtbot.waitSignal(ctrl.sun_estimated, timeout=20_000) as estimated:
        box.estimate_button.click()
    est = estimated.args[0]
    assert est is not None and ps.sun_estimate is est
    assert _angle_deg(est.direction, ps.prior.sun) < 6.0
    assert ps.sun_source.startswith("photo's shading")
    assert "read from the photo's shading" in box.source_label.text()
    assert box.azimuth_spin.value() == pytest.approx(ctrl.sun_angles()[0], abs=0.05)
    _idle(wb, qtbot)
    assert ctrl.shown_look == ("sunlit", tuple(ps.sun))

    box.preview_check.setChecked(False)
    _idle(wb, qtbot)
    assert ctrl.shown_look == ("plain",) and layer.name == "render"


def test_trial_history_says_where_each_pose_came_from_and_how_the_render_was_lit(
        workbench, qtbot):
    from napari_imgreg.registration.params import RegistrationParams
    from napari_imgreg.registration.pipeline import Trial
    from napari_imgreg.widgets._quality import HISTORY_COLUMNS

    wb = workbench
    ctrl = _load_sample(wb, qtbot)
    ps = ctrl.current
    for k, (origin, mode, matcher) in enumerate((
            ("prior", "plain", "keypoints"), ("sun-lit render", "sunlit", "keypoints"),
            ("edges", "sunlit", "keypoints"), ("mutual information", "plain", "keypoints"),
            ("area matching", "sunlit", "area"), ("edges", "sunlit", "area"))):
        trial = Trial(index=k, params=RegistrationParams(), metrics={}, q=-0.5, grade="poor",
                      hints=[], pose=None, start_pose=ps.pose, rounds=1, converged=False,
                      verified=False, residual_flow_px=float("inf"), origin=origin,
                      render_mode=mode, matcher=matcher)
        ctrl.workspace.add_trial(trial, "Auto", run=1)  # the panel follows the workspace
    history = wb.quality.history
    assert history.rowCount() == 6
    col = {name: HISTORY_COLUMNS.index(name) for name in ("trial", "from", "Q")}
    assert [history.item(r, col["from"]).text() for r in range(6)] == [
        "prior", "sun-lit render", "edges ☀", "mutual information", "area matching ☀",
        "edges ▦ ☀"]
    tip = history.item(2, col["from"]).toolTip()
    assert "edges" in tip and "relit for the photo's sun" in tip
    assert "as textured" in history.item(3, col["from"]).toolTip()
    assert "by correlation" in history.item(5, col["from"]).toolTip()
    assert history.item(5, col["trial"]).text().endswith(": blocks")
    assert history.item(2, col["trial"]).text().endswith(": SIFT–SIFT")
    assert history.item(0, col["Q"]).toolTip().startswith("poor")
    assert history.item(2, col["trial"]).toolTip() == f"trial 3: {ps.trials[2].label}"

    # Correspondences of trials with many, then few lines, drawn while hidden
    # (napari does not re-slice a hidden layer: its colours must not go stale).
    from napari_imgreg.registration.round import Correspondences

    rng = np.random.default_rng(0)
    for rec, n in zip(ps.trials[:2], (40, 5)):
        pts = rng.uniform(0, 700, (n, 2))
        rec.trial.correspondences = Correspondences(pts, pts + 3.0, np.ones(n, bool),
                                                    np.ones(n, bool), np.ones(n, bool))
    ctrl.select_trial(0)
    lines = ctrl.layers.get("correspondences")
    assert lines.visible and len(lines.data) == 40
    wb.register_panel.corr_check.setChecked(False)
    ctrl.select_trial(1)
    assert not lines.visible
    wb.register_panel.corr_check.setChecked(True)
    assert lines.visible and len(lines.data) == 5 and len(lines.edge_color) == 5


# ----------------------------------------------------------------- manual
def _truth_pairs(ctrl, n=8):
    """Check points seen in both images (see :func:`~napari_imgreg.sample.truth_pairs`)."""
    ps = ctrl.current
    truth = load_truth(ps.photo.path)
    photo_px, ref_px, _ = truth_pairs(truth, ps.reference, ps.size, n=n, margin_px=0.0)
    return truth, photo_px, ref_px


def test_manual_pairs_from_the_truth_recover_the_pose(workbench, qtbot):
    wb = workbench
    ctrl = _load_sample(wb, qtbot)
    wb.scene_panel.photo_list.setCurrentRow(1)
    _idle(wb, qtbot)
    panel = wb.manual_panel
    wb.show_tab("Manual")
    assert not panel.solve_button.isEnabled()
    with qtbot.waitSignal(ctrl.reference_ready, timeout=20_000):
        panel.ref_pose_button.click()
    assert ctrl.layers.get("reference").visible
    truth, photo_px, ref_px = _truth_pairs(ctrl)
    assert ctrl.current.pose.rotation_error_deg(truth.pose) > 2.0  # the prior is off

    # Click alternately on the photo and the reference (the widget switches layers).
    panel.pick_button.click()
    viewer = wb.viewer
    photo_layer, ref_layer = ctrl.layers.get("photo_pairs"), ctrl.layers.get("reference_pairs")
    for p, r in zip(photo_px, ref_px):
        assert viewer.layers.selection.active is photo_layer and photo_layer.mode == "add"
        photo_layer.add(napari_from_pixels(p))
        assert viewer.layers.selection.active is ref_layer and ref_layer.mode == "add"
        ref_layer.add(napari_from_pixels(r))
    assert panel.table.rowCount() == 8
    assert [panel.table.item(i, 3).text() for i in range(8)] == ["✓"] * 8
    assert list(ref_layer.features["pair"]) == list(range(1, 9))
    np.testing.assert_array_equal(photo_layer.face_color, ref_layer.face_color)  # colour-matched
    # A wrong extra pair, deleted from the table; deleting a point deletes its pair.
    photo_layer.add([100.0, 100.0])
    ref_layer.add([5.0, 5.0])
    assert panel.table.rowCount() == 9
    panel.table.selectRow(8)
    panel.delete_button.click()
    assert len(photo_layer.data) == len(ref_layer.data) == 8
    photo_layer.add([50.0, 60.0])
    ref_layer.add([40.0, 30.0])
    photo_layer.selected_data = {8}
    photo_layer.remove_selected()
    assert len(photo_layer.data) == len(ref_layer.data) == 8

    assert panel.solve_button.isEnabled()
    with qtbot.waitSignal(ctrl.manual_finished, timeout=60_000) as solved:
        panel.solve_button.click()
    sol = solved.args[0]
    assert sol.ok and sol.inliers.all()
    pose = ctrl.current.pose
    assert pose.rotation_error_deg(truth.pose) < 0.5
    assert np.linalg.norm(pose.center - truth.pose.center) < 0.5
    assert all(panel.table.item(i, 4).text().endswith("px") for i in range(8))
    rec = ctrl.current.trials[-1]
    assert rec.kind == "Manual" and rec.trial.grade in ("excellent", "good")
    assert "manual pairs" in wb.quality.banner.text()
    assert "RMS" in panel.result_label.text()
    # The clicks are the workspace's pairs (the focal length: tests/test_workspace.py).
    np.testing.assert_allclose(ctrl.workspace.pairs()[0], photo_px)
    np.testing.assert_allclose(ctrl.workspace.pairs()[1], ref_px)
    assert panel.focal_check.isEnabled()
    assert not panel.focal_check.isChecked()  # the record gives the focal length
    # A photo whose focal length is not known: solving it is ticked for the user,
    # until they untick it.
    ctrl.current.intrinsics = replace(ctrl.current.intrinsics, estimated=("fx", "fy"))
    panel.refresh_buttons()
    assert panel.focal_check.isChecked() and "not known" in panel.focal_check.toolTip()
    panel.focal_check.setChecked(False)
    panel.refresh_buttons()
    assert not panel.focal_check.isChecked()


def test_reference_from_the_3d_view_sees_what_the_view_shows(workbench, qtbot):
    wb = workbench
    ctrl = _load_sample(wb, qtbot)
    panel = wb.manual_panel
    panel.fly_button.click()  # the 3D view looks from the photo's pose
    assert wb.viewer.dims.ndisplay == 3
    with qtbot.waitSignal(ctrl.reference_ready, timeout=20_000):
        panel.ref_view_button.click()
    assert wb.viewer.dims.ndisplay == 2  # back to picking
    ref = ctrl.current.reference
    assert ctrl.current.reference_source == "view"
    assert ref.cam_from_world.rotation_error_deg(ctrl.current.pose) < 0.05
    assert np.linalg.norm(ref.cam_from_world.center - ctrl.current.pose.center) < 0.5
    assert ref.coverage > 0.5


# ------------------------------------------------------------ entry points
def test_plugin_menu_docks_the_workbench_with_its_quality_panel(make_napari_viewer, qtbot):
    from npe2 import PluginManifest

    manifest = PluginManifest.from_distribution("napari-imgreg")
    names = {w.display_name for w in manifest.contributions.widgets}
    assert {"Registration workbench", "Registration quality", "Orient model"} <= names
    viewer = make_napari_viewer()
    _, wb = viewer.window.add_plugin_dock_widget("napari-imgreg", "Registration workbench")
    assert isinstance(wb, Workbench)
    qtbot.waitUntil(lambda: wb.quality is not None, timeout=5000)
    assert viewer.window.dock_widgets[QUALITY_NAME].panel is wb.quality
    assert wb.quality.ctrl is wb.controller


def test_demo_gui_opens_the_sample_in_the_workbench(make_napari_viewer, qtbot, monkeypatch):
    import napari

    from napari_imgreg.cli.demo import open_gui as _demo_gui
    from napari_imgreg.sample import sample_scene

    viewers = []

    def viewer_factory(**kwargs):
        viewers.append(make_napari_viewer())
        return viewers[-1]

    monkeypatch.setattr(napari, "Viewer", viewer_factory)
    monkeypatch.setattr(napari, "run", lambda: None)
    assert _demo_gui(sample_scene("small")) == 0
    wb = viewers[0].window.dock_widgets[WORKBENCH_NAME]
    qtbot.waitUntil(lambda: wb.controller.current is not None, timeout=LOAD_S)
    _idle(wb, qtbot)
    assert len(wb.controller.photos) == 3 and wb.controller.scene.dem is not None
    assert wb.controller.layers.get("render") is not None


def test_closing_the_docks_and_opening_the_workbench_again(workbench, qtbot):
    wb = workbench
    viewer = wb.viewer
    old = wb.controller
    quality = viewer.window.dock_widgets[QUALITY_NAME]
    viewer.window.remove_dock_widget(wb)
    viewer.window.remove_dock_widget(quality)
    # Deleted docks let their controller go: a workbench opened again starts afresh.
    wb.deleteLater()
    quality.deleteLater()
    qtbot.waitUntil(lambda: old.closed, timeout=5000)
    again = Workbench.add_to_viewer(viewer)
    assert again.controller is not old and not again.controller.closed
    assert viewer.window.dock_widgets[QUALITY_NAME].panel is again.quality
    ctrl = _load_sample(again, qtbot)
    assert ctrl.current is not None and ctrl.layers.get("render") is not None


def test_quality_hint_numbers_read_as_the_comparison_that_fired(workbench, qtbot):
    """An excellent pose 0.02 px over the limit: the hint's numbers say so
    ("1.27 px > 1.25 px", not "1.27 px > 1.3"), and so does the limits column."""
    from napari_imgreg.registration.quality import evaluate_rules
    from napari_imgreg.registration.round import Trial

    wb = workbench
    ctrl = _load_sample(wb, qtbot)
    ws = ctrl.workspace
    metrics = {"points_photo": 6000, "points_render": 6000, "feature_inliers": 400,
               "inliers_3d": 300, "inlier_ratio_2d": 0.6, "inlier_ratio_3d": 0.5,
               "reprojection_error_px": 1.27}
    hints = [h.hint for h in evaluate_rules(metrics, ws.params, 1024)]
    assert hints == ["The pose is probably right but imprecise (reprojection error 1.27 px "
                     "> 1.25 px): impose stricter correspondence constraints."]
    trial = Trial(index=0, params=ws.params, metrics=metrics, q=1.7, grade="excellent",
                  hints=hints, pose=ws.current.pose, start_pose=ws.current.pose, rounds=1,
                  converged=True, verified=True, residual_flow_px=0.3)
    ws.add_trial(trial)
    ws.select_trial(0)
    assert "1.27 px &gt; 1.25 px" in wb.quality.hint_label.text()
    import re

    # Limits with the value's two decimals (".1f" rounded them past the value).
    limits = wb.quality.metric_cell("reprojection_error_px", 3).text()
    assert re.fullmatch(r"> \d+\.\d\d \| ≤ \d+\.\d\d", limits), limits


def test_a_laptop_screen_keeps_the_layer_list_and_run_in_view(make_napari_viewer, qtbot):
    """At 1366 × 740 the quality panel sits under the canvas only (the layer
    list keeps the left column's height) and Run / Auto stay in view under
    the Register tab's parameters."""
    viewer = make_napari_viewer(show=True)
    viewer.window._qt_window.resize(1366, 740)
    for k in range(10):
        viewer.add_image(np.zeros((4, 4)), name=f"layer {k}")
    _, wb = viewer.window.add_plugin_dock_widget("napari-imgreg", "Registration workbench")
    qtbot.waitUntil(lambda: wb.quality is not None and wb.quality.isVisible(), timeout=5000)
    qtbot.wait(300)
    layer_list = viewer.window._qt_viewer.layers
    rows = layer_list.viewport().height() / layer_list.sizeHintForRow(0)
    assert rows >= 5, rows
    quality = viewer.window.dock_widgets[QUALITY_NAME]
    canvas = viewer.window._qt_viewer
    left = quality.mapToGlobal(quality.rect().topLeft()).x()
    assert left >= canvas.mapToGlobal(canvas.rect().topLeft()).x() - 20  # not under the left column
    wb.show_tab("Register")
    qtbot.wait(200)
    rp = wb.register_panel
    for button in (rp.run_button, rp.auto_button, rp.cancel_button):
        assert not button.visibleRegion().isEmpty(), button.text()
    page = wb.tabs.currentWidget()
    assert page.widget() is rp  # still a scrolling page of the panel
    page.ensureWidgetVisible(rp.sun_box)
