"""The orientation dock widget in a real napari viewer (run under Xvfb)."""

from __future__ import annotations

import numpy as np
import pytest

from napari_imgreg.widgets._layers import napari_from_world, world_from_napari
from napari_imgreg.io.orientation_tables import write_orientation_csv
from napari_imgreg.orient import rotate_points, rotation_error_deg
from napari_imgreg.sample.survey import simulate_survey
from napari_imgreg.widgets.orient_widget import STATUS_STYLE


@pytest.fixture
def tables(tmp_path):
    survey = simulate_survey(np.random.default_rng(21), noise_deg=1.0, doming_deg=24.0)
    est, meas = tmp_path / "estimated.csv", tmp_path / "measured.csv"
    write_orientation_csv(est, survey.estimated)
    write_orientation_csv(meas, survey.measured)
    return est, meas, survey


@pytest.fixture
def widget(orient_widget):
    return orient_widget


def _run(widget, qtbot):
    with qtbot.waitSignal(widget.orientation_done, timeout=15000) as blocker:
        worker = widget.run()
    assert worker is not None  # the estimate ran in a thread worker, not on the GUI thread
    qtbot.waitUntil(lambda: widget.run_button.isEnabled(), timeout=5000)
    return blocker.args[0]


def test_run_shows_rotation_estimators_flags_and_plots(widget, tables, qtbot):
    est, meas, survey = tables
    widget.set_tables(est, meas)
    result = _run(widget, qtbot)
    assert rotation_error_deg(result.rotation, survey.rotation) < 1.0
    assert "Rotation" in widget.summary_label.text()
    assert widget.estimators_table.rowCount() == 3
    shown = {widget.estimators_table.item(r, 0).text() for r in range(3)}
    assert shown == {"robust ◀", "lsq", "paper"}
    by_key = {label.property("flag"): label for label in widget.flag_labels}
    doming = by_key["slope_vs_path"]
    assert doming.property("status") == "warn"
    assert "Doming along the survey path" in doming.text()
    assert STATUS_STYLE["warn"][0] in doming.text()  # coloured warn badge
    assert by_key["slope_vs_trend"].property("status") == "pass"
    assert STATUS_STYLE["pass"][0] in by_key["slope_vs_trend"].text()
    assert len(widget.figure.axes) == 2 and widget.figure.axes[0].collections  # Δξ/Δρ drawn
    assert widget.save_button.isEnabled()

    # Switching the estimator re-runs with that estimator.
    with qtbot.waitSignal(widget.orientation_done, timeout=15000) as blocker:
        widget.method_combo.setCurrentIndex(widget.method_combo.findData("paper"))
    assert blocker.args[0].method == "paper"


def test_apply_rotates_the_surface_layer_once(widget, tables, qtbot):
    est, meas, survey = tables
    viewer = widget.viewer
    model_vertices = survey.estimated.positions[:12]  # any points in the model frame
    faces = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8], [9, 10, 11]])
    viewer.add_surface((napari_from_world(model_vertices), faces), name="outcrop")
    assert widget.layer_combo.currentText() == "outcrop"
    widget.set_tables(est, meas)
    result = _run(widget, qtbot)
    assert widget.apply_button.isEnabled()

    expected = rotate_points(model_vertices, result.rotation, result.center)
    for _ in range(2):  # applying twice does not rotate twice
        with qtbot.waitSignal(widget.layer_oriented, timeout=2000):
            widget.apply_button.click()
        layer = viewer.layers["outcrop"]
        np.testing.assert_allclose(world_from_napari(layer.vertices), expected, atol=1e-6)
    assert "imgreg_orientation" in layer.metadata


def test_the_workbench_model_is_not_offered_for_rotation(widget, tables, qtbot):
    """The workbench's model stays as its photos were registered to it; other
    Surface layers are offered."""
    from napari_imgreg.widgets._layers import WORKBENCH_MODEL

    viewer = widget.viewer
    faces = np.array([[0, 1, 2]])
    vertices = np.eye(3)
    viewer.add_surface((vertices, faces), name="outcrop", metadata={WORKBENCH_MODEL: True})
    viewer.add_surface((vertices, faces), name="to orient")
    names = [widget.layer_combo.itemText(k) for k in range(widget.layer_combo.count())]
    assert names == ["to orient"]
    assert "the workbench's model is not offered" in widget.apply_button.toolTip()


def test_bad_table_is_reported_not_raised(widget, tmp_path, qtbot):
    bad = tmp_path / "measured.csv"
    bad.write_text("photo,trend_deg\nIMG_1,3\n")
    good = tmp_path / "estimated.csv"
    good.write_text("photo,trend_deg,plunge_deg,roll_deg\nIMG_1,3,0,0\n")
    widget.set_tables(good, bad)
    with qtbot.waitSignal(widget.orientation_failed, timeout=15000) as blocker:
        widget.run()
    assert "measured.csv" in blocker.args[0] and "missing column" in blocker.args[0]
    assert "missing column" in widget.status_label.text()
    qtbot.waitUntil(lambda: widget.run_button.isEnabled(), timeout=5000)
    assert widget.result is None and not widget.apply_button.isEnabled()


def test_untestable_flags_are_not_reported_as_all_pass(widget, tmp_path, qtbot):
    """Three photos from one spot: the slopes cannot be read, which is no pass."""
    survey = simulate_survey(np.random.default_rng(22), n_stations=1, noise_deg=0.5)
    est, meas = tmp_path / "estimated.csv", tmp_path / "measured.csv"
    write_orientation_csv(est, survey.estimated)
    write_orientation_csv(meas, survey.measured)
    widget.set_tables(est, meas)
    result = _run(widget, qtbot)
    assert [f.status for f in result.flags] == ["pass", "n/a", "n/a"]
    assert "all flags pass" not in widget.status_label.text()
    assert "2 flags n/a" in widget.status_label.text()


def test_phone_table_in_radians_is_reported_with_the_fix(widget, tables, tmp_path, qtbot):
    est, _, survey = tables
    att = survey.measured.attitudes
    radians = tmp_path / "phone_radians.csv"
    write_orientation_csv(radians, type(survey.measured).from_attitudes(
        survey.measured.photos, *np.radians(att).T))
    widget.set_tables(est, radians)
    with qtbot.waitSignal(widget.orientation_failed, timeout=15000) as blocker:
        widget.run()
    assert "phone_radians.csv: angles look like radians" in blocker.args[0]
    qtbot.waitUntil(lambda: widget.run_button.isEnabled(), timeout=5000)
    assert widget.result is None


def test_save_to_an_unwritable_place_is_reported(widget, tables, tmp_path, qtbot, monkeypatch):
    est, meas, _ = tables
    widget.set_tables(est, meas)
    _run(widget, qtbot)
    (tmp_path / "a_file").write_text("not a folder")
    target = tmp_path / "a_file" / "ORIENTATION.json"
    monkeypatch.setattr("napari_imgreg.widgets.orient_widget.QFileDialog.getSaveFileName",
                        lambda *a, **k: (str(target), "JSON (*.json)"))
    with qtbot.waitSignal(widget.orientation_failed, timeout=2000) as blocker:
        widget.save_button.click()
    assert "Could not save" in blocker.args[0] and not target.exists()
    assert widget.result is not None  # the result is kept, to save elsewhere
