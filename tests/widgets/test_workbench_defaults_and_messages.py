"""The workbench's and the Orient model dock's defaults and messages (run
under Xvfb): Reset of the filters, the Register tab's outcome
words, the quality dock's layout at 1600 × 1000 with long hints, the model
field's formats, the manual hint's GUI wording and the automatic
declination's messages."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from napari_imgreg.registration.params import RegistrationParams

from ._workbench import idle, load_sample


def test_filters_reset_returns_to_a_new_sessions_filters(workbench):
    wb = workbench
    ws = wb.controller.workspace
    fresh = RegistrationParams()
    editor = wb.filters_panel.photo_editor
    assert editor.wallis_check.isChecked()  # a new session: Wallis on
    editor.wallis_check.setChecked(False)
    editor.widgets["gamma"].setValue(2.0)
    assert not ws.params.photo_filters.wallis
    editor.reset()  # one side only
    assert ws.params.photo_filters == fresh.photo_filters
    assert ws.params.photo_filters == ws.params.render_filters  # the next Run matches them
    assert editor.wallis_check.isChecked()
    assert ws.params.to_dict()["photo_filters"]["wallis"] is True  # what the workspace saves


def test_register_status_says_not_registered_beside_a_fair_grade(workbench):
    panel = workbench.register_panel
    reg = SimpleNamespace(status="failed", grade="fair", q=0.4, trials=[object()],
                          timings_s={"total": 2.0})
    panel._finished(reg)
    text = panel.status_label.text()
    assert text.startswith("<b>not registered</b> — best trial fair (uncertain), Q = 0.40")
    assert "failed" not in text


def test_model_field_lists_a_dsm_among_the_formats(workbench, qtbot, tmp_path):
    wb = workbench
    wrong = tmp_path / "IMG_0001.json"
    wrong.write_text("{}")
    messages = []
    wb.controller.status.connect(messages.append)
    wb.scene_panel.mesh_edit.setText(str(wrong))
    wb.scene_panel.open_model()
    qtbot.waitUntil(lambda: any("not a model format" in m for m in messages), timeout=30_000)
    idle(wb, qtbot)
    said = next(m for m in messages if "not a model format" in m)
    assert "a DSM: .tif, .tiff, .asc" in said and "a point cloud:" in said


LONG_HINTS = [
    "The photo has far fewer distinct points than the render of the model (48 against 295), "
    "and settings changed from their defaults explain part of it: the feature detection "
    "threshold is ×3 (default ×1), which keeps only the strongest points. Set them back and "
    "run again; if the photo still has far fewer points, it is probably blurred.",
    "The matches hold only 2 of 16 parts of the photo (is the rest vegetation, sky, "
    "foreground or deep shadow?): a pose held by one patch tilts easily, so it could not be "
    "verified. Add control points in the other parts of the photo.",
    "Too few salient points (48 < 500 in the photo or the render): lower the detection "
    "threshold and keep more points.",
    "The pose was still moving after the last round: not verified.",
    "Independent check: the halves of the photo could not be solved separately (too few "
    "matches to estimate the error): the pose rests on too few matches to be checked.",
]


def _inside(widget, area) -> bool:
    """Whether ``widget`` is shown whole within the scroll area's viewport."""
    if not widget.isVisible():
        return False
    top_left = widget.mapTo(area.viewport(), widget.rect().topLeft())
    bottom = top_left.y() + widget.height()
    return top_left.y() >= 0 and bottom <= area.viewport().height() + 1


@pytest.fixture
def big_workbench(make_napari_viewer, qtbot):
    """The workbench docked in a 1600 × 1000 window, as a user opens it."""
    from napari_imgreg.widgets.workbench import Workbench

    viewer = make_napari_viewer(show=True)
    viewer.window._qt_window.resize(1600, 1000)
    qtbot.wait(100)
    wb = Workbench.add_to_viewer(viewer)
    qtbot.wait(300)  # the quality dock takes its share of the height
    yield wb
    qtbot.waitUntil(lambda: not wb.controller.busy, timeout=30_000)
    wb.controller.workspace.detach()


def test_quality_dock_fits_at_1600_by_1000_with_long_hints(big_workbench, qtbot):
    """The eight metrics, the hints' first lines, the suggestion's button and
    the Trials list are all in view in the bottom dock (22_run_done.png)."""
    from qtpy.QtWidgets import QScrollArea

    from napari_imgreg.registration.manual import RUN_FROM_IT, RUN_FROM_IT_GUI
    from napari_imgreg.registration.round import Trial

    wb = big_workbench
    window = wb.viewer.window._qt_window
    ctrl = load_sample(wb, qtbot)
    ws = ctrl.workspace
    metrics = {"points_photo": 48, "points_render": 295, "feature_inliers": 11,
               "correspondences_3d": 11, "inlier_ratio_2d": 1.0, "inliers_3d": 11,
               "inlier_ratio_3d": 1.0, "reprojection_error_px": 0.92}
    hints = LONG_HINTS + [f"115 of the photo's features agree with this pose: one Run from it "
                          f"{RUN_FROM_IT} refines it."]
    trial = Trial(index=0, params=ws.params, metrics=metrics, q=0.4, grade="fair",
                  hints=hints, pose=ws.current.pose, start_pose=ws.current.pose, rounds=1,
                  converged=False, verified=False, residual_flow_px=3.0)
    for _ in range(3):
        ws.add_trial(trial, kind="Run")
    ws.select_trial(2)
    qtbot.wait(300)
    q = wb.quality
    area = q.parentWidget().parentWidget()
    assert isinstance(area, QScrollArea)
    assert q.table.isVisible() and q.hint_label.isVisible()
    # The panel fits its dock: no scrolling of the whole panel.
    assert q.height() <= area.viewport().height()
    for widget in (q.banner, q.table, q.hint_scroll, q.apply_button, q.history,
                   q.restore_button):
        assert _inside(widget, area), widget
    # The table shows its eight rows whole.
    rows = q.table.rowCount()
    last = q.table.rowViewportPosition(rows - 1) + q.table.rowHeight(rows - 1)
    assert rows == 8 and last <= q.table.viewport().height()
    # Long hints scroll in their own bounded area, from the first.
    assert q.hint_scroll.height() < q.hint_label.height()
    assert q.hint_scroll.verticalScrollBar().value() == 0
    # The manual hint in the workbench's words.
    assert "--prior" not in q.hint_label.text() and RUN_FROM_IT_GUI in q.hint_label.text()
    window.grab().save(str(_shot_path("quality_dock_fits.png")))


def _shot_path(name):
    import os
    import tempfile
    from pathlib import Path

    folder = Path(os.environ.get("IMGREG_TEST_SHOTS", tempfile.gettempdir()))
    folder.mkdir(parents=True, exist_ok=True)
    return folder / name


# ------------------------------------------------------------ Orient model dock
def _run_auto_declination(widget, tables, signal, qtbot) -> list:
    """Orient with the declination from the World Magnetic Model; the
    arguments of ``signal`` (done or failed), once the dock is idle again."""
    widget.set_tables(*tables)
    widget.declination_auto.setChecked(True)
    with qtbot.waitSignal(signal, timeout=15_000) as blocker:
        widget.run()
    qtbot.waitUntil(lambda: widget.run_button.isEnabled(), timeout=5_000)
    return blocker.args


def test_orient_auto_without_a_site_speaks_of_the_dock(orient_widget, dated_orient_tables, qtbot):
    widget = orient_widget
    args = _run_auto_declination(widget, dated_orient_tables, widget.orientation_failed, qtbot)
    text = widget.status_label.text()
    assert args[0] == text
    assert "needs the site" in text and "--georef" not in text and "--declination" not in text
    assert "Georef field" in text and "untick Auto (WMM)" in text


def test_orient_auto_finds_georef_one_folder_up_and_says_so(orient_widget, dated_orient_tables,
                                                            qtbot):
    from napari_imgreg.geo import Georef

    est, _ = dated_orient_tables
    georef = est.parent.parent / "georef.json"
    Georef("EPSG:32721", [283_077.411822, 8_562_012.355651, 0.0]).save(georef)
    widget = orient_widget
    args = _run_auto_declination(widget, dated_orient_tables, widget.orientation_done, qtbot)
    assert args[0].inputs["declination"]["georef"] == str(georef)
    text = widget.status_label.text()
    assert f"origin of {georef}, found one folder up from the estimated table" in text


def test_no_height_slider_under_the_photos(workbench, qtbot):
    """The model (3D) among the layers gave the 2D view of the photos a slider
    for the model's height that moved nothing there; a user's own stack keeps
    its slider, and the 3D view is as napari makes it."""
    wb = workbench
    viewer = wb.controller.viewer
    bar = viewer.window._qt_viewer.dims
    load_sample(wb, qtbot)
    assert viewer.dims.ndisplay == 2 and viewer.dims.nsteps[0] > 1  # napari would show it
    assert bar.isHidden()
    stack = viewer.add_image(np.zeros((4, 5, 6), np.uint8), name="stack")
    assert not bar.isHidden()
    viewer.layers.remove(stack)
    assert bar.isHidden()
    wb.controller.show_3d()
    assert not bar.isHidden()
    wb.controller.show_2d()
    assert bar.isHidden()


def test_only_height_slider_is_decided_by_the_axes_and_the_visible_layers():
    from napari_imgreg.widgets._layers import NAPARI_AXIS_LABELS, only_height_slider

    assert only_height_slider(NAPARI_AXIS_LABELS, (1, 2), (60, 800, 2000), [2, 2])
    assert not only_height_slider(NAPARI_AXIS_LABELS, (1, 2), (60, 800, 2000), [2, 3])
    assert not only_height_slider(NAPARI_AXIS_LABELS, (0, 1, 2), (60, 800, 2000), [2])
    assert not only_height_slider(("t", "y", "x"), (1, 2), (60, 800, 2000), [2])
    assert not only_height_slider(("a",) + NAPARI_AXIS_LABELS, (2, 3), (5, 60, 8, 9), [2])


def test_closing_after_the_window_is_gone_does_not_abort(workbench):
    """At exit napari deletes its Qt widgets before the workbench shuts down:
    touching the deleted slider bar raised RuntimeError inside a Qt slot,
    and Python aborted."""

    class Deleted:
        def isHidden(self):
            raise RuntimeError("wrapped C/C++ object of type QtDims has been deleted")

    hider = workbench.controller._dims_bar
    hider._bar = Deleted()
    hider.update()
    hider.set_visible(True)
    assert not isinstance(hider._bar, Deleted)  # the window's own bar, found again
